"""Fitting a broken NSL to every (system, arch, resource, metric) of a merged sweep, and the fits' files."""


import json
import os
from collections.abc import Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from nsl_hpc.analysis.bootstrap import bootstrap_thetas, intervals
from nsl_hpc.analysis.broken_law import (
    NSLFit,
    NSLFitError,
    backtest_broken_law,
    fit_broken_law,
    lower_envelope,
)
from nsl_hpc.analysis.nsl_settings import Nsl
from nsl_hpc.analysis.published import comparison
from nsl_hpc.core.atomic import read_parquet, write_parquet, write_text
from nsl_hpc.core.errors import ConfigError, RunError
from nsl_hpc.core.progress import progress
from nsl_hpc.core.seeding import stable_seed
from nsl_hpc.studies.metrics import NORMALIZATIONS
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.launch_settings import LaunchSettings
from nsl_hpc.sweep.merge import results_path
from nsl_hpc.sweep.rehearsal import Rehearse, planted_law

KEY_COLUMNS = ("system", "arch", "resource", "metric")


def nsl_key(row: Mapping[str, Any]) -> str:
    """'system/arch/resource/metric': names one NSL (MLflow tags, figure lookup)."""
    return "/".join(row[k] for k in KEY_COLUMNS)


def fits_path(sweep_dir: Path) -> Path:
    return Path(sweep_dir) / layout.FITS


def metric_label(column: str, labels: Mapping[str, str]) -> str:
    """A figure label for a results column: its ``nsl.metrics`` label, or one spelled out from the
    ``<metric>_<mode>_<record>`` name of an extra score (``nmse_one_step_arrow_full``: nMSE, one step,
    arrow_full)."""
    if column in labels:
        return labels[column]
    for metric, label in labels.items():
        for way in NORMALIZATIONS:
            if column == f"{metric}_{way}":
                return f"{label} ({way.replace('_', ' ')})"
    for metric, label in {**labels, "rmse_mv": "RMSE [mV]"}.items():
        for mode in ("free_run", "one_step"):
            if column.startswith(f"{metric}_{mode}_"):
                return f"{label}, {mode.replace('_', ' ')}, {column.removeprefix(f'{metric}_{mode}_')}"
    return column


def choose_metrics(nsl: Nsl, metrics: Sequence[str] | None, results: pa.Table) -> Nsl:
    """``nsl`` fitting the results columns ``metrics`` (None: its own ``nsl.metrics``); refused with a one-line
    error naming the score columns there are when one is missing. The report's "What it takes" metric falls
    back to the first chosen."""
    if metrics is None:
        return nsl
    scores = [name for name in results.column_names if name.split("_")[0] in ("nmae", "nmse", "rmse")]
    missing = [metric for metric in metrics if metric not in scores]
    if missing or not metrics:
        raise ConfigError(f"metrics={list(metrics)}: {', '.join(missing) or 'none chosen'} not among the sweep's "
                          f"scores; choose from: {', '.join(scores)}")
    chosen = {metric: metric_label(metric, nsl.metrics) for metric in metrics}
    report = nsl.predict.report
    if report.metric not in chosen:
        report = replace(report, metric=metrics[0])
    return replace(nsl, metrics=chosen, predict=replace(nsl.predict, report=report))


def require_some_fit(rows: Sequence[Mapping[str, Any]], path: Path) -> None:
    """Raise RunError, before ``path`` is replaced, when not one NSL of ``rows`` could be fitted."""
    if rows and all(row["error"] is not None for row in rows):
        raise RunError(f"none of the {len(rows)} NSLs could be fitted ({nsl_key(rows[0])}: {rows[0]['error']}); "
                       f"{path.name} is left as it was")


def rehearsal_of(launch: LaunchSettings) -> Rehearse | None:
    """A launch's rehearsal settings (``rehearse``: its planted laws) when it is a rehearsal, else None."""
    return launch.rehearse if launch.rehearsal else None


def read_results(sweep_dir: Path) -> pa.Table:
    """The merged outcomes, refused with a one-line error when there are none."""
    path = results_path(sweep_dir)
    if not path.exists():
        raise ConfigError(f"{path} does not exist; run python -m nsl_hpc.merge sweep_dir={sweep_dir} first")
    results = read_parquet(path)
    if results.num_rows == 0:
        raise ConfigError(f"{path} holds no outcomes: no task of the sweep has finished")
    return results


