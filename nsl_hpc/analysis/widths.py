"""How sure a sweep's laws are while its rows land, and when a budgeted sweep's law counts as decided.

A law's widths are those of its bootstrap intervals (``nsl.bootstrap_level``, analysis/bootstrap.py):
``last_slope``: high - low of its last slope (log-log slope units); ``breaks``: the largest high / low of its
break positions (a factor; 1 without a break); ``prediction``: high / low of L at ten times its largest resource
(a factor). A law is settled once it is ``decided`` against the law of the round before (below). ``budget.stop_when``
sets the widths at which a settled law is narrow enough: a budgeted sweep then stops spending on the resource
whose laws (``share`` of them) are (or, with ``each_resource: false``, once every resource's are).

Against a full sweep (the replay's measurement, benchmarks/budget_replay.py), a budgeted law is decided when it
has the full law's number of breaks, and its last slope, its breaks and its value at ten times the full sweep's
largest resource lie inside the full law's intervals (each widened to hold the full law's own value).
"""

import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from nsl_hpc.analysis.fitting import fit_from_row, fit_sweep, nsl_key
from nsl_hpc.analysis.nsl_settings import Nsl
from nsl_hpc.core.atomic import write_text
from nsl_hpc.core.errors import damaged_file
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.budget import WIDTHS, StopWhen, stopped_resources


def widths_of(row: Mapping[str, Any]) -> dict[str, float]:
    """The widths (``WIDTHS``) of an nsl_fits row's intervals; inf where it has none (no fit, no bootstrap)."""
    if row.get("error") or not row.get("bootstrap") or row.get("last_slope_lo") is None:
        return dict.fromkeys(WIDTHS, math.inf)
    breaks = [row[f"sigma_{i}_hi"] / row[f"sigma_{i}_lo"] for i in range(1, row["b"] + 1)]
    return {"last_slope": row["last_slope_hi"] - row["last_slope_lo"], "breaks": max(breaks, default=1.0),
            "prediction": row["L_at_10x_hi"] / row["L_at_10x_lo"]}


# what a law state keeps of an nsl_fits row (with each break's sigma, phi, delta and sigma interval): the law and
# its intervals, as ``decided`` reads them
FIT_FIELDS = ("error", "b", "alpha", "beta", "delta0", "margin", "margins_by_b", "objective", "r_max", "bootstrap",
              "last_slope", "last_slope_lo", "last_slope_hi", "L_at_10x", "L_at_10x_lo", "L_at_10x_hi")


def kept_fit(row: Mapping[str, Any]) -> dict[str, Any]:
    """``row``'s law and intervals (``FIT_FIELDS`` and its breaks')."""
    fit = {name: row.get(name) for name in FIT_FIELDS}
    for i in range(1, (row.get("b") or 0) + 1):
        fit |= {f"{name}_{i}": row.get(f"{name}_{i}") for name in ("sigma", "phi", "delta")}
        fit |= {f"sigma_{i}_{end}": row.get(f"sigma_{i}_{end}") for end in ("lo", "hi")}
    return fit


def law_state(fits: Sequence[Mapping[str, Any]], before: Sequence[Mapping[str, Any]] = ()) -> list[dict[str, Any]]:
    """Per law of ``fits`` (nsl_fits rows with bootstrap intervals): its key, resource, outcomes, ``widths_of``,
    ``fit`` (``kept_fit``) and ``settled``: ``decided`` against the same law in the state ``before`` (the one
    after the round before; never settled without one)."""
    earlier = {law["law"]: law["fit"] for law in before}
    state = []
    for row in fits:
        fit, previous = kept_fit(row), earlier.get(nsl_key(row))
        state.append({"law": nsl_key(row), "resource": row["resource"], "outcomes": row["outcomes"],
                      **widths_of(row), "settled": previous is not None and decided(fit, previous), "fit": fit})
    return state


def inside(value: float, full: Mapping[str, Any], name: str) -> bool:
    """Whether ``value`` lies in the full law's interval of ``name`` widened to hold its own value (a basic
    interval of a biased quantity can leave it out: then only a law other than the full one could be inside)."""
    low, high, point = full[f"{name}_lo"], full[f"{name}_hi"], full[name]
    return bool(min(low, point) <= value <= max(high, point))


def decided(budgeted: Mapping[str, Any] | None, full: Mapping[str, Any]) -> bool:
    """Whether a budgeted sweep's law (an nsl_fits row) is decided against the full sweep's law of the same key:
    as many breaks, and last slope, breaks and L at ten times the full sweep's largest resource ``inside`` the full
    law's intervals (a full law without intervals decides nothing)."""
    if budgeted is None or budgeted.get("error") or full.get("error") or full.get("last_slope_lo") is None:
        return False
    if budgeted["b"] != full["b"] or not inside(budgeted["last_slope"], full, "last_slope"):
        return False
    if not all(inside(budgeted[f"sigma_{i}"], full, f"sigma_{i}") for i in range(1, full["b"] + 1)):
        return False
    return inside(float(fit_from_row(budgeted).predict(10 * full["r_max"])), full, "L_at_10x")


