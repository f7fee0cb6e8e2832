"""A sweep's files named by task id in bucket folders (``<folder>/<id[:2]>/<id><suffix>``: rows, failure
records), each read once while it is the same file.

A look at many tasks (status, launch, resubmit) lists the folders and takes each file's inode from the listing
(no ``stat`` per file: 616k of them took 2 s here and cost a metadata server call each on a parallel file
system); what was read from a file is kept in a table beside the sweep with its inode (rows:
``.row_checks.parquet``, failure records: ``.failure_checks.parquet``) and stands while the listing shows that
inode. The package writes these files only by renaming a new file into place (a new inode), so a file written,
replaced or removed is seen at the next look; a file changed in place (``truncate``, a ``cp`` over it) keeps its
inode and its kept reading until merge, which reads every row, or a look at fewer tasks, which reads each file.
"""

import contextlib
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import pyarrow as pa

from nsl_hpc.core.atomic import read_parquet, write_parquet

KEY_SCHEMA = pa.schema([("task_id", pa.string()), ("ino", pa.uint64())])
KEY = tuple(KEY_SCHEMA.names)


def listed(folder: str | os.PathLike, suffix: str) -> pa.Table:
    """task_id and ino (the inode the listing gives) of every ``<folder>/<xx>/<task id><suffix>``."""
    import pyarrow.compute as pc  # here: a job, which imports this module, starts without it (0.1 s)

    names, inodes = [], []
    with contextlib.suppress(FileNotFoundError, NotADirectoryError):
        for bucket in os.listdir(folder):
            with contextlib.suppress(FileNotFoundError, NotADirectoryError), \
                    os.scandir(os.path.join(folder, bucket)) as listing:
                entries = [entry for entry in listing if entry.name.startswith(bucket)]  # not rows/compacted/
            names += [entry.name for entry in entries]
            inodes += [entry.inode() for entry in entries]
    table = pa.table({"name": pa.array(names, pa.string()), "ino": pa.array(inodes, pa.uint64())})
    table = table.filter(pc.ends_with(table["name"], suffix))  # not a temporary being written
    task_ids = pc.utf8_slice_codeunits(table["name"], 0, -len(suffix))
    return pa.table({"task_id": task_ids, "ino": table["ino"]})


def read_listed(folder: str | os.PathLike, suffix: str, kept_at: Path, schema: pa.Schema,
                read: Callable[[str, int], Mapping[str, Any] | None]) -> pa.Table:
    """Every listed file of ``folder`` (``listed``) with the ``schema`` columns ``read(path, inode)`` gives for it
    (None: unreadable, left out; inode: the listing's): kept ones (``kept_at``) where the file has the inode they
    were read at, else read now, in inode order (a group's row paths name one file); kept again where anything
    changed (and the sweep takes writes)."""
    import pyarrow.compute as pc

    files = listed(folder, suffix)
    whole = pa.schema([*KEY_SCHEMA, *schema])
    try:
        kept = read_parquet(kept_at).select(whole.names).cast(whole)
    except (FileNotFoundError, KeyError, pa.ArrowInvalid, OSError):  # none kept (or of another form): read all
        kept = whole.empty_table()
    joined = files.join(kept.append_column("kept", pa.repeat(True, kept.num_rows)), list(KEY),
                        join_type="left outer")
    standing = joined.filter(pc.is_valid(joined["kept"])).select(whole.names)
    unread = joined.filter(pc.is_null(joined["kept"])).sort_by("ino")
    fresh: dict[str, list[Any]] = {name: [] for name in whole.names}  # by column: 616k rows of dicts take seconds
    prefix = os.path.join(folder, "")
    for task_id, ino in zip(unread["task_id"].to_pylist(), unread["ino"].to_pylist(), strict=True):
        if (values := read(f"{prefix}{task_id[:2]}{os.sep}{task_id}{suffix}", ino)) is not None:
            fresh["task_id"].append(task_id)
            fresh["ino"].append(ino)
            for name in schema.names:
                fresh[name].append(values.get(name))
    if not fresh["task_id"] and standing.num_rows == kept.num_rows:
        return standing
    table = pa.concat_tables([standing, pa.table(fresh, schema=whole)]).combine_chunks()
    with contextlib.suppress(OSError):  # a folder that takes no writes keeps nothing
        write_parquet(table, kept_at)
    return table
