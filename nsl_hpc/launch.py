"""Expand a sweep's grid, write its manifest, print the plan and run or submit its tasks.

    python -m nsl_hpc.launch +sweep=demo                          # local processes, foreground
    python -m nsl_hpc.launch +sweep=input_state launcher=slurm launcher.partition=cpu
    python -m nsl_hpc.launch +sweep=input_state dry_run=true      # manifest and plan only

Everything lands in sweep_dir (default runs/<sweep name>): manifest.parquet, configs/, launch.yaml, run.yaml,
rows/, logs/, failures/, submissions/. Launching again on the same sweep_dir runs only the tasks without a valid
row and not queued in SLURM; a sweep_dir holding a different grid, or in use by another launch, resubmit or
clean, is refused. launcher=slurm returns as soon as the job arrays are submitted; watch them with
`python -m nsl_hpc.status sweep_dir=<dir>`.
"""

import functools
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from nsl_hpc import cli
from nsl_hpc.studies.base import model_of
from nsl_hpc.sweep.directory import check_control_files, private_umask, sweep_lock, usable_sweep_dir
from nsl_hpc.sweep.executors import run_jobs
from nsl_hpc.sweep.groups import saved_groups
from nsl_hpc.sweep.launch_settings import check_run_settings
from nsl_hpc.sweep.limits import ClusterLimits, cluster_limits, describe_fit, within_limits
from nsl_hpc.sweep.plan import Grouping, Pack
from nsl_hpc.sweep.prepare import (
    PAIR_KEYS,
    BuiltSweep,
    PreparedSweep,
    build_sweep,
    describe_infeasible,
    prepare_sweep,
)
from nsl_hpc.sweep.rehearsal import plant_job_deaths
from nsl_hpc.sweep.rounds import Budgeted, TrackedLaws, budgeted_rounds, launch_rounds
from nsl_hpc.sweep.storage import read_storage


def describe_lockstep(tasks: Sequence[Mapping[str, Any]], packs: Sequence[Pack], lockstep: Grouping) -> str:
    """How the tasks to run train: as how many models, in how many lockstep groups."""
    models = len({model_of(task, lockstep.model_keys) for task in tasks})
    groups = sum(len(pack.groups) for pack in packs)
    alone = sorted({task["arch"] for task in tasks if not task.get("stackable", True)})
    return (f"  lockstep: {len(tasks):,} tasks as {models:,} models in {groups:,} group{'s' * (groups != 1)} of up to "
            f"{lockstep.size} models" + (" (epoch milestones: a row per task after its epochs)"
                                         if lockstep.model_keys else "")
            + (f"; {', '.join(alone)}: one model per group, priced alone (a torch.nn.Module the lockstep training "
               "cannot batch)" if alone else ""))


def describe_plan(prepared: PreparedSweep, packs: Sequence[Pack], launcher: str) -> str:
    """The plan in a few lines: tasks, jobs, time limits, predicted core-hours (and the groups compiled)."""
    total, todo, done = prepared.manifest.num_rows, prepared.todo.num_rows, prepared.done
    later = total - done - todo - len(prepared.infeasible) - prepared.queued  # a budget's later rounds or skipped
    by_limit: dict[int, int] = {}
    for pack in packs:
        by_limit[pack.time_limit_min] = by_limit.get(pack.time_limit_min, 0) + 1
    classes = ", ".join(f"{n:,} x {limit} min" for limit, n in sorted(by_limit.items()))
    chains = sorted(pack.chain for pack in packs if pack.chain > 1)
    if chains:
        classes += (f"; {len(chains):,} longer than the longest time limit run as chains of "
                    f"{chains[0]}{f'-{chains[-1]}' if chains[-1] > chains[0] else ''} jobs")
    core_hours = sum(pack.seconds for pack in packs) / 3600
    predicted = f"{core_hours:,.1f} core-hours" if core_hours >= 1 else f"{core_hours * 60:.1f} core-minutes"
    groups = [group for pack in packs for group in pack.groups]
    if compiled := sum(group.compiled for group in groups):
        predicted += f" ({compiled:,} of {len(groups):,} lockstep groups compiled)"
    notes = "".join([f", {prepared.queued:,} queued in SLURM (not submitted again)" if prepared.queued else "",
                     f", {later:,} not in this round of the budget" if later else "",
                     f", {prepared.set_aside:,} corrupt rows moved to corrupt/" if prepared.set_aside else ""])
    return (f"sweep {prepared.sweep_dir}: {total:,} tasks, {done:,} done, {todo:,} to run{notes}\n"
            f"  jobs: {len(packs):,} ({launcher}; time limits: {classes or 'none'})\n"
            f"  predicted: {predicted}")


