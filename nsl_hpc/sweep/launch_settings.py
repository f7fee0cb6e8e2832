"""A launch config's settings as a sweep's planner, jobs and post-processing use them, typed once where a command or
a job reads the config (``launch_settings``): the sweep (its name and its grid, interpolations resolved), its study
and seed, the run settings (``RunSettings``), the launcher, how a task's process runs (threads, compile), a
rehearsal's settings, the sweep directory's compile cache and trust, how tasks are grouped (``plan.Grouping``), and
what the launch itself was asked (a dry run, the cap on tasks, the budget, whether a code change may mix).
``check_run_settings`` refuses, before any work, the settings no job can run with."""

import functools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any

from nsl_hpc.config import plain
from nsl_hpc.config.launchers import LocalLauncher, SlurmLauncher, check_batch_text, launcher_from
from nsl_hpc.config.schema import setting, typed
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.studies import study_named
from nsl_hpc.studies.settings import Runtime, StudyName
from nsl_hpc.sweep.budget import BudgetSettings
from nsl_hpc.sweep.plan import (
    Group,
    Grouping,
    JobPacking,
    Pack,
    check_signal_delay,
    packing_for,
    plan_jobs,
    sweep_groups,
)
from nsl_hpc.sweep.rehearsal import Rehearse
from nsl_hpc.sweep.run_settings import RunSettings


@dataclass(frozen=True)
class SweepSettings:
    """The ``sweep`` group (conf/sweep/<name>.yaml, a preset or the user's): its name, grid and compute cap."""

    name: str = setting("the sweep's name: its directory under runs/ and its jobs' name")
    grid: Any = setting("axis -> values, or a list of such sub-grids (their tasks together)")
    max_flops: float | None = setting("only the grid's tasks below this compute are the sweep's (null: all)", 0,
                                      low_open=True, default=None)
    max_flops_column: str = setting("the compute column max_flops caps: flops (exact p), or flops_paper (the "
                                    "paper's 4 n_d n_h^2; input-state)", default="flops")


@dataclass(frozen=True)
class LaunchSettings(RunSettings, Runtime):
    """The run settings and the launch config's top-level keys its planner, jobs and post-processing read (threads
    and compile: ``Runtime``). ``values``: the plain config it was typed from (what MLflow logs as the sweep's
    params)."""

    sweep: SweepSettings = setting("the sweep: its name and grid")
    study: StudyName = setting("the sweep's study")
    sweep_seed: int = setting("mixed into every random draw of the sweep", 0)
    launcher: Any = setting("where the jobs run: a config.launchers instance")
    rehearsal: bool = setting("true: a rehearsal, nothing trains")
    rehearse: Rehearse = setting("a rehearsal's planted laws and faults")
    compile_cache_dir: str | None = setting("the jobs' compiled kernels (null: torch's default)")
    allow_shared_sweep_dir: bool = setting("true: control files others can write are accepted", default=False)
    allow_code_change: bool = setting("true: a sweep may mix rows of changed user code", default=False)
    dry_run: bool = setting("expand, write the manifest, print the plan, submit nothing", default=False)
    max_tasks: int | None = setting("a larger grid is refused before it is expanded (null: no cap)", 1, default=None)
    budget: BudgetSettings | None = setting("a budgeted sweep's rounds (null: a sweep stored before budgets)",
                                            default=None)
    grouping: Any = setting("how tasks are grouped (plan.Grouping, from lockstep, the study and compile)",
                            default=None)
    values: dict[str, Any] = field(default_factory=dict, compare=False, repr=False, kw_only=True)

    @property
    def signal_delay_s(self) -> int | None:
        """Seconds before its time limit SLURM warns a job (None: no warning, a local launcher)."""
        return self.launcher.signal_delay_s if isinstance(self.launcher, SlurmLauncher) else None

    @property
    def feed_minutes(self) -> int | None:
        """The time limit of the job that submits what the cluster's submit limits held back (None: none, or a
        local launcher)."""
        return self.launcher.feed_minutes if isinstance(self.launcher, SlurmLauncher) else None

    @property
    def job_startup_s(self) -> float:
        """A job's predicted start-up: ``cost.startup_s`` where each job is its own process (SLURM); 0 for local
        workers, which start once each, not once per pack."""
        return self.cost.startup_s if isinstance(self.launcher, SlurmLauncher) else 0.0

    def packing_for(self, time_factor: float = 1.0) -> JobPacking:
        """The packing its launcher's jobs get (``plan.packing_for``)."""
        return packing_for(self.packing, self.launcher, time_factor)

    def plan(self, tasks: Sequence[Mapping[str, Any]], time_factor: float = 1.0,
             saved: Sequence[Sequence[str]] = ()) -> list[Pack]:
        """The jobs that run ``tasks`` (manifest rows; ``plan.plan_jobs``), time limits stretched by
        ``time_factor``, the checkpointed groups ``saved`` kept whole."""
        return plan_jobs(tasks, self.grouping, self.cost, self.packing_for(time_factor), self.job_startup_s, saved)

    def groups(self, tasks: Sequence[Mapping[str, Any]], saved: Sequence[Sequence[str]] = ()) -> list[Group]:
        """The lockstep groups of ``tasks`` (manifest rows) with their predicted seconds (``plan.sweep_groups``)."""
        return sweep_groups(tasks, self.grouping, self.cost, self.packing_for(), self.job_startup_s, saved)


