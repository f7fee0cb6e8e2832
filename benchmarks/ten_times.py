"""The input-state study at its size and at ten times it, side by side: launch's plan and submission, status and
merge, on a sweep written as a real one would be. Prints figures, asserts nothing.

    python benchmarks/ten_times.py --root runs/ten_times [--scales 1 10]

Scale 10 is 635,040 tasks: 70 seeds, not 7 (the width, depth and data tiers are those the study's systems
have). Each scale is launched on the
SLURM cluster its commands find (`cluster/up.sh`) with every job held (`launcher.hold=true`: the queue holds its
arrays as a real sweep's, nothing runs), then filled as its jobs would have left it: a row for 97% of the tasks
(each lockstep group the launch planned writes one file of its rows, which each task's path names) and a failure
record for the rest. Then, each timed as its command: status (the queue's held jobs, every row file checked) and
status again (the files it read before), merge (reading and compacting every row), status and merge again (the
rows compacted), then the arrays are cancelled. Cancelled jobs count against MaxJobCount until
MinJobAge (600 s on cluster/): on this machine's cluster, leave 10 minutes before running it again.
"""

import argparse
import subprocess
import sys
import time
from pathlib import Path

from commands import timed_command
from synthetic import fill_sweep

from nsl_hpc.sweep.layout import MANIFEST, SUBMISSIONS
from nsl_hpc.sweep.submissions import read_submissions

STUDY = ["+sweep=input_state", "launcher=slurm", "launcher.hold=true"]
SCALES = {1: [], 10: ["sweep.grid.seed=[" + ",".join(map(str, range(70))) + "]", "max_tasks=1000000"]}


def size_mib(path: Path) -> float:
    files = [path] if path.is_file() else [file for file in path.rglob("*") if file.is_file()]
    return sum(file.stat().st_size for file in files) / 2**20


def measure(scale: int, root: Path) -> dict[str, str]:
    sweep_dir = root / f"x{scale}"
    out, plan_s, _ = timed_command("nsl_hpc.launch", *STUDY, *SCALES[scale], f"sweep_dir={sweep_dir}",
                                   "dry_run=true")
    tasks = next(line for line in out.splitlines() if " tasks, " in line).split(": ", 1)[1].split(" tasks")[0]
    jobs = next(line.strip() for line in out.splitlines() if line.strip().startswith("jobs: ")).split(" (")[0]
    out, launch_s, launch_gib = timed_command("nsl_hpc.launch", *STUDY, *SCALES[scale], f"sweep_dir={sweep_dir}")
    try:
        arrays = len(read_submissions(sweep_dir))
        started = time.perf_counter()
        rows, failures = fill_sweep(sweep_dir)
        fill_s = time.perf_counter() - started
        _, status_s, status_gib = timed_command("nsl_hpc.status", f"sweep_dir={sweep_dir}")
        _, status_read_s, _ = timed_command("nsl_hpc.status", f"sweep_dir={sweep_dir}")
        merged, merge_s, merge_gib = timed_command("nsl_hpc.merge", f"sweep_dir={sweep_dir}")
        _, status_again_s, _ = timed_command("nsl_hpc.status", f"sweep_dir={sweep_dir}")
        _, merge_again_s, _ = timed_command("nsl_hpc.merge", f"sweep_dir={sweep_dir}")
    finally:  # held jobs: cancel them whatever happened
        subprocess.run(["scancel", *(record["array_id"] for record in read_submissions(sweep_dir))], check=False)
        subprocess.run(["scancel", "-n", "nsl-input_state-feed"], check=False)  # where the job limits held some back
    return {
        "tasks; jobs": f"{tasks}; {jobs.removeprefix('jobs: ')}",
        "launch's plan (dry run) / plan and submit (held)": f"{plan_s:.1f} s / {launch_s:.1f} s ({arrays} arrays)",
        "manifest; submission records": f"{size_mib(sweep_dir / MANIFEST):.1f} MiB; "
                                        f"{size_mib(sweep_dir / SUBMISSIONS):.1f} MiB",
        "rows and failure records written (not timed as a target)": f"{rows:,} and {failures:,} in {fill_s:.0f} s",
        "status: the rows in their groups' files, first look / again (files read before) / rows compacted":
            f"{status_s:.1f} s / {status_read_s:.1f} s / {status_again_s:.1f} s",
        "merge: first, compacting the rows / again": f"{merge_s:.1f} s / {merge_again_s:.1f} s",
        "merge says": merged.splitlines()[0] if merged else "",
        "peak memory of launch / status / merge":
            f"{launch_gib:.2f} / {status_gib:.2f} / {merge_gib:.2f} GiB",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", type=Path, required=True, help="a new directory: one sweep_dir per scale in it")
    parser.add_argument("--scales", nargs="+", type=int, choices=sorted(SCALES), default=sorted(SCALES))
    args = parser.parse_args()
    if args.root.exists() and any(args.root.iterdir()):
        sys.exit(f"--root {args.root} is not empty: measure into a new directory")
    results = {f"x{scale}": measure(scale, args.root) for scale in args.scales}
    print("| | " + " | ".join(results) + " |\n|---|" + "---|" * len(results))
    for key in next(iter(results.values())):
        print(f"| {key} | " + " | ".join(result[key] for result in results.values()) + " |")


if __name__ == "__main__":
    main()
