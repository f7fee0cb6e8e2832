"""A budgeted sweep's rounds: which tasks each round holds (levels of the study's length axis), deciding the next
round from the rows of those before (the rule that decides is nsl_hpc/sweep/budget.py; the decisions on disk
nsl_hpc/sweep/decisions.py), and the loop that runs them: round after round with the local launchers, or on SLURM
one round and, behind it, the job that launches the next."""

import dataclasses
import logging
import time
from collections import defaultdict
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.compute as pc

from nsl_hpc.config.launchers import SlurmLauncher
from nsl_hpc.core.errors import ConfigError, RunError
from nsl_hpc.studies.base import Study
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.budget import (
    Budget,
    StopWhen,
    budget_of,
    decide_round,
    describe_budget,
)
from nsl_hpc.sweep.decisions import (
    cancel_round_job,
    decided_structure,
    decision_files,
    read_decisions,
    record_round_job,
    write_decisions,
)
from nsl_hpc.sweep.executors import submit_next_round
from nsl_hpc.sweep.failures import read_failures
from nsl_hpc.sweep.launch_settings import LaunchSettings, planned_seconds
from nsl_hpc.sweep.prepare import BuiltSweep, PreparedSweep, prepare_sweep, queued_tasks
from nsl_hpc.sweep.rows import read_task_rows
from nsl_hpc.sweep.submissions import read_submissions

LOG = logging.getLogger(__name__)


def round_of_level(level: int, first_levels: int, levels_per_round: int) -> int:
    """The round (1, 2, ...) that runs the tasks at ``level`` (0: the cheapest value of the length axis)."""
    return 1 if level < first_levels else 2 + (level - first_levels) // levels_per_round


def levels_of(tasks: Sequence[Mapping[str, Any]], study: Study) -> dict[Any, int]:
    """Each value of the study's length axis among ``tasks`` -> its level (0: the cheapest)."""
    return {value: index for index, value in enumerate(sorted({task[study.length_axis] for task in tasks}))}


def first_round_levels(tasks: Sequence[Mapping[str, Any]], study: Study, budget: Budget,
                       planned_s: Callable[[Sequence[str]], float]) -> int:
    """How many of the cheapest levels round 1 runs: the most, up to ``budget.first_levels``, whose tasks the
    planner predicts within ``budget.first_share`` of the budget; at least one."""
    level = levels_of(tasks, study)
    count = 1
    while count < min(budget.settings.first_levels, len(level)) and planned_s(
            [task["task_id"] for task in tasks if level[task[study.length_axis]] <= count]) \
            <= budget.settings.first_share * budget.seconds:
        count += 1
    return count


class Rounds:
    """The rounds of a sweep's tasks: round 1 the ``first_levels`` cheapest levels of the length axis, each later
    one the next ``levels_per_round``; each task's round and its line's tasks in earlier rounds (``earlier``:
    latest first, none in round 1)."""

    def __init__(self, tasks: Sequence[Mapping[str, Any]], study: Study, first_levels: int, levels_per_round: int):
        self.first_levels, self.levels_per_round = first_levels, levels_per_round
        axis = self.axis = study.length_axis
        level = levels_of(tasks, study)
        self.values = sorted(level)  # the length axis's values, cheapest first
        self.round = {task["task_id"]: round_of_level(level[task[axis]], first_levels, levels_per_round)
                      for task in tasks}
        self.count = max(self.round.values())
        lines: dict[tuple, dict[int, str]] = defaultdict(dict)  # line -> level -> task id
        for task in tasks:
            lines[tuple(task[key] for key in study.axes if key != axis)][level[task[axis]]] = task["task_id"]
        self.earlier: dict[str, list[str]] = {}
        for line in lines.values():
            for task_id in line.values():
                self.earlier[task_id] = [line[lv] for lv in sorted(line, reverse=True)
                                         if self.round[line[lv]] < self.round[task_id]]

    def ancestor(self, task_id: str, ran: Collection[str]) -> str | None:
        """The latest task of ``task_id``'s line that an earlier round ran (``ran``), if any."""
        return next((earlier for earlier in self.earlier[task_id] if earlier in ran), None)

    @property
    def structure(self) -> tuple[int, int]:
        """(levels of round 1, levels per later round): what the decisions record and a relaunch must match."""
        return self.first_levels, self.levels_per_round

    def tasks_of(self, number: int) -> list[str]:
        return [task_id for task_id, r in self.round.items() if r == number]


