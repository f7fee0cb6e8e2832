"""What both parts of the benchmark use: a timer, the study's manifest and the planner's prediction of it,
and interpolation of per-step costs measured on a (width, depth) grid."""

import dataclasses
import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

from nsl_hpc.config import compose_config
from nsl_hpc.config.launchers import SlurmLauncher
from nsl_hpc.studies import study_named
from nsl_hpc.sweep.grid import build_manifest
from nsl_hpc.sweep.launch_settings import launch_settings
from nsl_hpc.sweep.prepare import pair_configs

# what a process that trains tasks imports (python -c): the task runner and the training code it imports later
TASK_IMPORTS = "import nsl_hpc.sweep.task, nsl_hpc.studies; nsl_hpc.studies.import_training_code()"


def timed(function: Callable[..., Any], *args: Any) -> tuple[Any, float]:
    """(function(*args), the wall-clock seconds it took)."""
    started = time.perf_counter()
    result = function(*args)
    return result, time.perf_counter() - started


def interpolate(table: Mapping[tuple[int, int], float], widths: list[int], depths: list[int], width: int,
                depth: int) -> float:
    """Bilinear interpolation (clamped) of per-step seconds measured on the (width, depth) grid."""
    w = float(np.clip(width, widths[0], widths[-1]))
    d = float(np.clip(depth, depths[0], depths[-1]))
    at_depth = [np.interp(w, widths, [table[wi, dj] for wi in widths]) for dj in depths]
    return float(np.interp(d, depths, at_depth))


def study_manifest(sweep: str, *overrides: str) -> tuple[DictConfig, list[dict[str, Any]]]:
    """The launch config and manifest rows of a study's sweep (``+sweep=<sweep>`` and ``overrides``)."""
    arguments = [f"+sweep={sweep}", *overrides]
    launch = compose_config(arguments, "launch")
    settings = launch_settings(launch)
    study, grid = study_named(settings.study.name), settings.sweep.grid
    return launch, build_manifest(grid, study, pair_configs(grid, arguments, study), settings.sweep_seed).to_pylist()


def planner_core_hours(launch: DictConfig, manifest: list[dict[str, Any]]) -> float:
    """The core-hours ``launch +sweep=<its sweep> launcher=slurm dry_run=true`` predicts (``cost.*``)."""
    settings = launch_settings(launch)
    on_slurm = dataclasses.replace(settings, launcher=SlurmLauncher())
    packs = on_slurm.plan(manifest)
    return sum(pack.seconds for pack in packs) / 3600


def matmul_peak_flops(size: int, repeats: int = 20) -> float:
    """Dense float32 matmul rate of this core (flop/s)."""
    a, b = torch.randn(size, size), torch.randn(size, size)
    torch.mm(a, b)
    _, seconds = timed(lambda: [torch.mm(a, b) for _ in range(repeats)])
    return 2.0 * size**3 * repeats / seconds
