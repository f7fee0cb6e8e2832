"""Task outcome rows: a Parquet file per task, written atomically by its job.

A lockstep group's rows are one Parquet file, which each of its tasks' paths names (hard links, or copies where
the file system has none): a task's file holds its group's rows, its own the one whose ``task_id`` is its name
(``named_rows``), and a merge reads such a file once for the whole group (a file read costs pyarrow 0.4-0.6 ms
whatever it holds). The file's footer names each of its tasks (``TASK_IDS``).

A file that does not look like a whole Parquet file (a truncated or overwritten row) is not a row: the task
counts as ``corrupt`` (``row_state``), runs again, and the bad file is moved aside (``set_aside``), never deleted.

merge moves finished rows into a few files of many rows (``rows/compacted/``: a sweep of 63k tasks would
otherwise keep 63k files, a parallel file system's inode quota). It writes such a file before it removes the
rows' own files, and ``row_states`` reads the compacted files after the own files: a row being moved is found
either way, never lost.

Asked about many tasks (status, launch, resubmit), ``row_states`` lists the row folders instead of opening each
task's file, and reads only the files written since it last looked (``nsl_hpc.sweep.listing``: 616k rows, their
listing, not 616k files).
"""

import contextlib
import importlib.abc
import os
import sys
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import pyarrow as pa

from nsl_hpc.core.atomic import link_or_copy, read_parquet, write_parquet
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.listing import read_listed

PARQUET_MAGIC = b"PAR1"  # the first and last four bytes of every Parquet file
TAIL_BYTES = 64 * 1024  # what row_state reads of a file's end: its footer and end magic (a group's rows: ~14 KB)
LISTED_FROM = 1000  # row_states lists the row folders for this many tasks or more, else opens each task's file
CHECK_SCHEMA = pa.schema([("state", pa.string())])  # what a row file's check keeps
TASK_IDS = b"nsl_hpc.task_ids"  # a row file's metadata: the task ids of its rows, space-separated (in its footer)
PART_IDS: dict[Path, tuple[tuple[int, int, int], frozenset[str]]] = {}  # compacted file: (its stat key, its ids)


def write_rows_atomically(rows: Sequence[Mapping[str, Any]], paths: Sequence[Path]) -> None:
    """Write ``rows`` (``paths[i]``: the file of ``rows[i]``) as one Parquet file that every path names: written
    to a temporary file and renamed to the first path, then linked to each other one (``link_or_copy``), so each
    task's file appears whole or not at all."""
    table = pa.Table.from_pylist([dict(row) for row in rows])
    table = table.replace_schema_metadata({TASK_IDS: " ".join(table["task_id"].to_pylist())})
    write_parquet(table, paths[0])
    for path in paths[1:]:
        link_or_copy(paths[0], path)


def write_row_atomically(row: Mapping[str, Any], path: Path) -> None:
    """Write ``row`` as a one-row Parquet file (``write_rows_atomically``)."""
    write_rows_atomically([row], [path])


def named_rows(table: pa.Table, paths: Sequence[str]) -> tuple[pa.Table, list[str]]:
    """The rows of a row file (``table``, read from the file that ``paths`` all name) that its names own, each
    with the path that names it; every row, each with the first path, where none names a row of it (a compacted
    file, or a row copied under another name), so that merge counts such a row a duplicate or unknown. Without
    the file's metadata."""
    table = table.replace_schema_metadata(None)
    if len(paths) == 1 and table.num_rows == 1:
        return table, list(paths)
    names = {os.path.basename(path).removesuffix(".parquet"): path for path in paths}
    ids = table["task_id"].to_pylist()
    owned = [index for index, task_id in enumerate(ids) if task_id in names]
    if not owned:
        return table, [paths[0]] * table.num_rows
    return table.take(owned), [names[ids[index]] for index in owned]


class _NoPandas(importlib.abc.MetaPathFinder):
    """Refuses to import pandas (``refuse_pandas``)."""

    def find_spec(self, name: str, path: Any = None, target: Any = None) -> None:
        if name == "pandas" or name.startswith("pandas."):
            raise ImportError("pandas is not imported here (nsl_hpc.sweep.rows.refuse_pandas)")


