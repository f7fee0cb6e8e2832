"""The second hardening probe (issue 29): settings that would switch a protection off, grids too large for the
machine that expands them, overrides resubmit cannot honour, answers that were wrong with exit 0, and commands
that hung. Checkpoints that lie are in tests/test_checkpoints.py."""

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from nsl_hpc.config import compose_config
from nsl_hpc.errors import ConfigError
from nsl_hpc.resubmit import refuse_task_overrides
from nsl_hpc.sweep.failures import read_failures
from nsl_hpc.sweep.groups import held_locks
from nsl_hpc.sweep.layout import row_path
from nsl_hpc.sweep.plan import check_run_settings
from nsl_hpc.sweep.rows import row_state, write_row_atomically
from tests.sweeps import TINY_GRID, nsl


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
    (["compile=sometimes"], "compile='sometimes'; choose one of: auto, always, never"),
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


# 5. resubmit runs the sweep's tasks as launched: an override that would change them is refused, not ignored.
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


# 8. report with a tracking server that does not answer: one line within mlflow.timeout_s, nothing replaced.
@pytest.mark.e2e
@pytest.mark.parametrize("uri", ["http://127.0.0.1:9", "http://10.255.255.1:5000"])  # refused; unroutable
def test_report_with_a_tracking_server_that_does_not_answer_stops_before_writing(uri, tmp_path):
    sweep_dir = tmp_path / "sweep"
    assert nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={sweep_dir}", "dry_run=true").returncode == 0
    fits = sweep_dir / "nsl_fits.parquet"
    fits.write_bytes(b"the fits of an earlier report")
    started = time.monotonic()
    result = nsl("report", f"sweep_dir={sweep_dir}", f"mlflow.tracking_uri={uri}", "mlflow.timeout_s=2")
    assert time.monotonic() - started < 60
    assert result.returncode == 1 and len(result.stderr.splitlines()) == 1, result.stderr
    assert result.stderr.startswith(f"error: no MLflow tracking server answers at {uri} (mlflow.timeout_s=2; ")
    assert fits.read_bytes() == b"the fits of an earlier report" and not (sweep_dir / "results.parquet").exists()


# 9. A reader that goes away (| head -1) ends a command quietly, not with a BrokenPipeError traceback.
@pytest.mark.e2e
def test_a_closed_pipe_ends_status_quietly(tmp_path):
    sweep_dir = tmp_path / "sweep"
    assert nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={sweep_dir}", "dry_run=true").returncode == 0
    read, write = os.pipe()
    os.close(read)
    result = subprocess.run([sys.executable, "-m", "nsl_hpc.status", f"sweep_dir={sweep_dir}"], stdout=write,
                            stderr=subprocess.PIPE, text=True)
    os.close(write)
    assert result.returncode == 1 and result.stderr == ""


# 9. A row copied over another task's path is no row of that task: status and resubmit call it corrupt.
def test_a_row_copied_over_another_tasks_path_is_corrupt_not_done(tmp_path):
    mine, other = "0123456789abcdef", "fedcba9876543210"
    write_row_atomically({"task_id": mine, "nmae": 0.1}, row_path(tmp_path, mine))
    assert row_state(row_path(tmp_path, mine)) == "done"
    assert row_state(row_path(tmp_path, other)) == "missing"
    row_path(tmp_path, other).parent.mkdir(parents=True)
    shutil.copy(row_path(tmp_path, mine), row_path(tmp_path, other))
    assert row_state(row_path(tmp_path, other)) == "corrupt"


# 3. A grid too large for the machine that expands it is refused before anything is written or expanded.
@pytest.mark.e2e
def test_a_grid_above_max_tasks_is_refused_before_anything_is_written(tmp_path):
    sweep_dir = tmp_path / "sweep"
    result = nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={sweep_dir}", "dry_run=true", "max_tasks=3")
    assert result.returncode == 2 and len(result.stderr.splitlines()) == 1
    assert result.stderr.startswith("error: the grid has 4 tasks, more than max_tasks=3 (expanding it takes")
    assert not sweep_dir.exists()
    assert "max_tasks=250000" in nsl("launch", "--help").stdout  # the default, documented


# 6. A local worker killed or stopped: its group recorded, the other workers finish, the launch says what happened.
@pytest.mark.e2e
@pytest.mark.parametrize(("sent", "state", "reason"), [
    (signal.SIGKILL, "failed", "died while training it (kill -9, the OOM killer?)"),
    (signal.SIGSTOP, "frozen", "stopped answering: its group's lock was not renewed for"),
])
def test_a_local_worker_killed_or_stopped_is_recorded_and_the_others_finish(sent, state, reason, tmp_path):
    """4 tasks on 2 workers, a task each at a time: the worker of the first group to take its lock gets ``sent``
    (SIGSTOP, to it and its training process: noticed after watchdog.worker_silence_s=30); its group is recorded,
    its other task is not run, the other worker's two tasks finish."""
    sweep_dir = tmp_path / "sweep"
    launch = subprocess.Popen([sys.executable, "-m", "nsl_hpc.launch", *TINY_GRID, "sweep.grid.epochs=[4000]",
                               "launcher=local", "launcher.workers=2", "lockstep.enabled=false",
                               "watchdog.worker_silence_s=30", f"sweep_dir={sweep_dir}"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    locks = []
    while not locks:
        assert launch.poll() is None, launch.stderr.read()
        time.sleep(0.2)
        locks = [lock for lock in held_locks(sweep_dir) if lock.task_ids]
    if sent == signal.SIGSTOP:  # the worker and its training process: a stopped or stuck process tree
        children = Path(f"/proc/{locks[0].pid}/task/{locks[0].pid}/children")
        while not children.read_text().split():  # the lock is taken just before the training process starts
            time.sleep(0.05)
        for child in children.read_text().split():
            os.kill(int(child), sent)
    os.kill(locks[0].pid, sent)
    if sent == signal.SIGSTOP:  # 30 s before it is noticed: the sweep runs, and status and merge say so
        status, merged = nsl("status", f"sweep_dir={sweep_dir}").stdout, nsl("merge", f"sweep_dir={sweep_dir}").stdout
        assert re.search(r"running [12] \|", status) and "missing 0 |" in status, status
        assert "0 of 4 tasks (0.0%) dropped" in merged and "still running or queued in a running launch" in merged
    out, _ = launch.communicate(timeout=300)
    assert launch.returncode == 1
    assert f"finished: 1 {state}, 1 not run, 2 ok" in out and "the other workers go on" in out, out
    failure = read_failures(sweep_dir)[locks[0].task_ids[0]]
    assert failure["status"] == state and reason in failure["reason"]
    status = nsl("status", f"sweep_dir={sweep_dir}").stdout
    assert "done 2 |" in status and f"{state} 1 |" in status and "missing 1 |" in status
