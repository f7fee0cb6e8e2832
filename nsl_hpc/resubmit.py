"""Run again the tasks of a sweep that have no valid row: failed, frozen, timed out, missing (cancelled, lost,
never submitted) or corrupt (the bad row is moved to corrupt/). Finished tasks are never re-run and rows never
duplicated; running and pending tasks are left alone.

    python -m nsl_hpc.resubmit sweep_dir=runs/input_state
    python -m nsl_hpc.resubmit sweep_dir=runs/input_state 'states=[timeout]' time_factor=4
    python -m nsl_hpc.resubmit sweep_dir=runs/input_state launcher=slurm launcher.partition=long
    python -m nsl_hpc.resubmit sweep_dir=runs/input_state 'states=[frozen]' watchdog.overrun_factor=100

It runs with the sweep's last run settings (launcher, packing, cost, watchdog, lockstep, checkpoint:
<sweep_dir>/run.yaml, written by every launch or resubmit that ran something), with those named on the command
line instead (a key that would change the tasks, such as train.lr, is refused: other tasks are a new sweep).
A group with a training checkpoint (its job crashed, was killed or lost its node) is run as that
group again and continues from the checkpoint.
"""

import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa
import pyarrow.compute as pc
from omegaconf import DictConfig, OmegaConf

from nsl_hpc import cli
from nsl_hpc.config.schema import field_names, setting, typed
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.studies import study_named
from nsl_hpc.sweep.code import require_same_code
from nsl_hpc.sweep.directory import check_control_files, private_umask, sweep_lock
from nsl_hpc.sweep.executors import run_jobs
from nsl_hpc.sweep.groups import saved_groups
from nsl_hpc.sweep.launch_settings import check_run_settings
from nsl_hpc.sweep.layout import row_path
from nsl_hpc.sweep.limits import cluster_limits, describe_fit, within_limits
from nsl_hpc.sweep.manifest import read_launch_config, read_manifest, read_pair, require_sweep
from nsl_hpc.sweep.prepare import describe_infeasible, override_key, split_runnable
from nsl_hpc.sweep.rows import set_aside
from nsl_hpc.sweep.run_settings import RUN_KEYS
from nsl_hpc.sweep.storage import read_storage
from nsl_hpc.sweep.task_states import read_sweep_state

RESUBMITTABLE = ("failed", "frozen", "timeout", "missing", "corrupt")


@dataclass(frozen=True)
class ResubmitSettings:
    """resubmit's own keys (conf/resubmit.yaml; the rest of its config is the sweep's run settings)."""

    sweep_dir: str = setting("the sweep directory (holds manifest.parquet)")
    states: list[str] = setting("which tasks without a valid row to run again", choices=RESUBMITTABLE, nonempty=True)
    time_factor: float = setting("multiply the time limits (e.g. 2 after timeouts)", 1, 1000)
    allow_shared_sweep_dir: bool = setting("true: run although others can write the sweep's control files")
    allow_code_change: bool = setting("true: run although the code of a system or arch of yours changed since its "
                                      "rows were made (each row's code column says which code made it)")


OWN_KEYS = field_names(ResubmitSettings)


def refuse_task_overrides(overrides: Sequence[str]) -> None:
    """A ConfigError for an override resubmit cannot honour: the tasks are the sweep's, as launched (another
    train.lr would be other tasks); only run settings and resubmit's own keys may be named."""
    for override in overrides:
        key = override_key(override)
        if key.split(".")[0] not in (*RUN_KEYS, *OWN_KEYS):
            raise ConfigError(f"{override} would change the tasks: resubmit runs them as launched and changes only "
                              f"run settings ({', '.join(RUN_KEYS)}); launch other tasks as a new sweep "
                              "(python -m nsl_hpc.launch ... sweep_dir=<new dir>)")


