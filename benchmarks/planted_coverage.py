"""How often the fits' 90% intervals hold a rehearsal's planted compute laws, over fresh draws of its outcomes.

    .venv/bin/python benchmarks/planted_coverage.py runs/rehearsals/input_state runs/rehearsals/input_output \\
        --replicates 4 --variants "nsl.bootstrap_draw=replacement" "" [--near-sd 0.05]

A rehearsal (docs/operations.md) draws each task's scores from the planted laws once, so its count of planted
laws inside the intervals is one draw. Here every (system, arch) of the merged rehearsal sweeps keeps its ok
tasks' computes (flops) and draws their scores afresh ``--replicates`` times (the rehearsal's own rule,
``rehearsal.drawn_scores``, seeded by replicate, sweep, pair and task; ``--near-sd``: the best tasks scattered
above the law instead of on it); each compute law of a planted metric is fitted as ``nsl_hpc.fit`` fits it
(without the backtest), once per variant (``nsl.*`` overrides on the fit config). Per variant: the laws whose
last slope, whose L at the largest compute and whose both lie inside their intervals, and the median of
|L / planted - 1| at the largest compute and of the L interval's width (hi / lo - 1).
"""

import argparse
import shlex
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from nsl_hpc.analysis.fitting import fit_one, fittable, pair_outcomes, read_results, rehearsal_of
from nsl_hpc.analysis.nsl_settings import nsl_settings
from nsl_hpc.config import compose_config
from nsl_hpc.core.seeding import stable_seed
from nsl_hpc.sweep.launch_settings import launch_settings
from nsl_hpc.sweep.manifest import read_launch_config
from nsl_hpc.sweep.rehearsal import drawn_scores


def redrawn_laws(sweep_dir: Path, replicates: int, near_sd: float | None) -> list[tuple]:
    """Per replicate, pair and planted metric: (key, r, e, rehearse), fit_one's arguments but the settings
    (``near_sd``: the near tasks' scatter in place of the rehearsal's ``rehearse.near_sd``)."""
    rehearse = rehearsal_of(launch_settings(read_launch_config(sweep_dir)))
    if rehearse is None:
        raise SystemExit(f"{sweep_dir} is not a rehearsal (launch ... rehearsal=true)")
    if near_sd is not None:
        rehearse = replace(rehearse, near_sd=near_sd)
    results = read_results(sweep_dir)
    laws = []
    for system, arch in sorted(set(zip(results["system"].to_pylist(), results["arch"].to_pylist(), strict=True))):
        pair = pair_outcomes(results, system, arch)
        r = pair["flops"].to_numpy().astype(float)[fittable(pair, "flops", "nmae")]
        for replicate in range(replicates):
            drawn = [drawn_scores(rehearse, c, np.random.default_rng(
                stable_seed("coverage", replicate, sweep_dir.name, system, arch, i))) for i, c in enumerate(r)]
            for metric in rehearse.laws:
                e = np.array([scores[metric] for scores in drawn])
                key = {"system": system, "arch": arch, "resource": "compute", "metric": metric}
                laws.append((key, r, e, rehearse))
    return laws


def inside(rows: Sequence[dict]) -> str:
    """How many fitted laws hold the planted one inside both intervals, of how many."""
    both = sum(row["planted_recovered"] for row in rows)
    return f"{both} of {len(rows)} ({both / len(rows):.0%})"


def summary(rows: list[dict], sweeps: list[str]) -> str:
    """A table row's cells: slope, L and both inside (all, then per sweep), median offset and L interval width,
    each over the laws that could be fitted."""
    fitted, sweeps = zip(*[(row, sweep) for row, sweep in zip(rows, sweeps, strict=True) if row["error"] is None],
                         strict=True)
    slope = [row["last_slope_lo"] <= row["planted_last_slope"] <= row["last_slope_hi"] for row in fitted]
    value = [row["L_at_max_lo"] <= row["planted_L_at_max"] <= row["L_at_max_hi"] for row in fitted]
    off = np.median([abs(row["L_at_max"] / row["planted_L_at_max"] - 1) for row in fitted])
    width = np.median([row["L_at_max_hi"] / row["L_at_max_lo"] - 1 for row in fitted])
    n = len(fitted)
    per_sweep = " | ".join(inside([row for row, sweep in zip(fitted, sweeps, strict=True) if sweep == name])
                           for name in dict.fromkeys(sweeps))
    return (f"{sum(slope)} of {n} ({sum(slope) / n:.0%}) | {sum(value)} ({sum(value) / n:.0%}) | {inside(fitted)} | "
            f"{per_sweep} | {off:.2%} | {width:.2%}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sweeps", nargs="+", type=Path, help="merged rehearsal sweep directories")
    parser.add_argument("--replicates", type=int, default=4, help="fresh draws of every pair's outcomes")
    parser.add_argument("--variants", nargs="+", default=[""],
                        help="fit settings, each a space-separated list of nsl.* overrides ('' the defaults)")
    parser.add_argument("--near-sd", type=float, default=None,
                        help="the near tasks' log(e / L) = |N(0, near_sd)| (default: the rehearsal's, 0: on the law)")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    drawn = {sweep.name: redrawn_laws(sweep, args.replicates, args.near_sd) for sweep in args.sweeps}
    laws = [law for sweep_laws in drawn.values() for law in sweep_laws]
    sweeps = [name for name, sweep_laws in drawn.items() for _ in sweep_laws]
    print(f"{len(laws)} laws: {len(laws) // args.replicates} per draw, {args.replicates} draws\n")
    print("| fit settings | last slope inside | L at the largest compute inside | both | "
          + " | ".join(f"both: {name}" for name in drawn) + " | median abs(L / planted - 1) | median L interval width "
          "(hi / lo - 1) | s |")
    print("|---" * (7 + len(drawn)) + "|")
    for variant in args.variants:
        overrides = shlex.split(variant)
        nsl = nsl_settings(compose_config([f"sweep_dir={args.sweeps[0]}", *overrides], "fit").nsl)
        start = time.perf_counter()
        with ProcessPoolExecutor(args.workers) as pool:
            rows = list(pool.map(fit_one, *zip(*[(key, r, e, 0, nsl, "c", rehearse, False)
                                                 for key, r, e, rehearse in laws], strict=True)))
        print(f"| {variant or 'defaults'} | {summary(rows, sweeps)} | {time.perf_counter() - start:.0f} |", flush=True)


if __name__ == "__main__":
    main()
