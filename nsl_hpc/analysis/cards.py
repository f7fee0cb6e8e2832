"""Law cards: one JSON file per fitted law (``<sweep_dir>/law_cards/<system>__<arch>__<resource>__<metric>.json``)
with what a reader needs to reproduce or reject it: the grid and its hash, the envelope and its points, the
objective, b and why, M, the bootstrap intervals, the backtest, the published law beside it, the code version and
the fit settings' hash, and the sweep's predicted against measured core-hours."""

import contextlib
import json
import math
import subprocess
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from nsl_hpc.analysis.fitting import fit_note, nsl_key
from nsl_hpc.analysis.nsl_settings import Nsl
from nsl_hpc.core.atomic import write_text
from nsl_hpc.core.seeding import stable_hash
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.formats import package_version
from nsl_hpc.sweep.launch_settings import LaunchSettings
from nsl_hpc.sweep.manifest import read_manifest
from nsl_hpc.sweep.submissions import predicted_shares, read_submissions

INTERVALS = ("last_slope", "L_at_max", "L_at_10x", "alpha")  # and sigma_1.. as the law has breaks


def card_path(sweep_dir: Path, row: Mapping[str, Any]) -> Path:
    return Path(sweep_dir) / layout.LAW_CARDS / f"{nsl_key(row).replace('/', '__')}.json"


def code_commit() -> str | None:
    """The git commit of the nsl_hpc source in use, None outside a git checkout."""
    with contextlib.suppress(OSError, subprocess.SubprocessError):
        result = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent,
                                capture_output=True, text=True, timeout=10)
        if result.returncode == 0:
            return result.stdout.strip()
    return None


def sweep_context(launch: LaunchSettings, nsl: Nsl, core_hours: Mapping[str, float]) -> dict[str, Any]:
    """What every card of a sweep shares: its grid, the fit settings, the code, the core-hours (predicted by
    the planner and measured, of the merged tasks)."""
    grid, fit_settings = launch.sweep.grid, asdict(nsl)
    return {"sweep": launch.sweep.name, "rehearsal": launch.rehearsal, "sweep_seed": launch.sweep_seed,
            "grid": grid, "grid_hash": stable_hash(grid), "fit_settings": fit_settings,
            "fit_settings_hash": stable_hash(fit_settings), "how_fitted": fit_note(nsl),
            "package_version": package_version(), "commit": code_commit(), "core_hours": dict(core_hours)}


def law_card(row: Mapping[str, Any], context: Mapping[str, Any], nsl: Nsl) -> dict[str, Any]:
    """The card of one nsl_fits row (a law that could not be fitted: its key and why) of a sweep fitted with
    ``nsl``."""
    key = {name: row[name] for name in ("system", "arch", "resource", "metric")}
    provenance = {name: context[name] for name in ("sweep", "rehearsal", "sweep_seed", "grid", "grid_hash",
                                                     "fit_settings_hash", "package_version", "commit")}
    if row["error"] is not None:
        return {**key, "fitted": False, "why_not": row["error"], "outcomes": row["outcomes"], **provenance}
    breaks = [{"sigma": row[f"sigma_{i}"], "phi": row[f"phi_{i}"], "delta": row[f"delta_{i}"]}
              for i in range(1, row["b"] + 1)]
    names = [*INTERVALS, *(f"sigma_{i}" for i in range(1, row["b"] + 1))]
    return {
        **key, "fitted": True,
        "law": {"formula": row["formula"], "b": row["b"], "alpha": row["alpha"], "beta": row["beta"],
                "delta0": row["delta0"], "breaks": breaks, "slopes": row["slopes"],
                "segment_points": row["segment_points"], "undetermined": row["undetermined"] or None},
        "outcomes": {"fitted": row["outcomes"], "excluded": row["excluded"],
                     "resource_range": [row["r_min"], row["r_max"]]},
        "envelope": {"kind": row["envelope"], "points": nsl.K,
                     "definition": "Definition 1: the smallest error of the outcomes with a resource at most r, at "
                                   "K log-spaced resources from the smallest to the largest"
                                   + ("" if row["envelope"] == "step" else "; the law was fitted to the envelope "
                                      "interpolated in log-log between its outcomes"),
                     "r": row["envelope_r"], "e": row["envelope_e"]},
        "objective": {"name": row["objective"], "how_fitted": context["how_fitted"]},
        "margin": {"M": row["margin"], "on_fitted_envelope": row["fit_margin"],
                   "by_b": {int(b): m for b, m in json.loads(row["margins_by_b"]).items()}},
        "b_why": why_b(row, nsl),
        "intervals": ({"resamples": row["bootstrap"], "draw": nsl.bootstrap_draw, "level": nsl.bootstrap_level,
                       "kind": nsl.bootstrap_interval,
                       **{name: {"value": row.get(name), "lo": row.get(f"{name}_lo"), "hi": row.get(f"{name}_hi")}
                          for name in names}} if row.get("bootstrap") else None),
        "backtest": {"fitted_below": row["backtest_cut"], "M_above": row["backtest_margin"],
                     "L_over_E_at_max": row["backtest_final_ratio"]},
        "published": ({name.removeprefix("paper_"): value for name, value in row.items() if name.startswith("paper_")}
                      if row.get("paper_b") is not None else None),
        "planted": ({name.removeprefix("planted_"): value for name, value in row.items()
                     if name.startswith("planted_")} if row.get("planted_formula") is not None else None),
        "core_hours": context["core_hours"],
        "provenance": provenance,
    }


