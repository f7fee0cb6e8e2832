"""A sweep when SLURM's accounting database is down or lags: launch needs no sacctmgr, status and resubmit work
from the queue, and a task the controller still holds is never called missing (issue: pending tasks were
submitted twice after slurmdbd came back)."""

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from tests.sweeps import TINY_GRID, nsl

pytestmark = pytest.mark.slurm


def accounting_answers() -> bool:
    return subprocess.run(["sacctmgr", "-n", "show", "cluster"], capture_output=True, timeout=30).returncode == 0


def slurmdbd_pid() -> int | None:
    """The pid of this cluster's slurmdbd (its slurmdbd.conf lies beside SLURM_CONF), None when it is not running."""
    conf = Path(os.environ.get("SLURM_CONF", "/etc/slurm/slurm.conf")).with_name("slurmdbd.conf")
    settings = dict(line.split("=", 1) for line in conf.read_text().splitlines() if "=" in line)
    pid_file = Path(settings["PidFile"])
    if not pid_file.exists():
        return None
    pid = int(pid_file.read_text())
    comm = Path(f"/proc/{pid}/comm")
    return pid if comm.exists() and comm.read_text() == "slurmdbd\n" else None


def stop_slurmdbd() -> None:
    if (pid := slurmdbd_pid()) is not None:
        os.kill(pid, signal.SIGTERM)
    for _ in range(60):
        if not accounting_answers():
            return
        time.sleep(0.5)
    raise AssertionError("slurmdbd did not stop")


def start_slurmdbd() -> None:
    if slurmdbd_pid() is None:
        subprocess.run(["/usr/sbin/slurmdbd"], check=True)
    for _ in range(120):
        if accounting_answers():
            return
        time.sleep(0.5)
    raise AssertionError("slurmdbd did not come back")


def test_tasks_queued_while_accounting_was_down_are_never_submitted_again(slurm_cluster, tmp_path):
    sweep_dir = tmp_path / "sweep"
    held = [*TINY_GRID, "launcher=slurm", f"sweep_dir={sweep_dir}", "launcher.hold=true",
            "packing.enabled=false", "lockstep.enabled=false", "sweep.name=unaccounted"]
    stop_slurmdbd()
    try:
        launched = nsl("launch", *held)
        assert launched.returncode == 0, launched.stderr
        assert "submitted 4 jobs in 1 arrays" in launched.stdout
        assert "the user's job limits are unknown (sacctmgr failed: " in launched.stdout
        status = nsl("status", f"sweep_dir={sweep_dir}")
        assert status.returncode == 0, status.stderr
        assert "pending 4" in status.stdout and "missing 0" in status.stdout
        assert "accounting did not answer (sacct failed: " in status.stdout and "cannot be told apart" in status.stdout
        assert "nothing to resubmit" in nsl("resubmit", f"sweep_dir={sweep_dir}").stdout
        start_slurmdbd()
        resubmitted = nsl("resubmit", f"sweep_dir={sweep_dir}")
        assert resubmitted.returncode == 0 and "nothing to resubmit" in resubmitted.stdout, resubmitted.stdout
        queued = subprocess.run(["squeue", "-h", "-r", "-n", "nsl-unaccounted", "-o", "%i"], capture_output=True,
                                text=True, check=True).stdout.split()
        assert len(queued) == 4 and len({element.split("_")[0] for element in queued}) == 1
    finally:
        start_slurmdbd()
        subprocess.run(["scancel", "-n", "nsl-unaccounted"], check=False)


def test_a_task_cancelled_before_accounting_records_it_is_missing_and_resubmitted_at_once(slurm_cluster, tmp_path):
    """Cancelled within a second of its submission, when sacct may not know the job or still says PENDING: the
    queue, which no longer holds it, decides; resubmit submits the tasks at once and only once."""
    sweep_dir = tmp_path / "sweep"
    held = [*TINY_GRID, "launcher=slurm", f"sweep_dir={sweep_dir}", "launcher.hold=true", "sweep.name=lost"]
    try:
        assert nsl("launch", *held).returncode == 0
        subprocess.run(["scancel", "-n", "nsl-lost"], check=True)
        for _ in range(60):  # the controller drops the cancelled job from the queue
            if not subprocess.run(["squeue", "-h", "-n", "nsl-lost"], capture_output=True, text=True).stdout.strip():
                break
            time.sleep(0.5)
        status = nsl("status", f"sweep_dir={sweep_dir}")
        assert "missing 4" in status.stdout and "pending 0" in status.stdout, status.stdout
        resubmitted = nsl("resubmit", f"sweep_dir={sweep_dir}")
        assert resubmitted.returncode == 0 and "resubmitting 4 tasks" in resubmitted.stdout, resubmitted.stdout
        assert "nothing to resubmit" in nsl("resubmit", f"sweep_dir={sweep_dir}").stdout
    finally:
        subprocess.run(["scancel", "-n", "nsl-lost"], check=False)