def fittable(results: pa.Table, column: str, metric: str) -> np.ndarray:
    """Mask of the tasks that enter a fit: status ok, finite and positive resource and error."""
    ok = np.asarray(results["status"].to_pylist()) == "ok"
    r = results[column].to_numpy().astype(float)
    e = results[metric].to_numpy().astype(float)
    return ok & np.isfinite(r) & np.isfinite(e) & (r > 0) & (e > 0)


def pair_outcomes(results: pa.Table, system: str, arch: str) -> pa.Table:
    """The results of one (system, arch)."""
    return results.filter(pc.and_(pc.equal(results["system"], system), pc.equal(results["arch"], arch)))


def fit_one(key: dict[str, str], r: np.ndarray, e: np.ndarray, excluded: int, nsl: Nsl, symbol: str,
            rehearse: Rehearse | None = None, backtest: bool = True) -> dict[str, Any]:
    """One NSL's row (KEY_COLUMNS, outcomes, excluded, b, parameters, margin, formula, backtest, bootstrap
    intervals and thetas, the published law's paper_* columns, a rehearsal's planted_* ones; error on failure).
    ``excluded``: merged tasks left out (not ok, or non-finite / non-positive values); ``rehearse``: a
    rehearsal's settings (its planted laws), None for a real sweep; ``backtest``: false leaves the backtest out (a
    second fit)."""
    options: dict[str, Any] = {"breaks": nsl.breaks, "max_breaks": nsl.max_breaks, "K": nsl.K, "settings": nsl}
    row: dict[str, Any] = {**key, "outcomes": len(r), "excluded": excluded, "error": None,
                           **({"rehearsal": True} if rehearse is not None else {})}
    try:
        fit = fit_broken_law(r, e, **options)
    except NSLFitError as error:
        return {**row, "error": str(error)}
    slots = nsl.breaks if nsl.breaks is not None else nsl.max_breaks
    padded = fit.breaks + [(None, None, None)] * (slots - fit.b)
    row.update(b=fit.b, alpha=fit.alpha, beta=fit.beta, delta0=fit.delta0, margin=fit.margin,
               fit_margin=fit.fit_margin, envelope=fit.envelope, formula=fit.formula(symbol),
               margins_by_b=json.dumps(fit.margins), objective=fit.objective, r_min=float(r.min()),
               r_max=float(r.max()), slopes=fit.slopes.tolist(), last_slope=float(fit.slopes[-1]),
               segment_points=list(fit.segment_points),
               undetermined_segments=sorted(fit.undetermined), undetermined=fit.undetermined_text(),
               envelope_r=fit.envelope_r.tolist(), envelope_e=fit.envelope_e.tolist())
    for i, (sigma, phi, delta) in enumerate(padded, start=1):
        row.update({f"sigma_{i}": sigma, f"phi_{i}": phi, f"delta_{i}": delta})
    thetas = bootstrap_thetas(fit, r, e, nsl.bootstrap, stable_seed("bootstrap", *key.values()), nsl.K, nsl,
                              nsl.bootstrap_draw)
    row.update(bootstrap=nsl.bootstrap, bootstrap_thetas=thetas.tolist())
    if nsl.bootstrap:
        bounds = intervals(fit, thetas, float(r.max()), nsl.bootstrap_level, nsl.bootstrap_interval)
        row.update({name: bounds.get(name) for name in interval_columns(slots)})
    row.update(comparison(tuple(key.values()), r, e, nsl.K))
    if rehearse is not None:
        row.update(planted_comparison(rehearse, key, row, r, e, nsl.K))
    if not backtest:
        return row
    log_r = np.log(r)
    cut = float(np.exp(log_r.min() + nsl.backtest_cut * (log_r.max() - log_r.min())))
    try:
        held_out = backtest_broken_law(r, e, cut, **options | {"breaks": fit.b})
        row.update(backtest_cut=cut, backtest_margin=held_out.margin, backtest_final_ratio=held_out.final_ratio)
    except NSLFitError:
        row.update(backtest_cut=cut, backtest_margin=None, backtest_final_ratio=None)
    return row


