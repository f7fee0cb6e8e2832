"""Remove from a sweep directory what finished tasks no longer need: submitit's pickles and logs of jobs
whose tasks all have a row, stale failure records and logs of tasks that succeeded since, stale training
checkpoints (of groups whose tasks all have a row, or that are not in the manifest) and group locks no job
renews, and the temporaries of atomic writes whose writer was killed (``.<name>.<random>.tmp`` not written to
for 2 minutes). Rows, the manifest, the sweep's configs, the checkpoints of groups still to finish and the failure
records and logs of tasks without a row are kept, as are the files of jobs still pending or running, whatever
the paths are set to. The simulated-data cache's entries go once every task has a row (or, in a budgeted sweep,
was skipped), and so does the compiled-step cache when it lies inside the sweep directory (one shared with other
sweeps is left alone).

    python -m nsl_hpc.clean sweep_dir=runs/input_state dry_run=true    # list what would go
    python -m nsl_hpc.clean sweep_dir=runs/input_state

The dry run lists every path the real run removes (a folder with a trailing /: it goes with its content).
"""

import contextlib
import re
import shutil
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from omegaconf import DictConfig

from nsl_hpc import cli
from nsl_hpc.core.atomic import TEMPORARY, leftover_temporaries
from nsl_hpc.core.checkpoint import info_path
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.directory import process_alive, sweep_lock
from nsl_hpc.sweep.groups import STALE_S, lock_path, saved_groups
from nsl_hpc.sweep.layout import failure_path, task_log_path
from nsl_hpc.sweep.manifest import read_launch_config, require_sweep
from nsl_hpc.sweep.slurm import ACTIVE_JOB_STATES
from nsl_hpc.sweep.submissions import read_submissions
from nsl_hpc.sweep.task_states import read_sweep_state

ENTRY = re.compile(r"[0-9a-f]{32}\.npz")  # an ArrayCache entry's name


def finished_slurm_job_files(sweep_dir: Path, done: set[str], element_states: dict[str, str]) -> Iterator[Path]:
    """submitit's files of array elements that are no longer active and whose tasks all have a row."""
    for record in read_submissions(sweep_dir):
        folder = sweep_dir / layout.SUBMITIT / record["array_id"]
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
    for folder in layout.local_jobs_folder(sweep_dir).glob("*"):
        if not (folder.name.isdigit() and process_alive(int(folder.name))):
            yield folder


def stale_failure_files(sweep_dir: Path, done: set[str], failed: set[str]) -> Iterator[Path]:
    """Failure records and logs of tasks that have a row now."""
    for task_id in failed & done:
        yield failure_path(sweep_dir, task_id)
        yield task_log_path(sweep_dir, task_id)


def stale_checkpoint_files(sweep_dir: Path, done: set[str], known: set[str]) -> Iterator[Path]:
    """Checkpoints (with their descriptions and locks) of groups whose tasks all have a row or are not in the
    manifest, and locks not renewed for ``STALE_S`` (their job is gone)."""
    finished = [saved.path for saved in saved_groups(sweep_dir)
                if all(task_id in done or task_id not in known for task_id in saved.task_ids)]
    for path in finished:
        yield from (path, info_path(path), lock_path(path))
    finished_locks = {lock_path(path) for path in finished}
    for lock in (sweep_dir / layout.CHECKPOINTS).glob("*/*.lock"):
        with contextlib.suppress(FileNotFoundError):
            if lock not in finished_locks and time.time() - lock.stat().st_mtime > STALE_S:
                yield lock


def cache_entries(cache_dir: Path) -> Iterator[Path]:
    """The entries of an ``ArrayCache`` (``<root>/<2 hex>/<32 hex>.npz``), their folders once emptied and the
    root once nothing else is in it: only what the cache itself wrote, whatever else shares its root."""
    emptied = set()
    for folder in sorted(cache_dir.glob("[0-9a-f][0-9a-f]")):
        entries = [path for path in folder.glob("*.npz") if ENTRY.fullmatch(path.name)]
        yield from entries
        if folder.is_dir() and set(folder.iterdir()) == set(entries):
            emptied.add(folder)
            yield folder
    if cache_dir.is_dir() and set(cache_dir.iterdir()) == emptied:
        yield cache_dir


def protected(sweep_dir: Path, done: set[str]) -> Callable[[Path], bool]:
    """Whether removing a path would touch what clean must keep: rows, the manifest, configs, launch and run
    settings, results, reports, set-aside rows, and the failure records and logs of tasks without a row."""
    kept = [sweep_dir / name for name in layout.RECORDS]

    def check(path: Path) -> bool:
        if TEMPORARY.fullmatch(path.name):  # a killed writer's half-written file, wherever it is, is no record
            return False
        if any(path == keep or keep.is_relative_to(path) or path.is_relative_to(keep) for keep in kept):
            return True
        if path.parent.parent.name in (layout.FAILURES, layout.LOGS) and path.parents[2] == sweep_dir:
            return path.stem not in done
        return False

    return check


def size_bytes(path: Path) -> int:
    if path.is_dir():
        return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    return path.stat().st_size if path.exists() else 0


def remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def doomed_paths(sweep_dir: Path) -> tuple[list[Path], int, int]:
    """What clean removes, and how many tasks have a row and how many do not."""
    state = read_sweep_state(sweep_dir)
    done = {task_id for task_id, status in state.states.items() if status == "done"}
    doomed = [*finished_slurm_job_files(sweep_dir, done, state.element_states),
              *finished_local_job_files(sweep_dir), *stale_failure_files(sweep_dir, done, set(state.failures)),
              *stale_checkpoint_files(sweep_dir, done, set(state.states)), *leftover_temporaries(sweep_dir, STALE_S)]
    settled = done | {task_id for task_id, status in state.states.items() if status == "skipped"}
    if len(settled) == len(state.states):  # every task has a row, or a budget decided not to run it
        launch = read_launch_config(sweep_dir)
        doomed += cache_entries(Path(launch["cache_dir"]))
        if launch.get("compile_cache_dir") and Path(launch["compile_cache_dir"]).resolve().is_relative_to(sweep_dir):
            doomed.append(Path(launch["compile_cache_dir"]).resolve())
    keep = protected(sweep_dir, done)
    return [path for path in doomed if path.exists() and not keep(path)], len(done), len(state.states) - len(done)


def main(cfg: DictConfig) -> int:
    sweep_dir = require_sweep(cfg.sweep_dir).resolve()
    with sweep_lock(sweep_dir, "clean"):
        doomed, done, kept = doomed_paths(sweep_dir)
        freed = sum(size_bytes(path) for path in doomed)
        if cfg.dry_run:
            for path in doomed:
                print(f"{path}{'/' if path.is_dir() else ''}")
        else:
            for path in doomed:
                remove(path)
    verb = "would remove" if cfg.dry_run else "removed"
    print(f"{verb} {len(doomed):,} files and folders ({freed / 2**20:.1f} MiB); {done:,} rows kept, "
          f"{kept:,} tasks without a row keep their records and logs")
    return 0


if __name__ == "__main__":
    cli.run(main, __doc__, config_name="clean")