def refuse_pandas() -> None:
    """From now on this process does not import pandas: pyarrow looks for it at its first conversion of Python
    values and imports it where installed (0.35 s of CPU), else converts them itself (the same values). For a
    process that runs no user code: a rehearsal's job, status."""
    if "pandas" not in sys.modules and not any(isinstance(finder, _NoPandas) for finder in sys.meta_path):
        sys.meta_path.insert(0, _NoPandas())


def prepare_row_writes(pandas: bool = True) -> None:
    """Import what writing a row imports, once in a job's runner rather than in each group's process forked from
    it; ``pandas=False`` (a rehearsal's job) writes it without pandas (``refuse_pandas``)."""
    if not pandas:
        refuse_pandas()
    pa.array([0])


def read_row(path: Path) -> dict[str, Any]:
    """The row stored at ``path`` (its task's, ``named_rows``)."""
    return named_rows(read_parquet(path, small=True), [str(path)])[0].to_pylist()[0]


def row_state(path: str | Path) -> str:
    """``done`` (a whole Parquet file, its magic bytes at both ends, whose footer names the task of its path: its
    ``TASK_IDS``), ``missing`` or ``corrupt`` (truncated, overwritten, or another task's row copied there). One
    read of the file's end (a group's rows are tens of KB: the whole of it), so a sweep's 63k rows are checked in
    seconds (a damaged file with intact ends is caught by merge, which reads every row)."""
    return named_state(path, row_footer(path)[1])


def named_state(path: str | Path, footer: bytes | str) -> str:
    """``row_state`` from the ``row_footer`` of the file at ``path``."""
    if isinstance(footer, str):
        return footer
    return "done" if str(path).rpartition(os.sep)[2].removesuffix(".parquet").encode() in footer else "corrupt"


