"""A job whose node is lost moves to another node of cluster/nodes.sh's 3-node cluster and continues from the
group's training checkpoint, with the rows of the group trained uninterrupted (bit for bit). That cluster is its
own (its controller, nodes and job ids), so this test runs beside the other SLURM tests, on another worker
(tests/conftest.py)."""

import json
import os
import re
import subprocess
import time
from pathlib import Path

import pytest

from nsl_hpc.sweep.submissions import read_submissions
from nsl_hpc.sweep.task_states import read_sweep_state
from tests.cluster.long_jobs import (
    group_finished,
    launch,
    outcome_rows,
    running_for,
    running_with_checkpoint,
    slow,
    wait_until,
)
from tests.cluster.requeues import Releaser, jobs
from tests.sweeps import nsl

pytestmark = pytest.mark.slurm


@pytest.fixture
def three_nodes(monkeypatch):
    """The 3-node cluster of cluster/nodes.sh, stopped after the test; the test's SLURM clients, nsl_hpc's
    commands and their jobs reach it through SLURM_CONF."""
    up = subprocess.run(["bash", "cluster/nodes.sh", "up"], capture_output=True, text=True, timeout=180)
    if up.returncode != 0:
        (pytest.fail if os.environ.get("CI") == "true" else pytest.skip)(f"no 3-node cluster: {up.stderr.strip()}")
    monkeypatch.setenv("SLURM_CONF", up.stdout.rsplit("SLURM_CONF=", 1)[1].strip())
    yield
    subprocess.run(["bash", "cluster/nodes.sh", "down"], capture_output=True, timeout=180)


def lose_node(node: str) -> None:
    """Lose ``node`` as to a power cut: its slurmd and every process of its jobs killed (SIGKILL), then the
    controller told it is down (as SlurmdTimeout would, later), which requeues its batch jobs elsewhere."""
    def tree(pid: str) -> list[str]:
        children = subprocess.run(["pgrep", "-P", pid], capture_output=True, text=True).stdout.split()
        return [pid, *(grandchild for child in children for grandchild in tree(child))]

    config = Path(os.environ["SLURM_CONF"])
    victims = [(config.parent / f"slurmd-{node}.pid").read_text().strip()]
    for job in subprocess.run(["squeue", "-h", "-w", node, "-o", "%A"], capture_output=True, text=True,
                              check=True).stdout.split():
        steps = subprocess.run(["pgrep", "-f", rf"slurmstepd: \[{job}\."], capture_output=True, text=True).stdout
        victims += [pid for step in steps.split() for pid in tree(step)]
    subprocess.run(["kill", "-9", *victims], check=False)
    subprocess.run(["scontrol", "update", f"NodeName={node}", "State=DOWN", "Reason=lost"], check=True)


def test_a_lost_nodes_job_moves_to_another_node_and_continues_from_the_checkpoint(
        three_nodes, uninterrupted, tmp_path):
    sweep_dir = tmp_path / "lost" / "sweep"
    launch(sweep_dir, "lost-node", "checkpoint.every_minutes=0.1", *slow(24))  # every 6 s
    wait_until(running_with_checkpoint(sweep_dir, "lost-node", min_step=2000), "lost-node")
    ((job_id, _, _),) = jobs("nsl-lost-node")
    first = subprocess.run(["squeue", "-h", "-j", job_id, "-o", "%N"], capture_output=True, text=True,
                           check=True).stdout.strip()
    (lock,) = (sweep_dir / "checkpoints").glob("*/*.lock")
    assert json.loads(lock.read_text())["host"] == first  # a group's lock names its node, not the shared host
    lose_node(first)
    nodes = set()

    def finished_elsewhere(seen: dict) -> bool:
        nodes.update(node for node in subprocess.run(["squeue", "-h", "-j", job_id, "-o", "%N"], capture_output=True,
                                                     text=True).stdout.split())
        return group_finished(sweep_dir, "lost-node")(seen)

    seen = wait_until(finished_elsewhere, "lost-node")
    print(f"\nnode {first} lost: job {job_id} requeued onto {sorted(nodes)}, resumed {seen['resumes']}+ times")
    assert nodes and first not in nodes, nodes
    assert seen["resumes"] >= 1, f"the group was trained again from scratch on {nodes}: {seen}"
    assert outcome_rows(sweep_dir) == uninterrupted()
    status = nsl("status", f"sweep_dir={sweep_dir}").stdout  # from the queue alone: this cluster keeps no accounting
    assert "done 2 |" in status and "accounting did not answer" in status, status


