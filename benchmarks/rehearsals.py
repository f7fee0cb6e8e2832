"""Both studies rehearsed back to back through a SLURM cluster, each step timed: prints figures, asserts nothing.

    python benchmarks/rehearsals.py --root runs/rehearsals [--studies input_state input_output] [--look-s 20]

For each study: launch (`rehearsal=true`, launcher=slurm), status every --look-s seconds until no job runs or waits
(each call timed), resubmit what the planted faults and the killed job left, status again, merge twice (compacting,
then again), fit every law with its bootstrap, and the counts that account for every task. The cluster is the one
SLURM's commands find (`cluster/up.sh`: this machine's). docs/operations.md states the figures.
"""

import argparse
import re
import statistics
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
from commands import timed_command

STUDIES = {"input_state": "+sweep=input_state", "input_output": "+sweep=input_output",
           "demo": "+sweep=demo"}  # the demo's 216 tasks: a check of this script in a minute
ACTIVE = re.compile(r"running ([\d,]+) \| pending ([\d,]+)")


def watch(sweep_dir: Path, look_s: float) -> tuple[float, list[float], str]:
    """Status every ``look_s`` s until no task runs or waits in the queue: seconds until then, each status call's
    seconds, its last output."""
    started, calls = time.perf_counter(), []
    while True:
        out, seconds, _ = timed_command("nsl_hpc.status", f"sweep_dir={sweep_dir}")
        calls.append(seconds)
        running, pending = (int(value.replace(",", "")) for value in ACTIVE.search(out).groups())
        if not running and not pending:
            return time.perf_counter() - started, calls, out
        time.sleep(look_s)


def files(sweep_dir: Path) -> int:
    return sum(1 for path in sweep_dir.rglob("*") if path.is_file())


def rehearse(study: str, root: Path, look_s: float) -> dict[str, str]:
    sweep_dir = root / study
    started = time.perf_counter()
    out, launch_s, _ = timed_command("nsl_hpc.launch", STUDIES[study], "launcher=slurm", "rehearsal=true",
                            f"sweep_dir={sweep_dir}")
    tasks = re.search(r"([\d,]+) tasks", out).group(1)
    jobs = re.search(r"submitted ([\d,]+) jobs in (\d+) arrays", out)
    jobs_s, calls, _ = watch(sweep_dir, look_s)
    out, resubmit_s, _ = timed_command("nsl_hpc.resubmit", f"sweep_dir={sweep_dir}")
    again = re.search(r"submitted ([\d,]+) jobs", out)
    rerun_s, more_calls, last = watch(sweep_dir, look_s)
    calls += more_calls
    merged, merge_s, _ = timed_command("nsl_hpc.merge", f"sweep_dir={sweep_dir}")
    _, merge_again_s, _ = timed_command("nsl_hpc.merge", f"sweep_dir={sweep_dir}")
    _, fit_s, _ = timed_command("nsl_hpc.fit", f"sweep_dir={sweep_dir}")
    total_s = time.perf_counter() - started
    fits = pq.read_table(sweep_dir / "nsl_fits.parquet").to_pylist()
    planted = [row for row in fits if row.get("planted_formula") is not None]
    dropped = pq.read_table(sweep_dir / "dropped.parquet").to_pylist()
    by_state = {state: sum(row["state"] == state for row in dropped) for state in ("frozen", "failed")}
    return {
        "tasks; jobs (arrays)": f"{tasks}; {jobs.group(1)} ({jobs.group(2)})",
        "launch: plan and submit": f"{launch_s:.1f} s",
        "the jobs, to the last one's end": f"{jobs_s / 60:.1f} min",
        "resubmit: its jobs; to their end": f"{resubmit_s:.1f} s, {again.group(1) if again else 0} jobs; "
                                            f"{rerun_s / 60:.1f} min",
        f"status every {look_s:g} s while jobs run: median / max (calls over 5 s)":
            f"{statistics.median(calls):.1f} s / {max(calls):.1f} s ({sum(c > 5 for c in calls)} of {len(calls)})",
        "last status": last.splitlines()[0],
        "merge: first, compacting the rows / again": f"{merge_s:.1f} s / {merge_again_s:.1f} s",
        "merge says": next(line for line in merged.splitlines() if " dropped" in line),
        "the sweep's files at the end": f"{files(sweep_dir):,}",
        "fit: every law, with its bootstrap and law cards": f"{fit_s:.0f} s ({len(fits)} laws)",
        "end to end": f"{total_s / 60:.1f} min",
        "dropped, each named in dropped.parquet": f"{len(dropped):,}: {by_state['frozen']:,} frozen, "
                                                  f"{by_state['failed']:,} failed",
        "planted compute laws recovered": f"{sum(bool(row.get('planted_recovered')) for row in planted)} of "
                                          f"{len(planted)}",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", type=Path, required=True, help="a new directory: one sweep_dir per study in it")
    parser.add_argument("--studies", nargs="+", choices=list(STUDIES), default=["input_state", "input_output"])
    parser.add_argument("--look-s", type=float, default=20.0, help="seconds between status calls")
    args = parser.parse_args()
    if args.root.exists() and any(args.root.iterdir()):
        sys.exit(f"--root {args.root} is not empty: rehearse into a new directory")
    started = time.perf_counter()
    results = {}
    for study in args.studies:
        results[study] = rehearse(study, args.root, args.look_s)
        print(f"{study}: " + "; ".join(f"{key}: {value}" for key, value in results[study].items()), flush=True)
    print("| | " + " | ".join(results) + " |\n|---|" + "---|" * len(results))
    for key in next(iter(results.values())):
        print(f"| {key} | " + " | ".join(result[key] for result in results.values()) + " |")
    print(f"both, back to back: {(time.perf_counter() - started) / 60:.1f} min")


if __name__ == "__main__":
    main()
