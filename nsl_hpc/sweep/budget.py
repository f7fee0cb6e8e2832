"""Budgeted sweeps: the budget, and the rule that decides which tasks of each round run (the rounds, along the
study's length axis, input-state: epochs, input-output: iter_multiplier, are nsl_hpc/sweep/rounds.py), so that a
budget is spent where the lower envelopes are decided.

The rule. The grid's values of the length axis are levels (2, 4, ..., 16384 epochs: 14 levels). Round 1 runs every
task at the cheapest levels: as many as the planner predicts within ``budget.first_share`` of the budget, at most
``budget.first_levels`` and at least one (fixed when round 1 is decided); each later round takes the next
``budget.levels_per_round``. A task of a later round has a line (its task with every coordinate equal but the
length axis) and an ancestor: the line's latest task that an earlier round ran (a line the budget left out of a
round may come back in a later one). It runs only if its ancestor has a row (not failed) and, for some
resource (compute, data, model) and metric that the sweep's fits use (conf/nsl), the ancestor's error divided
by ``budget.margin`` is below the lower envelope (Definition 1's step envelope of every row of its (system,
arch) so far) at the task's own resource value: trained longer, it could still lower that envelope. The
candidates run in the order of that ratio (its smallest over resources and metrics: most promising first; of
equal ones, common at 1 / margin, the one with the smaller geometric mean of all its ratios first)
as long as the planner's prediction of them (``cost.*``: their lockstep groups' seconds, planned as the round
runs them) fits in the round's allowance: with ``budget.spread`` its equal share of what the budget has left for
it and the rounds after it (so the long rounds are reached), else all that is left; a candidate that does not
fit is passed over for later ones that do (``affordable``); the others are skipped, each with its reason.
``budget.share`` is a share of the planner's prediction for the whole sweep. With ``budget.track_laws`` (or
``budget.stop_when``) every law is fitted with its bootstrap intervals on the rows before each later round
(analysis/widths.py; status shows their widths); a resource of which ``budget.stop_when.share`` of the laws are
settled and as narrow as it asks runs no more candidates for its own sake (none at all once every resource has
stopped; with ``each_resource: false``, nothing stops before every resource could). Every decision depends only
on the rows of earlier rounds; a round's decisions are written (``budget/round-<r>.parquet``) before its tasks
run, so a launch that stops anywhere continues with the same decisions.
"""

import math
from collections import defaultdict
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from nsl_hpc.config.schema import setting
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.sweep.decisions import describe_rounds

WIDTHS = ("last_slope", "breaks", "prediction")


@dataclass(frozen=True)
class StopWhen:
    """The widths (``WIDTHS``; None: not asked) at which a settled law (one that lies inside the intervals of its
    fit a round before) is narrow enough, the share of a resource's laws that must be, and whether each resource
    stops on its own laws (else the sweep stops once every resource's are)."""

    last_slope: float | None = setting("high - low of the last slope's interval", 0, low_open=True, default=None)
    breaks: float | None = setting("high / low of the break positions' intervals", 1, low_open=True, default=None)
    prediction: float | None = setting("high / low of L at 10x the largest resource", 1, low_open=True,
                                       default=None)
    each_resource: bool = setting("false: wait for every resource", default=True)
    share: float = setting("the share of a resource's laws that must be narrow", 0, 1, low_open=True, default=1.0)

    def check(self) -> None:
        if all(getattr(self, name) is None for name in WIDTHS):
            raise ConfigError("budget.stop_when sets no width: give last_slope, breaks or prediction (or "
                              "stop_when=null)")

    def narrow(self, law: Mapping[str, Any]) -> bool:
        """Whether a law (of a law state: its widths and whether it is settled) is settled and every width asked for
        is at most its limit (a law without intervals never is)."""
        return bool(law["settled"]) and all(law[name] <= limit for name in WIDTHS
                                            if (limit := getattr(self, name)) is not None)


@dataclass(frozen=True)
class BudgetSettings:
    """A budgeted sweep: the grid's tasks in rounds along the length axis while the budget lasts."""

    core_hours: float | None = setting("spend at most this many predicted core-hours", 0, low_open=True)
    share: float | None = setting("or this share of the planner's prediction for the whole sweep", 0, 1,
                                  low_open=True)
    first_levels: int = setting("round 1: every task at up to this many cheapest values of the length axis", 1)
    first_share: float = setting("as many as fit in this share of the budget", 0, 1, low_open=True)
    levels_per_round: int = setting("each later round: the next this many values", 1)
    margin: float = setting("a task runs if its ancestor's error / margin is below an envelope", 1)
    spread: bool = setting("a later round spends at most (budget left) / (rounds left)")
    round_job_minutes: int = setting("launcher=slurm: time limit of the job that launches the next round", 1)
    track_laws: bool = setting("fit the laws with their intervals before each later round")
    stop_when: StopWhen | None = setting("the widths at which a law is narrow enough (null: spend the budget)")

    @property
    def requested(self) -> bool:
        """Whether a budget is set (``core_hours`` or ``share``)."""
        return self.core_hours is not None or self.share is not None

    def check(self) -> None:
        if self.core_hours is not None and self.share is not None:
            raise ConfigError(f"budget.core_hours={self.core_hours} and budget.share={self.share}: set one of them")


