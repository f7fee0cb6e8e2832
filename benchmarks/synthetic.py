"""A full-size sweep directory without training: the manifest of a real grid and one row per task with
made-up errors that follow a power law in compute. For benchmarking status, merge and fitting at scale."""

import multiprocessing
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from nsl_hpc.sweep.failures import record_failure
from nsl_hpc.sweep.launch_settings import launch_settings
from nsl_hpc.sweep.layout import row_path
from nsl_hpc.sweep.manifest import read_launch_config, read_manifest
from nsl_hpc.sweep.plan import lockstep_groups
from nsl_hpc.sweep.rows import write_rows_atomically


def synthetic_row(task: dict, rng: np.random.Generator) -> dict:
    """A row as a task writes it, with nMAE ~ 2 c^-0.15 scattered upwards (c: flops)."""
    nmae = 2.0 * task["flops"] ** -0.15 * (1 + rng.exponential(0.5))
    return {**task, "batch_size": 256, "lr": 1e-3, "nmae": nmae, "nmse": nmae**2, "final_loss": nmae,
            "status": "ok", "train_seconds": 1.0, "wall_seconds": 2.0, "package_version": "synthetic",
            "torch_version": "", "python_version": "", "host": "synthetic"}


def write_rows(sweep_dir: str, groups: Sequence[Sequence[dict]]) -> None:
    """Each group's rows as its job writes them: one file that each task's path names."""
    rng = np.random.default_rng(int(groups[0][0]["task_id"][:8], 16))
    for group in groups:
        write_rows_atomically([synthetic_row(task, rng) for task in group],
                              [row_path(sweep_dir, task["task_id"]) for task in group])


def fill_sweep(sweep_dir: Path, failed_fraction: float = 0.03, processes: int = 2) -> tuple[int, int]:
    """Write a row for all but ``failed_fraction`` of the manifest's tasks, in the lockstep groups the launch
    planned, and a failure record for the rest (alternately failed and frozen); returns (rows, failures)."""
    tasks = read_manifest(sweep_dir).to_pylist()
    failing = set(range(0, len(tasks), round(1 / failed_fraction))) if failed_fraction else set()
    done = [task for index, task in enumerate(tasks) if index not in failing]
    groups = lockstep_groups(done, launch_settings(read_launch_config(sweep_dir)).grouping)
    chunks = [groups[start:start + 64] for start in range(0, len(groups), 64)]
    with multiprocessing.Pool(processes) as pool:
        pool.starmap(write_rows, [(str(sweep_dir), chunk) for chunk in chunks])
    for n, index in enumerate(sorted(failing)):
        record_failure(sweep_dir, tasks[index]["task_id"], ("failed", "frozen")[n % 2], "synthetic")
    return len(done), len(failing)


def corrupt_rows(sweep_dir: Path, count: int) -> list[Path]:
    """Replace ``count`` row files by their first half (half-written shards; a file of its own, not a change of
    the file its group's other paths name)."""
    paths = sorted((Path(sweep_dir) / "rows").glob("*/*.parquet"))[:count]
    for path in paths:
        data = path.read_bytes()
        path.unlink()
        path.write_bytes(data[: len(data) // 2])
    return paths



def synthetic_input_state_sweep(sweep_dir: Path) -> Path:
    """The input-state grid's manifest (a dry-run launch) in ``sweep_dir``, not yet filled."""
    from nsl_hpc.config import compose_config
    from nsl_hpc.sweep.launch_settings import check_run_settings
    from nsl_hpc.sweep.prepare import build_sweep, prepare_sweep

    overrides = ["+sweep=input_state", f"sweep_dir={sweep_dir}", "dry_run=true"]
    cfg = compose_config(overrides, "launch")
    sweep_dir.mkdir(parents=True)
    return prepare_sweep(build_sweep(check_run_settings(cfg), overrides), sweep_dir).sweep_dir
