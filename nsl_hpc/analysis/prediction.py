"""What it takes: the resource a fitted law needs to reach a target error, with its bootstrap interval, how far
that extrapolates, and (for compute) the model and data sizes of the outcomes that got near it."""

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyarrow as pa

from nsl_hpc.analysis.bootstrap import thetas_of
from nsl_hpc.analysis.broken_law import log_law, pareto_indices
from nsl_hpc.analysis.fitting import fit_from_row, fittable, pair_outcomes
from nsl_hpc.analysis.nsl_settings import Nsl


def resource_for(theta: np.ndarray, target: float, start: float, decades: float, points: int = 4000) -> float:
    """The smallest resource r in [start, start 10^decades] with L(r) <= target (theta as in log_law),
    to 1e-9 relative; inf when the law stays above the target over that range."""
    x = np.linspace(math.log(start), math.log(start) + decades * math.log(10), points)
    below = np.nonzero(log_law(theta, x) <= math.log(target))[0]
    if len(below) == 0:
        return math.inf
    if below[0] == 0:
        return start
    low, high = x[below[0] - 1], x[below[0]]
    while high - low > 1e-9:
        middle = (low + high) / 2
        low, high = (low, middle) if log_law(theta, np.array([middle]))[0] <= math.log(target) else (middle, high)
    return math.exp(high)


@dataclass(frozen=True)
class Need:
    """The resource one NSL needs for a target error: point value and interval (inf: not reachable within
    the law over the searched range), decades beyond the largest observed resource (0 inside it), and whether
    the point value lies on a segment whose slope the outcomes do not determine."""

    target: float
    resource: float
    low: float
    high: float
    extrapolation_decades: float
    undetermined: bool = False

    @property
    def reachable(self) -> bool:
        return math.isfinite(self.resource)


def need_for(row: Mapping[str, Any], target: float, smallest: float, decades: float, level: float) -> Need:
    """The resource an nsl_fits row's law needs to reach ``target``, searched from ``smallest`` (the
    smallest observed resource) over ``decades`` decades; the interval from its bootstrap thetas."""
    fit = fit_from_row(row)
    point = resource_for(fit.parameters(), target, smallest, decades)
    thetas = thetas_of(row)
    low = high = point
    if len(thetas):
        needs = np.array([resource_for(theta, target, smallest, decades) for theta in thetas])
        tail = (1 - level) / 2
        low, high = (float(v) for v in np.quantile(needs, [tail, 1 - tail], method="inverted_cdf"))  # inf: last
    beyond = math.log10(point / row["r_max"]) if math.isfinite(point) and point > row["r_max"] else 0.0
    segment = int(np.searchsorted([sigma for sigma, _, _ in fit.breaks], point))
    return Need(target, point, low, high, beyond, segment in (row.get("undetermined_segments") or []))


def envelope_mix(compute: np.ndarray, errors: np.ndarray, params: np.ndarray, data: np.ndarray, needed: float,
                 window_decades: float) -> tuple[float, float, str]:
    """(smallest model size, smallest data size, where) of the outcomes on the envelope within
    ``window_decades`` of ``needed`` compute; beyond the observed range, of the last three on it."""
    on = pareto_indices(compute, errors)
    near = on[np.abs(np.log10(compute[on] / needed)) <= window_decades]
    where = f"the outcomes on the envelope within {window_decades:g} decades"
    if len(near) == 0:
        near, where = on[-3:], "the last 3 outcomes on the envelope (largest compute)"
    return float(params[near].min()), float(data[near].min()), where


def format_need(need: Need, best: float) -> str:
    """The resource ``need`` names, as a line reads it; ``best``: the pair's best observed error."""
    if not need.reachable and best <= need.target:
        return (f"beyond the law's fitted range: a task already reached {best:.3g}, and the law, fitted above the "
                "envelope, stays above the target")
    if not need.reachable:
        return "not reachable within the law"
    interval = ("" if need.low == need.high else
                f" [{need.low:.2g}, {'not reachable' if math.isinf(need.high) else f'{need.high:.2g}'}]")
    beyond = f", extrapolated {need.extrapolation_decades:.1f} decades" if need.extrapolation_decades else ""
    unsure = ", on a slope the outcomes do not determine" if need.undetermined else ""
    return f"{need.resource:.3g}{interval}{beyond}{unsure}"


def what_it_takes(results: pa.Table, fits: Sequence[Mapping[str, Any]], resource: str, metric: str,
                  targets: Callable[[float], Sequence[float]], nsl: Nsl) -> list[dict[str, Any]]:
    """Per fitted (system, arch) law of ``resource`` and ``metric`` and per target error (``targets`` of the
    pair's best observed error): system, arch, target, best (observed), need (a Need) and, for compute,
    the smallest model and data sizes on the envelope near the needed compute (model, data, mix_where);
    search and window: ``nsl.predict``."""
    columns = {name: spec.column for name, spec in nsl.resources.items()}
    entries = []
    for row in fits:
        if row["resource"] != resource or row["metric"] != metric or row["error"] is not None:
            continue
        pair = pair_outcomes(results, row["system"], row["arch"])
        keep = fittable(pair, columns[resource], metric)
        outcomes = {name: pair[column].to_numpy().astype(float)[keep] for name, column in columns.items()}
        e = pair[metric].to_numpy().astype(float)[keep]
        r = outcomes[resource]
        for target in targets(float(e.min())):
            need = need_for(row, target, float(r.min()), nsl.predict.decades, nsl.bootstrap_level)
            entry = {"system": row["system"], "arch": row["arch"], "target": target, "best": float(e.min()),
                     "need": need}
            if resource == "compute" and need.reachable:
                entry |= dict(zip(("model", "data", "mix_where"), envelope_mix(
                    r, e, outcomes["model"], outcomes["data"], need.resource, nsl.predict.window_decades),
                    strict=True))
            entries.append(entry)
    return entries


def describe_need(entry: Mapping[str, Any], symbol: str) -> str:
    """One line of what_it_takes."""
    text = (f"{entry['system']} / {entry['arch']}: {entry['target']:.3g} (best observed {entry['best']:.3g}) "
            f"needs {symbol} = {format_need(entry['need'], entry['best'])}")
    if "model" in entry:
        text += (f"; {entry['mix_where']}: models from {entry['model']:,.0f} parameters, "
                 f"data from {entry['data']:,.0f} points")
    return text
