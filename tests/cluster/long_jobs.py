"""What the long-job tests share (tests/cluster/test_long_jobs.py, test_node_loss.py): one slowed lockstep group,
its launch on the cluster, waiting for it while SLURM's held requeues are released, and its rows trained
uninterrupted by the local launcher (the bit-for-bit reference).

Each test needs the group to train longer than something (the cap, the time to preempt it): ``fault.kind=slow``
sleeps at every heartbeat, so the group lasts at least ``seconds`` on any machine, however fast, and its rows stay
those of the group trained at full speed. SLURM holds a requeued job for about two minutes before it may start
again; the tests release it after a few seconds (``tests.cluster.requeues``).
"""

import subprocess
import time
from pathlib import Path

import pytest

from nsl_hpc.sweep.groups import saved_groups
from nsl_hpc.sweep.rows import read_row
from tests.cluster.requeues import Releaser, jobs
from tests.sweeps import TINY_GRID, nsl, row_files

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
    rows = [read_row(path) for path in row_files(sweep_dir)]
    return {row["task_id"]: tuple(row[key] for key in OUTCOME) for row in rows}


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
