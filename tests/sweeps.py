"""Running the sweep commands as a user would, on tiny grids."""

import os
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq

# 4 tasks: one system, one architecture, 4 seeds, 2 epochs on ~150 points.
TINY_GRID = ["+sweep=demo", "sweep.grid.system=[spring]", "sweep.grid.arch=[input_affine]", "sweep.grid.epochs=[2]",
             "sweep.grid.data_tier=[2]", "sweep.grid.width_tier=[4]", "sweep.grid.seed=[0,1,2,3]"]


# Faults strike a whole lockstep group; the tests of per-task faults train every task alone.
ALONE = "lockstep.enabled=false"


def nsl(verb: str, *args: str, timeout: float = 600, cwd: Path | None = None,
        umask: int | None = None) -> subprocess.CompletedProcess:
    """``python -m nsl_hpc.<verb> args...`` (in ``cwd``, with ``umask``)."""
    return subprocess.run([sys.executable, "-m", f"nsl_hpc.{verb}", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd, preexec_fn=None if umask is None else lambda: os.umask(umask))


def row_files(sweep_dir: Path) -> list[Path]:
    return sorted((sweep_dir / "rows").glob("*/*.parquet"))


def manifest_ids(sweep_dir: Path) -> list[str]:
    return pq.read_table(sweep_dir / "manifest.parquet", columns=["task_id"])["task_id"].to_pylist()
