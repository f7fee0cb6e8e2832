"""Whether the file system of a sweep directory holds the sweep: its type, free space and inodes, whether it
takes flock (Lustre without its flock mount option answers ENOSYS, some NFS setups ENOLCK), and how many files
the sweep will write (one row per task, a job's submitit files, a lockstep group's checkpoint while it trains).
"""

import errno
import fcntl
import os
import socket
from dataclasses import dataclass
from pathlib import Path

FILES_PER_JOB = 4  # submitit: an element's pickle, its stdout / stderr log and its result
FILES_PER_GROUP = 3  # a group's checkpoint, its description and its lock, while it trains
FIXED_FILES = 600  # the manifest, configs, records, and the 256-way buckets of rows, logs, failures, checkpoints


@dataclass(frozen=True)
class Storage:
    """A sweep directory's file system: ``free_inodes`` None where it does not count them; ``flock``: None when
    it takes flock, else why not."""

    path: Path
    fs_type: str
    free_bytes: int
    free_inodes: int | None
    flock: str | None

    def describe(self) -> str:
        inodes = "inodes not counted" if self.free_inodes is None else f"{self.free_inodes:,} inodes free"
        return (f"sweep_dir {self.path}: {self.fs_type}, {self.free_bytes / 2**30:,.1f} GiB and {inodes}; "
                + ("flock works" if self.flock is None else f"no flock ({self.flock})"))


def predicted_files(tasks: int, groups: int, jobs: int) -> int:
    """The files a sweep of ``tasks`` in ``groups`` lockstep groups and ``jobs`` SLURM jobs writes at most at once
    (a row file per task: merge compacts them, but a sweep may run to its end unmerged)."""
    return tasks + FILES_PER_GROUP * groups + FILES_PER_JOB * jobs + FIXED_FILES


def fs_type(path: Path) -> str:
    """The type of the file system that holds ``path`` (/proc/mounts: the longest mount point above it)."""
    best, kind = "", "unknown"
    try:
        with open("/proc/mounts") as mounts:
            for line in mounts:
                fields = line.split()
                point = fields[1].replace("\\040", " ")
                if len(fields) > 2 and (path == Path(point) or path.is_relative_to(point)) and len(point) > len(best):
                    best, kind = point, fields[2]
    except OSError:
        pass
    return kind


def flock_refusal(folder: Path) -> str | None:
    """None when ``folder``'s file system takes an exclusive flock, else the error it answers."""
    probe = folder / f".flock-test-{socket.gethostname()}-{os.getpid()}"
    descriptor = os.open(probe, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        fcntl.flock(descriptor, fcntl.LOCK_UN)
        return None
    except OSError as error:
        return f"{errno.errorcode.get(error.errno or 0, error.errno)}: {error.strerror}"
    finally:
        os.close(descriptor)
        probe.unlink(missing_ok=True)


def read_storage(sweep_dir: Path) -> Storage:
    """The file system of ``sweep_dir`` (an existing directory)."""
    path = Path(sweep_dir).resolve()
    stats = os.statvfs(path)
    return Storage(path, fs_type(path), stats.f_bavail * stats.f_frsize, stats.f_favail if stats.f_files else None,
                   flock_refusal(path))
