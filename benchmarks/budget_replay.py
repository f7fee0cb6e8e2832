"""Replay a budget's rounds on a finished full sweep, without training: what the rule (nsl_hpc/sweep/budget.py)
would run, and what its envelopes and fits would be against the full sweep's.

    python benchmarks/budget_replay.py FULL_SWEEP_DIR +sweep=repro 'repro.seeds=[0]' sweep.max_flops=3e8 \\
        budget.share=0.2 [--goal 1.15] [--no-fits]

The overrides are the launch's (those of the full sweep plus a budget). A task's outcome depends only on its
config and seed, so a budgeted sweep's rows are the full sweep's rows of the tasks it runs: each round is decided
by the rule's own code (``next_round``) from the full sweep's rows of the tasks run before it, in seconds instead
of a sweep's minutes. With lockstep packing a row may differ from the full sweep's in its last digits (the
groups differ), so a real budgeted run can decide a close call differently. Prints markdown: the rounds, one line
per resource (the range of the laws' median and largest envelope ratios, the share of points within ``--goal``,
the last slopes inside the full fits' 90% intervals) and, with ``--laws``, every law.
"""

import argparse
from collections import defaultdict
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from budget_comparison import fitted, law_ratios, law_rows, summary_rows

from nsl_hpc.analysis.fitting import fit_sweep
from nsl_hpc.config import compose_config, plain
from nsl_hpc.errors import ConfigError
from nsl_hpc.sweep.budget import Rounds, budget_of, first_round_levels, next_round, planned_seconds
from nsl_hpc.sweep.prepare import build_sweep


def replay(full, overrides: list[str]) -> tuple[list[dict], dict[str, float]]:
    """The decisions of every round of the budget in ``overrides`` on the rows of ``full`` (a results table), and
    each run task's trained seconds in the full sweep."""
    cfg = compose_config(overrides, "launch")
    built = build_sweep(cfg, overrides)
    manifest = {task["task_id"]: task for task in built.manifest.to_pylist()}
    ok = full.filter(pc.equal(full["status"], "ok")).to_pylist()
    rows = {row["task_id"]: row for row in ok}
    if missing := len(set(manifest) - {row["task_id"] for row in full.to_pylist()}):
        raise ConfigError(f"{missing:,} of the {len(manifest):,} tasks of these overrides have no row in the full "
                          "sweep: give the full sweep's own overrides (and a budget)")
    planned_s = planned_seconds(manifest, cfg)
    budget = budget_of(cfg, planned_s(list(manifest)))
    if budget is None:
        raise ConfigError("give a budget below the whole sweep: budget.share=<0..1) or budget.core_hours=<B>")
    tasks = list(manifest.values())
    rounds = Rounds(tasks, built.study, first_round_levels(tasks, built.study, budget, planned_s),
                    budget.levels_per_round)
    decisions: list[dict] = []
    for number in range(1, rounds.count + 1):
        decisions += next_round(number, rounds, manifest, decisions, rows, planned_s, budget)
    return decisions, {task_id: float(row["train_seconds"]) for task_id, row in rows.items()}


def round_lines(decisions: list[dict], seconds: dict[str, float]) -> list[str]:
    by_round: dict[int, list[dict]] = defaultdict(list)
    for decision in decisions:
        by_round[decision["round"]].append(decision)
    lines = ["| round | run of candidates | predicted / trained core-hours |", "|---:|---:|---:|"]
    for number, chosen in sorted(by_round.items()):
        run = [d for d in chosen if d["run"]]
        lines.append(f"| {number} | {len(run):,} of {len(chosen):,} | {sum(d['cost_s'] for d in run) / 3600:.3f} / "
                     f"{sum(seconds[d['task_id']] for d in run) / 3600:.3f} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("full", help="a finished full sweep's directory (merged and fitted where it is not yet)")
    parser.add_argument("overrides", nargs="+", help="the launch's overrides, a budget among them")
    parser.add_argument("--goal", type=float, default=1.15, help="the envelope ratio the budget should stay within")
    parser.add_argument("--laws", action="store_true", help="print every law's line as well")
    parser.add_argument("--no-fits", action="store_true", help="envelopes only (no bootstrap fits: seconds)")
    args = parser.parse_args()
    full, full_fits = fitted(Path(args.full))
    decisions, seconds = replay(full, args.overrides)
    ran = sorted(d["task_id"] for d in decisions if d["run"])
    budgeted = full.filter(pc.is_in(full["task_id"], value_set=pa.array(ran, pa.string())))
    fit_cfg = compose_config([f"sweep_dir={args.full}"], "fit")
    nsl = plain(fit_cfg.nsl)
    budgeted_fits = [] if args.no_fits else fit_sweep(budgeted, fit_cfg.nsl, None)
    trained = sum(seconds.get(task_id, 0.0) for task_id in ran) / 3600
    total = float(np.nansum(full["train_seconds"].to_numpy(zero_copy_only=False))) / 3600
    print(f"replayed: {len(ran):,} of {full.num_rows:,} tasks run, trained core-hours {trained:.3f} of {total:.3f} "
          f"({trained / total:.0%})\n")
    print("\n".join(round_lines(decisions, seconds)) + "\n")
    ratios = law_ratios(full, full_fits, budgeted, budgeted_fits, nsl)
    print("\n".join(summary_rows(ratios, args.goal, fits=not args.no_fits)))
    if args.laws:
        print("\n" + "\n".join(law_rows(ratios, args.goal)))


if __name__ == "__main__":
    main()
