"""Training checkpoints: one file that lets a lockstep group (or a lone task) continue exactly where it stopped.

A training loop hands ``block_done`` a function that returns its state (plain dicts, lists, numbers and tensors:
``torch.load(weights_only=True)`` reads it back) at each block boundary. The state is written atomically when
``every_s`` seconds have passed since the last write, and at once when a stop was asked (``ask_to_stop``: SLURM's
warning before a time limit or a preemption, a requeue's SIGTERM); after that write training stops with
``TrainingStopped``. ``<name>.json`` beside the file says what it holds (tasks, progress, resumes, write time)
without loading it: the planner, ``status`` and ``clean`` read that.

A checkpoint is only used for what it was made for: its file starts with a line holding the SHA-256 of the rest
(``torch.load`` does not check its zip's CRCs, so a flipped byte would resume silently from wrong numbers), and it
records its format and the layout of the run that wrote it (tensor shapes the training loop names; the task ids
hash every outcome-changing config value). A checkpoint that fails either check is set aside (``<name>.unreadable``
or ``<name>.mismatched``, never deleted), the task log says why, and the group trains from the start.
"""

import hashlib
import io
import json
import logging
import os
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from nsl_hpc.core.atomic import replacing, write_text

LOG = logging.getLogger(__name__)

FORMAT = 2  # 1: torch.save's bytes alone; 2: a header line with their SHA-256 first, and the run's layout inside
HEADER = b"nsl_hpc checkpoint sha256="


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


def scoring_progress(checkpoint: "Checkpointer | None", on_progress: Callable[[], None]) -> Callable[[], None]:
    """The heartbeat of the scoring after training: ``on_progress``, then, once a stop was asked, the end of
    training written (``Checkpointer.training_done``) and TrainingStopped, so that a resumed run only scores."""
    if checkpoint is None:
        return on_progress

    def heartbeat() -> None:
        on_progress()
        checkpoint.stop_after_training()

    return heartbeat


def encoded(payload: dict[str, Any]) -> bytes:
    """``payload`` as a checkpoint file's bytes: the header line with the SHA-256 of torch.save's bytes, then them."""
    import torch  # here, not with the module: the commands that read a sweep only read checkpoints' descriptions

    buffer = io.BytesIO()
    torch.save(payload, buffer)
    body = buffer.getvalue()
    return HEADER + hashlib.sha256(body).hexdigest().encode() + b"\n" + body


def decoded(raw: bytes) -> dict[str, Any]:
    """The payload of a checkpoint file's bytes ``raw``; ValueError when its checksum does not match (or it has
    none: another format)."""
    header, _, body = raw.partition(b"\n")
    if not header.startswith(HEADER):
        raise ValueError("no checksum header (not a checkpoint of this format)")
    if hashlib.sha256(body).hexdigest().encode() != header[len(HEADER):]:
        raise ValueError("checksum mismatch: the file was changed after it was written")
    import torch

    return torch.load(io.BytesIO(body), weights_only=True)


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
        self.made_for: dict[str, Any] = {"format": FORMAT}
        self.trained: tuple[Callable[[], dict[str, Any]], int] | None = None  # the end of training: state, steps
        self.blocks = 0  # blocks of training this run has ended

    @property
    def progressed(self) -> bool:
        """Whether this run has trained anything to write: before its first block ends (data loading, kernels
        compiling) what it would write is what the file already holds."""
        return self.blocks > 0 or self.trained is not None

    def ask_to_stop(self, *_: Any) -> None:
        """Write a checkpoint at the next block boundary and stop (a signal handler)."""
        self.stop_asked = True

    def load(self, layout: Mapping[str, Any]) -> dict[str, Any] | None:
        """The state saved for these tasks by a run of this ``layout`` (what the training loop's state is made of:
        names to tensor shapes and sizes, plain data), or None (train from the start). Counts the resume in the
        description. A damaged file or one of another format or layout is set aside and training starts afresh."""
        self.made_for = {"format": FORMAT, **json.loads(json.dumps(layout))}
        try:
            raw = self.path.read_bytes()
        except FileNotFoundError:
            return None
        try:
            saved = decoded(raw)
        except Exception as error:  # a damaged file, another format, or one from an incompatible torch
            self.set_aside("unreadable", f"{type(error).__name__}: {error}")
            return None
        if saved["task_ids"] != self.task_ids:
            return None
        if saved["made_for"] != self.made_for:
            self.set_aside("mismatched", f"made for {saved['made_for']}, this run is {self.made_for}")
            return None
        self.resumes, self.trained_before_s = saved["resumes"] + 1, saved["trained_s"]
        self.describe(saved["step"], saved["total_steps"], saved["saved"])
        return saved["state"]

    def set_aside(self, why: str, detail: str) -> None:
        """Move the checkpoint to ``<name>.<why>`` (not deleted: it may be inspected) and say so in the log."""
        os.replace(self.path, self.path.with_suffix(f".{why}"))
        LOG.warning("checkpoint %s %s (%s): set aside as %s, training from the start", self.path.name, why, detail,
                    self.path.with_suffix(f".{why}").name)

    def block_done(self, state: Callable[[], dict[str, Any]], step: int, total_steps: int) -> None:
        """After a block of training (``step`` of ``total_steps`` of the longest member): write ``state()`` when
        due; stop (TrainingStopped) when asked to."""
        self.blocks += 1
        if self.stop_asked or time.monotonic() - self.last_write >= self.every_s:
            self.save(state(), step, total_steps)
        if self.stop_asked:
            raise TrainingStopped

    def training_done(self, state: Callable[[], dict[str, Any]], total_steps: int) -> None:
        """Training has ended after ``total_steps``; ``state()`` is its state then (a run resumed from it trains no
        more): a stop asked while the models are scored writes it (``stop_after_training``)."""
        self.trained = (state, total_steps)

    def stop_after_training(self) -> None:
        """When a stop was asked after training ended: write the end of training and stop (TrainingStopped)."""
        if self.stop_asked and self.trained is not None:
            state, steps = self.trained
            self.save(state(), steps, steps)
            raise TrainingStopped

    def save(self, state: dict[str, Any], step: int, total_steps: int) -> None:
        """Write ``state`` atomically, then its description."""
        started = time.perf_counter()
        saved = time.time()
        raw = encoded({"task_ids": self.task_ids, "made_for": self.made_for, "resumes": self.resumes, "step": step,
                       "total_steps": total_steps, "saved": saved, "state": state,
                       "trained_s": self.trained_before_s + time.monotonic() - self.started})
        with replacing(self.path) as temporary:
            temporary.write_bytes(raw)
        self.writes += 1
        self.write_seconds += time.perf_counter() - started
        self.last_write = time.monotonic()
        self.describe(step, total_steps, saved)

    def describe(self, step: int, total_steps: int, saved: float) -> None:
        write_text(json.dumps({"task_ids": self.task_ids, "step": step, "total_steps": total_steps, "saved": saved,
                               "resumes": self.resumes, "bytes": self.path.stat().st_size,
                               "write_seconds": self.write_seconds / max(self.writes, 1)}), info_path(self.path))
