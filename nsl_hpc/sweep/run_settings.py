"""The typed owners of a launch's run settings (conf/launch.yaml): how tasks are grouped and packed into jobs,
what the planner predicts from, how often groups checkpoint and when the watchdog stops a task. None of them
changes an outcome. ``run_settings`` checks them all and returns them typed; each refuses its own bad values
(``config.schema``), ranges chosen so that no protection is switched off by a value (NaN or inf would silence
the watchdog, 1e-9-minute checkpoints would write at every block).
"""

import typing
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from nsl_hpc.config.schema import setting, typed
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.sweep.groups import RENEW_S

DAY_S, WEEK_MINUTES, YEAR_MINUTES = 86400, 10080, 525600


FAULT_KINDS = ("raise", "hang", "slow", "pause")
# where a job pauses (fault.kind=pause): before its first group, in a group's process before its first block (data
# loading, compiling), after its first group, after its last row
PAUSE_POINTS = ("start", "loading", "between", "end")


@dataclass(frozen=True)
class Fault:
    """Test-only fault injection (``sweep.task.inject_fault``, ``sweep.task.pause_if_asked``) for tasks of one
    seed."""

    kind: str | None = setting("raise: the task fails, hang: it freezes, slow: it sleeps at every heartbeat, "
                               "pause: its job sleeps once at pause_at (null: none)", choices=FAULT_KINDS)
    seed: int | None = setting("the seed whose tasks it strikes (null: every task)", 0)
    once: bool = setting("true: a task's first attempt only")
    heartbeat_s: float = setting("slow: seconds slept at every heartbeat", 0, DAY_S)
    pause_at: str | None = setting("pause: where (start, loading, between, end)", choices=PAUSE_POINTS,
                                   default=None)
    pause_s: float = setting("pause: seconds slept there, once per sweep", 0, DAY_S, default=0.0)


@dataclass(frozen=True)
class LockstepSettings:
    """Tasks of one system, arch and depth trained up to ``size`` at a time in one process, each as if alone."""

    enabled: bool = setting("false: one task per process")
    size: int = setting("K: the most models one group trains in lockstep", 1)
    width_buckets: list[int] = setting("widths in one bucket train together, zero-padded to the group's widest "
                                       "([]: equal widths only)", 1)
    memory_mb: float = setting("a group's models x the largest's training memory stays below this (MB)", 0, 100000,
                               low_open=True)


@dataclass(frozen=True)
class Packing:
    """Short tasks packed several to one job (array element), each writing its own row."""

    enabled: bool = setting("false: one lockstep group per job")
    short_task_minutes: float = setting("tasks predicted shorter than this are packed", 0, WEEK_MINUTES,
                                        low_open=True)
    pack_minutes: float = setting("into packs of about this much predicted work", 0, WEEK_MINUTES, low_open=True)
    time_safety: float = setting("a job asks for this multiple of its predicted time, rounded up to a class", 1, 100)
    time_classes_minutes: list[float] = setting("the time limits a job may ask for (minutes)", 0, YEAR_MINUTES,
                                                low_open=True, nonempty=True)


@dataclass(frozen=True)
class Cost:
    """What the planner predicts a task's, a group's and a job's wall time from (seconds on one core)."""

    startup_s: float = setting("a SLURM job's process start, once per job; the floor of a group's watchdog "
                               "allowance", 0, 3600)
    group_start_s: float = setting("a lockstep group's own start in its job", 0, 3600)
    step_seconds: dict[str, float] = setting("per arch: seconds of one training step of the smallest model", 0, 3600,
                                             low_open=True)
    params_per_overhead: dict[str, float] = setting("per arch: a step costs 1 + params / this of step_seconds", 0,
                                                    1e12, low_open=True)
    lockstep_extra: dict[str, float] = setting("per arch: share of the largest model's step added per further "
                                               "model of a group", 0, 100, low_open=True)
    score_seconds: float = setting("input-state scoring: seconds per test sample and model parameter", 0, 1)
    compile_speedup: dict[str, float | None] = setting("per arch: eager / compiled step time (null: never compiled "
                                                       "under compile=auto)", 0, 100, low_open=True)
    compile_s: dict[str, float | None] = setting("per arch: seconds a group's step takes to compile", 0, DAY_S)

    def check(self) -> None:
        for arch, speedup in self.compile_speedup.items():
            if speedup is not None and self.compile_s.get(arch) is None:
                raise ConfigError(f"cost.compile_speedup.{arch} needs cost.compile_s.{arch} (seconds a group "
                                  "compiles)")


@dataclass(frozen=True)
class Checkpoint:
    """Training checkpoints of a lockstep group under <sweep_dir>/checkpoints/."""

    every_minutes: float = setting("written every this many minutes of training", 0.1, WEEK_MINUTES,
                                   also="0: no checkpoints")


@dataclass(frozen=True)
class Watchdog:
    """Frozen-task detection inside a job."""

    heartbeat_timeout_s: float = setting("a task whose heartbeat stops this long is stopped and recorded frozen",
                                         0, DAY_S, low_open=True)
    overrun_factor: float = setting("... or that runs this many times longer than predicted", 1, 1000)
    worker_silence_s: float = setting("local launcher: a worker whose group's lock is silent this long is killed",
                                      2 * RENEW_S, DAY_S)


@dataclass(frozen=True)
class RunSettings:
    """The run-setting groups of a launch config (the launcher's aside: ``config.launchers``)."""

    lockstep: LockstepSettings = setting("tasks trained together in one process")
    packing: Packing = setting("short tasks packed into one job")
    cost: Cost = setting("what the planner predicts wall time from")
    checkpoint: Checkpoint = setting("training checkpoints")
    watchdog: Watchdog = setting("frozen-task detection")


RUN_GROUPS: dict[str, type] = typing.get_type_hints(RunSettings)  # name -> owner
# what a resubmit may change (run.yaml holds them): the launcher, the run groups, the top-level compile
RUN_KEYS = ("launcher", *RUN_GROUPS, "compile")


def run_settings(launch: Mapping[str, Any]) -> RunSettings:
    """The launch config's run-setting groups, typed and checked (one-line ConfigError)."""
    return RunSettings(**{name: typed(schema, launch[name], name) for name, schema in RUN_GROUPS.items()})
