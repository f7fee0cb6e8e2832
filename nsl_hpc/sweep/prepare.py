"""Preparing a sweep directory: compose each (system, arch) config, validate and expand the grid (``build_sweep``,
writing nothing), then write the manifest and find which tasks still need to run (``prepare_sweep``, under the
sweep's lock). Nothing is submitted here."""

import itertools
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.compute as pc
from omegaconf import OmegaConf

from nsl_hpc.config import compose_config, plain, unknown_key
from nsl_hpc.core.errors import ConfigError, require_non_negative_int
from nsl_hpc.studies import study_named
from nsl_hpc.studies.base import Pair, Study
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.code import require_same_code
from nsl_hpc.sweep.failures import record_failure
from nsl_hpc.sweep.grid import Grid, build_manifest, grid_size, sub_grids, validate_grid
from nsl_hpc.sweep.launch_settings import LaunchSettings
from nsl_hpc.sweep.layout import base_config_path, row_path
from nsl_hpc.sweep.manifest import (
    manifest_path,
    read_launch_config,
    read_manifest,
    read_yaml,
    write_sweep,
    write_yaml,
)
from nsl_hpc.sweep.rows import row_states, set_aside
from nsl_hpc.sweep.task import check_settings
from nsl_hpc.sweep.task_states import read_sweep_state

LOG = logging.getLogger(__name__)

MISSING = object()


def override_key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")


def validate_launch(settings: LaunchSettings, overrides: Sequence[str]) -> Study:
    """Refuse, before any work, a launch with grid axes set outside the grid or a grid its study cannot expand;
    returns its study."""
    study = study_named(settings.study.name)
    for override in overrides:
        if override_key(override) in study.axes:
            raise ConfigError(f"{override_key(override)} is a grid axis of the sweep; set "
                              f"sweep.grid.{override_key(override)}=[...] instead of {override}")
    validate_grid(settings.sweep.grid, study)
    return study


def validate_grid_values(grid: Grid, study: Study, pairs: Mapping[tuple[str, str], Pair]) -> None:
    """Check every coordinate value of every sub-grid as a task would, for each of its (system, arch)."""
    for part in sub_grids(grid):
        for seed in part["seed"]:
            require_non_negative_int("sweep.grid.seed value", seed)
        for system, arch in itertools.product(part["system"], part["arch"]):
            for axis in study.size_axes:
                for value in part[axis]:
                    study.check_coordinate(f"sweep.grid.{axis} value", axis, value, pairs[system, arch])


# Keys whose overrides apply to the grid's (system, arch) pairs that have them: arch.feedthrough=true sets the
# input-affine pairs' option and leaves the others alone; a key no pair has is refused.
PAIR_KEYS = ("arch.", "system.")


def pair_configs(grid: Grid, overrides: Sequence[str], study: Study) -> dict[tuple[str, str], Pair]:
    """The typed settings of every (system, arch) of ``grid`` (``Study.pair``: its resolved plain config beside
    them), composed with the launch's overrides (those of ``PAIR_KEYS`` where the pair has the key), each checked by its
    study (``Study.check_pair``) and priced (``require_costs``)."""
    pairs = {(system, arch) for part in sub_grids(grid) for system in part["system"] for arch in part["arch"]}
    scoped = [o for o in overrides if o.lstrip("+~").startswith(PAIR_KEYS)]
    common = [o for o in overrides if o not in scoped]
    configs, used = {}, set()
    for system, arch in sorted(pairs):
        selection = [*common, f"system={system}", f"arch={arch}"]
        selected = compose_config(selection, "launch")
        applicable = [o for o in scoped if OmegaConf.select(selected, override_key(o), default=MISSING) is not MISSING]
        used.update(applicable)
        values = plain(compose_config([*applicable, *selection], "launch") if applicable else selected)
        configs[system, arch] = check_settings(values)
        study.check_pair(configs[system, arch])
        require_costs(values)
    for override in scoped:
        if override not in used:
            first = sorted(pairs)[0]
            raise ConfigError(unknown_key(override_key(override), [*common, f"system={first[0]}",
                                                                   f"arch={first[1]}"], "launch")
                              + "; no (system, arch) of the grid has it")
    return configs


PRICED_BY_ARCH = ("step_seconds", "params_per_overhead", "lockstep_extra")  # cost.* the planner needs per arch


def require_costs(base: Mapping[str, Any]) -> None:
    """Refuse an architecture the planner cannot price: each of ``PRICED_BY_ARCH`` needs an entry of its name."""
    arch = base["arch"]["name"]
    for key in PRICED_BY_ARCH:
        if arch not in base["cost"][key]:
            raise ConfigError(f"cost.{key} has no entry for arch {arch}: add cost.{key}.{arch} to your sweep "
                              f"(unstructured's is {base['cost'][key].get('unstructured')}; python -m nsl_hpc.bench "
                              "measures a package architecture's; docs/own_study.md)")


