"""The manifest of a sweep: one row per task with its id, grid coordinates and drawn sizes.

``<sweep_dir>/manifest.parquet`` has the columns ``task_id``, the grid axes under their ``nsl_hpc.train``
names (system, arch, seed, epochs, data_tier, width_tier, depth_tier), ``sweep_seed``, the drawn sizes
(data_size, n_traj, width, depth) and what they imply (train_points, params, steps, flops).
``<sweep_dir>/configs/<system>__<arch>.yaml`` holds the resolved task config shared by those tasks; a task's
own config is that with its manifest row's values set.
"""

from collections.abc import Iterable, Mapping
from functools import cache
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq
from omegaconf import DictConfig, OmegaConf

from nsl_hpc.atomic import write_parquet, write_text
from nsl_hpc.datasets import points_per_trajectory, training_points
from nsl_hpc.grid import GRID_AXES, expand_grid
from nsl_hpc.models import build_model
from nsl_hpc.models.blocks import parameter_count
from nsl_hpc.systems import SYSTEMS
from nsl_hpc.task import TASK_OUTCOME_KEYS, draw_sizes, shared_identity, task_id_from
from nsl_hpc.training import batch_count

MANIFEST_FILE = "manifest.parquet"
TASK_SCALARS = (*GRID_AXES, "sweep_seed")


def manifest_path(sweep_dir: Path) -> Path:
    return Path(sweep_dir) / MANIFEST_FILE


def base_config_path(sweep_dir: Path, system: str, arch: str) -> Path:
    return Path(sweep_dir) / "configs" / f"{system}__{arch}.yaml"


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


def write_sweep(sweep_dir: Path, manifest: pa.Table, base_configs: Mapping[tuple[str, str], Mapping]) -> None:
    """Write the manifest and the shared task configs (atomically, configs first)."""
    for (system, arch), values in base_configs.items():
        write_text(OmegaConf.to_yaml(OmegaConf.create(dict(values))), base_config_path(sweep_dir, system, arch))
    write_parquet(manifest, manifest_path(sweep_dir))


def read_manifest(sweep_dir: Path, columns: list[str] | None = None) -> pa.Table:
    return pq.read_table(manifest_path(sweep_dir), columns=columns)


def task_config(sweep_dir: Path, task: Mapping[str, Any]) -> DictConfig:
    """The full config of one manifest row ``task`` (a dict with the manifest's columns)."""
    cfg = OmegaConf.load(base_config_path(sweep_dir, task["system"], task["arch"]))
    for key in (*TASK_OUTCOME_KEYS, "task_id"):  # system and arch are the base config's groups
        cfg[key] = task[key]
    return cfg