def describe_first_round(budget: Budget, rounds: Rounds, planned_s: Callable[[Sequence[str]], float]) -> str:
    """A line: round 1's tasks, their predicted core-hours and share of the budget (a warning where it is most of
    over its ``budget.first_share`` and half the budget: the later rounds, which decide the envelopes, share the
    rest)."""
    tasks = rounds.tasks_of(1)
    seconds = planned_s(tasks)
    values = rounds.values[:rounds.first_levels]
    line = (f"budget: round 1 is the {len(tasks):,} tasks at {rounds.axis} {values[0]}"
            + (f"-{values[-1]}" if len(values) > 1 else "")
            + f", {seconds / 3600:,.3g} predicted core-hours ({seconds / budget.seconds:.0%} of the budget)")
    if seconds > max(budget.settings.first_share, 0.5) * budget.seconds and rounds.count > 1:  # one level: most
        later = "round 2 gets" if rounds.count == 2 else f"rounds 2-{rounds.count} share"
        line += (f"; {later} the rest and will run few tasks: raise the budget (on a small grid the tasks' fixed "
                 "costs, start-up and scoring, dominate)")
    return line


def refuse_small_budget(budget: Budget, rounds: Rounds, planned_s: Callable[[Sequence[str]], float]) -> None:
    """A budget that does not cover round 1 is refused, in one line."""
    first = planned_s(rounds.tasks_of(1))
    if first > budget.seconds:
        raise ConfigError(f"the budget ({budget.seconds / 3600:.3g} core-hours) is less than its first round "
                          f"({first / 3600:.3g} predicted core-hours, the tasks at the {rounds.first_levels} "
                          f"cheapest level{'s' * (rounds.first_levels > 1)} of the length axis): raise it")


def sweep_rounds(sweep_dir: Path, tasks: Sequence[Mapping[str, Any]], study: Study, budget: Budget,
                 planned_s: Callable[[Sequence[str]], float]) -> Rounds:
    """The rounds of a budgeted sweep: as already decided (a budget with other budget.levels_per_round is
    refused), else round 1 sized by ``first_round_levels``; a budget below round 1 is refused."""
    decided = decided_structure(sweep_dir)
    if decided is not None and decided[1] != budget.settings.levels_per_round:
        raise ConfigError(f"the rounds of sweep_dir={str(sweep_dir)!r} were decided with budget.levels_per_round="
                          f"{decided[1]}: relaunch with it (the rounds of a budgeted sweep stay as decided)")
    first = decided[0] if decided is not None else first_round_levels(tasks, study, budget, planned_s)
    rounds = Rounds(tasks, study, first, budget.settings.levels_per_round)
    refuse_small_budget(budget, rounds, planned_s)
    return rounds


def done_rows(sweep_dir: Path, task_ids: Sequence[str]) -> dict[str, dict[str, Any]]:
    """The rows (status ok) of those of ``task_ids`` that have one."""
    return {task_id: row for task_id, row in read_task_rows(sweep_dir, task_ids).items()
            if row.get("status", "ok") == "ok"}