def with_named_settings(launch: DictConfig, cfg: DictConfig, overrides: Sequence[str]) -> DictConfig:
    """``launch`` (the sweep's config and last run settings) with the run settings the command line names:
    ``launcher=<name>`` replaces the launcher group, ``group.key=value`` one value, ``compile=<mode>`` the mode."""
    keys = [override_key(override) for override in overrides]
    if "launcher" in keys:
        launch.launcher = cfg.launcher
    for key in keys:
        group = key.split(".")[0]
        if key == "compile":  # the one run setting that is a value, not a group
            launch.compile = cfg.compile
        elif "." in key and group in RUN_KEYS and not (group == "launcher" and "launcher" in keys):
            OmegaConf.update(launch, key, OmegaConf.select(cfg, key), force_add=True)
    return launch


def main(config: DictConfig, overrides: Sequence[str]) -> int:
    refuse_task_overrides(overrides)
    cfg = typed(ResubmitSettings, OmegaConf.masked_copy(config, OWN_KEYS), "")
    sweep_dir = require_sweep(cfg.sweep_dir)
    with private_umask(), sweep_lock(sweep_dir, "resubmit"):
        launch = with_named_settings(OmegaConf.create(read_launch_config(sweep_dir)), config, overrides)
        check_control_files(sweep_dir, launch.compile_cache_dir, cfg.allow_shared_sweep_dir)
        settings = check_run_settings(launch)
        state = read_sweep_state(sweep_dir)
        if note := state.accounting_note():
            print(note)
        wanted = [task_id for task_id, task_state in state.states.items() if task_state in cfg.states]
        manifest = read_manifest(sweep_dir)
        selected = manifest.filter(pc.is_in(manifest["task_id"], value_set=pa.array(wanted, type=pa.string())))
        configs = {pair: read_pair(sweep_dir, *pair)
                   for pair in set(zip(selected["system"].to_pylist(), selected["arch"].to_pylist(), strict=True))}
        require_same_code(sweep_dir, configs, cfg.allow_code_change)
        runnable, infeasible = split_runnable(selected, study_named(settings.study.name), configs)
        if infeasible:
            print(describe_infeasible(sweep_dir, infeasible, record=True))
        tasks = runnable.to_pylist()
        if not tasks:
            print(f"nothing to resubmit: no task that can run is {' / '.join(cfg.states)}")
            return 0
        for task in tasks:
            if state.states[task["task_id"]] == "corrupt":
                set_aside(row_path(sweep_dir, task["task_id"]))
        limits = cluster_limits(settings)
        packs = (within_limits(settings, limits) if limits else settings).plan(
            tasks, cfg.time_factor, [saved.task_ids for saved in saved_groups(sweep_dir)])
        print(f"resubmitting {len(tasks):,} tasks ({', '.join(cfg.states)}) in {len(packs):,} jobs "
              f"({launch.launcher.name})")
        for line in describe_fit(limits, read_storage(sweep_dir), packs, len(tasks),
                                 settings.checkpoint.every_minutes > 0, settings.feed_minutes):
            print(f"  {line}")
        return run_jobs(sweep_dir, settings, packs, tasks, configs, limits)


def sweeps_launcher(argv: Sequence[str]) -> list[str]:
    """``["launcher=<the sweep's launcher>"]`` to compose the config with where ``argv`` names launcher keys but
    no launcher (a ``launcher.partition=cpu`` changes the sweep's slurm launcher, not the default local one);
    else none."""
    overrides = [argument.lstrip("+~") for argument in argv]
    sweep_dirs = [argument.split("=", 1)[1] for argument in overrides if argument.startswith("sweep_dir=")]
    if not sweep_dirs or not any(argument.startswith("launcher.") for argument in overrides) or \
            any(argument.startswith("launcher=") for argument in overrides):
        return []
    try:
        return [f"launcher={read_launch_config(Path(sweep_dirs[-1]))['launcher']['name']}"]
    except (ConfigError, OSError, KeyError, TypeError):  # main refuses a bad sweep_dir in its own words
        return []


if __name__ == "__main__":
    cli.run(main, __doc__, config_name="resubmit", pass_overrides=True, composed_with=sweeps_launcher(sys.argv[1:]))
