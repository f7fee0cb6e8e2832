"""Long jobs on the real cluster: a group longer than the site's time cap runs as a chain of requeued jobs, a
preempted job, a killed training process, a `scontrol requeue` and a job whose node is lost (requeued onto
another node of cluster/nodes.sh's 3-node cluster) all continue from the group's training checkpoint, and every
time the rows are those of the same group trained uninterrupted (bit for bit).

SLURM holds a requeued job for about two minutes before it may start again; the tests release it after a few
seconds (``tests.cluster.requeues``).

Each test needs the group to train longer than something (the cap, the time to preempt it): ``fault.kind=slow``
sleeps at every heartbeat, so the group lasts at least ``SLOW`` seconds on any machine, however fast, and its
rows stay those of the group trained at full speed.
"""

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from nsl_hpc.sweep.groups import saved_groups
from tests.cluster.requeues import Releaser, jobs
from tests.sweeps import TINY_GRID, nsl, row_files

pytestmark = pytest.mark.slurm

# One lockstep group of two models (seeds 0 and 3 draw the same depth and width bucket) that trains ~10 s on one
# core (input-affine, ~150 points, a step per epoch: 200 heartbeats of 32 steps). Eager in every run: compile=auto
# would compile the slowed groups (``slow`` raises their prediction) but not the uninterrupted one, and compiled
# steps agree with eager ones to rounding only (compiled resumes: tests/test_checkpoints.py).
STEPS = 6400
GROUP = [*TINY_GRID, "sweep.grid.seed=[0,3]", f"sweep.grid.epochs=[{STEPS}]", "compile=never"]


def slow(seconds: float) -> list[str]:
    """Overrides that make the group train for at least ``seconds`` on any machine, and the planner predict twice
    that (the requeue budget of a chain of jobs comes from the prediction)."""
    return ["fault.kind=slow", f"fault.heartbeat_s={seconds / (STEPS // 32)}",
            f"cost.step_seconds.input_affine={2 * seconds / STEPS}"]
OUTCOME = ("nmae", "nmse", "final_loss", "steps", "params", "flops", "train_points", "width")


def outcome_rows(sweep_dir: Path) -> dict[str, tuple]:
    rows = [pq.read_table(path).to_pylist()[0] for path in row_files(sweep_dir)]
    return {row["task_id"]: tuple(row[key] for key in OUTCOME) for row in rows}


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The group trained uninterrupted by the local launcher, started at once (it runs beside the cluster's
    job on the other core); call it for its rows."""
    sweep_dir = tmp_path_factory.mktemp("uninterrupted") / "sweep"
    process = subprocess.Popen([sys.executable, "-m", "nsl_hpc.launch", *GROUP, "launcher=local", "launcher.workers=1",
                                f"sweep_dir={sweep_dir}"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                               text=True)

    def rows() -> dict[str, tuple]:
        output, _ = process.communicate(timeout=600)
        assert process.returncode == 0 and "finished: 2 ok" in output, output
        return outcome_rows(sweep_dir)

    yield rows
    process.kill()


def launch(sweep_dir: Path, name: str, *extra: str) -> str:
    result = nsl("launch", *GROUP, "launcher=slurm", f"sweep_dir={sweep_dir}", f"sweep.name={name}", *extra)
    assert result.returncode == 0 and "submitted 1 jobs" in result.stdout, result.stdout + result.stderr
    return result.stdout


def wait_until(condition, name: str, timeout_s: float = 420) -> dict:
    """Poll until ``condition()`` holds, releasing the requeued jobs named ``nsl-<name>`` SLURM holds back;
    returns what was seen: the most resumes of the group's checkpoint."""
    seen, releaser = {"resumes": 0, "releases": 0}, Releaser(f"nsl-{name}")
    deadline = time.time() + timeout_s
    while time.time() < deadline:
        releaser.poll()
        seen["releases"] = releaser.releases
        if condition(seen):
            return seen
        time.sleep(1)
    subprocess.run(["scancel", "-n", f"nsl-{name}"], check=False)
    pytest.fail(f"not done within {timeout_s} s: {seen}, queue {jobs(f'nsl-{name}')}")


def group_finished(sweep_dir: Path, name: str):
    def check(seen: dict) -> bool:
        for saved in saved_groups(sweep_dir):
            seen["resumes"] = max(seen["resumes"], saved.resumes)
        return len(row_files(sweep_dir)) == 2 and not jobs(f"nsl-{name}")
    return check


def running_with_checkpoint(sweep_dir: Path, name: str, min_step: int = 1):
    def check(seen: dict) -> bool:
        states = [state for _, state, _ in jobs(f"nsl-{name}")]
        steps = [saved.step for saved in saved_groups(sweep_dir)]
        return states == ["RUNNING"] and bool(steps) and max(steps) >= min_step
    return check


def running_for(name: str, seconds: float):
    started = {}

    def check(seen: dict) -> bool:
        if [state for _, state, _ in jobs(f"nsl-{name}")] == ["RUNNING"]:
            started.setdefault("at", time.time())
            return time.time() - started["at"] >= seconds
        return False
    return check


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
        slurm_cluster, three_nodes, uninterrupted, tmp_path):
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