def ran_rows(sweep_dir: Path, decisions: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """The rows (status ok) of the tasks that ``decisions`` ran, by task id."""
    return done_rows(sweep_dir, sorted(d["task_id"] for d in decisions if d["run"]))


def next_round(number: int, rounds: Rounds, manifest: Mapping[str, Mapping[str, Any]],
               decisions: Sequence[Mapping[str, Any]], rows: Mapping[str, Mapping[str, Any]],
               planned_s: Callable[[Sequence[str]], float], budget: Budget, stopped: Collection[str] = ()
               ) -> list[dict[str, Any]]:
    """The decisions of round ``number`` from those of the rounds before (``decisions``), the rows of their run
    tasks that finished (``rows``, by task id), what they left of the budget and the resources whose laws are
    narrow enough (``stopped``, result columns: ``stopped_resources``)."""
    chosen = {d["task_id"] for d in decisions if d["run"]}
    rows = {task_id: {**manifest[task_id], **row} for task_id, row in rows.items() if task_id in chosen}
    left = budget.seconds - sum(d["cost_s"] for d in decisions)
    if budget.settings.spread and number > 1:  # this round's equal share of what is left to it and the rounds after it
        left /= rounds.count - number + 1
    ancestors = {task_id: rounds.ancestor(task_id, chosen) for task_id in rounds.tasks_of(number)}
    return decide_round(number, ancestors, manifest, rows, planned_s, left, budget, stopped)


def decide_next_round(sweep_dir: Path, number: int, rounds: Rounds, manifest: Mapping[str, Mapping[str, Any]],
                      planned_s: Callable[[Sequence[str]], float], budget: Budget, stopped: Collection[str] = ()
                      ) -> None:
    """Decide round ``number`` from the rows of the rounds before (``next_round``) and write its decisions."""
    if decided_structure(sweep_dir) not in (None, rounds.structure):
        raise RunError(f"another launch decided round 1 of sweep_dir={str(sweep_dir)!r} with other rounds while "
                       "this one waited for the sweep: launch again")
    decisions = read_decisions(sweep_dir)
    write_decisions(sweep_dir, number, next_round(number, rounds, manifest, decisions, ran_rows(sweep_dir, decisions),
                                                  planned_s, budget, stopped), rounds.structure)


# (sweep_dir, round, rows, committed core-hours, stop_when) -> the result columns whose laws are narrow enough: the
# fits' law tracker (analysis.widths.track_laws with the nsl settings), which the launch hands down
LawTracker = Callable[[Path, int, Sequence[Mapping[str, Any]], Mapping[str, float], StopWhen | None], set[str]]


@dataclass(frozen=True)
class TrackedLaws:
    """The laws a budgeted sweep's rounds look at (the launch's ``nsl`` group, typed where launch reads it):
    ``columns``, each resource's results column by its name; ``metrics``; ``track``, the law tracker."""

    columns: dict[str, str]
    metrics: tuple[str, ...]
    track: LawTracker


Budgeted = tuple[Budget, Rounds, Callable[[Sequence[str]], float], TrackedLaws] | None


def budgeted_rounds(built: BuiltSweep, sweep_dir: Path, laws: TrackedLaws | None) -> Budgeted:
    """The launch's budget (its settings' budget group; ``laws``, those its rounds look at: None where no budget is
    set), the rounds of its tasks and the planner's seconds of any of them; None without a budget or with one that
    covers the whole sweep (``budget_of``). A budget below round 1's cost, with another budget.levels_per_round than
    the rounds already decided, or none for a sweep whose rounds have begun, is refused; nothing is written."""
    settings = built.settings.budget
    if laws is None or settings is None:
        if decision_files(sweep_dir):
            raise ConfigError(f"sweep_dir={str(sweep_dir)!r} is a budgeted sweep (its budget/ holds decided rounds): "
                              "launch it with budget.core_hours or budget.share (budget.share=1: every task left)")
        return None
    manifest = {task["task_id"]: task for task in built.manifest.to_pylist()}
    planned_s = planned_seconds(manifest, built.settings)
    budget = budget_of(settings, planned_s(list(manifest)), list(laws.columns.values()), laws.metrics)
    if budget is None:
        return None
    rounds = sweep_rounds(sweep_dir, list(manifest.values()), built.study, budget, planned_s)
    return budget, rounds, planned_s, laws


def launch_rounds(built: BuiltSweep, prepared: PreparedSweep, overrides: Sequence[str], budget: Budget,
                  rounds: Rounds, planned_s: Callable[[Sequence[str]], float], laws: TrackedLaws,
                  run_tasks: Callable[[BuiltSweep, PreparedSweep], int]) -> int:
    """A budgeted sweep: decide the next round once the rounds before have run (the laws fitted on their rows
    first by ``laws.track``), run its tasks (``run_tasks``: plan, print and run or submit them), and go on (the
    local launchers) until the last round; on SLURM submit one round and, behind it, a job that launches again
    (``overrides``) once it has run, and return."""
    sweep_dir, manifest = prepared.sweep_dir, {task["task_id"]: task for task in prepared.manifest.to_pylist()}
    attempted = set(read_failures(sweep_dir))  # a task that failed runs again by resubmit, not by the rounds
    worst = 0
    while True:
        decisions = read_decisions(sweep_dir)
        chosen = {d["task_id"] for d in decisions if d["run"]}
        decided = max((d["round"] for d in decisions), default=0)
        LOG.info(describe_budget(budget, decisions, rounds.count))
        if not decided:
            LOG.info(describe_first_round(budget, rounds, planned_s))
        if built.settings.dry_run:  # the round that runs next, as far as it is decided (round 1 always is)
            return run_tasks(built, only(prepared, chosen if decisions else set(rounds.tasks_of(1))))
        this_round = only(prepared, chosen - attempted)
        if this_round.todo.num_rows or prepared.queued:
            started = time.time()
            worst = max(worst, run_tasks(built, this_round))
            if prepared.queued or isinstance(built.settings.launcher, SlurmLauncher):
                if decided < rounds.count:
                    LOG.info(next_round_line(built.settings, sweep_dir, overrides, chosen, started, decided))
                return worst
            attempted |= set(this_round.todo["task_id"].to_pylist())
            prepared = prepare_sweep(built, sweep_dir)
            continue
        if decided == rounds.count:
            LOG.info("budget: every round has run")
            if not layout.law_state_path(sweep_dir, decided).exists():
                track_round_laws(sweep_dir, decided, manifest, budget, laws)
            return worst
        stopped = track_round_laws(sweep_dir, decided, manifest, budget, laws)
        decide_next_round(sweep_dir, decided + 1, rounds, manifest, planned_s, budget, stopped)


def track_round_laws(sweep_dir: Path, number: int, manifest: Mapping[str, Mapping[str, Any]], budget: Budget,
                     laws: TrackedLaws) -> set[str]:
    """``laws.track`` on the rows of the rounds up to ``number``: the result columns whose laws are narrow enough
    (none without ``budget.track_laws`` or before round 1)."""
    if not budget.track_laws or number == 0:
        return set()
    decisions = read_decisions(sweep_dir)
    rows = [{**manifest[task_id], **row} for task_id, row in ran_rows(sweep_dir, decisions).items()]
    committed = {"all": sum(d["cost_s"] for d in decisions if d["run"]) / 3600}
    for name, column in laws.columns.items():  # what the candidates promising on each resource's envelopes cost
        committed[name] = sum(d["cost_s"] for d in decisions if d["run"] and d["resource"] == column) / 3600
    return laws.track(sweep_dir, number, rows, committed, budget.settings.stop_when)


def only(prepared: PreparedSweep, task_ids: set[str]) -> PreparedSweep:
    """``prepared`` with only those of its tasks to run that are among ``task_ids``."""
    keep = pc.is_in(prepared.todo["task_id"], value_set=pa.array(sorted(task_ids), pa.string()))
    return dataclasses.replace(prepared, todo=prepared.todo.filter(keep))


def next_round_line(settings: LaunchSettings, sweep_dir: Path, overrides: Sequence[str], chosen: set[str],
                    since: float, decided: int) -> str:
    """Submit the job that decides the next round once the arrays that hold this round's ``chosen`` tasks (those
    submitted since ``since``, or still queued from before) have ended, in place of one queued by an earlier
    launch (this launch's settings win), and say so."""
    records = read_submissions(sweep_dir)
    queued = queued_tasks(sweep_dir)
    arrays = [record["array_id"] for record in records
              if any(task_id in chosen and (record["submitted"] >= since or task_id in queued)
                     for element in record["elements"] for task_id in element)]
    launcher, budget = settings.launcher, settings.budget
    if not arrays or not isinstance(launcher, SlurmLauncher) or budget is None:
        return (f"budget: round {decided} is queued or running in SLURM; launch again with launcher=slurm once it "
                f"has run to decide round {decided + 1}")
    cancel_round_job(sweep_dir)
    job = submit_next_round(sweep_dir, overrides, launcher, settings.sweep.name, arrays, budget.round_job_minutes)
    record_round_job(sweep_dir, job)
    return (f"budget: round {decided} submitted; job {job} launches again once it has run (afterany), to decide "
            f"and submit round {decided + 1} (python -m nsl_hpc.status sweep_dir={sweep_dir})")