def test_a_lost_nodes_job_that_goes_on_training_there_trains_its_group_once(three_nodes, tmp_path):
    """Only the node's slurmd is lost (kill -9): its job's processes go on training while SLURM requeues the job onto
    another node. The new run waits while the earlier one renews the group's lock and leaves the group to it: the
    group trains once, its rows are written once (issue: both runs trained it and the row was written twice)."""
    sweep_dir = tmp_path / "still" / "sweep"
    launch(sweep_dir, "still-training", *slow(40))
    wait_until(running_for("still-training", 5), "still-training")
    ((job_id, _, _),) = jobs("nsl-still-training")
    first = subprocess.run(["squeue", "-h", "-j", job_id, "-o", "%N"], capture_output=True, text=True,
                           check=True).stdout.strip()
    config = Path(os.environ["SLURM_CONF"])
    subprocess.run(["kill", "-9", (config.parent / f"slurmd-{first}.pid").read_text().strip()], check=True)
    subprocess.run(["scontrol", "update", f"NodeName={first}", "State=DOWN", "Reason=lost"], check=True)
    wait_until(group_finished(sweep_dir, "still-training"), "still-training")
    logs = "".join(path.read_text(errors="replace") for path in (sweep_dir / "submitit").rglob("*_log.*"))
    trained = re.findall(r"group \w+(?: \+\d+ tasks)?: ok", logs)
    assert len(trained) == 1, logs[-3000:]
    assert "an earlier run of job" in logs  # the requeued run waited for it


def queued_elements(name: str) -> set[str]:
    """The array elements (``<array>_<index>``) the queue holds of the jobs named ``name``, pending ones one by one."""
    out = subprocess.run(["squeue", "-h", "-r", "-n", name, "-o", "%i"], capture_output=True, text=True,
                         check=True).stdout
    return set(out.split())


def test_a_rehearsal_on_three_nodes_with_a_node_lost_and_elements_cancelled_accounts_for_every_task_once(
        three_nodes, tmp_path):
    """The demo's 216 tasks rehearsed on the 3-node cluster (no accounting): mid-way a node is lost with its jobs'
    processes, a running and two pending elements are cancelled. No status calls a task missing while the queue
    held its element before and after the look, a task once done stays done; resubmit runs exactly what is left;
    every task ends done or with its planted fault, and no group trains twice."""
    name, sweep_dir = "nsl-three-nodes", tmp_path / "rehearsal"
    launched = nsl("launch", "+sweep=demo", "launcher=slurm", "rehearsal=true", "sweep.name=three-nodes",
                   "packing.pack_minutes=0.02", f"sweep_dir={sweep_dir}")
    assert launched.returncode == 0, launched.stderr
    releaser, looks, done, disturbed = Releaser(name), 0, set(), False
    deadline = time.time() + 420
    try:
        for round_ in ("launch", "resubmit"):
            while time.time() < deadline:
                releaser.poll()
                before = queued_elements(name)
                state = read_sweep_state(sweep_dir)
                after = queued_elements(name)
                looks += 1
                submitted = {task: element for record in read_submissions(sweep_dir)
                             for element, tasks in zip(record["element_ids"], record["elements"], strict=True)
                             for task in tasks}
                wrong = [task for task, task_state in state.states.items()
                         if task_state == "missing" and submitted.get(task) in before & after]
                assert not wrong, f"look {looks}: {len(wrong)} tasks called missing while queued: {wrong[:3]}"
                now_done = {task for task, task_state in state.states.items() if task_state == "done"}
                assert done <= now_done, f"look {looks}: done tasks no longer done: {sorted(done - now_done)[:3]}"
                done = now_done
                if not disturbed and len(done) >= 30 and lose_a_running_node_and_cancel_elements(name):
                    disturbed = True
                if not before and not after:
                    break
                time.sleep(0.5)
            if round_ == "launch":
                assert disturbed, "the jobs ended before a node could be lost"
                resubmitted = nsl("resubmit", f"sweep_dir={sweep_dir}")
                assert resubmitted.returncode == 0, resubmitted.stderr
    finally:
        subprocess.run(["scancel", "-n", name], check=False)
    final = read_sweep_state(sweep_dir).counts
    assert final["done"] + final["frozen"] + final["failed"] == 216 and final["done"] > 150, final
    logs = "".join(path.read_text(errors="replace") for path in (sweep_dir / "submitit").rglob("*_log.*"))
    trained = re.findall(r"(group \w+)(?: \+\d+ tasks)?: ok", logs)
    assert trained and len(trained) == len(set(trained)), f"groups trained twice: {len(trained) - len(set(trained))}"
    print(f"\n{looks} looks, none wrong; {final['done']} done, {final['frozen']} frozen, {final['failed']} failed")


def lose_a_running_node_and_cancel_elements(name: str) -> bool:
    """Lose the node of a running element of ``name``, cancel another running element and two pending ones;
    False where fewer than two run and two wait."""
    out = subprocess.run(["squeue", "-h", "-r", "-n", name, "-o", "%i %T %N"], capture_output=True, text=True,
                         check=True).stdout
    running = [line.split() for line in out.splitlines() if " RUNNING " in line]
    pending = [line.split()[0] for line in out.splitlines() if " PENDING " in line]
    if len(running) < 2 or len(pending) < 2:
        return False
    (_, _, node), (other, _, _) = running[0], next((job for job in running if job[2] != running[0][2]), running[1])
    lose_node(node)
    subprocess.run(["scancel", other, *pending[-2:]], check=True)
    return True
