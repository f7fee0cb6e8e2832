"""Running the sweep commands as a user would, on tiny grids."""

import os
import subprocess
from pathlib import Path

import pyarrow.parquet as pq

from tests import preloaded

# 4 tasks: one system, one architecture, 4 seeds, 2 epochs on ~150 points.
TINY_GRID = ["+sweep=demo", "sweep.grid.system=[spring]", "sweep.grid.arch=[input_affine]", "sweep.grid.epochs=[2]",
             "sweep.grid.data_tier=[2]", "sweep.grid.width_tier=[4]", "sweep.grid.seed=[0,1,2,3]"]


# Faults strike a whole lockstep group; the tests of per-task faults train every task alone.
ALONE = "lockstep.enabled=false"


# A launch that names no cache_dir simulates into the trajectory cache of the test session (tests/conftest.py sets
# it, one per xdist worker), not into its sweep directory's: a system's test set is simulated once per worker, not
# once per sweep (3 s of CPU for spring). The cache is keyed by what it holds; the tests of the sweep's own cache
# name it.
SHARED_CACHE = "NSL_TESTS_TRAJECTORY_CACHE"
OWN_CACHE = "cache_dir=${sweep_dir}/cache"  # launch.yaml's default


# A local launch (launch.yaml's default launcher) that names no launcher.workers runs on one worker: each worker is a
# process of its own that imports torch (3 s of CPU), and a test's sweep trains for a second or two. The tests of
# several workers name them.
ONE_WORKER = "launcher.workers=1"
OWN_WORKERS = ("launcher=slurm", "launcher=debug", "launcher.workers=")  # a launch with one of these keeps its own


def nsl(verb: str, *args: str, timeout: float = 600, cwd: Path | None = None,
        umask: int | None = None) -> subprocess.CompletedProcess:
    """``python -m nsl_hpc.<verb> args...`` (in ``cwd``, with ``umask``), forked from a process that has imported
    its libraries (tests/preloaded.py); a launch into the session's cache, a local one on one worker."""
    if verb == "launch" and SHARED_CACHE in os.environ and not any(arg.startswith("cache_dir=") for arg in args):
        args = (*args, f"cache_dir={os.environ[SHARED_CACHE]}")
    if verb == "launch" and not any(arg.startswith(OWN_WORKERS) for arg in args):
        args = (*args, ONE_WORKER)
    return preloaded.run(f"nsl_hpc.{verb}", args, timeout=timeout, cwd=cwd, umask=umask)


def row_files(sweep_dir: Path) -> list[Path]:
    return sorted((sweep_dir / "rows").glob("*/*.parquet"))


def manifest_ids(sweep_dir: Path) -> list[str]:
    return pq.read_table(sweep_dir / "manifest.parquet", columns=["task_id"])["task_id"].to_pylist()