def row_footer(path: str | Path) -> tuple[int, bytes | str]:
    """The inode of the file at ``path`` and its Parquet footer, or ``missing`` or ``corrupt`` (not a whole Parquet
    file; inode 0 where there is none)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return 0, "missing"
    try:
        tail = os.pread(fd, TAIL_BYTES, 0)  # a row's whole file, without asking its size first
        size = chunk = len(tail)
        stat = os.fstat(fd)
        inode = stat.st_ino
        if chunk == TAIL_BYTES:  # a larger file: its end
            size = stat.st_size
            tail = os.pread(fd, chunk, size - chunk)
        if size < 12:
            return inode, "corrupt"
        head = tail[:4] if chunk == size else os.pread(fd, 4, 0)
        footer_size = int.from_bytes(tail[-8:-4], "little")
        if head != PARQUET_MAGIC or tail[-4:] != PARQUET_MAGIC or footer_size > size - 12:
            return inode, "corrupt"
        return inode, (tail[-8 - footer_size:-8] if footer_size + 8 <= chunk
                       else os.pread(fd, footer_size, size - 8 - footer_size))
    finally:
        os.close(fd)


def compacted_parts(out_dir: str | os.PathLike) -> list[Path]:
    """The compacted row files of ``out_dir``, by name."""
    folder = layout.compacted_dir(out_dir)
    return sorted(folder.glob("*.parquet")) if folder.is_dir() else []


def compacted_ids(out_dir: str | os.PathLike) -> list[frozenset[str]]:
    """The task ids whose rows each compacted file holds (one that is no Parquet file holds none: merge sets it
    aside; an I/O error is raised, not taken for missing rows, which would run again). A file's ids are read once
    per process while its size, time and inode stand (a job asks before each group)."""
    held = []
    for part in compacted_parts(out_dir):
        with contextlib.suppress(pa.ArrowInvalid, FileNotFoundError):
            stat = part.stat()
            key = (stat.st_size, stat.st_mtime_ns, stat.st_ino)
            if part not in PART_IDS or PART_IDS[part][0] != key:
                PART_IDS[part] = (key, frozenset(read_parquet(part, columns=["task_id"])["task_id"].to_pylist()))
            held.append(PART_IDS[part][1])
    return held


def row_states(out_dir: str | os.PathLike, task_ids: Iterable[str]) -> dict[str, str]:
    """Each task's row state (``done``, ``missing``, ``corrupt``): ``done`` where a compacted file holds its row,
    else its own file's (``row_state``; for many tasks ``listed_row_states``). Read in an order that misses no row
    a merge moves meanwhile (merge syncs the compacted file before it removes the own files): the compacted files,
    the own files of the tasks they do not hold, then the compacted files again for the tasks still without a
    row."""
    task_ids = list(task_ids)
    held = compacted_among(set(task_ids), compacted_ids(out_dir))
    own = [task_id for task_id in task_ids if task_id not in held] if held else task_ids
    if len(own) >= LISTED_FROM:
        listed = listed_row_states(out_dir, own)
    else:
        listed = {task_id: row_state(layout.row_file(out_dir, task_id)) for task_id in own}
    if held:
        states = dict.fromkeys(task_ids, "done")
        states.update(listed)
    else:
        states = listed
    if all(state == "done" for state in states.values()):
        return states
    since = compacted_among({task_id for task_id, state in states.items() if state != "done"}, compacted_ids(out_dir))
    return {task_id: "done" if task_id in since else state for task_id, state in states.items()} if since else states


def compacted_among(task_ids: set[str], compacted: Sequence[frozenset[str]]) -> set[str]:
    """Those of ``task_ids`` that one of the ``compacted`` files (``compacted_ids``) holds."""
    return set().union(*(task_ids & ids for ids in compacted))


def listed_row_states(out_dir: str | os.PathLike, task_ids: Iterable[str]) -> dict[str, str]:
    """The own row files' states of ``task_ids`` from a listing of the row folders (``listing.read_listed``):
    ``missing`` without a file, else its state (``row_state``) as read while it is the same file."""
    import pyarrow.compute as pc  # here: a job asks about its few tasks, and starts without it (0.1 s)

    last: tuple[int, bytes | str] = (0, b"")  # the file read last: its group's other paths come next (by inode)

    def check(path: str, listed_inode: int) -> dict[str, str]:
        nonlocal last
        if last[0] != listed_inode:  # else the same file, named by another task of its group
            last = row_footer(path)
        return {"state": named_state(path, last[1])}

    checked = read_listed(os.path.join(out_dir, layout.ROWS), ".parquet", Path(out_dir) / layout.ROW_CHECKS,
                          CHECK_SCHEMA, check)
    task_ids = task_ids if isinstance(task_ids, list) else list(task_ids)
    found = pc.index_in(pa.array(task_ids, pa.string()), value_set=checked["task_id"])
    states = pc.fill_null(checked["state"].take(found), "missing")
    return dict(zip(task_ids, states.to_pylist(), strict=True))


def all_done(out_dir: str | os.PathLike, task_ids: Iterable[str]) -> bool:
    return all(state == "done" for state in row_states(out_dir, task_ids).values())


def read_task_rows(out_dir: str | os.PathLike, task_ids: Iterable[str]) -> dict[str, dict[str, Any]]:
    """The rows of those of ``task_ids`` that have one (in their own file or a compacted one), by task id."""
    rows, wanted = {}, set()
    for task_id in task_ids:
        path = layout.row_path(out_dir, task_id)
        if row_state(path) == "done":
            rows[task_id] = read_row(path)
        else:
            wanted.add(task_id)
    for part in compacted_parts(out_dir) if wanted else []:
        with contextlib.suppress(pa.ArrowInvalid, FileNotFoundError):
            table = read_parquet(part)
            found = [index for index, task_id in enumerate(table["task_id"].to_pylist()) if task_id in wanted]
            for row in table.take(found).to_pylist():
                rows.setdefault(row["task_id"], row)
    return rows


def set_aside(path: Path) -> Path:
    """Move a bad row from ``<out_dir>/rows/xx/`` to ``<out_dir>/corrupt/`` (with a time stamp); returns where."""
    target = path.parents[2] / layout.CORRUPT / f"{path.name}.{time.strftime('%Y%m%dT%H%M%S')}.{time.time_ns() % 10**9}"
    target.parent.mkdir(parents=True, exist_ok=True)
    os.replace(path, target)
    return target
