"""A budgeted sweep against the full sweep of the same grid: per fitted law, the budgeted envelope over the full
one, and the budgeted last slope against the full fit's interval; per round, the tasks kept and their cost.

    python benchmarks/budget_comparison.py FULL_SWEEP_DIR BUDGETED_SWEEP_DIR [--goal 1.15]

Both directories are merged and fitted first where they have no fits (``python -m nsl_hpc.merge`` and
``python -m nsl_hpc.fit``, the fits with their bootstrap intervals). The envelopes are Definition 1's step
envelopes at the K = ``nsl.K`` log-spaced points over the full sweep's resource range. Prints markdown.
"""

import argparse
import subprocess
import sys
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from nsl_hpc.analysis.broken_law import lower_envelope
from nsl_hpc.analysis.fitting import fittable, pair_outcomes
from nsl_hpc.config import compose_config, plain
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.decisions import read_decisions


def fitted(sweep_dir: Path) -> tuple:
    """(results, fits) of a sweep, merging and fitting it first where needed."""
    if not (sweep_dir / layout.FITS).exists():
        for verb in ("merge", "fit"):
            subprocess.run([sys.executable, "-m", f"nsl_hpc.{verb}", f"sweep_dir={sweep_dir}"], check=True)
    return pq.read_table(sweep_dir / layout.RESULTS), pq.read_table(sweep_dir / layout.FITS).to_pylist()


def envelope_at(results, system: str, arch: str, column: str, metric: str, grid: np.ndarray) -> np.ndarray:
    """The step envelope of a sweep's outcomes at the resources ``grid`` (inf below its smallest outcome)."""
    subset = pair_outcomes(results, system, arch)
    keep = fittable(subset, column, metric)
    r = subset[column].to_numpy().astype(float)[keep]
    e = subset[metric].to_numpy().astype(float)[keep]
    order = np.argsort(r)
    r, e = r[order], np.minimum.accumulate(e[order])
    index = np.searchsorted(r, grid, side="right") - 1
    return np.where(index >= 0, e[np.maximum(index, 0)], np.inf)


def law_ratios(full, full_fits, budgeted, budgeted_fits, nsl: dict) -> list[dict]:
    """Per law of the full sweep's fits: its key (system, arch, resource, metric), the budgeted envelope over the
    full one at the full sweep's K envelope points (``ratio``), the budgeted fit's last slope (nan without one)
    and the full fit's with its 90% interval."""
    columns = {name: spec["column"] for name, spec in nsl["resources"].items()}
    by_key = {(f["system"], f["arch"], f["resource"], f["metric"]): f for f in budgeted_fits}
    laws = []
    for fit in full_fits:
        key = (fit["system"], fit["arch"], fit["resource"], fit["metric"])
        column = columns[fit["resource"]]
        subset = pair_outcomes(full, fit["system"], fit["arch"])
        keep = fittable(subset, column, fit["metric"])
        grid, full_envelope = lower_envelope(subset[column].to_numpy().astype(float)[keep],
                                             subset[fit["metric"]].to_numpy().astype(float)[keep], nsl["K"])
        other = by_key.get(key)
        laws.append({"key": key, "ratio": envelope_at(budgeted, *key[:2], column, fit["metric"], grid) / full_envelope,
                     "slope": other["last_slope"] if other else float("nan"), "full_slope": fit["last_slope"],
                     "low": fit.get("last_slope_lo", np.nan), "high": fit.get("last_slope_hi", np.nan)})
    return laws


def inside(law: dict) -> bool:
    return bool(law["low"] <= law["slope"] <= law["high"])


def law_rows(laws: list[dict], goal: float) -> list[str]:
    lines = [f"| law | budgeted / full envelope: largest (median) | points within {goal}x | last slope budgeted | "
             "full (90% interval) | inside |", "|---|---:|---:|---:|---:|---|"]
    for law in laws:
        ratio = law["ratio"]
        lines.append(f"| {' / '.join(law['key'])} | {np.max(ratio):.2f} ({np.median(ratio):.2f}) | "
                     f"{np.mean(ratio <= goal):.0%} | {law['slope']:.2f} | {law['full_slope']:.2f} "
                     f"({law['low']:.2f} .. {law['high']:.2f}) | {'yes' if inside(law) else 'no'} |")
    return lines