def why_b(row: Mapping[str, Any], nsl: Nsl) -> str:
    """Why the law has its number of breaks, in one sentence."""
    if nsl.breaks is not None:
        return f"b fixed at {nsl.breaks} (nsl.breaks)"
    margins = ", ".join(f"b={b}: {m:.3g}" for b, m in sorted(json.loads(row["margins_by_b"]).items()))
    return (f"b={row['b']} of 0..{nsl.max_breaks}: the most breaks whose every segment stands on at least "
            f"{nsl.min_segment_points} outcomes of the envelope and each of which cuts the margin (without the "
            f"{nsl.choice_trim:.0%} of envelope points the law fits worst) by {nsl.min_gain:.0%} or more; "
            f"the best margin on the fitted envelope by b: {margins}")


def core_hours(sweep_dir: Path, launch: LaunchSettings, results: pa.Table) -> dict[str, Any]:
    """Core-hours of the merged tasks: predicted (each task's share as recorded when it was submitted last, as
    status reads it; a task never submitted to SLURM: the planner's lockstep groups of those, as launch plans)
    and measured (their rows' wall seconds, a group's shared among its tasks)."""
    merged = set(results["task_id"].to_pylist())
    recorded = predicted_shares(read_submissions(sweep_dir))
    tasks = [task for task in read_manifest(sweep_dir).to_pylist() if task["task_id"] in merged]
    unrecorded = [task for task in tasks if task["task_id"] not in recorded]
    groups = launch.groups(unrecorded) if unrecorded else []
    predicted = sum(recorded[task["task_id"]] for task in tasks if task["task_id"] in recorded)
    measured = (float(np.nansum(results["wall_seconds"].to_numpy(zero_copy_only=False).astype(float))) / 3600
                if "wall_seconds" in results.column_names else None)
    return {"tasks": len(tasks), "predicted": (predicted + sum(group.seconds for group in groups)) / 3600,
            "measured": measured}


def strict_json(value: Any) -> Any:
    """``value`` with what strict JSON has no number for spelt out: a non-finite float as "inf", "-inf" or
    "nan" (a planted law's ln alpha of an alpha of 0), numpy scalars as Python ones."""
    if isinstance(value, Mapping):
        return {str(key): strict_json(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [strict_json(item) for item in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


def write_cards(sweep_dir: Path, rows: Sequence[Mapping[str, Any]], context: Mapping[str, Any], nsl: Nsl
                ) -> list[Path]:
    """Write each row's card (atomically), remove cards of laws the fit no longer has; returns the paths."""
    paths = []
    for row in rows:
        path = card_path(sweep_dir, row)
        write_text(json.dumps(strict_json(law_card(row, context, nsl)), indent=1, allow_nan=False) + "\n", path)
        paths.append(path)
    for stale in set((Path(sweep_dir) / layout.LAW_CARDS).glob("*.json")) - set(paths):
        stale.unlink(missing_ok=True)
    return paths


def write_law_cards(sweep_dir: Path, launch: LaunchSettings, nsl: Nsl, results: pa.Table,
                    rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Write the cards of a fit's ``rows`` (fit and report write them beside nsl_fits.parquet); returns what
    they share (sweep_context)."""
    context = sweep_context(launch, nsl, core_hours(sweep_dir, launch, results))
    write_cards(sweep_dir, rows, context, nsl)
    return context