def stopped_resources(state: Sequence[Mapping[str, Any]], stop_when: StopWhen | None,
                      resources: Mapping[str, str]) -> set[str]:
    """The result columns (of ``resources``: name -> column) of which at least ``stop_when.share`` of the laws in
    ``state`` are narrow enough: each resource on its own, or every one once all are (``each_resource: false``)."""
    if stop_when is None or not state:
        return set()
    narrow = {name: np.mean([stop_when.narrow(law) for law in state if law["resource"] == name] or [False])
              >= stop_when.share for name in resources}
    if stop_when.each_resource:
        return {resources[name] for name, done in narrow.items() if done}
    return set(resources.values()) if all(narrow.values()) else set()


@dataclass(frozen=True)
class Budget:
    """A sweep's budget: ``seconds`` of predicted core time (of ``full_seconds``, the whole sweep's), the budget
    group's ``settings`` (the rule's), and the result columns of the fits' ``resources`` (flops, train_points,
    params) and their ``metrics`` (nmae, nmse) whose envelopes the rule reads."""

    seconds: float
    full_seconds: float
    settings: BudgetSettings
    resources: tuple[str, ...]
    metrics: tuple[str, ...]

    @property
    def track_laws(self) -> bool:
        """Fit the laws with their intervals before each round (status shows their widths): asked for, or needed by
        ``stop_when``."""
        return self.settings.track_laws or self.settings.stop_when is not None


def describe_budget(budget: Budget, decisions: Sequence[Mapping[str, Any]], rounds: int) -> str:
    """A line: the budget of the sweep's predicted core-hours, its rounds and ``describe_rounds``."""
    return (f"budget: {budget.seconds / 3600:,.3g} of the sweep's {budget.full_seconds / 3600:,.3g} predicted "
            f"core-hours in {rounds} rounds; {describe_rounds(decisions)}")


def budget_of(settings: BudgetSettings, full_seconds: float, resources: Sequence[str], metrics: Sequence[str]
              ) -> Budget | None:
    """The budget of ``settings`` (``budget.core_hours`` or ``budget.share`` of ``full_seconds``, the sweep's
    predicted seconds) over the envelopes of the result columns ``resources`` and ``metrics``; None without one, or
    when it covers the whole sweep (``budget.share=1``: a full sweep)."""
    if not settings.requested:
        return None
    hours, share = settings.core_hours, settings.share
    seconds = 3600 * hours if hours is not None else (share or 0.0) * full_seconds
    if seconds >= full_seconds:
        return None
    return Budget(seconds, full_seconds, settings, tuple(resources), tuple(metrics))


class Envelopes:
    """Lower envelopes (Definition 1, the step envelope) of the outcomes so far, per (system, arch), resource column
    and metric: ``at`` gives the smallest error of the outcomes whose resource is at most x."""

    def __init__(self, rows: Sequence[Mapping[str, Any]], resources: Sequence[str], metrics: Sequence[str]):
        self.curves: dict[tuple[str, str, str, str], tuple[np.ndarray, np.ndarray]] = {}
        by_pair: dict[tuple[str, str], list[Mapping[str, Any]]] = defaultdict(list)
        for row in rows:
            by_pair[row["system"], row["arch"]].append(row)
        for pair, pair_rows in by_pair.items():
            for resource in resources:
                for metric in metrics:
                    points = sorted((float(row[resource]), float(row[metric])) for row in pair_rows
                                    if math.isfinite(float(row[metric])) and float(row[metric]) > 0)
                    if points:
                        r, e = np.array(points).T
                        self.curves[(*pair, resource, metric)] = (r, np.minimum.accumulate(e))

    def at(self, system: str, arch: str, resource: str, metric: str, x: float) -> float:
        """The envelope at resource ``x`` (inf where no outcome has a resource at most x)."""
        curve = self.curves.get((system, arch, resource, metric))
        if curve is None:
            return math.inf
        index = int(np.searchsorted(curve[0], x, side="right")) - 1
        return math.inf if index < 0 else float(curve[1][index])


class Promise(NamedTuple):
    """How promising a candidate is: ``ratio``, the smallest over resources and metrics of its ancestor's error /
    margin over the envelope at its own resource value (below 1, it could lower an envelope); ``spread``, the
    geometric mean of those ratios (of candidates as promising, the one near more envelopes first: many tie at 1 /
    margin, their ancestor on one); ``resource``, the result column of the smallest (None: no ratio)."""

    ratio: float
    spread: float
    resource: str | None


