"""Expansion of a sweep's grid (``sweep.grid`` in config) into tasks, and into the manifest table:
one row per task with its id, coordinates, drawn sizes and what they imply.

``sweep.grid`` is one mapping of axis -> values (every combination is a task) or a list of such mappings
(the union of their combinations: e.g. widths that differ by architecture). The axes are the study's.
"""

import itertools
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import pyarrow as pa

from nsl_hpc.core.errors import ConfigError
from nsl_hpc.studies.base import Pair, Study
from nsl_hpc.sweep.task import task_id_from

Grid = Mapping[str, Sequence[Any]] | Sequence[Mapping[str, Sequence[Any]]]


def sub_grids(grid: Grid) -> list[Mapping[str, Sequence[Any]]]:
    """The product grids of ``grid``: itself when it is a mapping, else its members."""
    return [grid] if isinstance(grid, Mapping) else list(grid)


def validate_grid(grid: Grid, study: Study) -> None:
    """Raise ConfigError unless every sub-grid names exactly the study's axes, each with distinct values."""
    axes = ", ".join(study.axes)
    if not isinstance(grid, Mapping | Sequence) or isinstance(grid, str):
        raise ConfigError(f"sweep.grid={grid!r} must map each axis to its values (or be a list of such mappings)")
    parts = sub_grids(grid)
    if not parts:
        raise ConfigError("sweep.grid is an empty list: the grid has zero tasks")
    for index, part in enumerate(parts):
        where = "sweep.grid" if isinstance(grid, Mapping) else f"sweep.grid[{index}]"
        if not isinstance(part, Mapping):
            raise ConfigError(f"{where} must map each axis to its values; axes: {axes}")
        missing, unknown = set(study.axes) - set(part), set(part) - set(study.axes)
        if unknown:
            raise ConfigError(f"unknown grid axis {sorted(unknown)[0]!r} in {where}; axes of the {study.name} "
                              f"study: {axes}")
        if missing:
            raise ConfigError(f"{where} lacks the axis {sorted(missing)[0]!r}; axes of the {study.name} study: {axes}")
        for axis in study.axes:
            if not isinstance(part[axis], Sequence) or isinstance(part[axis], str):
                raise ConfigError(f"{where}.{axis}={part[axis]!r} must be a list of values, e.g. "
                                  f"{where}.{axis}=[{part[axis] if part[axis] is not None else '...'}]")
            values = list(part[axis])
            if not values:
                raise ConfigError(f"{where}.{axis} is empty: the grid has zero tasks")
            if len(set(values)) != len(values):
                raise ConfigError(f"{where}.{axis} repeats a value: {values}")


def grid_size(grid: Grid, study: Study) -> int:
    """Number of combinations: the sum over sub-grids of the product of their axis lengths."""
    total = 0
    for part in sub_grids(grid):
        size = 1
        for axis in study.axes:
            size *= len(part[axis])
        total += size
    return total


def expand_grid(grid: Grid, study: Study) -> Iterator[dict[str, Any]]:
    """Every combination of axis values, sub-grid after sub-grid, each in the study's axis order (the last
    axis varies fastest)."""
    validate_grid(grid, study)
    for part in sub_grids(grid):
        for values in itertools.product(*(list(part[axis]) for axis in study.axes)):
            yield dict(zip(study.axes, values, strict=True))


def build_manifest(grid: Grid, study: Study, pairs: Mapping[tuple[str, str], Pair], sweep_seed: int) -> pa.Table:
    """Expand ``grid`` into the manifest; ``pairs[(system, arch)]`` is that pair's typed settings. Refuses a grid
    with a repeated task (overlapping sub-grids)."""
    identities = {key: study.shared_identity(pair.values) for key, pair in pairs.items()}
    columns: dict[str, list] = {"task_id": []}
    sizes: dict[tuple, dict[str, Any]] = {}  # tasks of equal draw keys (shared draws) draw alike: reuse
    for task in expand_grid(grid, study):
        task["sweep_seed"] = sweep_seed
        pair = pairs[task["system"], task["arch"]]
        key = tuple(task[axis] for axis in study.draw_keys(pair.draws))
        if key not in sizes:
            sizes[key] = study.draw(task, pair)
        drawn = {**sizes[key], **study.training_length(task, sizes[key], pair)}
        values = {"task_id": task_id_from(study, identities[task["system"], task["arch"]], task), **task, **drawn}
        for name, value in values.items():
            columns.setdefault(name, []).append(value)
    manifest = pa.table(columns)
    if len(set(columns["task_id"])) != len(columns["task_id"]):
        raise ConfigError("sweep.grid lists some task twice (its sub-grids overlap); make them disjoint")
    return manifest
