"""Where a sweep keeps the training checkpoints of its lockstep groups, and the lock that lets one job at a time
train a group.

``<sweep_dir>/checkpoints/<key[:2]>/<key>.pt`` (with ``<key>.json``, ``nsl_hpc.core.checkpoint``) holds the state of
the group of the task ids whose hash is ``key``, in training order; ``<key>.lock`` says which job trains it now
(job, node, pid and the task ids: ``status`` and ``merge`` call them running).
A job takes the lock before it trains a group and renews it as long as the group trains; a second job that finds
a live lock leaves the group to its holder. A lock is stale (taken over) when its job runs no more: its process
is gone (same node), or it was not renewed for ``STALE_S`` seconds (a lost node, a killed job). An earlier run of
the same SLURM job (requeued) is waited for while it renews its lock: SLURM requeues the job of a lost node while
that node's processes may still train the group, and two runs must not train it twice.
"""

import contextlib
import json
import logging
import os
import socket
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from nsl_hpc.core.atomic import replacing
from nsl_hpc.core.checkpoint import read_info
from nsl_hpc.core.seeding import stable_hash
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.directory import process_alive

LOG = logging.getLogger(__name__)
RENEW_S = 15.0  # a running group's lock is renewed this often
STALE_S = 120.0  # a lock not renewed for this long belongs to a job that is gone (8 missed renewals)


def group_key(task_ids: Sequence[str]) -> str:
    """The name of a group's checkpoint and lock: a hash of its task ids in training order."""
    return stable_hash(list(task_ids))


def checkpoint_path(sweep_dir: Path, task_ids: Sequence[str]) -> Path:
    return layout.checkpoint_file(sweep_dir, group_key(task_ids))


def lock_path(checkpoint: Path) -> Path:
    """The lock of the group whose checkpoint is ``checkpoint``."""
    return checkpoint.with_suffix(".lock")


def this_node() -> str:
    """The SLURM node this process runs on (several may share a host), or the host's name outside SLURM."""
    return os.environ.get("SLURMD_NODENAME") or socket.gethostname()


def this_job() -> str:
    """The SLURM job (array element) this process runs in, or '' outside SLURM."""
    array, index = os.environ.get("SLURM_ARRAY_JOB_ID"), os.environ.get("SLURM_ARRAY_TASK_ID")
    return f"{array}_{index}" if array and index else os.environ.get("SLURM_JOB_ID", "")


@dataclass(frozen=True)
class SavedGroup:
    """A checkpoint on disk: its group's task ids (training order), progress and how often it was resumed."""

    path: Path
    task_ids: tuple[str, ...]
    step: int
    total_steps: int
    resumes: int
    saved: float  # when it was written (s since the epoch)


def saved_groups(sweep_dir: Path) -> Iterator[SavedGroup]:
    """Every readable checkpoint of a sweep."""
    for path in sorted((Path(sweep_dir) / layout.CHECKPOINTS).glob("*/*.pt")):
        info = read_info(path)
        if info is not None:
            yield SavedGroup(path, tuple(info["task_ids"]), info["step"], info["total_steps"], info["resumes"],
                             info["saved"])


@dataclass(frozen=True)
class HeldLock:
    """A group's lock as found on disk: who holds it, for which tasks, and how long since it was renewed (s)."""

    path: Path
    host: str
    pid: int
    task_ids: tuple[str, ...]
    silent_s: float

    @property
    def live(self) -> bool:
        """Renewed within STALE_S, by a process that still runs (as far as this host can tell)."""
        return self.silent_s <= STALE_S and (self.host != this_node() or process_alive(self.pid))


def held_locks(sweep_dir: Path) -> list[HeldLock]:
    """Every readable group lock of a sweep (locks written before they named their tasks name none)."""
    locks, now = [], time.time()
    for path in (Path(sweep_dir) / layout.CHECKPOINTS).glob("*/*.lock"):
        try:
            record, renewed = json.loads(path.read_text()), path.stat().st_mtime
            locks.append(HeldLock(path, record["host"], record["pid"], tuple(record.get("task_ids", ())),
                                  now - renewed))
        except (OSError, ValueError, KeyError, TypeError):
            continue  # removed meanwhile, or half-written
    return locks


