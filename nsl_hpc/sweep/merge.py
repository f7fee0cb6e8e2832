"""Merging a sweep's rows into results.parquet, with an account of the tasks that have none."""


import contextlib
import json
import os
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from nsl_hpc.core.atomic import create_parquet, make_durable, read_parquet, write_parquet, write_text
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.core.progress import progress
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.decisions import read_decisions, skip_reasons
from nsl_hpc.sweep.directory import sweep_lock
from nsl_hpc.sweep.failures import FAILURE_STATES
from nsl_hpc.sweep.manifest import read_manifest
from nsl_hpc.sweep.rows import named_rows, set_aside
from nsl_hpc.sweep.task_states import read_sweep_state

SHARD_KEY = ("shard", "size", "mtime_ns")  # a cached row stands while its shard keeps this key
READ_ATTEMPTS = 3  # listings of the row files a merge reads, where files vanish under it (read_rows)
READ_CHUNK = 512  # row files a thread reads at a time (a future per file costs as much as reading it)
CACHE_FORMAT = (b"nsl_hpc.rows", b"whole")  # the cache's schema metadata: it holds every column of a row


@dataclass(frozen=True)
class MergeSummary:
    """What the merge kept and dropped (task counts) and which shards it skipped."""

    tasks: int
    merged: int
    frozen: int
    failed: int
    timeout: int
    missing: int
    diverged: int  # merged, but with non-finite errors: kept with status 'diverged', never fitted
    corrupt_shards: list[str]
    duplicate_rows: int
    unknown_rows: int
    running: int = 0  # without a row yet, but a job trains them now or a running launch will: not dropped
    skipped: int = 0  # a budgeted sweep's tasks decided not to run (not dropped: never meant to run)
    waiting: int = 0  # a budgeted sweep's tasks whose round is not decided yet (not dropped)
    skipped_reasons: dict[str, int] | None = None  # why the skipped ones were
    compacted_files: int = 0  # row files whose rows moved into rows/compacted/ (or that held copies of them)
    not_compacted: str = ""  # why rows were not compacted: the command that held the sweep

    @property
    def dropped(self) -> int:
        return self.tasks - self.merged - self.running - self.skipped - self.waiting

    def describe(self) -> str:
        share = 100 * self.dropped / self.tasks if self.tasks else 0.0
        lines = [f"{self.dropped:,} of {self.tasks:,} tasks ({share:.1f}%) dropped: {self.frozen:,} frozen, "
                 f"{self.failed:,} failed, {self.missing:,} missing"
                 + (f", {self.timeout:,} timed out" if self.timeout else "")
                 + (f" (each with its reason in {layout.DROPPED})" if self.dropped else "")]
        if self.skipped or self.waiting:
            reasons = ", ".join(f"{n:,} {why}" for why, n in sorted((self.skipped_reasons or {}).items()))
            lines.append(f"{self.skipped:,} tasks skipped by the budget" + (f" ({reasons})" if reasons else "")
                         + (f", {self.waiting:,} waiting for their round" if self.waiting else ""))
        if self.running:
            lines.append(f"{self.running:,} tasks still running or queued in a running launch: merge again once "
                         "they finish")
        if self.diverged:
            lines.append(f"{self.diverged:,} merged tasks diverged (non-finite errors): kept, not fitted")
        if self.corrupt_shards:
            lines.append(f"{len(self.corrupt_shards):,} corrupt shards moved to corrupt/ (their tasks count as "
                         "missing; resubmit runs them again): "
                         + ", ".join(self.corrupt_shards[:5]) + (" ..." if len(self.corrupt_shards) > 5 else ""))
        if self.duplicate_rows:
            lines.append(f"{self.duplicate_rows:,} duplicate rows of already merged tasks ignored")
        if self.unknown_rows:
            lines.append(f"{self.unknown_rows:,} rows of tasks outside the manifest ignored")
        if self.compacted_files:
            lines.append(f"{self.compacted_files:,} row files compacted into {layout.ROWS}/{layout.COMPACTED}/")
        if self.not_compacted:
            lines.append(f"rows not compacted: {self.not_compacted.removeprefix('sweep_dir=')}; merge again later")
        return "\n".join(lines)


def results_path(sweep_dir: Path) -> Path:
    return Path(sweep_dir) / layout.RESULTS


class Vanished(Exception):
    """A row file listed by merge was gone when read: moved by a compaction that ran meanwhile."""