def tracked_laws(nsl: DictConfig) -> TrackedLaws:
    """The laws a budgeted sweep's rounds look at, from the launch's ``nsl`` group typed once. The law fits (scipy:
    ~0.7 s to import) are imported here, where a budget needs them: a launch without one starts sooner."""
    from nsl_hpc.analysis.nsl_settings import nsl_settings
    from nsl_hpc.analysis.widths import track_laws

    settings = nsl_settings(nsl)
    return TrackedLaws({name: resource.column for name, resource in settings.resources.items()},
                       tuple(settings.metrics), functools.partial(track_laws, nsl=settings))


def main(cfg: DictConfig, overrides: Sequence[str]) -> int:
    settings = check_run_settings(cfg)  # the launch's settings, typed once; every check first: nothing is written
    built = build_sweep(settings, overrides)  # for a refused launch
    limits = cluster_limits(settings, settings.dry_run)  # SLURM's commands and the cluster answer, or a refusal
    laws = tracked_laws(cfg.nsl) if settings.budget is not None and settings.budget.requested else None
    budgeted = budgeted_rounds(built, Path(cfg.sweep_dir), laws)
    with private_umask():
        sweep_dir = usable_sweep_dir(cfg.sweep_dir)
        with sweep_lock(sweep_dir, "launch"):
            check_control_files(sweep_dir, settings.compile_cache_dir, settings.allow_shared_sweep_dir)
            return launch(built, sweep_dir, limits, budgeted, overrides)


def launch(built: BuiltSweep, sweep_dir: Path, limits: ClusterLimits | None, budgeted: Budgeted = None,
           overrides: Sequence[str] = ()) -> int:
    """Prepare the sweep directory, then run or submit its tasks to run within the cluster's ``limits`` (None: a
    local launcher's, or not read): all of them, or with a budget round after round (``launch_rounds``;
    ``overrides``: the command line's, for the job that launches the next round)."""
    prepared = prepare_sweep(built, sweep_dir)
    run = functools.partial(run_tasks, limits=limits)
    if budgeted is None:
        return run(built, prepared)
    return launch_rounds(built, prepared, overrides, *budgeted, run)


def run_tasks(built: BuiltSweep, prepared: PreparedSweep, limits: ClusterLimits | None) -> int:
    """Print the plan of ``prepared.todo`` within the cluster's ``limits`` and the sweep directory's file system,
    and (unless a dry run) run or submit it."""
    settings, tasks = built.settings, prepared.todo.to_pylist()
    packs = (within_limits(settings, limits) if limits else settings).plan(
        tasks, saved=[saved.task_ids for saved in saved_groups(prepared.sweep_dir)])
    print(describe_plan(prepared, packs, settings.launcher.name))
    for line in describe_fit(limits, read_storage(prepared.sweep_dir), packs, len(tasks),
                             settings.checkpoint.every_minutes > 0, settings.feed_minutes):
        print(f"  {line}")
    if built.above_max_flops:
        sweep = settings.sweep
        print(f"  sweep.max_flops={sweep.max_flops:g} ({sweep.max_flops_column}): {built.above_max_flops:,} tasks "
              "of the grid above it are not part of the sweep")
    if tasks and (settings.grouping.size > 1 or settings.grouping.model_keys):
        print(describe_lockstep(tasks, packs, settings.grouping))
    if prepared.infeasible:
        print(describe_infeasible(prepared.sweep_dir, prepared.infeasible, record=not settings.dry_run))
    if settings.dry_run or not packs:
        print("dry run: nothing submitted" if settings.dry_run else "nothing to run: every task has a row"
              + (" or is queued" if prepared.queued else ""))
        return 0
    if settings.rehearsal:  # the jobs this launch's lost nodes kill
        plant_job_deaths(prepared.sweep_dir, settings.rehearse, packs)
    return run_jobs(prepared.sweep_dir, settings, packs, tasks, prepared.configs, limits)


if __name__ == "__main__":
    cli.run(main, __doc__, config_name="launch", pass_overrides=True, per_pair=PAIR_KEYS)
