"""Launching a SLURM sweep twice submits nothing twice: tasks pending or running in SLURM are left to their
jobs (issue: launch and resubmit ignored what was queued)."""

import subprocess
import time

import pytest

from tests.sweeps import TINY_GRID, nsl

pytestmark = pytest.mark.slurm


def queued_arrays(name: str) -> set[str]:
    out = subprocess.run(["squeue", "-h", "-n", name, "-o", "%F"], capture_output=True, text=True, check=True).stdout
    return set(out.split())


def test_a_second_launch_leaves_queued_tasks_to_their_jobs(slurm_cluster, tmp_path):
    sweep_dir = tmp_path / "sweep"
    held = [*TINY_GRID, "launcher=slurm", f"sweep_dir={sweep_dir}", "launcher.hold=true",
            "packing.enabled=false", "lockstep.enabled=false", "sweep.name=held-sweep"]
    first = nsl("launch", *held)
    assert first.returncode == 0 and "submitted 4 jobs in 1 arrays" in first.stdout, first.stderr
    try:
        assert len(queued_arrays("nsl-held-sweep")) == 1
        second = nsl("launch", *held)
        assert second.returncode == 0, second.stderr
        assert "4 queued in SLURM (not submitted again)" in second.stdout and "nothing to run" in second.stdout
        resubmitted = nsl("resubmit", f"sweep_dir={sweep_dir}")
        assert "nothing to resubmit" in resubmitted.stdout
        assert len(queued_arrays("nsl-held-sweep")) == 1  # still the first array alone
        status = nsl("status", f"sweep_dir={sweep_dir}")
        assert "pending 4" in status.stdout
    finally:
        subprocess.run(["scancel", "-n", "nsl-held-sweep"], check=False)


def test_a_job_trains_nothing_over_a_compile_cache_others_can_write(slurm_cluster, tmp_path):
    """The compile cache turned writable by others after the launch checked it: each job checks it again before
    anything compiles, and records its tasks failed instead of running them (Inductor unpickles what it finds)."""
    sweep_dir = tmp_path / "sweep"
    held = [*TINY_GRID, "launcher=slurm", f"sweep_dir={sweep_dir}", "launcher.hold=true",
            "sweep.name=shared-cache"]
    launched = nsl("launch", *held)
    assert launched.returncode == 0, launched.stderr
    try:
        cache = sweep_dir / "compile_cache"
        cache.mkdir(exist_ok=True)
        cache.chmod(0o777)
        for job in queued_arrays("nsl-shared-cache"):
            subprocess.run(["scontrol", "release", job], check=True)
        status = nsl("status", f"sweep_dir={sweep_dir}", "wait=true", "interval_s=1")
        assert "failed 4" in status.stdout, status.stdout + status.stderr
        assert f"not run: {cache} is not safe: group and others can write it" in status.stdout
        assert not list((sweep_dir / "rows").rglob("*.parquet"))
    finally:
        subprocess.run(["scancel", "-n", "nsl-shared-cache"], check=False)


def test_a_stopped_job_holds_its_tasks_and_nothing_is_queued_again(slurm_cluster, tmp_path):
    """A job stopped by a signal (scancel --signal=STOP: squeue says STOPPED) still holds its tasks: status counts
    them running, not missing, and resubmit queues none again (issue: they were submitted a second time, and after
    SIGCONT both trained them)."""
    sweep_dir = tmp_path / "sweep"
    slow = [*TINY_GRID, "launcher=slurm", f"sweep_dir={sweep_dir}", "sweep.name=stopped", "sweep.grid.epochs=[640]",
            "fault.kind=slow", "fault.heartbeat_s=0.25"]  # ~10 s of training, mostly asleep
    launched = nsl("launch", *slow)
    assert launched.returncode == 0, launched.stderr
    try:
        for _ in range(120):  # until the job runs
            states = subprocess.run(["squeue", "-h", "-n", "nsl-stopped", "-o", "%i|%T"], capture_output=True,
                                    text=True, check=True).stdout.split()
            if any(state.endswith("|RUNNING") for state in states):
                break
            time.sleep(1)
        running = next(state.split("|")[0] for state in states if state.endswith("|RUNNING"))
        subprocess.run(["scancel", "--signal=STOP", running], check=True)
        for _ in range(60):
            state = subprocess.run(["squeue", "-h", "-j", running, "-o", "%T"], capture_output=True, text=True,
                                   check=True).stdout.strip()
            if state == "STOPPED":
                break
            time.sleep(1)
        assert state == "STOPPED"
        status = nsl("status", f"sweep_dir={sweep_dir}")
        assert "missing 0" in status.stdout, status.stdout
        resubmitted = nsl("resubmit", f"sweep_dir={sweep_dir}")
        assert resubmitted.returncode == 0 and "nothing to resubmit" in resubmitted.stdout, resubmitted.stdout
        assert len(queued_arrays("nsl-stopped")) == 1
    finally:
        subprocess.run(["scancel", "-n", "nsl-stopped"], check=False)
