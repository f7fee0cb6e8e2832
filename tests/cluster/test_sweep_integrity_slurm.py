"""Launching a SLURM sweep twice submits nothing twice: tasks pending or running in SLURM are left to their
jobs (issue: launch and resubmit ignored what was queued)."""

import subprocess

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
