"""The cheapest configuration for a target error: the joint law (``joint_law``) of a (system, arch) over model
size, data and training length, searched over the configurations the study could train, each costed by the
planner's cost model calibrated by the sweep's measured seconds.

Candidates are the study's own tasks: every combination of the values of its size axes the sweep ran, and
``nsl.joint.beyond_doublings`` doublings of each axis beyond its largest; each drawn as the study draws a task
(its seed and draws those of the sweep's first task of the pair) and checked as launch checks it (an input-output
data tier beyond the training pool is no candidate). A configuration's cost is the planner's seconds of it
trained alone (``plan.planned_group``), times the sweep's measured over predicted core-hours, times the seeds per
configuration: the law is fitted on the best of each configuration's seeds, so that is the cost of the outcome it
predicts. The interval of the cost comes from the law refitted on resampled configurations; the backtest fits on
the cheapest configurations up to ``nsl.joint.backtest_share`` of the core-hours and predicts the others.
"""

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from nsl_hpc.analysis.cards import core_hours
from nsl_hpc.analysis.fitting import fittable, pair_outcomes
from nsl_hpc.analysis.joint_law import VARIABLES, JointLaw, JointLawError, bootstrap_joint_laws, fit_joint_law
from nsl_hpc.analysis.nsl_settings import Joint
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.core.progress import progress
from nsl_hpc.core.seeding import stable_seed
from nsl_hpc.studies import study_named
from nsl_hpc.studies.base import Pair, Study
from nsl_hpc.sweep.launch_settings import LaunchSettings
from nsl_hpc.sweep.manifest import read_manifest, read_pair
from nsl_hpc.sweep.plan import planned_group

SIZE_COLUMNS = {"model": "params", "data": "train_points"}  # the length variable: the study's length axis


@dataclass(frozen=True)
class Configurations:
    """Configurations of one (system, arch): their size-axis coordinates, sizes (VARIABLES -> (n,)) and the
    planner's seconds of one run of each (n,)."""

    coordinates: list[dict[str, Any]]
    sizes: dict[str, np.ndarray]
    seconds: np.ndarray

    def subset(self, keep: np.ndarray) -> "Configurations":
        return Configurations([self.coordinates[i] for i in np.flatnonzero(keep)],
                              {name: values[keep] for name, values in self.sizes.items()}, self.seconds[keep])


def sizes_of(rows: Sequence[Mapping[str, Any]], study: Study) -> dict[str, np.ndarray]:
    """VARIABLES -> (len(rows),) of manifest or results rows."""
    columns = {**SIZE_COLUMNS, "length": study.length_axis}
    return {name: np.array([row[columns[name]] for row in rows], dtype=float) for name in VARIABLES}


def axis_values(rows: Sequence[Mapping[str, Any]], axes: Sequence[str], doublings: int) -> dict[str, list[Any]]:
    """Each axis's values among ``rows``, then ``doublings`` doublings of its largest."""
    values = {}
    for axis in axes:
        seen = sorted({row[axis] for row in rows})
        values[axis] = seen + [seen[-1] * 2 ** i for i in range(1, doublings + 1)]
    return values


def configurations_of(rows: Sequence[Mapping[str, Any]], study: Study, launch: LaunchSettings) -> Configurations:
    """Manifest or results rows as Configurations: their size-axis coordinates, sizes and the planner's seconds of
    each trained alone."""
    return Configurations([{axis: row[axis] for axis in study.size_axes} for row in rows], sizes_of(rows, study),
                          np.array([planned_group([row], launch.cost, launch.grouping).seconds for row in rows]))


def candidate_configurations(study: Study, pair: Pair, template: Mapping[str, Any],
                             values: Mapping[str, Sequence[Any]], launch: LaunchSettings) -> Configurations:
    """Every combination of ``values`` (size axis -> values) as a task like ``template`` (a manifest row), drawn
    and checked as the study does, with the planner's seconds of it trained alone."""
    rows = []
    for combination in itertools.product(*values.values()):
        task = {**template, **dict(zip(values, combination, strict=True))}
        drawn = study.draw(task, pair)
        sizes = {**drawn, **study.training_length(task, drawn, pair)}
        try:
            study.check_task(task, sizes, pair)
        except ConfigError:
            continue
        rows.append({**task, **sizes})
    return configurations_of(rows, study, launch)


def best_per_configuration(pair: pa.Table, rows: Sequence[Mapping[str, Any]], metric: str, study: Study,
                           launch: LaunchSettings) -> tuple[Configurations, np.ndarray]:
    """The configurations a pair's fittable outcomes ran (``rows``: ``pair``'s rows), each with its best outcome
    over the seeds (its sizes are that outcome's draw), and those best errors (n,)."""
    best: dict[tuple, Mapping[str, Any]] = {}
    for row, kept in zip(rows, fittable(pair, SIZE_COLUMNS["model"], metric), strict=True):
        key = tuple(row[axis] for axis in study.size_axes)
        if kept and (key not in best or row[metric] < best[key][metric]):
            best[key] = row
    chosen = list(best.values())
    return configurations_of(chosen, study, launch), np.array([row[metric] for row in chosen], dtype=float)


