"""Remove from a sweep directory what finished tasks no longer need: submitit's pickles and logs of jobs
whose tasks all have a row, and stale failure records and logs of tasks that succeeded since. Rows, the
manifest, the sweep's configs and the failure records and logs of tasks without a row are kept, as are
the files of jobs still pending or running. The simulated-data cache goes once every task has a row.

    python -m nsl_hpc.clean sweep_dir=runs/input_state [dry_run=true]
"""

import os
import shutil
import sys
from collections.abc import Iterator
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from nsl_hpc import cli
from nsl_hpc.failures import failure_path, task_log_path
from nsl_hpc.manifest import LAUNCH_CONFIG_FILE, require_sweep
from nsl_hpc.submissions import read_submissions
from nsl_hpc.sweep_state import ACTIVE_JOB_STATES, read_sweep_state


def finished_slurm_job_files(sweep_dir: Path, done: set[str], element_states: dict[str, str]) -> Iterator[Path]:
    """submitit's files of array elements that are no longer active and whose tasks all have a row."""
    for record in read_submissions(sweep_dir):
        folder = sweep_dir / "submitit" / record["array_id"]
        finished = [element for element, task_ids in zip(record["element_ids"], record["elements"], strict=True)
                    if element_states.get(element) not in ACTIVE_JOB_STATES and set(task_ids) <= done]
        if len(finished) == len(record["element_ids"]):
            yield folder  # the whole array: its submission script too
            continue
        for element in finished:
            yield from folder.glob(f"{element}_*")


def finished_local_job_files(sweep_dir: Path) -> Iterator[Path]:
    """Folders of local jobs whose process has ended (a local job's id is its pid) and of debug jobs
    (they ran inside a launch that has returned)."""
    for folder in (sweep_dir / "submitit" / "local").glob("*"):
        if not (folder.name.isdigit() and process_alive(int(folder.name))):
            yield folder


def process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def stale_failure_files(sweep_dir: Path, done: set[str], failed: set[str]) -> Iterator[Path]:
    """Failure records and logs of tasks that have a row now."""
    for task_id in failed & done:
        yield failure_path(sweep_dir, task_id)
        yield task_log_path(sweep_dir, task_id)


def size_bytes(path: Path) -> int:
    if path.is_dir():
        return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    return path.stat().st_size if path.exists() else 0


def remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def main(cfg: DictConfig) -> int:
    sweep_dir = require_sweep(cfg.sweep_dir)
    state = read_sweep_state(sweep_dir)
    done = {task_id for task_id, status in state.states.items() if status == "done"}
    doomed = [*finished_slurm_job_files(sweep_dir, done, state.element_states),
              *finished_local_job_files(sweep_dir), *stale_failure_files(sweep_dir, done, set(state.failures))]
    cache_dir = Path(OmegaConf.load(sweep_dir / LAUNCH_CONFIG_FILE).cache_dir)
    if len(done) == len(state.states) and cache_dir.resolve().is_relative_to(sweep_dir.resolve()):
        doomed.append(cache_dir)  # a cache outside the sweep directory may serve other sweeps
    doomed = [path for path in doomed if path.exists()]
    freed = sum(size_bytes(path) for path in doomed)
    if not cfg.dry_run:
        for path in doomed:
            remove(path)
    verb = "would remove" if cfg.dry_run else "removed"
    kept = len(state.states) - len(done)
    print(f"{verb} {len(doomed):,} files and folders ({freed / 2**20:.1f} MiB); {len(done):,} rows kept, "
          f"{kept:,} tasks without a row keep their records and logs")
    return 0


if __name__ == "__main__":
    cli.run(main, __doc__, config_name="clean")
    sys.exit(0)
