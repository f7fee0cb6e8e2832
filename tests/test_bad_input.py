"""Bad input is one line, a non-zero exit, before any work, and touches nothing computed: launch settings and
grids (checked where the config is composed), text that would break a batch script, resubmit overrides that would
change the tasks."""

import os
import re
import subprocess
import sys

import pytest

from nsl_hpc.config import compose_config, tool_settings
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.resubmit import refuse_task_overrides
from nsl_hpc.sweep.launch_settings import check_run_settings
from tests.sweeps import TINY_GRID, nsl

LOCAL = [*TINY_GRID, "launcher=local"]


# Every numeric run setting is finite and in its range, checked where the config is composed.
@pytest.mark.parametrize(("overrides", "message"), [
    (["watchdog.overrun_factor=nan"], "watchdog.overrun_factor=nan must be a finite number in [1, 1000]"),
    (["watchdog.overrun_factor=inf"], "watchdog.overrun_factor=inf must be a finite number in [1, 1000]"),
    (["watchdog.heartbeat_timeout_s=1e300"], "watchdog.heartbeat_timeout_s=1e+300 must be a finite number in (0, "),
    (["checkpoint.every_minutes=nan"], "checkpoint.every_minutes=nan must be a finite number in [0.1, 10080] (or 0"),
    (["checkpoint.every_minutes=1e-9"], "checkpoint.every_minutes=1e-09 must be a finite number in [0.1, 10080]"),
    (["cost.startup_s=-1"], "cost.startup_s=-1 must be a finite number in [0, 3600]"),
    (["cost.step_seconds.narx=inf"], "cost.step_seconds.narx=inf must be a finite number in (0, 3600]"),
    (["launcher.workers=100000"], "launcher.workers=100000 must be an integer from 1 to"),
    (["packing.time_classes_minutes=[]"], "packing.time_classes_minutes=[] must be a list of at least one value"),
    (["packing.time_safety=nan"], "packing.time_safety=nan must be a finite number in [1, 100]"),
    (["launcher=slurm", "launcher.array_parallelism=0"], "launcher.array_parallelism=0 must be a positive integer"),
    (["launcher=slurm", "launcher.max_array_size=0"], "launcher.max_array_size=0 must be a positive integer"),
    (["launcher=slurm", "launcher.max_array_size=-1"], "launcher.max_array_size=-1 must be a positive integer"),
    (["launcher=slurm", "launcher.max_job_count=-5"], "launcher.max_job_count=-5 must be a positive integer"),
    (["launcher=slurm", "launcher.mem=abc"], "launcher.mem='abc' is no sbatch --mem"),
    (["launcher=slurm", "launcher.mem=0G"], "launcher.mem='0G' is no sbatch --mem"),
    (["launcher=slurm", "launcher.signal_delay_s=0"], "launcher.signal_delay_s=0 must be a positive integer"),
    (["cost.compile_speedup.unstructured=0"], "cost.compile_speedup.unstructured=0 must be a finite number in (0, "),
    (["cost.compile_s.subnet=null"], "cost.compile_speedup.subnet needs cost.compile_s.subnet"),
    (["cost.compile_s.unstructured=-1"], "cost.compile_s.unstructured=-1 must be a finite number in [0, 86400]"),
    (["compile=sometimes"], "compile='sometimes' is unknown; choose one of: auto, always, never"),
])
def test_settings_that_would_switch_a_protection_off_are_refused_in_one_line(overrides, message):
    launch = compose_config(["+sweep=demo", *overrides], "launch")
    with pytest.raises(ConfigError) as error:
        check_run_settings(launch)
    assert str(error.value).startswith(message) and "\n" not in str(error.value), str(error.value)


@pytest.mark.parametrize("overrides", [[], ["checkpoint.every_minutes=0"], ["checkpoint.every_minutes=0.1"],
                                       ["launcher=slurm", "launcher.mem=1500M", "launcher.max_array_size=1001"],
                                       ["compile=never"], ["compile=always"]])
def test_sane_run_settings_pass(overrides):
    check_run_settings(compose_config(["+sweep=demo", *overrides], "launch"))


