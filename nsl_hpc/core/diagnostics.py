"""Where diagnostics go: the records of every ``nsl_hpc.*`` logger. In a command, the library's progress (INFO:
"submitted 4 jobs in 1 arrays", "finished: 6 ok") is a plain line on stdout and a diagnostic (WARNING and worse) a
``warning: ...`` line on stderr; $NSL_HPC_LOG_LEVEL (as submitit's $SUBMITIT_LOG_LEVEL: DEBUG, INFO, WARNING, ERROR)
sets how much shows. A job writes each record with its time, level and where it arose (the job, or a lockstep group
and its tasks), to its log."""

import contextlib
import logging
import os
from collections.abc import Iterator
from typing import TextIO

from nsl_hpc.core.errors import ConfigError

LOGGER = logging.getLogger("nsl_hpc")
JOB_FORMAT = "%(asctime)s %(levelname)s [%(where)s] %(message)s"
LEVEL_VARIABLE = "NSL_HPC_LOG_LEVEL"
LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")


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


def command_level() -> int:
    """The level $NSL_HPC_LOG_LEVEL names (INFO when unset), or a one-line ConfigError."""
    name = os.environ.get(LEVEL_VARIABLE, "INFO").upper()
    if name not in LEVELS:
        raise ConfigError(f"${LEVEL_VARIABLE}={os.environ[LEVEL_VARIABLE]!r} is unknown; choose one of: "
                          f"{', '.join(LEVELS)}")
    return logging.getLevelNamesMapping()[name]


def log_command(out: TextIO, err: TextIO) -> None:
    """A command's records from ``command_level`` on: progress (below WARNING) as plain lines on ``out``,
    diagnostics as ``warning: ...`` lines on ``err``."""
    progress = logging.StreamHandler(out)
    progress.addFilter(lambda record: record.levelno < logging.WARNING)
    diagnostics = logging.StreamHandler(err)
    diagnostics.setLevel(logging.WARNING)
    diagnostics.setFormatter(CommandFormatter())
    LOGGER.handlers[:] = [progress, diagnostics]
    LOGGER.propagate = False
    LOGGER.setLevel(command_level())


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
