"""Sweeps on the real cluster: job arrays, array splitting under a lowered MaxArraySize, faults
(a hanging task, a raising task, scancel of part of an array) and resubmit."""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from nsl_hpc.sweep.decisions import read_decisions
from tests.cluster.requeues import releasing, wait_until_gone
from tests.sweeps import ALONE, TINY_GRID, manifest_ids, nsl, row_files

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.slurm
UNPACKED = ["launcher=slurm", "packing.enabled=false", ALONE]  # one array element per task


def wait_for_sweep(sweep_dir: Path) -> str:
    result = nsl("status", f"sweep_dir={sweep_dir}", "wait=true", "interval_s=1", "max_interval_s=2", timeout=900)
    assert result.returncode == 0, result.stderr
    return result.stdout


def submitted_arrays(stdout: str) -> list[str]:
    line = next(line for line in stdout.splitlines() if line.startswith("submitted"))
    return line.split(": ", 1)[1].split(", ")


def test_packed_sweep_completes_on_slurm(slurm_cluster, tmp_path):
    sweep_dir = tmp_path / "sweep"
    launched = nsl("launch", *TINY_GRID, "launcher=slurm", f"sweep_dir={sweep_dir}", "packing.pack_minutes=0.05",
                   "sweep.name=packed")
    assert launched.returncode == 0, launched.stderr
    assert "submitted" in launched.stdout
    status = wait_for_sweep(sweep_dir)
    assert "done 4 |" in status
    wait_until_gone("nsl-packed")  # an element writes its result after its rows: clean keeps a running one's files
    assert sorted(path.stem for path in row_files(sweep_dir)) == sorted(manifest_ids(sweep_dir))
    assert any((sweep_dir / "submitit").glob("*/*_submitted.pkl"))
    assert nsl("clean", f"sweep_dir={sweep_dir}").returncode == 0
    assert not any((sweep_dir / "submitit").glob("*/*"))  # every element finished
    assert len(row_files(sweep_dir)) == 4
    elsewhere = subprocess.run([sys.executable, "-m", "nsl_hpc.merge", f"sweep_dir={sweep_dir}"], capture_output=True,
                               text=True, env={**os.environ, "PATH": str(tmp_path)})  # no SLURM commands here
    assert elsewhere.returncode == 0 and "0 of 4 tasks (0.0%) dropped" in elsewhere.stdout, elsewhere.stderr


@pytest.fixture
def small_max_array_size(slurm_cluster):
    """The cluster restarted with MaxArraySize=3, restored afterwards."""
    path = {"PATH": "/usr/bin:/bin:/usr/sbin:/sbin"}
    subprocess.run(["bash", str(REPO / "cluster" / "up.sh")], env={**slurm_cluster, **path, "MAX_ARRAY_SIZE": "3"},
                   check=True, capture_output=True)
    yield 3
    subprocess.run(["bash", str(REPO / "cluster" / "up.sh")], env={**slurm_cluster, **path}, check=True,
                   capture_output=True)


def test_sweep_larger_than_max_array_size_is_split(small_max_array_size, tmp_path):
    sweep_dir = tmp_path / "sweep"
    launched = nsl("launch", *TINY_GRID, "sweep.grid.seed=[0,1,2,3,4,5,6]", *UNPACKED, f"sweep_dir={sweep_dir}")
    assert launched.returncode == 0, launched.stderr
    assert len(submitted_arrays(launched.stdout)) == 3  # 7 elements with indices 0..2 at most: 3 + 3 + 1
    assert "done 7 |" in wait_for_sweep(sweep_dir)


