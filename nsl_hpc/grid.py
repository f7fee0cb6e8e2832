"""Expansion of a sweep's grid (``sweep.grid`` in config) into tasks, and into the manifest table:
one row per task with its id, coordinates, drawn sizes and what they imply."""

import itertools
from collections.abc import Iterable, Iterator, Mapping, Sequence
from functools import cache
from typing import Any

import pyarrow as pa

from nsl_hpc.datasets import points_per_trajectory, training_points
from nsl_hpc.errors import ConfigError
from nsl_hpc.models import build_model
from nsl_hpc.models.blocks import parameter_count
from nsl_hpc.systems import SYSTEMS
from nsl_hpc.task import draw_sizes, shared_identity, task_id_from
from nsl_hpc.training import batch_count

# Axis order of the expansion (and of the manifest's columns); every axis is a `nsl_hpc.train` key.
GRID_AXES = ("system", "arch", "seed", "epochs", "data_tier", "width_tier", "depth_tier")
TASK_SCALARS = (*GRID_AXES, "sweep_seed")


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


@cache
def model_parameters(arch_items: tuple, system: str, width: int, depth: int) -> int:
    """Parameter count of one architecture, built once per distinct shape."""
    system_class = SYSTEMS[system]
    model = build_model(dict(arch_items), system_class.state_dim, system_class.input_dim, width, depth)
    return parameter_count(model)


def build_manifest(grid: Mapping[str, Iterable[Any]], base_configs: Mapping[tuple[str, str], Mapping[str, Any]],
                   sweep_seed: int) -> pa.Table:
    """Expand ``grid`` into the manifest; ``base_configs[(system, arch)]`` is that pair's plain config."""
    identities = {pair: shared_identity(values) for pair, values in base_configs.items()}
    columns: dict[str, list] = {name: [] for name in (
        "task_id", *TASK_SCALARS, "data_size", "n_traj", "width", "depth", "train_points", "params", "steps",
        "flops")}
    sizes: dict[tuple, dict[str, Any]] = {}  # the draws do not depend on the epoch count: reuse them
    for task in expand_grid(grid):
        task["sweep_seed"] = sweep_seed
        key = tuple(task[axis] for axis in TASK_SCALARS if axis != "epochs")
        if key not in sizes:
            sizes[key] = drawn_sizes(task, base_configs[task["system"], task["arch"]])
        drawn = sizes[key]
        values = {**task, **drawn, "task_id": task_id_from(identities[task["system"], task["arch"]], task),
                  "steps": task["epochs"] * drawn["batches"],
                  "flops": float(drawn["params"]) * task["epochs"] * drawn["train_points"]}
        for name, column in columns.items():
            column.append(values[name])
    return pa.table(columns)


def drawn_sizes(task: Mapping[str, Any], base: Mapping[str, Any]) -> dict[str, Any]:
    """The sizes a task draws and what follows from them (points, parameters, batches per epoch)."""
    data_size, width, depth = draw_sizes(task["sweep_seed"], task["system"], task["arch"], task["seed"],
                                         task["data_tier"], task["width_tier"], task["depth_tier"])
    n_traj = data_size / base["data_per_trajectory"]
    points = training_points(n_traj, points_per_trajectory(base["system"]))
    return {"data_size": data_size, "n_traj": n_traj, "width": width, "depth": depth, "train_points": points,
            "params": model_parameters(tuple(base["arch"].items()), task["system"], width, depth),
            "batches": batch_count(points, base["train"]["batch_size"])}
