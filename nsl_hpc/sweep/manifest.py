"""A sweep directory's own files, each with its one writer and its one reader.

- ``manifest.parquet``: one row per task with its id, the grid coordinates under their ``nsl_hpc.train`` names
  (system, arch, seed, epochs, data_tier, width_tier, depth_tier), ``sweep_seed``, the drawn sizes (data_size,
  n_traj, width, depth) and what they imply (train_points, params, steps, flops); created once, exclusively.
- ``configs/<system>__<arch>.yaml``: the resolved task config shared by those tasks; a task's own config is that
  with its manifest row's values set.
- ``launch.yaml``: the launch's whole config (grid, sweep seed, study, ...) and the directory's ``format``
  (``nsl_hpc.sweep.formats``: an older one is upgraded as it is read), written by the first launch.
- ``run.yaml``: the settings jobs run by (launcher, packing, cost, watchdog, lockstep, checkpoint), written at
  every launch or resubmit that dispatches work: resubmit starts from the last ones.
Paths inside the sweep directory are stored relative to it (``nsl_hpc.sweep.directory.portable_paths``), so a sweep can
be moved and its commands run from anywhere; a damaged file is a one-line error naming it.
"""

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pyarrow as pa
import yaml
from omegaconf import OmegaConf
from omegaconf._utils import get_yaml_loader

from nsl_hpc.config import plain
from nsl_hpc.core.atomic import create_parquet, read_parquet, write_text
from nsl_hpc.core.errors import ConfigError, damaged_file
from nsl_hpc.studies import study_named, study_of
from nsl_hpc.studies.base import Pair
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.directory import SWEEP_DIR_REFERENCE, portable_paths
from nsl_hpc.sweep.formats import FORMAT, upgrade_launch
from nsl_hpc.sweep.layout import base_config_path
from nsl_hpc.sweep.run_settings import RUN_KEYS


def manifest_path(sweep_dir: str | Path) -> Path:
    return Path(sweep_dir) / layout.MANIFEST


def require_sweep(sweep_dir: str | Path) -> Path:
    """The sweep directory, refused with a one-line error unless it holds a manifest."""
    if not manifest_path(sweep_dir).exists():
        raise ConfigError(f"sweep_dir={str(sweep_dir)!r} has no manifest.parquet; launch a sweep there first")
    return Path(sweep_dir)


def write_yaml(values: Mapping[str, Any], path: Path, sweep_dir: Path) -> None:
    write_text(OmegaConf.to_yaml(OmegaConf.create(portable_paths(values, sweep_dir))), path)


class StoredYamlLoader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # type: ignore[misc]
    """Reads what ``write_yaml`` wrote as ``OmegaConf.load`` does (its scalars: floats such as 1e-3, no
    timestamps), with libyaml's parser where PyYAML has it: 5x faster, a tenth of a rehearsal's job."""

    yaml_implicit_resolvers = get_yaml_loader().yaml_implicit_resolvers


def read_yaml(path: Path, sweep_dir: Path) -> dict[str, Any]:
    """A config written by ``write_yaml`` as plain data, its paths resolved against where the sweep directory is
    now (the ``${sweep_dir}`` references ``portable_paths`` wrote: the stored config's only interpolation). Read
    without OmegaConf, whose nodes for a config of this size take ~0.1 s: a third of a rehearsal's job."""
    try:
        values = yaml.load(Path(path).read_text(), Loader=StoredYamlLoader)
    except FileNotFoundError:
        raise ConfigError(f"{path} is missing; the sweep directory is damaged: restore it, or launch the sweep "
                          "into a new sweep_dir") from None
    except (yaml.YAMLError, ValueError, TypeError) as error:
        raise damaged_file(path, error) from None
    if not isinstance(values, dict):
        raise damaged_file(path, TypeError("not a mapping"))
    root = str(Path(sweep_dir).resolve())
    return {**with_sweep_dir(values, root), "sweep_dir": root}


def with_sweep_dir(value: Any, root: str) -> Any:
    """``value`` (stored plain data) with each ``${sweep_dir}`` in its strings replaced by ``root``."""
    if isinstance(value, dict):
        return {key: with_sweep_dir(item, root) for key, item in value.items()}
    if isinstance(value, list):
        return [with_sweep_dir(item, root) for item in value]
    if isinstance(value, str):
        return value.replace(SWEEP_DIR_REFERENCE, root)
    return value


def write_sweep(sweep_dir: Path, manifest: pa.Table, base_configs: Mapping[tuple[str, str], Mapping],
                launch: Mapping[str, Any]) -> None:
    """Write the shared task configs and the launch config (atomically), then create the manifest (exclusively:
    a concurrent launch that got there first makes this one fail)."""
    for (system, arch), values in base_configs.items():
        write_yaml(values, base_config_path(sweep_dir, system, arch), sweep_dir)
    write_yaml({**launch, "format": FORMAT}, Path(sweep_dir) / layout.LAUNCH_CONFIG, sweep_dir)
    try:
        create_parquet(manifest, manifest_path(sweep_dir))
    except FileExistsError:
        raise ConfigError(f"sweep_dir={str(sweep_dir)!r} got a manifest from another launch meanwhile; launch "
                          "again to compare grids") from None


def read_manifest(sweep_dir: Path, columns: list[str] | None = None) -> pa.Table:
    try:
        return read_parquet(manifest_path(sweep_dir), columns=columns)
    except (OSError, pa.ArrowException) as error:
        raise damaged_file(manifest_path(sweep_dir), error) from None


def read_base_config(sweep_dir: Path, system: str, arch: str) -> dict[str, Any]:
    """The task config shared by the tasks of (system, arch), with the settings added since it was stored at the
    value every task had before them (``Study.with_stored_defaults``, from ``config.identity``)."""
    cfg = read_yaml(base_config_path(sweep_dir, system, arch), sweep_dir)
    return study_of(cfg).with_stored_defaults(cfg)


def read_pair(sweep_dir: Path, system: str, arch: str) -> Pair:
    """The typed settings of the tasks of (system, arch) (``Study.pair`` of ``read_base_config``)."""
    values = read_base_config(sweep_dir, system, arch)
    return study_named(values["study"]["name"]).pair(values)


def read_launch_config(sweep_dir: Path) -> dict[str, Any]:
    """The launch's config with the run settings in force (``run.yaml``, when work was dispatched) over it."""
    launch = read_yaml(Path(sweep_dir) / layout.LAUNCH_CONFIG, sweep_dir)
    run_file = Path(sweep_dir) / layout.RUN_SETTINGS
    if run_file.exists():
        run = read_yaml(run_file, sweep_dir)
        for key in RUN_KEYS:  # each group replaced whole: a slurm launcher is no local one plus keys
            if key in run:  # one a format-1 sweep's run.yaml lacks is upgraded below
                launch[key] = run[key]
    return upgrade_launch(launch, str(Path(sweep_dir) / layout.LAUNCH_CONFIG))


def write_run_settings(sweep_dir: Path, cfg: Mapping[str, Any]) -> None:
    """Record the run settings of ``cfg`` (a launch config) as the ones jobs and the next resubmit use."""
    values = plain(cfg)
    write_yaml({key: values[key] for key in RUN_KEYS}, Path(sweep_dir) / layout.RUN_SETTINGS, sweep_dir)