@dataclass(frozen=True)
class BuiltSweep:
    """A launch's grid, validated and expanded, before anything is written."""

    manifest: pa.Table
    configs: dict[tuple[str, str], Pair]  # the typed settings of each (system, arch)
    study: Study
    settings: LaunchSettings  # what its jobs run by, its sweep group among them
    above_max_flops: int = 0  # tasks of the grid left out by sweep.max_flops


@dataclass(frozen=True)
class PreparedSweep:
    sweep_dir: Path
    manifest: pa.Table
    todo: pa.Table  # manifest rows of runnable tasks without a row, none of them queued in SLURM
    infeasible: dict[str, str]  # task id -> why it cannot run as configured (e.g. a window longer than its data)
    configs: dict[tuple[str, str], Pair]  # the typed settings of each (system, arch)
    queued: int  # tasks without a row that are pending or running in SLURM (left alone)
    set_aside: int  # corrupt rows moved to corrupt/ (their tasks run again)
    done: int  # tasks with a valid row


def require_tasks_at_most(tasks: int, cap: int | None) -> None:
    """Refuse, before the grid is expanded, a grid of more than ``cap`` tasks (``max_tasks``; None: no cap)."""
    if cap is not None and tasks > cap:
        raise ConfigError(f"the grid has {tasks:,} tasks, more than max_tasks={cap:,} (expanding it takes about "
                          f"{tasks * 3e3 / 2**30:.1f} GB of memory here): shrink sweep.grid, or raise max_tasks "
                          "where that memory is yours")


def build_sweep(settings: LaunchSettings, overrides: Sequence[str]) -> BuiltSweep:
    """Validate everything a launch (``settings``, typed by ``check_run_settings``; ``overrides``, its command line)
    depends on and expand its grid; writes nothing."""
    study = validate_launch(settings, overrides)
    sweep, grid = settings.sweep, settings.sweep.grid
    require_tasks_at_most(grid_size(grid, study), settings.max_tasks)
    configs = pair_configs(grid, overrides, study)
    validate_grid_values(grid, study, configs)
    max_flops, column = sweep.max_flops, sweep.max_flops_column
    manifest = build_manifest(grid, study, configs, settings.sweep_seed)
    compute_columns = [name for name in manifest.column_names if name.startswith("flops")]
    if column not in compute_columns:
        raise ConfigError(f"sweep.max_flops_column={column!r} is not a compute column of this study's tasks; "
                          f"choose one of: {', '.join(compute_columns)}")
    if max_flops is None:
        return BuiltSweep(manifest, configs, study, settings)
    kept = manifest.filter(pc.less(manifest[column], max_flops))
    if kept.num_rows == 0:
        raise ConfigError(f"sweep.max_flops={max_flops:g} leaves no task of the grid (its least {column} is "
                          f"{pc.min(manifest[column]).as_py():.3g})")
    return BuiltSweep(kept, configs, study, settings, manifest.num_rows - kept.num_rows)


def prepare_sweep(built: BuiltSweep, sweep_dir: Path) -> PreparedSweep:
    """Write the sweep's files the first time (refusing a directory that holds another grid) and find the tasks
    to run: without a valid row (corrupt rows are set aside), not queued in SLURM. Call it holding the lock."""
    manifest, settings = built.manifest, built.settings
    if manifest_path(sweep_dir).exists():
        existing = read_manifest(sweep_dir, columns=["task_id"])["task_id"]
        if existing.to_pylist() != manifest["task_id"].to_pylist():
            stored = {pair: read_yaml(base_config_path(sweep_dir, *pair), sweep_dir) for pair in built.configs
                      if base_config_path(sweep_dir, *pair).exists()}
            stored_launch = read_yaml(sweep_dir / layout.LAUNCH_CONFIG, sweep_dir)
            changed = changed_settings(stored_launch, settings.values, built.study,
                                       {pair: (stored[pair], built.configs[pair].values) for pair in stored})
            raise ConfigError(f"sweep_dir={str(sweep_dir)!r} holds a different grid ({len(existing):,} tasks, "
                              f"this one has {len(manifest):,}; {'; '.join(changed) or 'other draws'}): choose "
                              "another sweep_dir or launch with the same sweep and overrides")
        read_launch_config(sweep_dir)  # a damaged one is refused here, before any work
        require_same_code(sweep_dir, built.configs, settings.allow_code_change)
        for (system, arch), pair in built.configs.items():  # a deleted one is restored: it is the same
            if not base_config_path(sweep_dir, system, arch).exists():
                write_yaml(pair.values, base_config_path(sweep_dir, system, arch), sweep_dir)
    else:
        write_sweep(sweep_dir, manifest, {key: pair.values for key, pair in built.configs.items()}, settings.values)
        require_same_code(sweep_dir, built.configs, settings.allow_code_change)
    without_row, aside = tasks_without_row(sweep_dir, manifest)
    queued = queued_tasks(sweep_dir)
    queued_ids = pa.array(sorted(queued), type=pa.string())
    todo = without_row.filter(pc.invert(pc.is_in(without_row["task_id"], value_set=queued_ids)))
    runnable, infeasible = split_runnable(todo, built.study, built.configs)
    return PreparedSweep(sweep_dir, manifest, runnable, infeasible, built.configs, len(queued), aside,
                         manifest.num_rows - without_row.num_rows)


