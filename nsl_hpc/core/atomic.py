"""Atomic file writes: the one place that turns a temporary file into the final one; and whole Parquet files
read back.

Readers see either no file or a whole one: content goes to a private temporary file in the target's
directory, which ``os.replace`` renames into place (atomic on POSIX file systems, NFS and Lustre included).
"""

import contextlib
import os
import re
import shutil
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

TEMPORARY = re.compile(r"\..+\.[a-z0-9_]{8}\.tmp")  # replacing()'s temporaries: .<name>.<mkstemp's 8>.tmp


@contextmanager
def replacing(path: Path, exclusive: bool = False) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces ``path`` (``exclusive``: it becomes ``path`` only
    if there is none, else FileExistsError), on error it is removed. The file gets the permissions of the
    process's umask at that moment."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        yield Path(temporary)
        os.chmod(temporary, 0o666 & ~current_umask())
        if exclusive:
            os.link(temporary, path)  # atomic, and fails when path exists
            os.unlink(temporary)
        else:
            os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def current_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def link_or_copy(source: Path, path: Path) -> None:
    """Make ``path`` a hard link of ``source``, renamed into place (a copy where the file system has no hard
    links): ``path`` appears whole or not at all."""
    with replacing(path) as temporary:
        temporary.unlink()
        try:
            os.link(source, temporary)
        except OSError:  # EPERM, ENOTSUP, EXDEV: no hard links here
            shutil.copyfile(source, temporary)


def write_parquet(table: pa.Table, path: Path) -> None:
    with replacing(path) as temporary:
        pq.write_table(table, temporary)


def create_parquet(table: pa.Table, path: Path) -> None:
    """Write ``table`` to ``path`` atomically, only if ``path`` does not exist yet (FileExistsError)."""
    with replacing(path, exclusive=True) as temporary:
        pq.write_table(table, temporary)


def make_durable(path: Path) -> None:
    """Flush ``path`` and its directory entry to disk (before what it replaces is removed)."""
    descriptor = os.open(path, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


def read_parquet(path: Path, columns: list[str] | None = None, small: bool = False) -> pa.Table:
    """The table of one Parquet file (``columns``: only those). Read as one file, not through pyarrow's dataset
    layer (``pq.read_table``), whose import pulls in pandas: 0.4-1 s of every job's and command's start.
    ``small``: a file of a few rows (a task's row), read without pyarrow's read-ahead and threads, which cost
    more than such a file's read (0.5 ms a row against 0.6-0.9 ms)."""
    if small:
        return pq.ParquetFile(path, pre_buffer=False).read(columns=columns, use_threads=False)
    return pq.ParquetFile(path).read(columns=columns)


def write_text(text: str, path: Path) -> None:
    with replacing(path) as temporary:
        temporary.write_text(text)


def leftover_temporaries(folder: Path, idle_s: float) -> Iterator[Path]:
    """The temporaries of ``replacing`` under ``folder`` not written to for ``idle_s`` seconds: their writer was
    killed (SIGKILL, a lost node) before it could rename or remove them."""
    now = time.time()
    for path in folder.rglob(".*.tmp"):
        with contextlib.suppress(FileNotFoundError):
            if TEMPORARY.fullmatch(path.name) and now - path.stat().st_mtime > idle_s:
                yield path
