"""Accuracy anchors of the input-output study: SUBNET on measured Silverbox and Wiener-Hammerstein, each at the
largest grid point that trains in about 20 minutes on one core, through the study's packed path; prints every
score next to the published SUBNET anchors, asserts nothing.

    python benchmarks/io_accuracy.py [--data-dir data] [--workers 2] [--lr 1e-3 3e-3]

Each line is one real task (``nsl_hpc.sweep.task.run_task``: the packed path with K = 1, scored on every test
record): drawn sizes, training time, free-run RMSE (mV) on each test record beside the anchor (Beintema,
Schoukens and Toth, Automatica 2023: Silverbox arrow full 1.41 mV, arrow without extrapolation 0.316 mV;
Wiener-Hammerstein 0.241 mV), and the row's nMAE / nMSE. ``--lr`` lists the learning rates to run (the
study's is 1e-3; the paper names no other).
"""

import argparse
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from nsl_hpc.config import compose_config
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.sweep.task import run_task

ANCHORS_MV = {"silverbox": {"arrow_full": 1.41, "arrow_no_extrapolation": 0.316}, "wiener_hammerstein": {"test": 0.241}}
# (system, grid point): m = 1 on the largest data tier whose n_i = n_l iterations at the largest width and
# depth train in about 20 minutes (0.12-0.15 s an iteration on the development machine's core).
CASES = [("silverbox", {"data_tier": 8000, "iter_multiplier": 1, "width_tier": 32, "depth": 2}),
         ("wiener_hammerstein", {"data_tier": 10000, "iter_multiplier": 1, "width_tier": 32, "depth": 3})]


def run_case(system: str, coordinates: dict, lr: float, data_dir: str, root: str) -> str:
    overrides = ["study=input_output", f"system={system}", "arch=subnet", f"out_dir={root}/{system}-{lr}",
                 f"cache_dir={root}/cache", f"data_dir={data_dir}", f"train.lr={lr}",
                 *(f"{key}={value}" for key, value in coordinates.items())]
    try:
        row = run_task(compose_config(overrides, "one_task")).row
    except ConfigError as error:
        return f"{system:18s} skipped: {error}"
    scores = "  ".join(f"{record} {row[f'rmse_mv_free_run_{record}']:.3f} (anchor {anchor})"
                       for record, anchor in ANCHORS_MV[system].items())
    others = "  ".join(f"{name.removeprefix('rmse_mv_free_run_')} {value:.3f}" for name, value in row.items()
                       if name.startswith("rmse_mv_free_run_") and name.removeprefix("rmse_mv_free_run_")
                       not in ANCHORS_MV[system])
    return (f"{system:18s} lr {lr:g}  n_l {row['train_points']:,}  n_i {row['steps']:,}  n_h {row['width']}  "
            f"n_d {row['depth']}  {row['train_seconds'] / 60:.1f} min  RMSE mV: {scores}"
            f"{'  ' + others if others else ''}  nMAE {row['nmae']:.4f} nMSE {row['nmse']:.2e}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data-dir", default="data", help="the measured systems' data_dir")
    parser.add_argument("--workers", type=int, default=2, help="tasks run at once (one core each)")
    parser.add_argument("--lr", type=float, nargs="+", default=[1e-3], help="learning rates to run")
    args = parser.parse_args()
    runs = [(system, coordinates, lr) for lr in args.lr for system, coordinates in CASES]
    with tempfile.TemporaryDirectory() as root, ProcessPoolExecutor(args.workers) as pool:
        futures = [pool.submit(run_case, *run, str(Path(args.data_dir).resolve()), root) for run in runs]
        for future in futures:
            print(future.result(), flush=True)


if __name__ == "__main__":
    main()