def launch_settings(launch: Mapping[str, Any]) -> LaunchSettings:
    """A launch config's (composed, or read by ``read_launch_config``) settings, typed (one-line ConfigError)."""
    names = [item.name for item in fields(LaunchSettings) if item.name not in ("grouping", "values")]
    settings = typed(LaunchSettings, {name: launch[name] for name in names if name in launch}, "")
    study = study_named(settings.study.name)
    lockstep = settings.lockstep
    grouping = Grouping(lockstep.size if lockstep.enabled and study.lockstep else 1, tuple(lockstep.width_buckets),
                        lockstep.memory_mb,
                        study.model_keys(launch["train"].get("schedule_epochs"), launch["draws"]), settings.compile)
    return replace(settings, launcher=launcher_from(launch["launcher"]), grouping=grouping, values=plain(launch))


def check_run_settings(launch: Mapping[str, Any]) -> LaunchSettings:
    """A launch config's settings (``launch_settings``), refusing (ConfigError) a launch without a sweep and the
    settings no job can run with or that would switch a protection off: each launcher's own rules, a site cap on
    time without checkpoints, a job name or a SLURM warning that would break the jobs."""
    if "sweep" not in launch:
        raise ConfigError("no sweep chosen: add +sweep=<name> (see conf/sweep/, e.g. +sweep=demo)")
    settings = launch_settings(launch)
    launcher = settings.launcher
    if isinstance(launcher, LocalLauncher | SlurmLauncher):
        launcher.check_runnable()
    if isinstance(launcher, SlurmLauncher):
        if launcher.max_time_minutes is not None and not settings.checkpoint.every_minutes:
            raise ConfigError(f"launcher.max_time_minutes={launcher.max_time_minutes} needs checkpoints "
                              "(checkpoint.every_minutes > 0): a group longer than the cap continues in its next "
                              "job from its checkpoint")
        check_batch_text("sweep.name", settings.sweep.name, flag=True)  # the jobs' --job-name
        check_signal_delay(launcher.signal_delay_s, settings.packing_for().time_classes_minutes)
    return settings


def planned_seconds(tasks: Mapping[str, Mapping[str, Any]], settings: LaunchSettings
                    ) -> Callable[[Sequence[str]], float]:
    """The planner's predicted core-seconds of running some of ``tasks`` (by id) as one launch with ``settings``:
    their lockstep groups' seconds (``cost.*``). Remembered per set of ids: a launch asks for round 1's to size it,
    to refuse a budget below it and to print it."""

    @functools.lru_cache(maxsize=8)
    def seconds_of(task_ids: frozenset[str]) -> float:
        return sum(group.seconds for group in settings.groups([tasks[t] for t in sorted(task_ids)]))

    return lambda task_ids: seconds_of(frozenset(task_ids))