# Resubmit runs the sweep's tasks as launched: an override that would change them is refused, not ignored.
@pytest.mark.parametrize("override", ["train.lr=0.5", "system=ball", "+sweep=demo", "sweep_seed=3", "epochs=8",
                                      "test_set=100x100s", "cache_dir=/tmp/other"])
def test_resubmit_refuses_an_override_that_would_change_the_tasks(override):
    with pytest.raises(ConfigError, match=f"^{re.escape(override)} would change the tasks: resubmit runs them as"):
        refuse_task_overrides([override])


def test_resubmit_refuses_it_in_one_line_before_reading_the_sweep(tmp_path):
    result = nsl("resubmit", f"sweep_dir={tmp_path}", "train.lr=0.5")
    assert result.returncode == 2 and len(result.stderr.splitlines()) == 1 and "launch other tasks" in result.stderr


def test_resubmit_still_takes_run_settings_and_its_own_keys():
    refuse_task_overrides(["launcher=slurm", "launcher.partition=long", "watchdog.overrun_factor=50",
                           "cost.startup_s=60", "packing.pack_minutes=60", "lockstep.size=16",
                           "checkpoint.every_minutes=1", "states=[failed]", "time_factor=2", "sweep_dir=x",
                           "allow_shared_sweep_dir=true", "launcher.hold=true"])


# A grid too large for the machine that expands it is refused before anything is written or expanded.
@pytest.mark.e2e
def test_a_grid_above_max_tasks_is_refused_before_anything_is_written(tmp_path):
    sweep_dir = tmp_path / "sweep"
    result = nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={sweep_dir}", "dry_run=true", "max_tasks=3")
    assert result.returncode == 2 and len(result.stderr.splitlines()) == 1
    assert result.stderr.startswith("error: the grid has 4 tasks, more than max_tasks=3 (expanding it takes")
    assert not sweep_dir.exists()
    assert "max_tasks=250000" in nsl("launch", "--help").stdout  # the default, documented


@pytest.mark.e2e
@pytest.mark.parametrize(("override", "message"), [
    ("sweep.grid.epochs=4", "sweep.grid.epochs=4 must be a list of values"),
    ("sweep.grid.epochs=null", "sweep.grid.epochs=None must be a list of values"),
    ("sweep.grid=[]", "Error merging override sweep.grid=[]"),
    ("launcher.workers=-1", "launcher.workers=-1 must be an integer from 1 to"),
    ("launcher.workers=abc", "launcher.workers=abc: Value 'abc' of type 'str' could not be converted to Integer"),
    ("train.lr=-1", "train.lr=-1 must be a finite number in (0, inf)"),
    ("watchdog.heartbeat_timeout_s=-1", "watchdog.heartbeat_timeout_s=-1 must be a finite number in (0, 86400]"),
    ("watchdog.overrun_factor=nan", "watchdog.overrun_factor=nan must be a finite number in [1, 1000]"),
])
def test_bad_launch_settings_are_one_line_before_anything_is_written(override, message, tmp_path):
    sweep_dir = tmp_path / "sweep"
    result = nsl("launch", *LOCAL, f"sweep_dir={sweep_dir}", override)
    assert result.returncode == 2 and result.stderr.splitlines() == [f"error: {result.stderr[7:].strip()}"]
    assert message in result.stderr
    assert not sweep_dir.exists()