def cheapest_index(law: JointLaw, configurations: Configurations, target: float) -> int | None:
    """The index of the configuration with the least seconds the law predicts at or below ``target``."""
    reaching = np.flatnonzero(law.log_predict(configurations.sizes) <= math.log(target))
    return int(reaching[np.argmin(configurations.seconds[reaching])]) if len(reaching) else None


@dataclass(frozen=True)
class JointBacktest:
    """A joint law fitted on a pair's cheaper configurations, predicting the dearer ones: the cheapest by the
    planner's seconds up to ``share`` of the pair's predicted core-hours are fitted. ``best_ratio``: its
    predicted best error of the dearer ones over the observed best; ``cost_ratio``: the seconds of the cheapest
    dearer configuration it predicts to reach that observed best over the seconds of the one that reached it
    (None: it predicts that none does)."""

    share: float
    fitted: int
    predicted: int
    best_ratio: float
    cost_ratio: float | None


def cheaper_share(seconds: np.ndarray, share: float) -> np.ndarray:
    """Mask of the cheapest configurations whose seconds sum to at most ``share`` of all."""
    order = np.argsort(seconds, kind="stable")
    keep = np.zeros(len(seconds), dtype=bool)
    keep[order[np.cumsum(seconds[order]) <= share * seconds.sum()]] = True
    return keep


def backtest(configurations: Configurations, errors: np.ndarray, share: float, settings: Joint
             ) -> JointBacktest:
    cheap = cheaper_share(configurations.seconds, share)
    law = fit_joint_law({k: v[cheap] for k, v in configurations.sizes.items()}, errors[cheap], settings)
    dear, dear_errors = configurations.subset(~cheap), errors[~cheap]
    best = int(np.argmin(dear_errors))
    predicted_best = float(np.exp(law.log_predict(dear.sizes).min()))
    chosen = cheapest_index(law, dear, float(dear_errors[best]))
    cost_ratio = None if chosen is None else float(dear.seconds[chosen] / dear.seconds[best])
    return JointBacktest(share, int(cheap.sum()), int((~cheap).sum()), predicted_best / float(dear_errors[best]),
                    cost_ratio)


@dataclass(frozen=True)
class Cheapest:
    """The cheapest configuration of one (system, arch) for ``target``: the joint law and the configurations it
    was fitted on; the chosen candidate (None: none reaches the target by the law) with its sizes, predicted error,
    the size axes on which it lies beyond the sweep, core-hours for ``runs`` runs and their bootstrap interval
    (inf: too many refits reach the target with no candidate); the best the law predicts among the candidates;
    the backtest (None: too few configurations); ``observed``: the cheapest configuration the sweep ran whose best
    outcome reached the target, with its core-hours for ``runs`` runs (None: none did)."""

    system: str
    arch: str
    law: JointLaw
    fitted: int
    target: float
    coordinates: dict[str, Any] | None
    sizes: dict[str, float] | None
    predicted: float | None
    beyond: tuple[str, ...]
    core_hours: float | None
    low: float
    high: float
    runs: int
    best_predicted: float
    backtest: JointBacktest | None
    observed: tuple[dict[str, Any], float] | None


def cost_interval(refits: Sequence[JointLaw], candidates: Configurations, hours: np.ndarray, target: float,
                  level: float) -> tuple[float, float]:
    """The ``level`` interval of the least core-hours (``hours``: (candidates,)) reaching ``target`` by each
    refit (inf where one reaches it with no candidate); (nan, nan) without refits."""
    if not refits:
        return math.nan, math.nan
    least = [hours[index] if (index := cheapest_index(refit, candidates, target)) is not None else math.inf
             for refit in refits]
    tail = (1 - level) / 2
    low, high = np.quantile(least, [tail, 1 - tail], method="inverted_cdf")
    return float(low), float(high)


