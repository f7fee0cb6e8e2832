"""The studies a sweep can run, by name. A study says which coordinates a task has (its grid axes), how the
sizes of a task are drawn from them, and how a task trains and is scored; everything else (task ids, rows,
manifests, launching, merging, fitting) is shared.

    input_state    spring, ball, motor; unstructured, input_affine, port_hamiltonian  (nsl_hpc.studies.input_state)
    input_output   silverbox, wiener_hammerstein and their *_sim stand-ins; narx, subnet  (.input_output)
"""

import importlib
from collections.abc import Mapping
from typing import Any

from nsl_hpc.config import require_one_study
from nsl_hpc.config.mapping import plain
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.studies.base import Pair, Study
from nsl_hpc.studies.input_output.study import InputOutput
from nsl_hpc.studies.input_state.study import InputState

# what the studies import where they build or train a model (their modules import none of it: a command that only
# reads a sweep starts without torch)
TRAINING_MODULES = ("nsl_hpc.models", "nsl_hpc.studies.input_state.lockstep", "nsl_hpc.studies.input_state.scaling",
                    "nsl_hpc.studies.input_output.lockstep", "nsl_hpc.studies.input_output.scoring")


def import_training_code() -> None:
    """Import torch, the models and the training loops now (~1.5 s): a job does, once, before it forks a process
    per lockstep group, each of which would import them again."""
    for module in TRAINING_MODULES:
        importlib.import_module(module)


def studies() -> dict[str, Study]:
    return {study.name: study for study in (InputState(), InputOutput())}


def study_named(name: str) -> Study:
    known = studies()
    if name not in known:
        raise ConfigError(f"unknown study {name!r}; choose one of: {', '.join(sorted(known))}")
    return known[name]


def study_of(cfg: Mapping[str, Any]) -> Study:
    """The study of a composed config, refusing a system or arch of another study."""
    study = study_named(cfg["study"]["name"])
    require_one_study(cfg)
    return study


def pair_of(cfg: Mapping[str, Any]) -> Pair:
    """The typed settings of a composed task config's (system, arch) (``Study.pair`` of its study)."""
    values = plain(cfg)
    return study_of(values).pair(values)
