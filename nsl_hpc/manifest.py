"""The manifest of a sweep: one row per task with its id, grid coordinates and drawn sizes.

``<sweep_dir>/manifest.parquet`` has the columns ``task_id``, the grid axes under their ``nsl_hpc.train``
names (system, arch, seed, epochs, data_tier, width_tier, depth_tier), ``sweep_seed``, the drawn sizes
(data_size, n_traj, width, depth) and what they imply (train_points, params, steps, flops).
``<sweep_dir>/configs/<system>__<arch>.yaml`` holds the resolved task config shared by those tasks; a task's
own config is that with its manifest row's values set.
"""

from collections.abc import Mapping
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
from omegaconf import OmegaConf

from nsl_hpc.atomic import write_parquet, write_text
from nsl_hpc.errors import ConfigError

MANIFEST_FILE = "manifest.parquet"
LAUNCH_CONFIG_FILE = "launch.yaml"  # the launch's whole config: launcher, packing and cost settings


def manifest_path(sweep_dir: Path) -> Path:
    return Path(sweep_dir) / MANIFEST_FILE


def require_sweep(sweep_dir: str | Path) -> Path:
    """The sweep directory, refused with a one-line error unless it holds a manifest."""
    if not manifest_path(sweep_dir).exists():
        raise ConfigError(f"sweep_dir={str(sweep_dir)!r} has no manifest.parquet; launch a sweep there first")
    return Path(sweep_dir)


def base_config_path(sweep_dir: Path, system: str, arch: str) -> Path:
    return Path(sweep_dir) / "configs" / f"{system}__{arch}.yaml"


def write_sweep(sweep_dir: Path, manifest: pa.Table, base_configs: Mapping[tuple[str, str], Mapping]) -> None:
    """Write the manifest and the shared task configs (atomically, configs first)."""
    for (system, arch), values in base_configs.items():
        write_text(OmegaConf.to_yaml(OmegaConf.create(dict(values))), base_config_path(sweep_dir, system, arch))
    write_parquet(manifest, manifest_path(sweep_dir))


def read_manifest(sweep_dir: Path, columns: list[str] | None = None) -> pa.Table:
    return pq.read_table(manifest_path(sweep_dir), columns=columns)