def cheapest_for(outcomes: pa.Table, metric: str, target: float, study: Study, pair: Pair,
                 template: Mapping[str, Any], launch: LaunchSettings, calibration: float,
                 settings: Joint, level: float) -> Cheapest:
    """The Cheapest of one (system, arch)'s ``outcomes`` (its typed settings ``pair``; raises JointLawError with
    too few configurations); ``calibration``: measured over predicted core-hours of the sweep; ``settings``:
    nsl.joint."""
    rows = outcomes.to_pylist()
    configurations, errors = best_per_configuration(outcomes, rows, metric, study, launch)
    law = fit_joint_law(configurations.sizes, errors, settings)
    axes = axis_values(rows, study.size_axes, settings.beyond_doublings)
    candidates = candidate_configurations(study, pair, template, axes, launch)
    runs = len({row["seed"] for row in rows})
    hours = candidates.seconds * calibration * runs / 3600  # (candidates,)
    refits = bootstrap_joint_laws(law, configurations.sizes, errors, settings.bootstrap,
                                  stable_seed("joint", template["system"], template["arch"]), settings)
    low, high = cost_interval(refits, candidates, hours, target, level)
    try:
        tested = backtest(configurations, errors, settings.backtest_share, settings)
    except JointLawError:
        tested = None
    log_errors = law.log_predict(candidates.sizes)
    reached = np.flatnonzero(errors <= target)
    ran = reached[np.argmin(configurations.seconds[reached])] if len(reached) else None
    common = {"system": template["system"], "arch": template["arch"], "law": law, "fitted": len(errors),
              "target": target, "low": low, "high": high, "runs": runs,
              "best_predicted": float(np.exp(log_errors.min())), "backtest": tested,
              "observed": None if ran is None else (configurations.coordinates[ran],
                                                    float(configurations.seconds[ran] * calibration * runs / 3600))}
    chosen = cheapest_index(law, candidates, target)
    if chosen is None:
        return Cheapest(**common, coordinates=None, sizes=None, predicted=None, beyond=(), core_hours=None)
    coordinates = candidates.coordinates[chosen]
    largest = {axis: max(row[axis] for row in rows) for axis in study.size_axes}
    return Cheapest(**common, coordinates=coordinates,
                    sizes={name: float(values[chosen]) for name, values in candidates.sizes.items()},
                    predicted=float(np.exp(log_errors[chosen])),
                    beyond=tuple(axis for axis, value in coordinates.items() if value > largest[axis]),
                    core_hours=float(hours[chosen]))


def calibration_of(sweep_dir: Path, launch: LaunchSettings, results: pa.Table) -> float:
    """The sweep's measured over predicted core-hours (1 where no row measured its seconds)."""
    hours = core_hours(sweep_dir, launch, results)
    return hours["measured"] / hours["predicted"] if hours["measured"] and hours["predicted"] else 1.0


def cheapest_configurations(sweep_dir: Path, results: pa.Table, launch: LaunchSettings, metric: str,
                            target: float, calibration: float, settings: Joint, level: float
                            ) -> list[Cheapest | str]:
    """The Cheapest of every (system, arch) of a merged sweep, or a line saying why a pair has no joint law."""
    study = study_named(launch.study.name)
    manifest = read_manifest(sweep_dir).to_pylist()
    found: list[Cheapest | str] = []
    pairs = dict.fromkeys(zip(results["system"].to_pylist(), results["arch"].to_pylist(), strict=True))
    for system, arch in progress(pairs, "joint laws", "pair"):
        template = next(task for task in manifest if task["system"] == system and task["arch"] == arch)
        try:
            found.append(cheapest_for(pair_outcomes(results, system, arch), metric, target, study,
                                      read_pair(sweep_dir, system, arch), template, launch, calibration, settings,
                                      level))
        except JointLawError as error:
            found.append(f"{system} / {arch}: no joint law ({error})")
    return found


def describe_cheapest(found: Cheapest) -> list[str]:
    """The lines of one Cheapest: the law, the configuration and its cost, the backtest."""
    runs = f"{found.runs} runs" if found.runs > 1 else "1 run"
    best_of = f"the best of {found.runs} seeds each" if found.runs > 1 else "one seed each"
    lines = [f"{found.system} / {found.arch}: {found.law.formula()} (on {found.fitted:,} configurations, {best_of})"]
    if found.coordinates is None or found.sizes is None:
        lines.append(f"    not reachable by any candidate: the law's best among them is {found.best_predicted:.3g}")
    else:
        where = ", ".join(f"{axis} {value:,}" for axis, value in found.coordinates.items())
        beyond = f"; beyond the sweep in {', '.join(found.beyond)}" if found.beyond else ""
        high = "not reachable" if math.isinf(found.high) else f"{found.high:.3g}"
        lines.append(f"    {where} (p {found.sizes['model']:,.0f} parameters, d {found.sizes['data']:,.0f} points): "
                     f"L {found.predicted:.3g}, {found.core_hours:.3g} core-hours for {runs} "
                     f"[{found.low:.3g}, {high}]{beyond}")
    if found.observed is not None:
        coordinates, hours = found.observed
        lines.append(f"    the cheapest the sweep ran that reached it: "
                     f"{', '.join(f'{axis} {value:,}' for axis, value in coordinates.items())}, {hours:.3g} core-hours")
    if found.backtest is not None:
        test = found.backtest
        cost = ("names none that reaches it" if test.cost_ratio is None else
                f"the cheapest it names to reach it costs {test.cost_ratio:.2g}x the one that did")
        lines.append(f"    backtest, fitted on the {test.fitted} cheapest configurations ({test.share:.0%} of the "
                     f"core-hours): the other {test.predicted}'s best error predicted {test.best_ratio:.2g}x the "
                     f"observed; {cost}")
    return lines
