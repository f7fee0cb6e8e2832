"""Long jobs on the real cluster: a group longer than the site's time cap runs as a chain of requeued jobs, and a
preempted job, a killed training process and a `scontrol requeue` all continue from the group's training
checkpoint, and every time the rows are those of the same group trained uninterrupted (bit for bit). A lost
node: tests/cluster/test_node_loss.py."""

import json
import os
import re
import subprocess
import time

import pytest

from nsl_hpc.sweep.groups import saved_groups
from tests.cluster.long_jobs import (
    group_finished,
    launch,
    outcome_rows,
    running_for,
    running_with_checkpoint,
    slow,
    wait_until,
)
from tests.cluster.requeues import jobs
from tests.sweeps import nsl, row_files

pytestmark = pytest.mark.slurm


def test_a_group_longer_than_the_time_cap_runs_as_a_chain_of_jobs(slurm_cluster, uninterrupted, tmp_path):
    sweep_dir = tmp_path / "cap" / "sweep"
    plan = launch(sweep_dir, "cap", "launcher.max_time_minutes=1", "launcher.signal_delay_s=25",
                  "checkpoint.every_minutes=5", *slow(40))  # past the warning, 35 s into a job at the latest
    chain = re.search(r"run as chains of (\d+)", plan)
    assert chain and int(chain.group(1)) >= 2, plan
    started = time.time()
    seen = wait_until(group_finished(sweep_dir, "cap"), "cap")
    print(f"\ncap of 1 minute: {seen['releases']} requeues, resumed {seen['resumes']}+ times, "
          f"{time.time() - started:.0f} s")
    assert seen["releases"] >= 1 and seen["resumes"] >= 1, f"the group needed a single job: {seen}"
    assert outcome_rows(sweep_dir) == uninterrupted()
    assert not list(saved_groups(sweep_dir))  # a finished group's checkpoint is deleted


def test_a_preempted_job_continues_from_its_checkpoint(slurm_cluster, uninterrupted, tmp_path):
    sweep_dir = tmp_path / "preempted" / "sweep"
    launch(sweep_dir, "preempted", "checkpoint.every_minutes=30", *slow(24))  # only the preemption's warning writes one
    wait_until(running_for("preempted", 8), "preempted")
    high = subprocess.run(["sbatch", "--parsable", "-p", "high", "-c", str(os.cpu_count()), "-o", "/dev/null",
                           "--wrap", "sleep 3"], capture_output=True, text=True, check=True).stdout.strip()
    seen = wait_until(group_finished(sweep_dir, "preempted"), "preempted")
    state = subprocess.run(["sacct", "-n", "-X", "-j", high, "-o", "State"], capture_output=True, text=True).stdout
    assert "COMPLETED" in state or "RUNNING" in state, state
    assert seen["resumes"] >= 1 and seen["releases"] >= 1, f"the group was not preempted while training: {seen}"
    assert outcome_rows(sweep_dir) == uninterrupted()


def test_a_killed_training_process_loses_at_most_the_checkpoint_interval_and_resubmit_finishes(
        slurm_cluster, uninterrupted, tmp_path):
    sweep_dir = tmp_path / "killed" / "sweep"
    launch(sweep_dir, "killed", "checkpoint.every_minutes=0.1", *slow(24))  # every 6 s
    wait_until(running_with_checkpoint(sweep_dir, "killed", min_step=2000), "killed")
    time.sleep(4)  # between two checkpoints
    (lock,) = (sweep_dir / "checkpoints").glob("*/*.lock")
    runner = json.loads(lock.read_text())["pid"]
    (child,) = subprocess.run(["pgrep", "-P", str(runner)], capture_output=True, text=True).stdout.split()
    os.kill(int(child), 9)  # as a node loss would
    wait_until(lambda seen: not jobs("nsl-killed"), "killed")
    assert len(row_files(sweep_dir)) == 0, "the group finished before it was killed"
    status = nsl("status", f"sweep_dir={sweep_dir}").stdout
    assert "failed 2" in status and "killed by signal SIGKILL" in status, status
    lost = float(re.search(r"(\d+) s of training lost since its last checkpoint", status).group(1))
    print(f"\nkill -9: {lost:.0f} s of training lost (checkpoint every 6 s)")
    assert lost <= 6 + 2
    assert "failed (resumed 0 times): 2 tasks in a group at step" in status
    resubmitted = nsl("resubmit", f"sweep_dir={sweep_dir}")
    assert "resubmitting 2 tasks" in resubmitted.stdout, resubmitted.stdout + resubmitted.stderr
    seen = wait_until(group_finished(sweep_dir, "killed"), "killed")
    assert seen["resumes"] >= 1, f"resubmit trained the group from scratch: {seen}"
    assert outcome_rows(sweep_dir) == uninterrupted()


def test_scontrol_requeue_continues_from_the_checkpoint_without_duplicate_rows(slurm_cluster, uninterrupted,
                                                                              tmp_path):
    sweep_dir = tmp_path / "requeued" / "sweep"
    launch(sweep_dir, "requeued", "checkpoint.every_minutes=30", *slow(24))  # only the requeue's SIGTERM writes one
    wait_until(running_for("requeued", 8), "requeued")
    ((job_id, _, _),) = jobs("nsl-requeued")
    subprocess.run(["scontrol", "requeue", job_id], check=True)
    seen = wait_until(group_finished(sweep_dir, "requeued"), "requeued")
    assert seen["resumes"] >= 1, f"the group was not requeued while training: {seen}"
    assert len(row_files(sweep_dir)) == 2
    assert outcome_rows(sweep_dir) == uninterrupted()
