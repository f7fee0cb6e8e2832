"""Replay a budget's rounds on a finished full sweep, without training: what the rule (nsl_hpc/sweep/budget.py)
would run, and its envelopes and fits against the full sweep's; or (``--oracle``) what a chooser that knew every
outcome would need.

    python benchmarks/budget_replay.py FULL_SWEEP_DIR +sweep=repro 'repro.seeds=[0]' sweep.max_flops=3e8 \\
        budget.share=0.2 [--goal 1.15] [--laws] [--no-fits]
    python benchmarks/budget_replay.py FULL_SWEEP_DIR +sweep=repro 'repro.seeds=[0]' sweep.max_flops=3e8 --oracle

The overrides are the launch's: those of the full sweep, plus a budget. A task's outcome depends only on its
config and seed, so a budgeted sweep's rows are the full sweep's rows of the tasks it runs: each round is decided
by the rule's own code (``next_round``) from the full sweep's rows of the tasks run before it, in seconds instead
of a sweep's minutes. With lockstep packing a row may differ from the full sweep's in its last digits (the
groups differ), so a real budgeted run can decide a close call differently. Prints markdown: the rounds, one line
per resource (the range of the laws' median and largest envelope ratios, the share of points within ``--goal``,
the last slopes inside the full fits' 90% intervals) and, with ``--laws``, every law. Where the budget tracks its
laws (``budget.track_laws``, on by default; ``budget.stop_when``) each round's laws are fitted as the launch fits
them, and a table says, per law, after which round and at what share of the prediction it was first decided
against the full fit (analysis/widths.py ``decided``).

``--oracle``: the cheapest tasks a chooser that knew every outcome would run to bring every law within 1.15x,
1.5x and 2x of the full envelope at all its K points (exact, by integer programming over the tasks' predicted
seconds alone), and the planner's prediction for them as a share of the whole sweep's: a floor under what any rule
can reach with a budget on this grid.
"""

import argparse
import math
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from budget_comparison import fitted, law_ratios, law_rows, round_rows, summary_rows, task_seconds
from scipy import sparse
from scipy.optimize import Bounds, LinearConstraint, milp

from nsl_hpc.analysis.broken_law import lower_envelope
from nsl_hpc.analysis.fitting import fit_sweep, fittable, nsl_key, pair_outcomes
from nsl_hpc.analysis.nsl_settings import nsl_settings
from nsl_hpc.analysis.widths import decided, law_state, widths_of
from nsl_hpc.config import compose_config, plain
from nsl_hpc.config.schema import typed
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.sweep.budget import WIDTHS, Budget, BudgetSettings, budget_of, stopped_resources
from nsl_hpc.sweep.launch_settings import check_run_settings, planned_seconds
from nsl_hpc.sweep.prepare import build_sweep
from nsl_hpc.sweep.rounds import Rounds, first_round_levels, next_round

