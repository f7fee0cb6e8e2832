"""Progress of a phase of work that takes more than a few seconds (fits, figures, MLflow runs, reading rows): a bar
on a terminal, and away from one (a log, a pipe, a SLURM job) a counted line at most every ``LINE_EVERY_S`` seconds
and at the end, as an INFO record of the ``nsl_hpc`` logger ($NSL_HPC_LOG_LEVEL=WARNING keeps it quiet)."""

import logging
import sys
import time
from collections.abc import Iterable, Iterator, Sized
from typing import TypeVar

from tqdm import tqdm

LOG = logging.getLogger(__name__)
LINE_EVERY_S = 10.0  # away from a terminal: a counted line at most this often
T = TypeVar("T")


def progress(items: Iterable[T], desc: str, unit: str, total: int | None = None) -> Iterator[T]:
    """``items``, one after another, with a bar on a terminal (stderr) or counted lines ("NSL fits: 12 of 36
    fits, 41 s"); ``total``: their number where ``items`` has no length."""
    if total is None and isinstance(items, Sized):
        total = len(items)
    if sys.stderr.isatty():
        yield from tqdm(items, desc=desc, unit=unit, total=total)
        return
    of = f" of {total:,}" if total is not None else ""
    started = last = time.monotonic()
    done = 0
    for item in items:
        yield item
        done += 1
        now = time.monotonic()
        if now - last >= LINE_EVERY_S and done != total:
            LOG.info(f"{desc}: {done:,}{of} {unit}s, {now - started:.0f} s")
            last = now
    if done and time.monotonic() - started >= 1.0:  # a phase too short to watch says nothing
        LOG.info(f"{desc}: {done:,}{of} {unit}s, {time.monotonic() - started:.0f} s")
