"""The format of a sweep directory, the one upgrade of an older one, and the version of the package that writes it.

launch.yaml records the ``format`` it was written in (``FORMAT``). A sweep launched before that (format 1: no
``format`` key) may lack settings added since, in launch.yaml and run.yaml; ``upgrade_launch`` gives each the value
such a sweep ran with, so every reader of a sweep's launch config sees one shape; ``upgrade_decisions`` does the
same for a budgeted sweep's decisions. The settings added to the pairs'
task configs are upgraded by ``Study.with_stored_defaults`` (they also keep the task ids). A sweep written in a
later format, by a newer nsl_hpc, is refused in one line.
"""

import copy
import functools
import importlib.metadata
from typing import Any

import pyarrow as pa

from nsl_hpc.core.errors import ConfigError
from nsl_hpc.sweep.groups import STALE_S

FORMAT = 2

# (dotted key, the value a format-1 sweep ran with where its launch.yaml and run.yaml lack the key)
FORMAT_1_SETTINGS: tuple[tuple[str, Any], ...] = (
    ("threads", 1),
    ("compile", "auto"),
    ("rehearsal", False),
    ("checkpoint", {"every_minutes": 0}),
    ("watchdog.worker_silence_s", STALE_S),
    ("cost.group_start_s", 0.0),
    ("cost.score_seconds", 0.0),
    ("cost.compile_s", {}),
    ("cost.compile_speedup", {}),
    ("metric", {"normalization": None}),  # input-state scores per dx/dt column, without the other normalisation
)


@functools.cache
def package_version() -> str | None:
    """The installed nsl_hpc's version (its metadata: pyproject's, from nsl_hpc.__version__), which rows and law cards
    record; None where it runs from a source tree it was not installed from."""
    try:
        return importlib.metadata.version("nsl_hpc")
    except importlib.metadata.PackageNotFoundError:
        return None


def format_of(launch: dict[str, Any], where: str) -> int:
    """The format ``launch`` (a stored launch config, from ``where``) was written in, refused when it is not one
    this nsl_hpc reads."""
    written = launch.get("format", 1)
    if not isinstance(written, int) or written < 1:
        raise ConfigError(f"{where} says format={written!r}; the sweep directory is damaged")
    if written > FORMAT:
        raise ConfigError(f"{where} was written in format {written} by a newer nsl_hpc (this one reads formats up "
                          f"to {FORMAT}): upgrade nsl_hpc to work on this sweep")
    return written


def upgrade_launch(launch: dict[str, Any], where: str) -> dict[str, Any]:
    """``launch`` (a stored launch config with its run settings, from ``where``, plain data) in the current format:
    a format-1 one with each of ``FORMAT_1_SETTINGS`` it lacks set to the value it ran with."""
    if format_of(launch, where) == 1:
        for key, value in FORMAT_1_SETTINGS:
            *parents, last = key.split(".")
            group = launch
            for parent in parents:
                group = group.setdefault(parent, {})
            group.setdefault(last, copy.deepcopy(value))
        launch["format"] = FORMAT
    return launch


def upgrade_decisions(table: pa.Table) -> pa.Table:
    """A budgeted round's decisions (budget/round-<r>.parquet) with the columns added since: ``resource`` (the
    envelope that made a task promising), null in rounds decided before it was recorded."""
    if "resource" not in table.column_names:
        table = table.append_column("resource", pa.nulls(table.num_rows, pa.string()))
    return table
