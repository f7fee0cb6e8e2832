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

import dataclasses
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.compute as pc
from omegaconf import DictConfig

from nsl_hpc import cli
from nsl_hpc.analysis.widths import track_laws
from nsl_hpc.config import plain
from nsl_hpc.config.launchers import SlurmLauncher, launcher_from
from nsl_hpc.errors import ConfigError
from nsl_hpc.studies.base import model_of
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.budget import (
    Budget,
    Rounds,
    budget_of,
    budget_requested,
    decide_next_round,
    describe_budget,
    describe_first_round,
    planned_seconds,
    sweep_rounds,
)
from nsl_hpc.sweep.decisions import cancel_round_job, decision_files, read_decisions, record_round_job
from nsl_hpc.sweep.directory import check_control_files, private_umask, sweep_lock, usable_sweep_dir
from nsl_hpc.sweep.executors import run_jobs, submit_next_round
from nsl_hpc.sweep.failures import read_failures
from nsl_hpc.sweep.groups import saved_groups
from nsl_hpc.sweep.limits import cluster_limits, describe_fit, within_limits
from nsl_hpc.sweep.plan import Pack, lockstep_settings, plan_jobs
from nsl_hpc.sweep.prepare import (
    PAIR_KEYS,
    BuiltSweep,
    PreparedSweep,
    build_sweep,
    describe_infeasible,
    prepare_sweep,
    queued_tasks,
)
from nsl_hpc.sweep.rehearsal import plant_job_deaths
from nsl_hpc.sweep.storage import read_storage
from nsl_hpc.sweep.submissions import read_submissions


def describe_lockstep(tasks: Sequence[Mapping[str, Any]], packs: Sequence[Pack], lockstep: Mapping[str, Any]) -> str:
    """How the tasks to run train: as how many models, in how many lockstep groups."""
    models = len({model_of(task, lockstep["model_keys"]) for task in tasks})
    groups = sum(len(pack.groups) for pack in packs)
    return (f"  lockstep: {len(tasks):,} tasks as {models:,} models in {groups:,} group{'s' * (groups != 1)} of up to "
            f"{lockstep['size']} models" + (" (epoch milestones: a row per task after its epochs)"
                                            if lockstep["model_keys"] else ""))


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


def main(cfg: DictConfig, overrides: Sequence[str]) -> int:
    built = build_sweep(cfg, overrides)  # every check first: nothing is written for a refused launch
    budgeted = budgeted_rounds(cfg, built, Path(cfg.sweep_dir))
    with private_umask():
        sweep_dir = usable_sweep_dir(cfg.sweep_dir)
        with sweep_lock(sweep_dir, "launch"):
            check_control_files(sweep_dir, cfg)
            return launch(cfg, built, sweep_dir, budgeted, overrides)


Budgeted = tuple[Budget, Rounds, Callable[[Sequence[str]], float]] | None


def launch(cfg: DictConfig, built: BuiltSweep, sweep_dir: Path, budgeted: Budgeted = None,
           overrides: Sequence[str] = ()) -> int:
    """Prepare the sweep directory, then run or submit its tasks to run: all of them, or with a budget round after
    round (``launch_rounds``; ``overrides``: the command line's, for the job that launches the next round)."""
    prepared = prepare_sweep(cfg, built, sweep_dir)
    if budgeted is None:
        return run_tasks(cfg, built, prepared)
    return launch_rounds(cfg, built, prepared, overrides, *budgeted)


def budgeted_rounds(cfg: DictConfig, built: BuiltSweep, sweep_dir: Path) -> Budgeted:
    """The launch's budget, the rounds of its tasks and the planner's seconds of any of them; None without a
    budget or with one that covers the whole sweep. A budget below round 1's cost, with another
    budget.levels_per_round than the rounds already decided, or none for a sweep whose rounds have begun, is
    refused; nothing is written."""
    if not budget_requested(cfg):
        if decision_files(sweep_dir):
            raise ConfigError(f"sweep_dir={str(sweep_dir)!r} is a budgeted sweep (its budget/ holds decided rounds): "
                              "launch it with budget.core_hours or budget.share (budget.share=1: every task left)")
        return None
    manifest = {task["task_id"]: task for task in built.manifest.to_pylist()}
    planned_s = planned_seconds(manifest, cfg)
    budget = budget_of(cfg, planned_s(list(manifest)))
    if budget is None:
        return None
    return budget, sweep_rounds(sweep_dir, list(manifest.values()), built.study, budget, planned_s), planned_s


