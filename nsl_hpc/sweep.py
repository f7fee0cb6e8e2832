"""Preparing a sweep directory: compose each (system, arch) config, expand the grid, write the manifest,
and find which tasks still need to run. Nothing is submitted here."""

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa
import pyarrow.compute as pc
from omegaconf import DictConfig, OmegaConf

from nsl_hpc.atomic import write_text
from nsl_hpc.cli import compose_config
from nsl_hpc.errors import ConfigError
from nsl_hpc.grid import GRID_AXES, build_manifest, grid_size, validate_grid
from nsl_hpc.manifest import LAUNCH_CONFIG_FILE, manifest_path, read_manifest, write_sweep
from nsl_hpc.plan import predicted_seconds
from nsl_hpc.rows import row_path
from nsl_hpc.task import require_member, require_positive_int


def override_key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")


def validate_launch(cfg: DictConfig, overrides: Sequence[str]) -> None:
    """Refuse, before any work, a launch without a sweep, grid axes set outside the grid, bad grid values."""
    if "sweep" not in cfg:
        raise ConfigError("no sweep chosen: add +sweep=<name> (see conf/sweep/, e.g. +sweep=demo)")
    for override in overrides:
        if override_key(override) in GRID_AXES:
            raise ConfigError(f"{override_key(override)} is a grid axis of the sweep; set "
                              f"sweep.grid.{override_key(override)}=[...] instead of {override}")
    grid = cfg.sweep.grid
    validate_grid(grid)
    for axis in ("epochs", "data_tier", "width_tier", "depth_tier"):
        for value in grid[axis]:
            require_positive_int(f"sweep.grid.{axis} value", value)
    for axis, tiers in (("data_tier", "data"), ("width_tier", "width"), ("depth_tier", "depth")):
        for value in grid[axis]:
            require_member(f"sweep.grid.{axis} value", value, list(cfg.tiers[tiers]))
    for seed in grid.seed:
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ConfigError(f"sweep.grid.seed value {seed!r} must be a non-negative integer")


def pair_configs(cfg: DictConfig, overrides: Sequence[str]) -> dict[tuple[str, str], dict]:
    """The resolved plain config of every (system, arch) of the grid, with the launch's overrides."""
    return {(system, arch): OmegaConf.to_container(
                compose_config([*overrides, f"system={system}", f"arch={arch}"], "launch"), resolve=True)
            for system in cfg.sweep.grid.system for arch in cfg.sweep.grid.arch}


@dataclass(frozen=True)
class PreparedSweep:
    sweep_dir: Path
    manifest: pa.Table
    todo: pa.Table  # manifest rows of tasks without a row, with a `seconds` column (predicted)
    reused: bool  # the sweep directory already held this grid


def prepare_sweep(cfg: DictConfig, overrides: Sequence[str]) -> PreparedSweep:
    """Validate, expand and (first time) write the manifest; refuse a directory holding another grid."""
    validate_launch(cfg, overrides)
    sweep_dir = Path(cfg.sweep_dir)
    configs = pair_configs(cfg, overrides)
    manifest = build_manifest(cfg.sweep.grid, configs, cfg.sweep_seed)
    reused = manifest_path(sweep_dir).exists()
    if reused:
        existing = read_manifest(sweep_dir, columns=["task_id"])["task_id"]
        if existing.to_pylist() != manifest["task_id"].to_pylist():
            raise ConfigError(f"sweep_dir={str(sweep_dir)!r} holds a different grid ({len(existing):,} tasks, "
                              f"this one has {grid_size(cfg.sweep.grid):,} or other settings); choose another "
                              "sweep_dir or launch with the same sweep and overrides")
    else:
        write_sweep(sweep_dir, manifest, configs)
        write_text(OmegaConf.to_yaml(cfg), sweep_dir / LAUNCH_CONFIG_FILE)
    return PreparedSweep(sweep_dir, manifest, pending_tasks(sweep_dir, manifest, OmegaConf.to_container(cfg.cost)),
                         reused)


def pending_tasks(sweep_dir: Path, manifest: pa.Table, cost) -> pa.Table:
    """Manifest rows of the tasks that have no row on disk, with their predicted ``seconds``."""
    done = [row_path(sweep_dir, task_id).exists() for task_id in manifest["task_id"].to_pylist()]
    todo = manifest.filter(pc.invert(pa.array(done, type=pa.bool_())))
    seconds = [predicted_seconds(arch, steps, params, cost) for arch, steps, params in zip(
        todo["arch"].to_pylist(), todo["steps"].to_pylist(), todo["params"].to_pylist(), strict=True)]
    return todo.append_column("seconds", pa.array(seconds, type=pa.float64()))
