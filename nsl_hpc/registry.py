"""The registry of config groups: each group's typed owner(s) (``config.schema``) and what kind of setting it is.
``--help`` reads every key's documentation from it; the kinds say what a setting may do to a sweep: an OUTCOME
group is in the task ids, a RUN group is what a resubmit may change (``sweep.run_settings.RUN_KEYS``: run.yaml).

    OUTCOME  changes a task's outcome (part of its id): train, system, arch, metric, rehearse
    GRID     which tasks a sweep runs and in what rounds: sweep, budget, tiers (the values a grid may use)
    RUN      how a sweep's jobs run: launcher, lockstep, packing, cost, checkpoint, watchdog (run.yaml, with
             compile) and the top-level threads and compile (``studies.settings.Runtime``)
    POST     post-processing: nsl, figures, mlflow
    TEST     test-only faults: fault

The owners are imported where the registry is read (``groups``): a command that does not ask starts without them.
"""

from dataclasses import dataclass

OUTCOME, GRID, RUN, POST, TEST = "outcome", "grid", "run", "post", "test"


@dataclass(frozen=True)
class ConfigGroup:
    """A config group (``name``; "" for top-level keys) of ``kind``, typed by one of ``owners`` (a group whose
    owner depends on the study or the architecture has several)."""

    name: str
    kind: str
    owners: tuple[type, ...]


def groups() -> tuple[ConfigGroup, ...]:
    """Every config group with its owners and kind."""
    from nsl_hpc.analysis.nsl_settings import Figures, MlflowSettings, Nsl
    from nsl_hpc.config.arch import ARCH_SCHEMAS, Arch
    from nsl_hpc.config.launchers import LAUNCHERS
    from nsl_hpc.config.system import InputOutputSystem, InputStateSystem
    from nsl_hpc.studies.base import Tiers
    from nsl_hpc.studies.input_state.study import InputStateTiers
    from nsl_hpc.studies.settings import InputOutputTrain, InputStateTrain, Metric, Runtime
    from nsl_hpc.sweep.budget import BudgetSettings
    from nsl_hpc.sweep.launch_settings import SweepSettings
    from nsl_hpc.sweep.rehearsal import Rehearse
    from nsl_hpc.sweep.run_settings import RUN_GROUPS, Fault

    return (ConfigGroup("train", OUTCOME, (InputStateTrain, InputOutputTrain)),
            ConfigGroup("system", OUTCOME, (InputStateSystem, InputOutputSystem)),
            ConfigGroup("arch", OUTCOME, (Arch, *ARCH_SCHEMAS.values())),
            ConfigGroup("metric", OUTCOME, (Metric,)),
            ConfigGroup("rehearse", OUTCOME, (Rehearse,)),
            ConfigGroup("sweep", GRID, (SweepSettings,)),
            ConfigGroup("budget", GRID, (BudgetSettings,)),
            ConfigGroup("tiers", GRID, (InputStateTiers, Tiers)),
            ConfigGroup("launcher", RUN, tuple(LAUNCHERS.values())),
            *(ConfigGroup(name, RUN, (owner,)) for name, owner in RUN_GROUPS.items()),
            ConfigGroup("", RUN, (Runtime,)),
            ConfigGroup("nsl", POST, (Nsl,)),
            ConfigGroup("figures", POST, (Figures,)),
            ConfigGroup("mlflow", POST, (MlflowSettings,)),
            ConfigGroup("fault", TEST, (Fault,)))

