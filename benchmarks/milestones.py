"""Epoch milestones against separate runs, with the default warm-up + cosine schedule: prints figures.

    python benchmarks/milestones.py [--seeds 4] [--epochs 2,4,...,256]

Runs one small input-state grid twice with the local launcher and shared draws (tasks that differ only in
epochs are the same model): every task alone, and with train.schedule_epochs = the largest epoch count (one
run per model, a row after each epoch count). Prints,
per epoch count, the median over tasks of nMAE (milestone row / separate row) and the steps both trained:
what a milestone row means is "this model after n_e of the largest run's epochs", not "trained for n_e".
"""

import argparse
import subprocess
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

import numpy as np

from nsl_hpc.sweep.rows import read_row

GRID = ["+sweep=demo", "sweep.grid.system=[spring]", "sweep.grid.arch=[port_hamiltonian,input_affine]",
        "sweep.grid.data_tier=[32]", "sweep.grid.width_tier=[8]", "sweep.grid.depth_tier=[2]", "launcher=local",
        "draws=shared_across_epochs"]


def sweep_rows(sweep_dir: Path, overrides: list[str]) -> dict[tuple, dict]:
    """Launch the grid into ``sweep_dir``; its rows by (arch, seed, epochs)."""
    subprocess.run([sys.executable, "-m", "nsl_hpc.launch", *GRID, *overrides, f"sweep_dir={sweep_dir}"],
                   check=True, capture_output=True)
    rows = [read_row(path) for path in sorted((sweep_dir / "rows").glob("*/*.parquet"))]
    return {(row["arch"], row["seed"], row["epochs"]): row for row in rows}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--epochs", default="2,4,8,16,32,64,128,256")
    args = parser.parse_args()
    epochs = [int(value) for value in args.epochs.split(",")]
    grid = [f"sweep.grid.seed=[{','.join(map(str, range(args.seeds)))}]", f"sweep.grid.epochs=[{args.epochs}]"]
    with tempfile.TemporaryDirectory() as folder:
        separate = sweep_rows(Path(folder) / "separate", grid)
        milestones = sweep_rows(Path(folder) / "milestones", [*grid, f"train.schedule_epochs={max(epochs)}"])
    ratios = defaultdict(list)
    seconds = {"separate": 0.0, "milestones": 0.0}
    for key, row in separate.items():
        ratios[key[2]].append(milestones[key]["nmae"] / row["nmae"])
        seconds["separate"] += row["train_seconds"]
        seconds["milestones"] += milestones[key]["train_seconds"]
    print(f"{len(separate)} tasks (spring; port_hamiltonian, input_affine; n_h~8, n_d~2, d~32; {args.seeds} seeds), "
          f"warm-up + cosine; training seconds: separate {seconds['separate']:.1f}, milestones "
          f"{seconds['milestones']:.1f}")
    print("| n_e | median nMAE milestone / separate | range |")
    print("|---:|---:|---|")
    for n_e in epochs:
        values = np.array(ratios[n_e])
        print(f"| {n_e} | {np.median(values):.3f} | {values.min():.3f} - {values.max():.3f} |")


if __name__ == "__main__":
    main()