def changed_settings(stored: Mapping[str, Any], launch: Mapping[str, Any], study: Study,
                     pairs: Mapping[tuple[str, str], tuple[Mapping[str, Any], Mapping[str, Any]]], shown: int = 4
                     ) -> list[str]:
    """'train.lr 0.001 -> 0.01': the outcome-changing settings (the grid, the sweep seed and the study's shared
    keys) in which the launch config ``launch`` differs from the ``stored`` one, or a (system, arch)'s config from
    its stored one (``pairs``: stored, new), the first ``shown`` of them; all plain."""
    keys = ("sweep", "sweep_seed", *study.shared_keys)
    compared = [(stored, launch), *pairs.values()]
    changes: list[str] = []
    for old, new in compared:
        changes += [change for key, before, after in
                    leaf_differences({k: old.get(k) for k in keys}, {k: new.get(k) for k in keys})
                    if (change := f"{key} {before!r} -> {after!r}") not in changes]
    return changes[:shown] + ([f"{len(changes) - shown} more"] if len(changes) > shown else [])


def leaf_differences(old: Any, new: Any, prefix: str = "") -> list[tuple[str, Any, Any]]:
    """(dotted key, old value, new value) of every leaf where two nested mappings differ."""
    if isinstance(old, dict) and isinstance(new, dict):
        return [change for key in sorted(old.keys() | new.keys(), key=str)
                for change in leaf_differences(old.get(key), new.get(key), f"{prefix}{key}.")]
    return [] if old == new else [(prefix.rstrip("."), old, new)]


def queued_tasks(sweep_dir: Path) -> set[str]:
    """Tasks without a row whose latest SLURM job is pending or running (one sacct call; none without
    submissions)."""
    if not any((Path(sweep_dir) / layout.SUBMISSIONS).glob("*.json")):
        return set()
    return {task_id for task_id, state in read_sweep_state(sweep_dir).states.items() if state in ("pending", "running")}


def prepare_shared_data(tasks: Sequence[Mapping[str, Any]], configs: Mapping[tuple[str, str], Pair],
                        study: Study) -> None:
    """Simulate (or read) into the cache the data the (system, arch) pairs of ``tasks`` share (the test sets),
    before any job starts: jobs then read it instead of all simulating it at once."""
    pairs = sorted({(task["system"], task["arch"]) for task in tasks})
    systems = sorted({system for system, _ in pairs})
    if not systems:
        return
    LOG.info(f"preparing the shared data of {', '.join(systems)} in {configs[pairs[0]].cache_dir}")
    done = set()
    for pair in pairs:
        if pair[0] not in done:
            study.prepare_data(configs[pair])
            done.add(pair[0])


def infeasible_tasks(tasks: pa.Table, study: Study, configs: Mapping[tuple[str, str], Pair]) -> dict[str, str]:
    """Task id -> reason, for the manifest rows ``tasks`` whose drawn sizes cannot run (``Study.check_task``)."""
    reasons = {}
    for task in tasks.to_pylist():
        try:
            study.check_task(task, task, configs[task["system"], task["arch"]])
        except ConfigError as error:
            reasons[task["task_id"]] = str(error)
    return reasons


def split_runnable(tasks: pa.Table, study: Study, configs: Mapping[tuple[str, str], Pair]
                   ) -> tuple[pa.Table, dict[str, str]]:
    """The manifest rows of ``tasks`` that can run as configured, and task id -> why for those that cannot:
    the one filter launch and resubmit share (a task that cannot run would take its lockstep group down)."""
    infeasible = infeasible_tasks(tasks, study, configs)
    runnable = pc.invert(pc.is_in(tasks["task_id"], value_set=pa.array(list(infeasible), type=pa.string())))
    return tasks.filter(runnable), infeasible


def describe_infeasible(sweep_dir: Path, infeasible: Mapping[str, str], record: bool) -> str:
    """The line that says how many tasks cannot run as configured, and why (one example); with ``record`` each is
    recorded as failed with its reason (status shows it, merge counts it)."""
    if record:
        for task_id, reason in infeasible.items():
            record_failure(sweep_dir, task_id, "failed", f"cannot run as configured: {reason}")
    count = len(infeasible)
    return (f"  {count:,} task{'s' if count > 1 else ''} cannot run as configured"
            + (": recorded as failed, not submitted" if record else " (dry run: not recorded)")
            + f"; e.g. {next(iter(infeasible.values()))}")


def tasks_without_row(sweep_dir: Path, manifest: pa.Table) -> tuple[pa.Table, int]:
    """Manifest rows of the tasks without a valid row on disk; corrupt rows are moved aside first (counted)."""
    aside, keep = 0, []
    for task_id, state in row_states(sweep_dir, manifest["task_id"].to_pylist()).items():
        if state == "corrupt":
            set_aside(row_path(sweep_dir, task_id))
            aside += 1
        keep.append(state != "done")
    return manifest.filter(pa.array(keep, type=pa.bool_())), aside