def planted_comparison(rehearse: Rehearse, key: Mapping[str, str], row: Mapping[str, Any], r: np.ndarray,
                       e: np.ndarray, K: int) -> dict[str, Any]:
    """A rehearsal's planted law beside the fitted one (a compute law of a planted metric): its formula, parameters,
    slope and value at the largest resource (``planted_last_slope``, ``planted_L_at_max``: what the fitted last
    slope and L_at_max estimate), the envelope there over it (``planted_envelope_excess``: an envelope of finite
    draws lies above the law it bounds) and its margin on our envelope; recovered when both planted values lie
    inside the fit's 90% intervals (last_slope, L_at_max)."""
    if key["resource"] != "compute" or key["metric"] not in rehearse.laws:
        return {}
    law = planted_law(rehearse, key["metric"])
    grid_r, grid_e = lower_envelope(r, e, K)
    with np.errstate(divide="ignore"):  # alpha 0: ln alpha = -inf
        theta = law.parameters().tolist()
    at_max = float(law.predict(r.max()))
    planted = {"planted_formula": law.formula("c"), "planted_theta": theta,
              "planted_last_slope": local_slope(law, float(r.max())), "planted_L_at_max": at_max,
              "planted_envelope_excess": float(grid_e[-1]) / at_max,
              "planted_margin_on_ours": float(np.mean((np.log(law.predict(grid_r)) - np.log(grid_e)) ** 2))}
    if row.get("last_slope_lo") is not None:
        planted["planted_recovered"] = bool(
            row["last_slope_lo"] <= planted["planted_last_slope"] <= row["last_slope_hi"]
            and row["L_at_max_lo"] <= at_max <= row["L_at_max_hi"])
    return planted


def local_slope(law: NSLFit, r: float) -> float:
    """d ln L / d ln r of ``law`` at the resource ``r``."""
    step = 1e-4
    return float(np.diff(np.log(law.predict(r * np.exp([-step, step]))))[0] / (2 * step))


def interval_columns(slots: int) -> list[str]:
    """The columns of the bootstrap intervals (point values where the fit has them, then _lo / _hi)."""
    names = ["last_slope", "alpha", "L_at_max", "L_at_10x", *(f"sigma_{i}" for i in range(1, slots + 1))]
    return ["last_slope", "L_at_max", "L_at_10x"] + [f"{name}_{end}" for name in names for end in ("lo", "hi")]


def fit_from_row(row: Mapping[str, Any]) -> NSLFit:
    """The law of an nsl_fits row (envelope not included: recompute it with lower_envelope)."""
    breaks = [(row[f"sigma_{i}"], row[f"phi_{i}"], row[f"delta_{i}"]) for i in range(1, row["b"] + 1)]
    return NSLFit(row["alpha"], row["beta"], row["delta0"], breaks, row["margin"], np.empty(0), np.empty(0),
                  {int(b): m for b, m in json.loads(row["margins_by_b"]).items()}, row["objective"])


def fit_sweep(results: pa.Table, nsl: Nsl, workers: int | None, rehearse: Rehearse | None = None,
              backtest: bool = True) -> list[dict[str, Any]]:
    """Every NSL of the sweep, fitted in parallel processes, in (system, arch, resource, metric) order
    (``rehearse``: a rehearsal's settings, whose planted laws are set beside the fitted ones; ``backtest``: see
    ``fit_one``)."""
    jobs = []
    present = set(zip(results["system"].to_pylist(), results["arch"].to_pylist(), strict=True))
    for system in dict.fromkeys(results["system"].to_pylist()):
        for arch in dict.fromkeys(results["arch"].to_pylist()):
            if (system, arch) not in present:  # a grid of sub-grids need not hold every pair
                continue
            subset = pair_outcomes(results, system, arch)
            for name, resource in nsl.resources.items():
                for metric in nsl.metrics:
                    keep = fittable(subset, resource.column, metric)
                    r = subset[resource.column].to_numpy().astype(float)[keep]
                    e = subset[metric].to_numpy().astype(float)[keep]
                    key = {"system": system, "arch": arch, "resource": name, "metric": metric}
                    jobs.append((key, r, e, int((~keep).sum()), nsl, resource.symbol, rehearse, backtest))
    with ProcessPoolExecutor(workers or os.cpu_count()) as pool:
        futures = [pool.submit(fit_one, *job) for job in jobs]
        return [future.result() for future in progress(futures, "NSL fits (with their bootstrap refits)", "fit")]


def last_slope_undetermined(row: Mapping[str, Any]) -> bool:
    """Whether an nsl_fits row's slope beyond its last break is undetermined (broken_law.undetermined_segments):
    what it extrapolates is then no law."""
    return row["b"] in (row.get("undetermined_segments") or [])