def running_task_ids(sweep_dir: Path) -> set[str]:
    """Tasks of the groups a live job trains now (its lock renewed within STALE_S)."""
    return {task_id for lock in held_locks(sweep_dir) if lock.live for task_id in lock.task_ids}


class GroupLock:
    """The lock of the group of ``task_ids``: held by at most one job at a time."""

    def __init__(self, sweep_dir: Path, task_ids: Sequence[str]):
        self.path = lock_path(checkpoint_path(sweep_dir, task_ids))
        self.record = {"job": this_job(), "host": this_node(), "pid": os.getpid(),
                       "task_ids": list(task_ids)}
        self.renewed = 0.0

    def acquire(self) -> str | None:
        """Take the lock; None when taken, else who holds it (a live job: leave the group to it)."""
        for _ in range(3):
            try:
                with replacing(self.path, exclusive=True) as temporary:
                    temporary.write_text(json.dumps({**self.record, "time": time.time()}))
                self.renewed = time.monotonic()
                return None
            except FileExistsError:
                pass
            holder, text = self.holder()
            if holder is not None and self.earlier_run(holder):
                holder, text = self.wait_for(holder, text)
                if holder is None:  # released: take it as any free lock
                    continue
            if holder is not None and not self.stale(holder):
                return f"job {holder['job'] or holder['pid']} on {holder['host']}"
            self.take_over(text)
        return "a job that keeps taking it (retried 3 times)"

    def earlier_run(self, holder: dict[str, Any]) -> bool:
        """Whether ``holder`` is another run of this SLURM job (it was requeued)."""
        return bool(holder["job"]) and holder["job"] == self.record["job"] and \
            (holder["host"], holder["pid"]) != (self.record["host"], self.record["pid"])

    def wait_for(self, earlier: dict[str, Any], text: str) -> tuple[dict[str, Any] | None, str]:
        """Wait while ``earlier``, a run of this job, renews the lock (whose text is ``text``); the holder then
        (None: released) and its text."""
        LOG.info("an earlier run of job %s holds the lock of %s on %s: waiting until it releases it or stops "
                 "renewing it", earlier["job"], self.path.name, earlier["host"])
        holder: dict[str, Any] | None = earlier
        while holder is not None and holder["job"] == self.record["job"] and not self.stale(holder):
            time.sleep(RENEW_S)
            holder, text = self.holder()
        return holder, text

    def holder(self) -> tuple[dict[str, Any] | None, str]:
        """The lock's record and text (None, '' when it is gone or unreadable)."""
        try:
            text = self.path.read_text()
            return json.loads(text), text
        except (OSError, ValueError):
            return None, ""

    def stale(self, holder: dict[str, Any]) -> bool:
        if holder["host"] == self.record["host"] and not process_alive(holder["pid"]):
            return True
        try:
            return time.time() - self.path.stat().st_mtime > STALE_S
        except FileNotFoundError:
            return True

    def take_over(self, seen: str) -> None:
        """Remove the stale lock whose text was ``seen``: moved aside first, so that of two jobs taking it over
        only one removes it, and a lock taken meanwhile by another is put back."""
        aside = self.path.with_name(f"{self.path.name}.{os.getpid()}.stale")
        try:
            os.rename(self.path, aside)
        except FileNotFoundError:
            return
        if aside.read_text() != seen:
            with contextlib.suppress(FileExistsError):
                os.link(aside, self.path)
        aside.unlink()

    def renew(self) -> None:
        """Mark the lock alive (every RENEW_S seconds at most)."""
        if time.monotonic() - self.renewed >= RENEW_S:
            self.renewed = time.monotonic()
            with contextlib.suppress(FileNotFoundError):
                os.utime(self.path)

    def release(self) -> None:
        """Remove the lock if this process holds it."""
        holder, _ = self.holder()
        if holder is not None and holder["pid"] == self.record["pid"] and holder["host"] == self.record["host"]:
            self.path.unlink(missing_ok=True)
