"""Expansion of a sweep's grid (``sweep.grid`` in config) into tasks: one dict of coordinates each."""

import itertools
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

from nsl_hpc.errors import ConfigError

# Axis order of the expansion (and of the manifest's columns); every axis is a `nsl_hpc.train` key.
GRID_AXES = ("system", "arch", "seed", "epochs", "data_tier", "width_tier", "depth_tier")


def validate_grid(grid: Mapping[str, Sequence[Any]]) -> None:
    """Raise ConfigError unless ``grid`` names exactly the axes of GRID_AXES, each with distinct values."""
    missing, unknown = set(GRID_AXES) - set(grid), set(grid) - set(GRID_AXES)
    axes = ", ".join(GRID_AXES)
    if unknown:
        raise ConfigError(f"unknown grid axis {sorted(unknown)[0]!r} in sweep.grid; axes: {axes}")
    if missing:
        raise ConfigError(f"sweep.grid lacks the axis {sorted(missing)[0]!r}; axes: {axes}")
    for axis in GRID_AXES:
        values = list(grid[axis])
        if not values:
            raise ConfigError(f"sweep.grid.{axis} is empty: the grid has zero tasks")
        if len(set(values)) != len(values):
            raise ConfigError(f"sweep.grid.{axis} repeats a value: {values}")


def grid_size(grid: Mapping[str, Sequence[Any]]) -> int:
    """Number of tasks: the product of the axis lengths."""
    size = 1
    for axis in GRID_AXES:
        size *= len(grid[axis])
    return size


def expand_grid(grid: Mapping[str, Sequence[Any]]) -> Iterator[dict[str, Any]]:
    """Every combination of axis values, in GRID_AXES order (the last axis varies fastest)."""
    validate_grid(grid)
    for values in itertools.product(*(list(grid[axis]) for axis in GRID_AXES)):
        yield dict(zip(GRID_AXES, values, strict=True))