def summary_rows(laws: list[dict], goal: float, fits: bool = True) -> list[str]:
    """One line per resource: the range of its laws' median and largest ratios, the mean share of points within
    ``goal`` and (``fits``) how many last slopes lie inside the full fits' intervals."""
    lines = [f"| resource | median | largest | within {goal}x |" + (" slopes inside |" if fits else ""),
             "|---|---|---|---:|" + ("---:|" if fits else "")]
    for resource in dict.fromkeys(law["key"][2] for law in laws):
        of = [law for law in laws if law["key"][2] == resource]
        medians = [float(np.median(law["ratio"])) for law in of]
        largest = [float(np.max(law["ratio"])) for law in of]
        within = np.mean([np.mean(law["ratio"] <= goal) for law in of])
        lines.append(f"| {resource} | {min(medians):.2f}-{max(medians):.2f} | {min(largest):.2f}-{max(largest):.2f} "
                     f"| {within:.0%} |" + (f" {sum(map(inside, of))}/{len(of)} |" if fits else ""))
    return lines


def task_seconds(results) -> dict[str, float]:
    """Task id -> its trained seconds (``train_seconds``) in a results table."""
    return dict(zip(results["task_id"].to_pylist(), results["train_seconds"].to_pylist(), strict=True))


def round_rows(decisions: list[dict], seconds: dict[str, float]) -> list[str]:
    """Per round of ``decisions``: its tasks, those run, those skipped and why, and the run ones' predicted and
    trained (``seconds``) core-hours."""
    rounds: dict[int, list[dict]] = defaultdict(list)
    for decision in decisions:
        rounds[decision["round"]].append(decision)
    lines = ["| round | tasks | run | skipped (why) | predicted core-hours | trained core-hours |",
             "|---:|---:|---:|---|---:|---:|"]
    for number, decisions in sorted(rounds.items()):
        run = [d for d in decisions if d["run"]]
        why = Counter(d["reason"] for d in decisions if not d["run"])
        lines.append(f"| {number} | {len(decisions):,} | {len(run):,} | {sum(why.values()):,}"
                     + (f" ({', '.join(f'{n:,} {reason}' for reason, n in sorted(why.items()))})" if why else "")
                     + f" | {sum(d['cost_s'] for d in run) / 3600:.3f} | "
                     f"{sum(seconds.get(d['task_id'], 0.0) for d in run) / 3600:.3f} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("full", type=Path)
    parser.add_argument("budgeted", type=Path)
    parser.add_argument("--goal", type=float, default=1.15, help="the envelope ratio the budget should stay within")
    args = parser.parse_args()
    nsl = plain(compose_config([f"sweep_dir={args.full}"], "fit").nsl)
    full, full_fits = fitted(args.full)
    budgeted, budgeted_fits = fitted(args.budgeted)
    trained = {name: float(np.nansum(table["train_seconds"].to_numpy(zero_copy_only=False))) / 3600
               for name, table in (("full", full), ("budgeted", budgeted))}
    print(f"Tasks with a row: full {full.num_rows:,}, budgeted {budgeted.num_rows:,}; trained core-hours: full "
          f"{trained['full']:.3f}, budgeted {trained['budgeted']:.3f} ({trained['budgeted'] / trained['full']:.0%})\n")
    laws = law_ratios(full, full_fits, budgeted, budgeted_fits, nsl)
    print("\n".join(summary_rows(laws, args.goal)) + "\n")
    print("\n".join(law_rows(laws, args.goal)) + "\n")
    print("\n".join(round_rows(read_decisions(args.budgeted), task_seconds(budgeted))))


if __name__ == "__main__":
    main()