def read_shards(paths: list[str], inodes: Sequence[int] | None = None) -> tuple[pa.Table, list[str]]:
    """The rows of the shards at ``paths`` (every column: what compaction keeps must be whole), with ``shard``,
    the path that names each row (``named_rows``); returns them and the unreadable shards (not Parquet).
    ``inodes`` (the listing's, one per path): the paths of one file (a group's rows, hard links) are read once.
    Each file is read on its own, a chunk of them per thread and core (a pyarrow dataset scan of small files is
    slower, and takes the first file's columns for all), and each chunk's rows are joined into one table as it is
    read (a one-row table holds ~35 KB: 616k of them at once filled this machine's 24 GB). Raises Vanished for a
    file gone meanwhile; an I/O error on a compacted file is raised, never taken for a damaged file (its rows
    would all be set aside)."""
    files: dict[int | str, list[str]] = {}
    keys: Sequence[int | str] = paths if inodes is None else inodes
    for path, key in zip(paths, keys, strict=True):
        files.setdefault(key, []).append(path)

    def read_chunk(chunk: Sequence[list[str]]) -> tuple[pa.Table | None, list[str]]:
        tables, shards, unreadable = [], [], []
        for names in chunk:
            try:
                table, named = named_rows(read_parquet(Path(names[0]), small=True), names)
                tables.append(table)
                shards += named
            except FileNotFoundError:
                raise Vanished(names[0]) from None
            except pa.ArrowInvalid:
                unreadable += names
            except OSError:
                if f"{os.sep}{layout.COMPACTED}{os.sep}" in names[0]:
                    raise
                unreadable += names
        if not tables:
            return None, unreadable
        rows = pa.concat_tables(tables, promote_options="permissive").combine_chunks()
        return rows.append_column("shard", pa.array(shards, pa.string())), unreadable

    units = list(files.values())
    with ThreadPoolExecutor(os.cpu_count()) as pool:
        chunks = list(progress(pool.map(read_chunk, [units[start:start + READ_CHUNK]
                                                     for start in range(0, len(units), READ_CHUNK)]),
                               f"reading {len(units):,} row files", "chunk", -(-len(units) // READ_CHUNK)))
    good = [table for table, _ in chunks if table is not None]
    unreadable = [path for _, bad in chunks for path in bad]
    if not good:
        return pa.table({"task_id": pa.array([], pa.string()), "shard": pa.array([], pa.string())}), unreadable
    # one chunk, not one per file: joining or sorting 63k chunks takes seconds
    return pa.concat_tables(good, promote_options="permissive").combine_chunks(), unreadable


def list_shards(sweep_dir: Path) -> pa.Table:
    """Every row file of the sweep with its SHARD_KEY (shard: path relative to the sweep dir) and inode (ino),
    sorted."""
    entries = [entry for bucket in os.scandir(Path(sweep_dir) / layout.ROWS) if bucket.is_dir()
               for entry in os.scandir(bucket.path) if entry.name.endswith(".parquet")] \
        if (Path(sweep_dir) / layout.ROWS).is_dir() else []
    stats = [entry.stat() for entry in entries]
    shards = [os.path.relpath(entry.path, sweep_dir) for entry in entries]
    table = pa.table({"shard": shards, "size": [s.st_size for s in stats],
                      "mtime_ns": [s.st_mtime_ns for s in stats], "ino": [s.st_ino for s in stats]},
                     schema=pa.schema([("shard", pa.string()), ("size", pa.int64()), ("mtime_ns", pa.int64()),
                                       ("ino", pa.uint64())]))
    return table.sort_by("shard")


def read_cache(sweep_dir: Path, shards: pa.Table) -> pa.Table | None:
    """Cached rows whose shard still has the same size and modification time (None without a cache, or with
    one of rows that are not whole: compaction writes the cached rows)."""
    try:
        cached = pq.read_table(Path(sweep_dir) / layout.MERGE_CACHE)
    except (pa.ArrowException, OSError):
        return None
    if (cached.schema.metadata or {}).get(CACHE_FORMAT[0]) != CACHE_FORMAT[1]:
        return None
    return cached.join(shards, list(SHARD_KEY), join_type="left semi")


def write_cache(sweep_dir: Path, rows: pa.Table) -> None:
    write_parquet(rows.replace_schema_metadata(dict([CACHE_FORMAT])), Path(sweep_dir) / layout.MERGE_CACHE)


def read_rows(sweep_dir: Path) -> tuple[pa.Table, list[str]]:
    """Every readable row of the sweep, whole (with its SHARD_KEY), in shard order, reading only the shards the
    cache does not hold as they are; returns the rows and the unreadable shards. Where a file vanished while
    it was read (a compaction by another merge moved it), the files are listed and read again."""
    for _ in range(READ_ATTEMPTS - 1):
        with contextlib.suppress(Vanished):
            return read_rows_once(sweep_dir)
    return read_rows_once(sweep_dir)


def read_rows_once(sweep_dir: Path) -> tuple[pa.Table, list[str]]:
    shards = list_shards(sweep_dir)
    cached = read_cache(sweep_dir, shards)
    unread = shards if cached is None else shards.join(cached.select(list(SHARD_KEY)), list(SHARD_KEY),
                                                       join_type="left anti")
    unread_paths = [os.path.join(sweep_dir, shard) for shard in unread["shard"].to_pylist()]
    new, corrupt = read_shards(unread_paths, unread["ino"].to_pylist())
    relative = {path: shard for path, shard in zip(unread_paths, unread["shard"].to_pylist(), strict=True)}
    new = new.set_column(new.schema.get_field_index("shard"), "shard",
                         pa.array([relative[path] for path in new["shard"].to_pylist()], pa.string()))
    new = new.join(shards.select(list(SHARD_KEY)), "shard", join_type="inner")  # add size and mtime_ns
    rows = new if cached is None else pa.concat_tables([cached, new], promote_options="permissive")
    rows = rows.combine_chunks().sort_by("shard")  # one chunk per shard would make every later step slow
    return rows, [relative[path] for path in corrupt]


def compact_rows(sweep_dir: Path, rows: pa.Table, task_ids: pa.ChunkedArray) -> tuple[pa.Table, int]:
    """Move the rows of ``task_ids`` that are in their own files into one new file of rows/compacted/ (written
    and synced to disk before their files are removed: sweep/rows.py), and remove the own files of tasks a
    compacted file holds already (copies an interrupted compaction left). ``rows``: read_rows's. Returns
    ``rows`` with their new SHARD_KEY, and how many files were removed."""
    prefix = f"{layout.ROWS}/{layout.COMPACTED}/"
    ids, shards = rows["task_id"].to_pylist(), rows["shard"].to_pylist()
    in_parts = {task_id for task_id, shard in zip(ids, shards, strict=True) if shard.startswith(prefix)}
    known = set(task_ids.to_pylist())
    own = [not shard.startswith(prefix) and os.path.basename(shard) == f"{task_id}.parquet"
           for task_id, shard in zip(ids, shards, strict=True)]
    moving = [mine and task_id in known and task_id not in in_parts for mine, task_id in zip(own, ids, strict=True)]
    removing = [mine and task_id in in_parts for mine, task_id in zip(own, ids, strict=True)]
    moved = rows.filter(pa.array(moving, pa.bool_())).drop_columns(list(SHARD_KEY))
    kept = rows.filter(pa.array([not (m or r) for m, r in zip(moving, removing, strict=True)], pa.bool_()))
    if moved.num_rows:
        part = layout.compacted_dir(sweep_dir) / f"{time.strftime('%Y%m%dT%H%M%S')}-{time.time_ns()}.parquet"
        create_parquet(moved, part)
        make_durable(part)
        stat, n = part.stat(), moved.num_rows
        moved = (moved.append_column("shard", pa.array([os.path.relpath(part, sweep_dir)] * n, pa.string()))
                 .append_column("size", pa.array([stat.st_size] * n, pa.int64()))
                 .append_column("mtime_ns", pa.array([stat.st_mtime_ns] * n, pa.int64())))
        kept = pa.concat_tables([kept, moved], promote_options="permissive").combine_chunks().sort_by("shard")
    write_cache(sweep_dir, kept)  # first: the cache never names a removed file
    gone = [shard for shard, m, r in zip(shards, moving, removing, strict=True) if m or r]
    for shard in gone:
        Path(sweep_dir, shard).unlink(missing_ok=True)
    return kept, len(gone)


def outcome_columns(names: Sequence[str], manifest_names: Sequence[str]) -> list[str]:
    """task_id and the columns of a row that the manifest does not hold already."""
    return ["task_id", *(name for name in names if name not in manifest_names)]


def one_row_per_manifest_task(rows: pa.Table, task_ids: pa.ChunkedArray) -> tuple[pa.Table, int, int]:
    """``rows`` without rows of tasks outside ``task_ids`` and without repeated task ids (the first row
    of a task wins); returns (rows, unknown, duplicates). ``rows`` should be a single chunk (speed)."""
    known = pc.is_in(rows["task_id"], value_set=task_ids)
    unknown = rows.num_rows - (pc.sum(known).as_py() or 0)
    rows = rows.filter(known)
    _, first = np.unique(rows["task_id"].to_numpy(zero_copy_only=False), return_index=True)
    return rows.take(pa.array(np.sort(first), pa.int64())), unknown, rows.num_rows - len(first)


UNRECORDED = "no row and no failure record: cancelled, killed, lost with its node, or never run"


def unmerged_tasks(sweep_dir: Path, manifest: pa.Table, merged_ids: pa.ChunkedArray) -> pa.Table:
    """The tasks without a merged row (task_id, system, arch, seed, state, reason), in the states status gives
    them (``task_states.read_sweep_state``): running (a job trains them or is queued to, a launch or resubmit that
    runs now will, or their row landed after the rows were read), failed, frozen or timeout (their failure
    record since their last submission), skipped or waiting (a budgeted sweep's rounds decided not to run them,
    or have not decided yet) or missing."""
    sweep = read_sweep_state(sweep_dir, queue_required=False)  # merging where no SLURM runs is fine
    unmerged = manifest.select(["task_id", "system", "arch", "seed"]).filter(
        pc.invert(pc.is_in(manifest["task_id"], value_set=merged_ids.combine_chunks() if merged_ids.num_chunks else
                           pa.array([], pa.string()))))
    states, reasons = [], []
    for task_id in unmerged["task_id"].to_pylist():
        state = {"pending": "running", "corrupt": "missing", "done": "running"}.get(sweep.states[task_id],
                                                                                   sweep.states[task_id])
        states.append(state)
        reasons.append(sweep.failures[task_id]["reason"] if state in FAILURE_STATES else
                       UNRECORDED if state == "missing" else "")
    return unmerged.append_column("state", pa.array(states, pa.string())).append_column(
        "reason", pa.array(reasons, pa.string()))


def dropped_counts(unmerged: pa.Table) -> dict[str, int]:
    """How many of the ``unmerged_tasks`` are in each state."""
    states = unmerged["state"].to_pylist()
    return {state: states.count(state) for state in (*FAILURE_STATES, "missing", "running", "skipped", "waiting")}


def read_and_compact(sweep_dir: Path, task_ids: pa.ChunkedArray, compact: bool
                     ) -> tuple[pa.Table, list[str], int, str]:
    """read_rows, and with ``compact`` compact_rows, both under the sweep's lock (a second merge reads and
    compacts after the first, never rows the first has moved meanwhile). Where another command holds the lock
    (a launch or resubmit, whose prepare reads the rows), the rows are read and stay where they are. Returns the
    rows, the unreadable shards, the files removed and why none were ('' when compacted or not asked to)."""
    with contextlib.ExitStack() as stack:
        busy = ""
        if compact:
            try:
                stack.enter_context(sweep_lock(sweep_dir, "merge"))
            except ConfigError as refusal:
                busy = str(refusal).split(";")[0]
        rows, corrupt = read_rows(sweep_dir)
        for shard in corrupt:  # no row: moved aside, so status, launch and resubmit see the task as to run
            with contextlib.suppress(FileNotFoundError):
                set_aside(sweep_dir / shard)
        if not compact or busy:
            write_cache(sweep_dir, rows)
            return rows, corrupt, 0, busy
        compacted, removed = compact_rows(sweep_dir, rows, task_ids)
        return compacted, corrupt, removed, ""


def merge_sweep(sweep_dir: Path, compact: bool = True) -> MergeSummary:
    """Write results.parquet and merge_summary.json for the sweep (``compact``: and move finished rows into
    rows/compacted/); returns the summary."""
    sweep_dir = Path(sweep_dir)
    manifest = read_manifest(sweep_dir)
    rows, corrupt, removed, busy = read_and_compact(sweep_dir, manifest["task_id"], compact)
    rows = rows.select(outcome_columns(rows.column_names, [*manifest.column_names, *SHARD_KEY]))
    rows, unknown, duplicates = one_row_per_manifest_task(rows, manifest["task_id"])
    ordered = manifest.append_column("manifest_index", pa.array(np.arange(manifest.num_rows)))
    results = ordered.join(rows, "task_id", join_type="inner")
    results = results.sort_by("manifest_index").drop_columns(["manifest_index"])
    write_parquet(results, results_path(sweep_dir))
    diverged = int(pc.sum(pc.not_equal(results["status"], "ok")).as_py() or 0) if results.num_rows else 0
    unmerged = unmerged_tasks(sweep_dir, manifest, results["task_id"])
    write_parquet(unmerged.filter(pc.is_in(unmerged["state"], value_set=pa.array([*FAILURE_STATES, "missing"]))),
                  Path(sweep_dir) / layout.DROPPED)
    summary = MergeSummary(tasks=manifest.num_rows, merged=results.num_rows, **dropped_counts(unmerged),
                           diverged=diverged, skipped_reasons=skip_reasons(read_decisions(sweep_dir),
                                                                     set(results["task_id"].to_pylist())),
                           corrupt_shards=corrupt, duplicate_rows=duplicates, unknown_rows=unknown,
                           compacted_files=removed, not_compacted=busy)
    write_text(json.dumps(asdict(summary), indent=1), sweep_dir / layout.MERGE_SUMMARY)
    return summary
