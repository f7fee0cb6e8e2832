"""jobs/one_task.sbatch on the real cluster: sbatch runs one task, sacct reports it, the row lands."""

import subprocess
import sys
from pathlib import Path

import pytest

from nsl_hpc.sweep.rows import read_row
from tests.cluster.requeues import sacct_state

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.slurm


def submit_and_wait(cluster: dict[str, str], log_dir: Path, *overrides: str) -> tuple[subprocess.CompletedProcess,
                                                                                      str, str]:
    """sbatch one task with --wait to ``cluster`` (the slurm_cluster fixture's); returns the sbatch result, the job
    id and the job's log."""
    submitted = subprocess.run(
        ["sbatch", "--parsable", "--wait", f"--output={log_dir}/slurm-%j.out",
         str(REPO / "jobs" / "one_task.sbatch"), *overrides],
        capture_output=True, text=True, timeout=600, cwd=log_dir,
        env={**cluster, "PATH": "/usr/bin:/bin:/usr/sbin:/sbin", "NSL_HPC_PYTHON": sys.executable})
    job_id = submitted.stdout.strip().split(";")[0]
    return submitted, job_id, (log_dir / f"slurm-{job_id}.out").read_text()


def test_one_task_runs_under_sbatch(slurm_cluster, tmp_path, cache_dir):
    out_dir = tmp_path / "out"
    submitted, job_id, log = submit_and_wait(
        slurm_cluster, tmp_path, "system=spring", "arch=input_affine", "epochs=2", "data_tier=2", "width_tier=2",
        "depth_tier=2", "seed=1", f"out_dir={out_dir}", f"cache_dir={cache_dir}")
    assert submitted.returncode == 0, submitted.stderr
    (row_file,) = out_dir.rglob("*.parquet")
    row = read_row(row_file)
    assert (row["system"], row["arch"], row["epochs"], row["status"]) == ("spring", "input_affine", 2, "ok")
    assert row["task_id"] in log
    assert sacct_state(job_id) == "COMPLETED"


def test_failing_task_is_reported_failed_by_sacct(slurm_cluster, tmp_path):
    submitted, job_id, log = submit_and_wait(slurm_cluster, tmp_path, "system=pendulum", f"out_dir={tmp_path / 'out'}")
    assert submitted.returncode != 0
    assert sacct_state(job_id) == "FAILED"
    assert "unknown system 'pendulum'" in log
    assert not (tmp_path / "out").exists()
