"""Run again the tasks of a sweep that have no row: failed, frozen, timed out or missing (cancelled,
lost, never submitted). Finished tasks are never re-run and rows never duplicated; running and pending
tasks are left alone.

    python -m nsl_hpc.resubmit sweep_dir=runs/input_state
    python -m nsl_hpc.resubmit sweep_dir=runs/input_state 'states=[timeout]' time_factor=4

It uses the launcher, packing and cost settings the sweep was launched with (<sweep_dir>/launch.yaml).
"""

import sys

from omegaconf import DictConfig, OmegaConf

from nsl_hpc import cli
from nsl_hpc.errors import ConfigError
from nsl_hpc.launcher import dispatch
from nsl_hpc.manifest import LAUNCH_CONFIG_FILE, base_config_path, require_sweep
from nsl_hpc.plan import lockstep_settings, make_packs, packing_for, planned_groups
from nsl_hpc.studies import study_named
from nsl_hpc.sweep import prepare_shared_data
from nsl_hpc.sweep_state import read_sweep_state

RESUBMITTABLE = ("failed", "frozen", "timeout", "missing")


def main(cfg: DictConfig) -> int:
    sweep_dir = require_sweep(cfg.sweep_dir)
    bad = sorted(set(cfg.states) - set(RESUBMITTABLE))
    if bad:
        raise ConfigError(f"states={list(cfg.states)} has {bad[0]!r}; choose from {', '.join(RESUBMITTABLE)}")
    if not cfg.time_factor >= 1:
        raise ConfigError(f"time_factor={cfg.time_factor} must be at least 1")
    launch = OmegaConf.load(f"{sweep_dir}/{LAUNCH_CONFIG_FILE}")
    state = read_sweep_state(sweep_dir)
    tasks = [task for task in state.manifest if state.states[task["task_id"]] in cfg.states]
    if not tasks:
        print(f"nothing to resubmit: no task is {' / '.join(cfg.states)}")
        return 0
    packing = packing_for(launch.packing, launch.launcher.name, cfg.time_factor)
    groups, seconds = planned_groups(tasks, lockstep_settings(launch), OmegaConf.to_container(launch.cost))
    packs = make_packs(groups, seconds, packing)
    print(f"resubmitting {len(tasks):,} tasks ({', '.join(cfg.states)}) in {len(packs):,} jobs")
    configs = {pair: OmegaConf.to_container(OmegaConf.load(base_config_path(sweep_dir, *pair)), resolve=True)
               for pair in {(task["system"], task["arch"]) for task in tasks}}
    prepare_shared_data(tasks, configs, study_named(launch.study.name))
    return dispatch(sweep_dir, packs, launch.launcher, launch.sweep.name)

if __name__ == "__main__":
    cli.run(main, __doc__, config_name="resubmit")
    sys.exit(0)