def describe_state(state: Sequence[Mapping[str, Any]], stop_when: StopWhen | None) -> list[str]:
    """Lines for status: per resource, how many of its laws could be fitted with intervals, the median and widest
    of their 90% widths, how many are settled and how many narrow enough by ``stop_when``."""
    lines = []
    for resource in dict.fromkeys(law["resource"] for law in state):
        laws = [law for law in state if law["resource"] == resource]
        fitted = [law for law in laws if math.isfinite(law["prediction"])]
        line = f"  {resource}: {len(fitted)} of {len(laws)} laws with intervals"
        for name, unit in (("last_slope", ""), ("prediction", "x"), ("breaks", "x")) if fitted else ():
            values = sorted(law[name] for law in fitted)
            line += (f"{',' if name != 'last_slope' else ':'} {name.replace('_', ' ')} "
                     f"{values[len(values) // 2]:.3g}{unit} (widest {values[-1]:.3g}{unit})")
        line += f"; {sum(bool(law['settled']) for law in laws)} settled"
        if stop_when is not None:
            line += f", {sum(stop_when.narrow(law) for law in laws)} narrow enough (budget.stop_when)"
        lines.append(line)
    return lines


def track_laws(sweep_dir: Path, number: int, rows: Sequence[Mapping[str, Any]], committed: Mapping[str, float],
               stop_when: StopWhen | None, *, nsl: Nsl) -> set[str]:
    """Fit the laws on ``rows`` (a budgeted sweep's rows of its rounds up to ``number``, manifest columns with
    each), record their state with the predicted core-hours ``committed`` so far (``all``, and per resource name
    those of the later rounds' tasks its envelopes made promising) (``layout.law_state_path``) and return the
    result columns whose laws are narrow enough by ``stop_when`` (``stopped_resources``)."""
    table = pa.Table.from_pylist(list(rows))
    fits = fit_sweep(table, nsl, len(os.sched_getaffinity(0)), backtest=False) if rows else []
    earlier = [record for record in law_records(sweep_dir) if record["round"] < number]
    state = law_state(fits, earlier[-1]["laws"] if earlier else ())
    record = {"round": number, "rows": len(rows), "committed_core_hours": dict(committed), "laws": state}
    write_text(json.dumps(record, indent=1, default=float), layout.law_state_path(sweep_dir, number))
    columns = {name: resource.column for name, resource in nsl.resources.items()}
    return stopped_resources(state, stop_when, columns)


def law_records(sweep_dir: Path) -> list[dict[str, Any]]:
    """The recorded law states of a budgeted sweep (``track_laws``), in round order (a damaged one refused)."""
    records = []
    for path in sorted((Path(sweep_dir) / layout.BUDGET).glob("laws-*.json")):
        try:
            records.append(json.loads(path.read_text()))
        except (OSError, ValueError) as error:
            raise damaged_file(path, error) from None
    return records


def narrowing(before: Mapping[str, Any], after: Mapping[str, Any]) -> dict[str, float]:
    """Per resource, how much its laws' intervals narrowed per predicted core-hour spent on its candidates between
    two law states: the mean over its laws of ln(width before / width after) of the last slope and the
    prediction, over the core-hours committed in between to the tasks its envelopes made promising (nan where none
    were, or no width is finite in both)."""
    earlier = {law["law"]: law for law in before["laws"]}
    gains: dict[str, list[float]] = {}
    for law in after["laws"]:
        for name in ("last_slope", "prediction"):
            old, new = earlier.get(law["law"], {}).get(name, math.inf), law[name]
            if math.isfinite(old) and math.isfinite(new) and old > 0 and new > 0:
                gains.setdefault(law["resource"], []).append(math.log(old / new))
    rates = {}
    for resource, values in gains.items():
        hours = after["committed_core_hours"][resource] - before["committed_core_hours"][resource]
        rates[resource] = float(np.mean(values)) / hours if hours > 0 else math.nan
    return rates


def describe_law_records(records: Sequence[Mapping[str, Any]], stop_when: StopWhen | None) -> list[str]:
    """status's lines on a budgeted sweep's laws: their widths after the latest round (``describe_state``) and the
    resource whose laws narrowed most per core-hour in it."""
    if not records:
        return []
    latest = records[-1]
    lines = [f"laws on the {latest['rows']:,} rows of rounds 1-{latest['round']} "
             f"({latest['committed_core_hours']['all']:,.3g} predicted core-hours), 90% interval widths:",
             *describe_state(latest["laws"], stop_when)]
    if len(records) > 1 and (rates := {k: v for k, v in narrowing(records[-2], latest).items() if math.isfinite(v)}):
        best = max(rates, key=lambda resource: rates[resource])
        lines.append(f"  narrowed most per core-hour spent on its candidates in round {latest['round']}: {best} "
                     f"({', '.join(f'{k} {v:.3g}' for k, v in sorted(rates.items()))}: mean ln(width before / after) "
                     "per predicted core-hour)")
    return lines