def describe_fit(row: dict[str, Any]) -> str:
    key = nsl_key(row).replace("/", " / ")
    if row["error"]:
        return f"{key}: not fitted ({row['error']})"
    backtest = ("" if row["backtest_margin"] is None else
                f", backtest M={row['backtest_margin']:.2g} (L/E at the largest resource "
                f"{row['backtest_final_ratio']:.2f})")
    excluded = f" ({row['excluded']:,} excluded: not ok or non-positive)" if row["excluded"] else ""
    lines = [f"{key}: b={row['b']} M={row['margin']:.2g} from {row['outcomes']:,} outcomes{excluded}{backtest}",
             f"    {row['formula']}",
             f"    slopes {', '.join(f'{slope:.2f}' for slope in row['slopes'])} on "
             f"{', '.join(str(n) for n in row['segment_points'])} outcomes of the envelope"]
    if row["undetermined"]:
        lines.append(f"    undetermined: {row['undetermined']}")
    if row.get("bootstrap"):
        breaks = "".join(f", sigma_{i} {row[f'sigma_{i}_lo']:.2g}..{row[f'sigma_{i}_hi']:.2g}"
                         for i in range(1, row["b"] + 1))
        last = "last slope" + (" (undetermined)" if last_slope_undetermined(row) else "")
        lines.append(f"    90% ({row['bootstrap']} resamples): {last} {row['last_slope']:.2f} "
                     f"[{row['last_slope_lo']:.2f}, {row['last_slope_hi']:.2f}]{breaks}, "
                     f"L(r_max) {row['L_at_max']:.2g} [{row['L_at_max_lo']:.2g}, {row['L_at_max_hi']:.2g}], "
                     f"L(10 r_max) {row['L_at_10x']:.2g} [{row['L_at_10x_lo']:.2g}, {row['L_at_10x_hi']:.2g}]")
    if row.get("planted_formula") is not None:
        recovered = {True: "recovered", False: "NOT recovered", None: "no intervals"}[row.get("planted_recovered")]
        lines.append(f"    planted (rehearsal): {row['planted_formula']}: slope at r_max "
                     f"{row['planted_last_slope']:.2f}, L(r_max) {row['planted_L_at_max']:.2g} (the envelope "
                     f"{row['planted_envelope_excess']:.3f}x above it), M on our envelope "
                     f"{row['planted_margin_on_ours']:.2g}: {recovered}")
    if row.get("paper_b") is not None:
        lines.append(f"    paper ({row['paper_where']}): b={row['paper_b']} M={row['paper_margin']:.2g} "
                     f"last slope {row['paper_last_slope']:.2f}; on our envelope M={row['paper_margin_on_ours']:.2g}")
    return "\n".join(lines)


def fit_note(nsl: Nsl) -> str:
    """How the sweep's laws were fitted: the envelope, the objective and what chose b."""
    if nsl.objective == "study":
        how = "Section 4.3's loss by Adam on Definition 1's step envelope (nsl.objective=study)"
    else:
        envelope = ("Definition 1's step envelope" if nsl.envelope == "step"
                    else "the envelope interpolated between its outcomes (M still on Definition 1's)")
        weight = ("" if nsl.above_weight == 1 else
                  f", a residual where the law lies above it weighed {nsl.above_weight:g}x (nsl.above_weight)")
        huber = ("" if nsl.huber_delta is None else
                 f", Huber's loss beyond a log residual of {nsl.huber_delta:g} (nsl.huber_delta)")
        how = f"least squares of the log residuals on {envelope} (nsl.envelope={nsl.envelope}){weight}{huber}"
    if nsl.breaks is not None:
        chosen = f"b fixed at {nsl.breaks} (nsl.breaks)"
    else:
        chosen = (f"b chosen in 0..{nsl.max_breaks} among the laws whose every segment stands on at least "
                  f"{nsl.min_segment_points} outcomes of the envelope: each break must cut the margin by "
                  f"{nsl.min_gain:.0%}, not counting the {nsl.choice_trim:.0%} of envelope points the law fits "
                  "worst (nsl.min_segment_points, nsl.min_gain, nsl.choice_trim)")
    bound = f"-{nsl.max_slope:g}"
    return (f"Fits: {how}, every segment's slope in [{bound}, {nsl.max_rise:g}] (a law never rises more than the "
            f"published ones do; nsl.max_slope, nsl.max_rise); {chosen}. A slope at {bound} or on fewer outcomes of "
            "the envelope is undetermined (marked ?, drawn grey).")


def write_fits(sweep_dir: Path, rows: list[dict[str, Any]]) -> None:
    columns = dict.fromkeys(name for row in rows for name in row)  # rows not fitted lack the law's columns
    write_parquet(pa.Table.from_pylist([{name: row.get(name) for name in columns} for row in rows]),
                  fits_path(sweep_dir))
    write_text("\n".join(describe_fit(row) for row in rows) + "\n", Path(sweep_dir) / layout.FITS_TEXT)
