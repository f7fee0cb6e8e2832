"""Sweep-machinery benchmark: prints figures, asserts nothing.

    python benchmarks/sweep_bench.py [--skip-slurm]

1. Expanding the 63,504-task input-state grid and writing its manifest (target < 5 s).
2. Submitting a 5,184-task sweep to the local SLURM cluster, held so nothing runs, then cancelled:
   client time per 1,000 tasks, unpacked (one array element per task) and packed (target < 1 s).
   Cancelled jobs count against MaxJobCount until MinJobAge (600 s on cluster/) purges them: run it on
   an idle cluster, not twice within 10 minutes.
3. `status` on the 63,504-task sweep with 97% of rows written and 3% failure records (target < 5 s).
"""

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from omegaconf import OmegaConf
from synthetic import fill_sweep

from nsl_hpc.bench.measure import timed
from nsl_hpc.config import compose_config
from nsl_hpc.launch import main as launch
from nsl_hpc.status import summary
from nsl_hpc.sweep.launch_settings import check_run_settings
from nsl_hpc.sweep.prepare import build_sweep, prepare_sweep
from nsl_hpc.sweep.submissions import read_submissions
from nsl_hpc.sweep.task_states import read_sweep_state

INPUT_STATE = ["+sweep=input_state"]
# 9 (system, arch) x 8 seeds x 9 data tiers x 4 width tiers x 2 depth tiers at 2 epochs = 5,184 tasks.
SUBMISSION_GRID = [*INPUT_STATE, "sweep.grid.seed=[0,1,2,3,4,5,6,7]", "sweep.grid.epochs=[2]", "launcher=slurm",
                   "launcher.hold=true"]


def bench_expansion(root: Path) -> Path:
    overrides = [*INPUT_STATE, f"sweep_dir={root / 'input_state'}", "dry_run=true"]
    cfg, compose_s = timed(compose_config, overrides, "launch")
    prepared, prepare_s = timed(lambda: prepare_sweep(build_sweep(check_run_settings(cfg), overrides),
                                                      Path(cfg.sweep_dir)))
    print(f"expansion: {prepared.manifest.num_rows:,} tasks, configs composed in {compose_s:.2f} s, grid expanded "
          f"and manifest written in {prepare_s:.2f} s (target 5 s)")
    return prepared.sweep_dir


def bench_submission(root: Path, packed: bool) -> None:
    name = "packed" if packed else "unpacked"
    overrides = [*SUBMISSION_GRID, f"sweep_dir={root / name}", f"packing.enabled={str(packed).lower()}"]
    cfg = compose_config(overrides, "launch")
    try:
        _, seconds = timed(launch, cfg, overrides)
    finally:  # the arrays are held: cancel them whatever happened
        records = read_submissions(root / name)
        if records:
            subprocess.run(["scancel", *(record["array_id"] for record in records)], check=True)
    tasks = sum(len(task_ids) for record in records for task_ids in record["elements"])
    print(f"submission ({name}): {tasks:,} tasks in {len(records)} arrays, {seconds:.2f} s client time "
          f"(manifest, plan, sbatch), {1000 * seconds / tasks:.2f} s per 1,000 tasks (target 1 s)")


def bench_status(sweep_dir: Path) -> None:
    (rows, failures), fill_s = timed(fill_sweep, sweep_dir)
    print(f"status: wrote {rows:,} synthetic rows and {failures:,} failure records in {fill_s:.0f} s")
    cfg = compose_config([f"sweep_dir={sweep_dir}"], "status")
    state, read_s = timed(read_sweep_state, sweep_dir)
    _, summary_s = timed(summary, state, OmegaConf.to_container(compose_config([*INPUT_STATE], "launch").cost))
    started = time.perf_counter()
    subprocess.run([sys.executable, "-m", "nsl_hpc.status", f"sweep_dir={cfg.sweep_dir}"], check=True,
                   capture_output=True)
    print(f"status: sweep state read in {read_s:.2f} s, summary in {summary_s:.2f} s; the whole "
          f"`python -m nsl_hpc.status` command {time.perf_counter() - started:.2f} s (target 5 s)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--skip-slurm", action="store_true", help="no submission benchmark (no cluster here)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        sweep_dir = bench_expansion(root)
        if not args.skip_slurm:
            bench_submission(root, packed=False)
            bench_submission(root, packed=True)
        bench_status(sweep_dir)


if __name__ == "__main__":
    main()
