"""SLURM's warning (``--signal``: a time limit ahead, or a preemption) can reach a job at any point of its life: before
its first group starts, while a group's process loads its data or compiles, between two groups, after its last row.
At each point the job is requeued with what it has left, or ends as it is where nothing is left: never FAILED, and
every task's row is written once. The warning is sent by hand (``scancel --signal=USR2``, as SLURM sends it) while
the job pauses at the point (``fault.kind=pause``)."""

import subprocess
import time

import pytest

from nsl_hpc.sweep.layout import pause_marker
from tests.cluster.requeues import Releaser, jobs, sacct_state
from tests.sweeps import ALONE, TINY_GRID, manifest_ids, nsl, row_files

pytestmark = pytest.mark.slurm

POINTS = ("start", "loading", "between", "end")
PAUSE_S = 30  # the warning comes within a second of the pause's start; at "end" the job then sleeps on


def launch_paused(sweep_dir, point: str) -> None:
    """Four tasks, each its own group, in one job that pauses at ``point`` (checkpoints on: a group stopped in its
    process is requeued)."""
    result = nsl("launch", *TINY_GRID, ALONE, "launcher=slurm", f"sweep_dir={sweep_dir}", f"sweep.name=warned-{point}",
                 "checkpoint.every_minutes=5", "fault.kind=pause", f"fault.pause_at={point}",
                 f"fault.pause_s={PAUSE_S}")
    assert result.returncode == 0 and "submitted 1 jobs" in result.stdout, result.stdout + result.stderr


def run_states(job_id: str) -> list[str]:
    """The state of each run of a job in accounting (a requeued job has one record per run)."""
    out = subprocess.run(["sacct", "-n", "-X", "-D", "-P", "-j", job_id, "--format=State"], capture_output=True,
                         text=True, check=True).stdout
    return out.split()


def test_slurms_warning_at_any_point_of_a_job_requeues_it_or_ends_it_never_failed(slurm_cluster, tmp_path):
    sweeps = {point: tmp_path / point / "sweep" for point in POINTS}
    for point, sweep_dir in sweeps.items():
        launch_paused(sweep_dir, point)
    releasers = {point: Releaser(f"nsl-warned-{point}") for point in POINTS}
    warned, rows_then = {}, {}
    deadline = time.time() + 300
    while len(warned) < len(POINTS) or any(jobs(f"nsl-warned-{point}") for point in POINTS):
        assert time.time() < deadline, f"not done in 300 s: warned {warned}"
        for point, sweep_dir in sweeps.items():
            releasers[point].poll()
            if point not in warned and pause_marker(sweep_dir, point).exists():
                ((job_id, state, _),) = jobs(f"nsl-warned-{point}")
                assert state == "RUNNING", (point, state)
                rows_then[point] = {path: path.stat().st_mtime_ns for path in row_files(sweep_dir)}
                subprocess.run(["scancel", "--signal=USR2", job_id], check=True)
                warned[point] = job_id
        time.sleep(0.5)

    for point, sweep_dir in sweeps.items():
        status = nsl("status", f"sweep_dir={sweep_dir}").stdout
        assert "done 4 |" in status, (point, status)
        assert sorted(path.stem for path in row_files(sweep_dir)) == sorted(manifest_ids(sweep_dir))
        assert all(path.stat().st_mtime_ns == mtime for path, mtime in rows_then[point].items()), point  # not again
        assert sacct_state(warned[point]) == "COMPLETED", (point, run_states(warned[point]))
        assert set(run_states(warned[point])) <= {"REQUEUED", "COMPLETED"}, (point, run_states(warned[point]))
    assert len(rows_then["between"]) == 1 and len(rows_then["end"]) == 4  # the points were where they say
    assert all(releasers[point].releases >= 1 for point in ("start", "loading", "between")), \
        {point: releaser.releases for point, releaser in releasers.items()}
    assert releasers["end"].releases == 0  # nothing left: it ended, not requeued
