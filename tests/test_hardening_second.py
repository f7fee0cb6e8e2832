"""The second hardening probe (issue 29): settings that would switch a protection off, grids too large for the
machine that expands them, overrides resubmit cannot honour, answers that were wrong with exit 0, and commands
that hung. Checkpoints that lie are in tests/test_checkpoints.py."""

import pytest

from nsl_hpc.config import compose_config
from nsl_hpc.errors import ConfigError
from nsl_hpc.sweep.plan import check_run_settings


# 4. Every numeric run setting is finite and in its range, checked where the config is composed.
@pytest.mark.parametrize(("overrides", "message"), [
    (["watchdog.overrun_factor=nan"], "watchdog.overrun_factor=nan must be a finite number in [1, 1000]"),
    (["watchdog.overrun_factor=inf"], "watchdog.overrun_factor=inf must be a finite number in [1, 1000]"),
    (["watchdog.heartbeat_timeout_s=1e300"], "watchdog.heartbeat_timeout_s=1e+300 must be a finite number in (0, "),
    (["checkpoint.every_minutes=nan"], "checkpoint.every_minutes=nan must be a finite number in [0.1, 10080] (or 0"),
    (["checkpoint.every_minutes=1e-9"], "checkpoint.every_minutes=1e-09 must be a finite number in [0.1, 10080]"),
    (["cost.startup_s=-1"], "cost.startup_s=-1 must be a finite number in [0, 3600]"),
    (["cost.step_seconds.narx=inf"], "cost.step_seconds.narx=inf must be a finite number in (0, 3600]"),
    (["launcher.workers=100000"], "launcher.workers=100000 must be an integer from 1 to"),
    (["packing.time_classes_minutes=[]"], "packing.time_classes_minutes=[] needs at least one time limit"),
    (["packing.time_safety=nan"], "packing.time_safety=nan must be a finite number in [1, 100]"),
    (["launcher=slurm", "launcher.array_parallelism=0"], "launcher.array_parallelism=0 must be a positive integer"),
    (["launcher=slurm", "launcher.max_array_size=0"], "launcher.max_array_size=0 must be a positive integer"),
    (["launcher=slurm", "launcher.max_array_size=-1"], "launcher.max_array_size=-1 must be a positive integer"),
    (["launcher=slurm", "launcher.max_job_count=-5"], "launcher.max_job_count=-5 must be a positive integer"),
    (["launcher=slurm", "launcher.mem=abc"], "launcher.mem='abc' is no sbatch --mem"),
    (["launcher=slurm", "launcher.mem=0G"], "launcher.mem='0G' is no sbatch --mem"),
])
def test_settings_that_would_switch_a_protection_off_are_refused_in_one_line(overrides, message):
    launch = compose_config(["+sweep=demo", *overrides], "launch")
    with pytest.raises(ConfigError) as error:
        check_run_settings(launch)
    assert str(error.value).startswith(message) and "\n" not in str(error.value), str(error.value)


@pytest.mark.parametrize("overrides", [[], ["checkpoint.every_minutes=0"], ["checkpoint.every_minutes=0.1"],
                                       ["launcher=slurm", "launcher.mem=1500M", "launcher.max_array_size=1001"]])
def test_sane_run_settings_pass(overrides):
    check_run_settings(compose_config(["+sweep=demo", *overrides], "launch"))