@pytest.mark.e2e
@pytest.mark.parametrize(("override", "message"), [
    ("launcher.partition='cpu\nexit'", "launcher.partition='cpu\\nexit' holds '\\n' at position 3: it would break the "
                                        "job's batch script (no whitespace or control characters)"),
    ("+launcher.extra_sbatch.constraint='a\rb'", "launcher.extra_sbatch.constraint='a\\rb' holds '\\r' at position 1"),
    ("+launcher.extra_sbatch.comment='two words'", "launcher.extra_sbatch.comment='two words' holds ' ' at position 3"),
    ("+launcher.extra_sbatch.x=[1,2]", "launcher.extra_sbatch.x=[1, 2] must be one value (a string or a number)"),
    ("+launcher.extra_sbatch.hold=true", "launcher.extra_sbatch.hold is set by the launcher itself (it plans --hold "
                                         "for every job): use launcher.hold"),
    ("+launcher.extra_sbatch.time=1", "launcher.extra_sbatch.time is set by the launcher itself (it plans --time for "
                                      "every job): use launcher.max_time_minutes (the plan gives each array the time "
                                      "its tasks need, up to that cap)"),
    ("+launcher.extra_sbatch.nodes=2", "launcher.extra_sbatch.nodes is set by the launcher itself (it plans --nodes "
                                       "for every job): each task is a single-CPU job element on one node"),
    ("+launcher.extra_sbatch.cpus_per_task=2", "launcher.extra_sbatch.cpus_per_task is set by the launcher itself"),
    ("launcher.extra_sbatch={x: 1}", "launcher.extra_sbatch takes its flags one at a time: +launcher.extra_sbatch."
                                     "<flag>=<value> (e.g. +launcher.extra_sbatch.constraint=cpu)"),
    ("launcher.setup=['module load python\nrm -rf x']", "launcher.setup line='module load python\\nrm -rf x' holds "
                                                        "'\\n' at position 18: it would break the job's batch script "
                                                        "(no control characters)"),
    ("sweep.name='a\tb'", "sweep.name='a\\tb' holds '\\t' at position 1"),
])
def test_text_that_would_break_a_batch_script_is_one_line_before_anything_is_written(override, message, tmp_path):
    sweep_dir = tmp_path / "sweep"
    result = nsl("launch", *LOCAL, "launcher=slurm", f"sweep_dir={sweep_dir}", "dry_run=true", override)
    assert result.returncode == 2 and len(result.stderr.splitlines()) == 1, result.stderr
    assert message in result.stderr
    assert not sweep_dir.exists()


def test_a_system_of_the_other_study_is_one_line_naming_the_study_to_add(tmp_path):
    """The README's one-task line with a measured system: what is missing is study=input_output, said before the
    system's interpolations (they read the input-output study's data_dir) and before anything is written."""
    result = nsl("train", "system=silverbox", "arch=narx", f"out_dir={tmp_path}")
    assert result.returncode == 2 and result.stderr == (
        "error: system=silverbox belongs to the input_output study, not input_state; add study=input_output (or "
        "pick a system of the input_state study)\n")
    assert not any(tmp_path.iterdir())


def test_a_slurm_launch_where_slurm_is_not_installed_is_one_line_before_anything_is_written(tmp_path):
    """No SLURM command on PATH (a laptop): launch launcher=slurm says where to run it and writes no sweep
    directory; its dry run still prints the plan, saying the cluster's limits were not read."""
    env = {**os.environ, "PATH": str(tmp_path / "empty")}  # python by its full path; nothing else on PATH
    launch = [sys.executable, "-m", "nsl_hpc.launch", *TINY_GRID, "launcher=slurm", f"sweep_dir={tmp_path / 'sweep'}"]
    refused = subprocess.run(launch, env=env, capture_output=True, text=True, timeout=120)
    assert refused.returncode == 2 and refused.stderr == (
        "error: scontrol not found: launcher=slurm needs SLURM's client commands; run this on the cluster's login "
        "node (or use launcher=local on this machine)\n")
    assert not (tmp_path / "sweep").exists()
    planned = subprocess.run([*launch, "dry_run=true"], env=env, capture_output=True, text=True, timeout=120)
    assert planned.returncode == 0, planned.stderr
    assert "the cluster's limits were not read, the plan below does not fit them: scontrol not found" in \
        planned.stdout + planned.stderr
    assert "dry run: nothing submitted" in planned.stdout


@pytest.mark.parametrize(("name", "override", "said"), [
    ("reproduction", "no_such=1", "error: Key 'no_such' is not in struct"),
    ("mechanisms", "only=[a", "error: while parsing a flow sequence"),
    ("nmse_tail", "tail=1", "error: Key 'tail' is not in struct"),
])
def test_a_tools_bad_override_is_one_line(name, override, said):
    """The tools' own files (benchmarks/reproduction_status.py, score_record.py, mechanisms.py, nmse_tail.py): a key
    the file does not have or a value that does not parse is one line, before any work."""
    with pytest.raises(SystemExit) as refused:
        tool_settings(name, [override])
    assert str(refused.value.code).startswith(said) and "\n" not in str(refused.value.code)