def run_tasks(cfg: DictConfig, built: BuiltSweep, prepared: PreparedSweep) -> int:
    """Print the plan of ``prepared.todo`` within the cluster's limits and the sweep directory's file system, and
    (unless a dry run) run or submit it."""
    lockstep, tasks = lockstep_settings(cfg), prepared.todo.to_pylist()
    limits = cluster_limits(cfg, cfg.dry_run)
    packs = plan_jobs(tasks, within_limits(cfg, limits) if limits else cfg,
                      saved=[saved.task_ids for saved in saved_groups(prepared.sweep_dir)])
    print(describe_plan(prepared, packs, cfg.launcher.name))
    for line in describe_fit(limits, read_storage(prepared.sweep_dir), packs, len(tasks),
                             cfg.checkpoint.every_minutes > 0):
        print(f"  {line}")
    if built.above_max_flops:
        print(f"  sweep.max_flops={cfg.sweep.max_flops:g}: {built.above_max_flops:,} tasks of the grid above it "
              "are not part of the sweep")
    if tasks and (lockstep["size"] > 1 or lockstep["model_keys"]):
        print(describe_lockstep(tasks, packs, lockstep))
    if prepared.infeasible:
        print(describe_infeasible(prepared.sweep_dir, prepared.infeasible, record=not cfg.dry_run))
    if cfg.dry_run or not packs:
        print("dry run: nothing submitted" if cfg.dry_run else "nothing to run: every task has a row"
              + (" or is queued" if prepared.queued else ""))
        return 0
    if cfg.rehearsal:  # the jobs this launch's lost nodes kill
        plant_job_deaths(prepared.sweep_dir, cfg.rehearse, packs)
    return run_jobs(prepared.sweep_dir, cfg, packs, tasks, prepared.configs, limits)


def launch_rounds(cfg: DictConfig, built: BuiltSweep, prepared: PreparedSweep, overrides: Sequence[str],
                  budget: Budget, rounds: Rounds, planned_s: Callable[[Sequence[str]], float]) -> int:
    """A budgeted sweep (nsl_hpc/sweep/budget.py): decide the next round once the rounds before have run, run its
    tasks, and go on (the local launchers) until the last round; on SLURM submit one round and, behind it, a job
    that launches again (``overrides``) once it has run, and return."""
    sweep_dir, manifest = prepared.sweep_dir, {task["task_id"]: task for task in prepared.manifest.to_pylist()}
    attempted = set(read_failures(sweep_dir))  # a task that failed runs again by resubmit, not by the rounds
    worst = 0
    while True:
        decisions = read_decisions(sweep_dir)
        chosen = {d["task_id"] for d in decisions if d["run"]}
        decided = max((d["round"] for d in decisions), default=0)
        print(describe_budget(budget, decisions, rounds.count))
        if not decided:
            print(describe_first_round(budget, rounds, planned_s))
        if cfg.dry_run:  # the round that runs next, as far as it is decided (round 1 always is)
            return run_tasks(cfg, built, only(prepared, chosen if decisions else set(rounds.tasks_of(1))))
        this_round = only(prepared, chosen - attempted)
        if this_round.todo.num_rows or prepared.queued:
            started = time.time()
            worst = max(worst, run_tasks(cfg, built, this_round))
            if prepared.queued or cfg.launcher.name == "slurm":
                if decided < rounds.count:
                    print(next_round_line(cfg, sweep_dir, overrides, chosen, started, decided))
                return worst
            attempted |= set(this_round.todo["task_id"].to_pylist())
            prepared = prepare_sweep(cfg, built, sweep_dir)
            continue
        if decided == rounds.count:
            print("budget: every round has run")
            if not layout.law_state_path(sweep_dir, decided).exists():
                track_laws(sweep_dir, decided, manifest, plain(cfg.nsl), budget)
            return worst
        stopped = track_laws(sweep_dir, decided, manifest, plain(cfg.nsl), budget)
        decide_next_round(sweep_dir, decided + 1, rounds, manifest, planned_s, budget, stopped)


def only(prepared: PreparedSweep, task_ids: set[str]) -> PreparedSweep:
    """``prepared`` with only those of its tasks to run that are among ``task_ids``."""
    keep = pc.is_in(prepared.todo["task_id"], value_set=pa.array(sorted(task_ids), pa.string()))
    return dataclasses.replace(prepared, todo=prepared.todo.filter(keep))


def next_round_line(cfg: DictConfig, sweep_dir: Path, overrides: Sequence[str], chosen: set[str], since: float,
                    decided: int) -> str:
    """Submit the job that decides the next round once the arrays that hold this round's ``chosen`` tasks (those
    submitted since ``since``, or still queued from before) have ended, in place of one queued by an earlier
    launch (this launch's settings win), and say so."""
    records = read_submissions(sweep_dir)
    queued = queued_tasks(sweep_dir)
    arrays = [record["array_id"] for record in records
              if any(task_id in chosen and (record["submitted"] >= since or task_id in queued)
                     for element in record["elements"] for task_id in element)]
    launcher = launcher_from(cfg.launcher)
    if not arrays or not isinstance(launcher, SlurmLauncher):
        return (f"budget: round {decided} is queued or running in SLURM; launch again with launcher=slurm once it "
                f"has run to decide round {decided + 1}")
    cancel_round_job(sweep_dir)
    job = submit_next_round(sweep_dir, overrides, launcher, cfg.sweep.name, arrays, cfg.budget.round_job_minutes)
    record_round_job(sweep_dir, job)
    return (f"budget: round {decided} submitted; job {job} launches again once it has run (afterany), to decide "
            f"and submit round {decided + 1} (python -m nsl_hpc.status sweep_dir={sweep_dir})")


if __name__ == "__main__":
    cli.run(main, __doc__, config_name="launch", pass_overrides=True, per_pair=PAIR_KEYS)
