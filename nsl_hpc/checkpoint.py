"""Training checkpoints: one file that lets a lockstep group (or a lone task) continue exactly where it stopped.

A training loop hands ``block_done`` a function that returns its state (plain dicts, lists, numbers and tensors:
``torch.load(weights_only=True)`` reads it back) at each block boundary. The state is written atomically when
``every_s`` seconds have passed since the last write, and at once when a stop was asked (``ask_to_stop``: SLURM's
warning before a time limit or a preemption, a requeue's SIGTERM); after that write training stops with
``TrainingStopped``. ``<name>.json`` beside the file says what it holds (tasks, progress, resumes, write time)
without loading it: the planner, ``status`` and ``clean`` read that.
"""

import json
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch

from nsl_hpc.atomic import replacing, write_text


class TrainingStopped(Exception):
    """Training stopped after writing a checkpoint, as asked."""


def info_path(path: Path) -> Path:
    """Where the description of checkpoint ``path`` lies."""
    return path.with_suffix(".json")


def read_info(path: Path) -> dict[str, Any] | None:
    """The description of checkpoint ``path`` (None when there is none or it cannot be read)."""
    try:
        return json.loads(info_path(path).read_text())
    except (OSError, ValueError):
        return None


def trained_before(checkpoint: "Checkpointer | None") -> float:
    """Seconds of training before this run that ``checkpoint`` continues (0 without one)."""
    return 0.0 if checkpoint is None else checkpoint.trained_before_s


def remove_checkpoint(path: Path) -> None:
    """Delete checkpoint ``path`` and its description (its group has its rows)."""
    path.unlink(missing_ok=True)
    info_path(path).unlink(missing_ok=True)


class Checkpointer:
    """The checkpoint of the group of ``task_ids`` (in training order) at ``path``, written every ``every_s``
    seconds of training (> 0) and when a stop is asked."""

    def __init__(self, path: Path, every_s: float, task_ids: Sequence[str]):
        if not every_s > 0:
            raise ValueError(f"every_s={every_s} must be positive")
        self.path, self.every_s, self.task_ids = Path(path), every_s, list(task_ids)
        self.stop_asked = False
        self.started = self.last_write = time.monotonic()
        self.trained_before_s = 0.0  # training time of the runs this one continues (s)
        self.resumes = 0
        self.writes, self.write_seconds = 0, 0.0

    def ask_to_stop(self, *_: Any) -> None:
        """Write a checkpoint at the next block boundary and stop (a signal handler)."""
        self.stop_asked = True

    def load(self) -> dict[str, Any] | None:
        """The state saved for these tasks, or None (train from the start). Counts the resume in the description.
        A file that cannot be read is kept aside as ``<name>.unreadable`` and training starts afresh."""
        try:
            saved = torch.load(self.path, weights_only=True)
        except FileNotFoundError:
            return None
        except Exception as error:  # a damaged file, or one from an incompatible torch
            os.replace(self.path, self.path.with_suffix(".unreadable"))
            print(f"checkpoint {self.path.name} unreadable ({type(error).__name__}): kept aside, training afresh")
            return None
        if saved["task_ids"] != self.task_ids:
            return None
        self.resumes, self.trained_before_s = saved["resumes"] + 1, saved["trained_s"]
        self.describe(saved["step"], saved["total_steps"], saved["saved"])
        return saved["state"]

    def block_done(self, state: Callable[[], dict[str, Any]], step: int, total_steps: int) -> None:
        """After a block of training (``step`` of ``total_steps`` of the longest member): write ``state()`` when
        due; stop (TrainingStopped) when asked to."""
        if self.stop_asked or time.monotonic() - self.last_write >= self.every_s:
            self.save(state(), step, total_steps)
        if self.stop_asked:
            raise TrainingStopped

    def save(self, state: dict[str, Any], step: int, total_steps: int) -> None:
        """Write ``state`` atomically, then its description."""
        started = time.perf_counter()
        saved = time.time()
        with replacing(self.path) as temporary:
            torch.save({"task_ids": self.task_ids, "resumes": self.resumes, "step": step,
                        "total_steps": total_steps, "saved": saved, "state": state,
                        "trained_s": self.trained_before_s + time.monotonic() - self.started}, temporary)
        self.writes += 1
        self.write_seconds += time.perf_counter() - started
        self.last_write = time.monotonic()
        self.describe(step, total_steps, saved)

    def describe(self, step: int, total_steps: int, saved: float) -> None:
        write_text(json.dumps({"task_ids": self.task_ids, "step": step, "total_steps": total_steps, "saved": saved,
                               "resumes": self.resumes, "bytes": self.path.stat().st_size,
                               "write_seconds": self.write_seconds / max(self.writes, 1)}), info_path(self.path))
