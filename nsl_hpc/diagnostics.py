"""Where diagnostics go: the records of every ``nsl_hpc.*`` logger. A command prints its own output plainly and
shows a diagnostic as ``warning: ...`` on stderr; a job writes each one with its time, level and where it arose
(the job, or a lockstep group and its tasks), to its log."""

import contextlib
import logging
from collections.abc import Iterator
from typing import TextIO

LOGGER = logging.getLogger("nsl_hpc")
JOB_FORMAT = "%(asctime)s %(levelname)s [%(where)s] %(message)s"


class CommandFormatter(logging.Formatter):
    """``<level>: <message>``, as a command's own errors read."""

    def format(self, record: logging.LogRecord) -> str:
        return f"{record.levelname.lower()}: {record.getMessage()}"


def send_records(stream: TextIO, formatter: logging.Formatter, level: int, where: str | None = None) -> None:
    """From now on, nsl_hpc's records of ``level`` and above go to ``stream`` alone, each naming ``where``."""
    handler = logging.StreamHandler(stream)
    handler.setFormatter(formatter)
    if where is not None:
        def name_where(record: logging.LogRecord) -> bool:
            record.where = where
            return True
        handler.addFilter(name_where)
    LOGGER.handlers[:] = [handler]
    LOGGER.setLevel(level)
    LOGGER.propagate = False


def log_command(stream: TextIO) -> None:
    """A command's diagnostics: warnings and worse, as ``warning: ...`` lines."""
    send_records(stream, CommandFormatter(), logging.WARNING)


def log_job(stream: TextIO, where: str) -> None:
    """A job's diagnostics, from INFO: a timestamped line each, naming ``where``."""
    send_records(stream, logging.Formatter(JOB_FORMAT), logging.INFO, where)


@contextlib.contextmanager
def job_records(stream: TextIO, where: str) -> Iterator[None]:
    """``log_job`` while the block runs, then the records go where they went before (a debug job runs inside the
    launch command)."""
    handlers, level, propagate = list(LOGGER.handlers), LOGGER.level, LOGGER.propagate
    log_job(stream, where)
    try:
        yield
    finally:
        LOGGER.handlers[:], LOGGER.propagate = handlers, propagate
        LOGGER.setLevel(level)