OracleLaw = tuple[list[str], np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # ids, resources, errors, grid, full


def sweep_of(full: pa.Table, overrides: list[str]) -> tuple[Any, Any, dict[str, dict], Callable]:
    """(launch config, study, manifest by task id, the planner's seconds of any of its tasks) of ``overrides``,
    whose every task must have a row in ``full``."""
    cfg = compose_config(overrides, "launch")
    built = build_sweep(check_run_settings(cfg), overrides)
    manifest = {task["task_id"]: task for task in built.manifest.to_pylist()}
    if missing := len(set(manifest) - set(full["task_id"].to_pylist())):
        raise ConfigError(f"{missing:,} of the {len(manifest):,} tasks of these overrides have no row in the full "
                          "sweep: give the full sweep's own overrides")
    return cfg, built.study, manifest, planned_seconds(manifest, built.settings)


def replay(full: pa.Table, overrides: list[str]) -> tuple[list[dict], list[dict], Budget]:
    """The decisions of every round of the budget in ``overrides`` on the rows of ``full`` (a results table); where
    the budget tracks its laws (``budget.track_laws``, ``budget.stop_when``), the laws as the launch fits them on
    the rows of the rounds so far, after each round (``round``, ``committed_s``: predicted seconds committed,
    ``fits``), which also stop spending on a resource as the launch would; and the budget."""
    cfg, study, manifest, planned_s = sweep_of(full, overrides)
    ok = full.filter(pc.equal(full["status"], "ok"))
    rows = {row["task_id"]: row for row in ok.to_pylist()}
    nsl = nsl_settings(cfg.nsl)
    columns = {name: resource.column for name, resource in nsl.resources.items()}
    budget = budget_of(typed(BudgetSettings, cfg.budget, "budget"), planned_s(list(manifest)),
                       list(columns.values()), list(nsl.metrics))
    if budget is None:
        raise ConfigError("give a budget below the whole sweep: budget.share=<0..1) or budget.core_hours=<B>")
    tasks = list(manifest.values())
    rounds = Rounds(tasks, study, first_round_levels(tasks, study, budget, planned_s), budget.settings.levels_per_round)
    decisions: list[dict] = []
    states: list[dict] = []
    state: list[dict] = []
    for number in range(1, rounds.count + 2):  # and the laws after the last round
        stopped: set[str] = set()
        if number > 1 and budget.track_laws:
            ran = pa.array(sorted(d["task_id"] for d in decisions if d["run"]), pa.string())
            fits = fit_sweep(ok.filter(pc.is_in(ok["task_id"], value_set=ran)), nsl, None, backtest=False)
            states.append({"round": number - 1, "committed_s": sum(d["cost_s"] for d in decisions), "fits": fits})
            state = law_state(fits, state)
            stopped = stopped_resources(state, budget.settings.stop_when, columns)
        if number <= rounds.count:
            decisions += next_round(number, rounds, manifest, decisions, rows, planned_s, budget, stopped)
    return decisions, states, budget


def decided_lines(states: Sequence[dict], full_fits: Sequence[dict], budget: Budget) -> list[str]:
    """Per law of the full fits, the round after which the budgeted law is first decided against it
    (analysis/widths.py ``decided``) and the share of the planner's prediction for the whole sweep committed by
    then, whether it still is after the last round, and its widths then; a line per resource above."""
    laws = []
    for full in full_fits:
        key = nsl_key(full)
        after = [next((fit for fit in state["fits"] if nsl_key(fit) == key), None) for state in states]
        first = next((i for i, fit in enumerate(after) if decided(fit, full)), None)
        widths = widths_of(after[-1]) if after and after[-1] else dict.fromkeys(WIDTHS, math.inf)
        laws.append({"key": key, "resource": full["resource"],
                     "round": states[first]["round"] if first is not None else None,
                     "share": states[first]["committed_s"] / budget.full_seconds if first is not None else None,
                     "end": bool(after) and decided(after[-1], full), "widths": widths})
    spent = states[-1]["committed_s"] / budget.full_seconds if states else 0.0
    lines = [f"laws decided (last slope, breaks, L at 10x the full sweep's largest resource inside the full fit's "
             f"90% intervals); the rule committed {spent:.1%} of the prediction in all\n",
             "| resource | decided at some round | still after the last | share of the prediction when first decided: "
             "median (range) |", "|---|---:|---:|---|"]
    for resource in dict.fromkeys(law["resource"] for law in laws):
        own = [law for law in laws if law["resource"] == resource]
        shares = sorted(law["share"] for law in own if law["share"] is not None)
        spread = (f"{shares[len(shares) // 2]:.1%} ({shares[0]:.1%}-{shares[-1]:.1%})" if shares else "-")
        lines.append(f"| {resource} | {len(shares)} of {len(own)} | {sum(law['end'] for law in own)} | {spread} |")
    lines += ["\n| law | first decided after round | share then | still after the last | widths after the last: "
              "last slope, breaks, prediction |", "|---|---:|---:|---|---|"]
    for law in laws:
        w, share = law["widths"], "-" if law["share"] is None else format(law["share"], ".1%")
        lines.append(f"| {law['key']} | {law['round'] or '-'} | {share} | {'yes' if law['end'] else 'no'} "
                     f"| {w['last_slope']:.3g}, {w['breaks']:.3g}x, {w['prediction']:.3g}x |")
    return lines


def oracle_laws(full: pa.Table, full_fits: Sequence[dict], nsl: dict, manifest: dict[str, dict]) -> list[OracleLaw]:
    """Per law of the full fits: the ids, resources and errors of the manifest's tasks with a fittable outcome,
    and the full envelope at its K points."""
    columns = {name: spec["column"] for name, spec in nsl["resources"].items()}
    full = full.filter(pc.is_in(full["task_id"], value_set=pa.array(sorted(manifest), pa.string())))
    laws = []
    for fit in full_fits:
        subset = pair_outcomes(full, fit["system"], fit["arch"])
        keep = fittable(subset, columns[fit["resource"]], fit["metric"])
        resources = subset[columns[fit["resource"]]].to_numpy().astype(float)[keep]
        errors = subset[fit["metric"]].to_numpy().astype(float)[keep]
        grid, envelope = lower_envelope(resources, errors, nsl["K"])
        laws.append(([t for t, k in zip(subset["task_id"].to_pylist(), keep, strict=True) if k], resources, errors,
                     grid, envelope))
    return laws


def oracle(laws: Sequence[OracleLaw], costs: dict[str, float], goal: float) -> list[str]:
    """The cheapest set of tasks (each priced at ``costs``, its predicted seconds run alone) whose outcomes bring
    every law within ``goal`` of the full envelope at each of its points: a task covers a point when its resource
    is at most the point's and its error at most ``goal`` x the full envelope there. Exact, by integer programming
    (scipy's HiGHS)."""
    ids = sorted(costs)
    column = {task_id: j for j, task_id in enumerate(ids)}
    covers = []
    for law_ids, resources, errors, grid, full in laws:
        covering = (resources[None, :] <= grid[:, None]) & (errors[None, :] <= goal * full[:, None])  # (K, tasks)
        columns = np.array([column[task_id] for task_id in law_ids])
        covers += [columns[row] for row in covering]
    matrix = sparse.lil_matrix((len(covers), len(ids)))
    for i, row in enumerate(covers):
        matrix[i, row] = 1.0
    result = milp(np.array([costs[task_id] for task_id in ids]), integrality=np.ones(len(ids)), bounds=Bounds(0, 1),
                  constraints=LinearConstraint(matrix.tocsr(), lb=1.0, ub=np.inf))
    if not result.success:
        raise RuntimeError(f"the oracle's integer program failed: {result.message}")
    return [ids[j] for j in np.flatnonzero(result.x > 0.5)]


def oracle_lines(full: pa.Table, full_fits: Sequence[dict], nsl: dict, overrides: list[str]) -> list[str]:
    """The ``oracle``'s tasks at goals 1.15, 1.5 and 2: their predicted seconds as a share of the whole sweep's,
    priced alone (what it minimises) and run together as one launch (lockstep groups: less), and where the 1.15x
    one's tasks sit on the length axis."""
    _, study, manifest, planned_s = sweep_of(full, overrides)
    laws = oracle_laws(full, full_fits, nsl, manifest)
    costs = {task_id: planned_s([task_id]) for task_id in manifest}
    whole = planned_s(list(manifest))
    lines = ["| goal | tasks | share of the prediction: priced alone (least) | run as one launch |",
             "|---:|---:|---:|---:|"]
    picks: dict[float, list[str]] = {}
    for goal in (1.15, 1.5, 2.0):
        picks[goal] = oracle(laws, costs, goal)
        alone = sum(costs[task_id] for task_id in picks[goal])
        lines.append(f"| {goal}x | {len(picks[goal]):,} | {alone / whole:.1%} | {planned_s(picks[goal]) / whole:.1%} |")
    axis = study.length_axis
    counts = Counter(manifest[task_id][axis] for task_id in picks[1.15])
    lines.append(f"\n1.15x: tasks by {axis}: " + ", ".join(f"{value}: {n}" for value, n in sorted(counts.items())))
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("full", type=Path, help="a finished full sweep's directory (merged and fitted first where "
                                                "it is not yet)")
    parser.add_argument("overrides", nargs="+", help="the launch's overrides (a budget among them unless --oracle)")
    parser.add_argument("--goal", type=float, default=1.15, help="the envelope ratio the budget should stay within")
    parser.add_argument("--laws", action="store_true", help="print every law's line as well")
    parser.add_argument("--no-fits", action="store_true", help="envelopes only (no bootstrap fits: seconds)")
    parser.add_argument("--oracle", action="store_true", help="what a chooser that knew every outcome would need")
    args = parser.parse_args()
    full, full_fits = fitted(args.full)
    fit_cfg = compose_config([f"sweep_dir={args.full}"], "fit")
    nsl = plain(fit_cfg.nsl)
    if args.oracle:
        print("\n".join(oracle_lines(full, full_fits, nsl, args.overrides)))
        return
    decisions, states, budget = replay(full, args.overrides)
    ran = sorted(d["task_id"] for d in decisions if d["run"])
    budgeted = full.filter(pc.is_in(full["task_id"], value_set=pa.array(ran, pa.string())))
    seconds = task_seconds(full)
    trained = sum(seconds[task_id] for task_id in ran) / 3600
    total = float(np.nansum(full["train_seconds"].to_numpy(zero_copy_only=False))) / 3600
    print(f"replayed: {len(ran):,} of {full.num_rows:,} tasks run, trained core-hours (in the full sweep) "
          f"{trained:.3f} of {total:.3f} ({trained / total:.0%})\n")
    print("\n".join(round_rows(decisions, seconds)) + "\n")
    budgeted_fits = [] if args.no_fits else fit_sweep(budgeted, nsl_settings(fit_cfg.nsl), None)
    laws = law_ratios(full, full_fits, budgeted, budgeted_fits, nsl)
    print("\n".join(summary_rows(laws, args.goal, fits=not args.no_fits)))
    if states:
        print("\n" + "\n".join(decided_lines(states, full_fits, budget)))
    if args.laws:
        print("\n" + "\n".join(law_rows(laws, args.goal)))


if __name__ == "__main__":
    main()
