"""examples/own_study on the real cluster: the user's module (PYTHONPATH=.) and records (a relative data_dir) are
found by the jobs on the node, as by the launch."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from tests.test_own_study import EXAMPLE

pytestmark = pytest.mark.slurm


def run(study: Path, verb: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", f"nsl_hpc.{verb}", "--config-dir", "conf", *args],
                          capture_output=True, text=True, cwd=study, env={**os.environ, "PYTHONPATH": "."},
                          timeout=600)


def test_your_own_system_model_and_records_run_on_slurm(slurm_cluster, tmp_path):
    study = Path(shutil.copytree(EXAMPLE, tmp_path / "own_study", ignore=shutil.ignore_patterns("__pycache__")))
    sweeps = {"own_study": ["sweep.grid.seed=[0]", "sweep.grid.epochs=[16]", "sweep.grid.data_tier=[8]",
                            "sweep.grid.width_tier=[4]"],  # unstructured, cascade_net, tank_mlp: 3 tasks
              "own_data": ["sweep.grid.seed=[0]", "sweep.grid.iter_multiplier=[1]", "sweep.grid.data_tier=[800]",
                           "sweep.grid.width_tier=[4]"]}  # 1 task
    for name, grid in sweeps.items():  # both queued before either is waited for
        launched = run(study, "launch", f"+sweep={name}", *grid, "launcher=slurm", f"sweep_dir=runs/{name}")
        assert launched.returncode == 0 and "submitted" in launched.stdout, launched.stderr
    for name, tasks in (("own_study", 3), ("own_data", 1)):
        waited = run(study, "status", f"sweep_dir=runs/{name}", "wait=true", "interval_s=1", "max_interval_s=2")
        assert waited.returncode == 0, waited.stderr
        merged = run(study, "merge", f"sweep_dir=runs/{name}")  # (fit and report: the local test's, on more tasks)
        assert merged.returncode == 0, merged.stderr
        results = pq.read_table(study / "runs" / name / "results.parquet").to_pandas()
        assert len(results) == tasks and (results["status"] == "ok").all(), results.get("error")