def promise(task: Mapping[str, Any], ancestor_row: Mapping[str, Any], envelopes: Envelopes, margin: float,
            resources: Sequence[str], metrics: Sequence[str]) -> Promise:
    """The ``Promise`` of ``task`` from its ancestor's row over the envelopes of ``resources`` and ``metrics``."""
    ratios = [(float(ancestor_row[metric]) / margin  # on the envelope: 1 / margin exactly
               / envelopes.at(task["system"], task["arch"], resource, metric, float(task[resource])), resource)
              for resource in resources for metric in metrics]
    finite = [(ratio, resource) for ratio, resource in ratios if not math.isnan(ratio)]
    if not finite:
        return Promise(math.inf, math.inf, None)
    smallest, resource = min(finite)
    spread = math.exp(float(np.mean(np.log(np.maximum([ratio for ratio, _ in finite], 1e-300)))))
    return Promise(smallest, spread, resource)


def longest_prefix(task_ids: Sequence[str], planned_s: Callable[[Sequence[str]], float], left_s: float,
                   at_least: int = 0) -> int:
    """The length of the longest prefix of ``task_ids`` (not shorter than ``at_least``, which must fit) whose
    predicted seconds fit in ``left_s`` (binary search: the prediction grows with the prefix)."""
    low, high = at_least, len(task_ids)
    while low < high:
        middle = (low + high + 1) // 2
        low, high = (middle, high) if planned_s(task_ids[:middle]) <= left_s else (low, middle - 1)
    return low


def affordable(ranked: Sequence[str], planned_s: Callable[[Sequence[str]], float], left_s: float) -> list[str]:
    """The tasks of ``ranked`` (most promising first) that run within ``left_s`` predicted seconds: the longest
    prefix that fits, then, passing over the first that did not, each later one whose own prediction fits what
    is left (so one long task does not end a round), as far as their lockstep groups together still fit."""
    first = longest_prefix(ranked, planned_s, left_s)
    chosen = list(ranked[:first])
    spare = left_s - (planned_s(chosen) if chosen else 0.0)
    for task_id in ranked[first + 1:]:
        if (alone := planned_s([task_id])) <= spare:
            chosen.append(task_id)
            spare -= alone
    return chosen[:longest_prefix(chosen, planned_s, left_s, at_least=first)]


def decide_round(number: int, ancestors: Mapping[str, str | None], tasks: Mapping[str, Mapping[str, Any]],
                 rows: Mapping[str, Mapping[str, Any]], planned_s: Callable[[Sequence[str]], float], left_s: float,
                 budget: Budget, stopped: Collection[str] = ()) -> list[dict[str, Any]]:
    """The decisions (DECISION_SCHEMA) of round ``number`` over its tasks (``ancestors``: each task id -> its
    line's latest task an earlier round ran, or None; ``rows``: the rows of the earlier rounds' tasks that
    finished): round 1 runs all its tasks; a later round the promising ones (``promise`` below 1 on a resource not
    in ``stopped``, the result columns whose laws are narrow enough), most promising first, those that
    ``affordable`` fits in ``left_s`` (by ``planned_s`` of their ids: lockstep groups and all). ``cost_s``: a run
    task's share of the round's predicted seconds."""
    candidates = sorted(ancestors)
    scored: list[tuple[Promise, str, str]] = []
    if number == 1:
        scored = [(Promise(0.0, 0.0, None), task_id, "") for task_id in candidates]
    envelopes = Envelopes(list(rows.values()), budget.resources, budget.metrics)
    open_resources = [resource for resource in budget.resources if resource not in stopped]
    for task_id in candidates if number > 1 else ():
        ancestor = ancestors[task_id]
        row = rows.get(ancestor) if ancestor is not None else None
        value = Promise(math.inf, math.inf, None) if row is None or not open_resources else promise(
            tasks[task_id], row, envelopes, budget.settings.margin, open_resources, budget.metrics)
        scored.append((value, task_id, "its ancestor did not finish" if row is None
                       else "laws narrow enough" if not open_resources else "far above the envelope"))
    scored.sort(key=lambda item: (item[0].ratio, item[0].spread, item[1]))
    promising = [task_id for value, task_id, _ in scored if value.ratio < 1]
    chosen = affordable(promising, planned_s, left_s)
    run = set(chosen)
    seconds = planned_s(chosen) if run else 0.0
    weights = {task_id: tasks[task_id]["steps"] * tasks[task_id]["params"] + 1.0 for task_id in run}
    total = sum(weights.values())
    return [{"task_id": task_id, "round": number, "run": task_id in run,
             "reason": ("first round" if number == 1 else "promising") if task_id in run
             else "budget spent" if value.ratio < 1 else reason, "promise": value.ratio, "resource": value.resource,
             "cost_s": seconds * weights[task_id] / total if task_id in run else 0.0}
            for value, task_id, reason in scored]


