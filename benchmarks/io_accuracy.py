"""Accuracy of well-sized NARX and SUBNET models in the input-output study: prints a table, asserts nothing.

    python benchmarks/io_accuracy.py [--data-dir data] [--workers 2]

Each line is one real task (`nsl_hpc.sweep.task.run_task`, default train config but SUBNET's lr) on the
simulated stand-ins and, where `--data-dir` holds the measured files (python -m nsl_hpc.place_data), on
Silverbox and Wiener-Hammerstein: drawn sizes, training time on one core, free-run test nMSE and RMSE in mV.
"""

import argparse
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from nsl_hpc.config import compose_config
from nsl_hpc.errors import ConfigError
from nsl_hpc.sweep.task import run_task

# (system, arch, overrides): sizes chosen to train in a few minutes on one core; SUBNET with a 3x larger
# learning rate than the default, which at these short budgets leaves it ~10x worse on Silverbox.
CASES = [(system, arch, coordinates)
         for system in ("silverbox_sim", "wiener_hammerstein_sim", "silverbox", "wiener_hammerstein")
         for arch, coordinates in (
             ("narx", {"data_tier": 8000 if "silverbox" in system else 10000, "iter_multiplier": 4,
                       "width_tier": 32, "depth": 2}),
             ("subnet", {"data_tier": 8000 if "silverbox" in system else 10000, "iter_multiplier": 1,
                         "width_tier": 32, "depth": 1, "train.lr": 3.0e-3}))]


def run_case(case: tuple, data_dir: str, root: str) -> str:
    system, arch, coordinates = case
    overrides = ["study=input_output", f"system={system}", f"arch={arch}", f"out_dir={root}/{system}-{arch}",
                 f"cache_dir={root}/cache", f"data_dir={data_dir}",
                 *(f"{key}={value}" for key, value in coordinates.items())]
    try:
        row = run_task(compose_config(overrides, "one_task")).row
    except ConfigError as error:
        return f"{system:24s} {arch:7s} skipped: {error}"
    return (f"{system:24s} {arch:7s} {row['train_points']:>6,} {row['steps']:>7,} {row['width']:>4} {row['depth']:>4} "
            f"{row['params']:>6,} {row['train_seconds']:>8.0f} {row['nmse']:>9.2e} {row['nmae']:>8.3f} "
            f"{row['rmse_mv']:>9.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data-dir", default="data", help="the measured systems' data_dir")
    parser.add_argument("--workers", type=int, default=2, help="tasks run at once (one core each)")
    args = parser.parse_args()
    print(f"{'system':24s} {'arch':7s} {'n_l':>6} {'n_i':>7} {'n_h':>4} {'n_d':>4} {'p':>6} {'train_s':>8} "
          f"{'nMSE':>9} {'nMAE':>8} {'RMSE_mV':>9}")
    with tempfile.TemporaryDirectory() as root, ProcessPoolExecutor(args.workers) as pool:
        for line in pool.map(run_case, CASES, [str(Path(args.data_dir).resolve())] * len(CASES),
                             [root] * len(CASES)):
            print(line, flush=True)


if __name__ == "__main__":
    main()
