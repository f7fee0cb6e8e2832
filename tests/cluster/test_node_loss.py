"""A job whose node is lost moves to another node of cluster/nodes.sh's 3-node cluster and continues from the
group's training checkpoint, with the rows of the group trained uninterrupted (bit for bit). That cluster is its
own (its controller, nodes and job ids), so this test runs beside the other SLURM tests, on another worker
(tests/conftest.py)."""

import json
import os
import re
import subprocess
from pathlib import Path

import pytest

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