def test_faults_on_slurm_then_resubmit_completes_every_task_once(slurm_cluster, tmp_path):
    sweep_dir = tmp_path / "sweep"
    launched = nsl("launch", *TINY_GRID, "sweep.grid.seed=[0,1,2,3]", "sweep.grid.epochs=[2,400]", *UNPACKED,
                   f"sweep_dir={sweep_dir}", "fault.kind=hang", "fault.seed=1", "watchdog.heartbeat_timeout_s=10")
    assert launched.returncode == 0, launched.stderr
    assert len(submitted_arrays(launched.stdout)) == 1, launched.stdout
    (array,) = submitted_arrays(launched.stdout)
    seeds = dict(zip(*pq.read_table(sweep_dir / "manifest.parquet", columns=["task_id", "seed"]).to_pydict().values(),
                     strict=True))
    record = json.loads((sweep_dir / "submissions" / f"{array}.json").read_text())
    others = [element for element, (task_id,) in zip(record["element_ids"], record["elements"], strict=True)
              if seeds[task_id] != 1]
    time.sleep(1)
    subprocess.run(["scancel", *others[-3:]], check=True)  # part of the array, none of the hanging tasks
    status = wait_for_sweep(sweep_dir)
    assert "frozen 2 |" in status  # seed 1 at both epoch counts
    assert "missing 3" in status  # the cancelled elements
    finished = {path: path.stat().st_mtime_ns for path in row_files(sweep_dir)}
    assert len(finished) == 3

    resubmitted = nsl("resubmit", f"sweep_dir={sweep_dir}")
    assert resubmitted.returncode == 0 and "resubmitting 5 tasks" in resubmitted.stdout
    status = wait_for_sweep(sweep_dir)
    assert "done 8 |" in status
    assert sorted(path.stem for path in row_files(sweep_dir)) == sorted(manifest_ids(sweep_dir))
    assert all(path.stat().st_mtime_ns == mtime for path, mtime in finished.items())  # nothing recomputed


def test_time_limit_records_timeout_requeues_unstarted_tasks_and_resubmit_finishes(slurm_cluster, tmp_path):
    """Two hanging tasks in one 1-minute job: SLURM's warning (--signal, 20-50 s before the limit) records
    the first as timeout and requeues the job with the second, which times out in turn; a resubmit
    (the fault strikes a first attempt only) finishes both."""
    sweep_dir = tmp_path / "sweep"
    launched = nsl("launch", *TINY_GRID, "sweep.grid.seed=[0,1]", "launcher=slurm", f"sweep_dir={sweep_dir}",
                   "packing.time_classes_minutes=[1]", "launcher.signal_delay_s=20", ALONE, "fault.kind=hang",
                   "watchdog.overrun_factor=1000")
    assert launched.returncode == 0, launched.stderr
    assert len(submitted_arrays(launched.stdout)) == 1 and "submitted 1 jobs" in launched.stdout
    with releasing("nsl-demo") as releaser:  # the job requeued with the second task
        status = wait_for_sweep(sweep_dir)
    assert "timeout 2 |" in status, status
    assert releaser.releases >= 1, "the job was not requeued with its second task"
    assert "reached its time limit" in status

    resubmitted = nsl("resubmit", f"sweep_dir={sweep_dir}", "states=[timeout]", "time_factor=2")
    assert resubmitted.returncode == 0 and "resubmitting 2 tasks" in resubmitted.stdout
    assert "done 2 |" in wait_for_sweep(sweep_dir)
    assert sorted(path.stem for path in row_files(sweep_dir)) == sorted(manifest_ids(sweep_dir))


def test_a_budgeted_sweep_runs_its_rounds_on_slurm_one_after_another(slurm_cluster, tmp_path):
    sweep_dir = tmp_path / "sweep"
    launched = nsl("launch", "+sweep=demo", "sweep.grid.system=[spring]", "sweep.grid.arch=[unstructured]",
                   "sweep.grid.data_tier=[2]", "budget.first_levels=2", "budget.first_share=1",
                   "budget.levels_per_round=1", "budget.share=0.99", "launcher=slurm", f"sweep_dir={sweep_dir}")
    assert launched.returncode == 0, launched.stderr
    assert "job" in launched.stdout and "launches again once it has run" in launched.stdout
    status = wait_for_sweep(sweep_dir)  # waits for the round job too: the next round comes
    assert "waiting 0" in status and "2 rounds decided" in status
    decisions = read_decisions(sweep_dir)
    assert {path.stem for path in row_files(sweep_dir)} == {d["task_id"] for d in decisions if d["run"]}
    assert {d["round"] for d in decisions} == {1, 2} and len(decisions) == 12
