"""examples/own_study on the real cluster: the user's module (PYTHONPATH=.) and records (a relative data_dir) are
found by the jobs on the node, as by the launch."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from nsl_hpc.sweep.rows import read_row
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


def test_an_edited_module_is_not_mixed_into_a_sweep_on_slurm_unless_allowed(slurm_cluster, tmp_path):
    """The issue's case on the cluster: one element of the user's sweep cancelled, the user's model edited, resubmit:
    refused in one line (nothing submitted); allowed, the task runs and its row records the edited code."""
    study = Path(shutil.copytree(EXAMPLE, tmp_path / "own_study", ignore=shutil.ignore_patterns("__pycache__")))
    grid = ["sweep.grid.seed=[0]", "sweep.grid.epochs=[16]", "sweep.grid.data_tier=[8]", "sweep.grid.width_tier=[4]",
            "sweep.grid.arch=[cascade_net]", "launcher=slurm", "launcher.hold=true", "sweep.name=edited"]
    launched = run(study, "launch", "+sweep=own_study", *grid, "sweep_dir=runs/edited")
    assert launched.returncode == 0 and "submitted" in launched.stdout, launched.stderr
    subprocess.run(["scancel", "-n", "nsl-edited"], check=True)  # its one task: to run again
    with open(study / "tanks.py", "a") as module:
        module.write("# CascadeNet edited after the launch\n")
    refused = run(study, "resubmit", "sweep_dir=runs/edited")
    assert refused.returncode == 2 and refused.stderr.startswith("error: the code of two_tank/cascade_net changed"), \
        refused.stderr
    assert len(list((study / "runs/edited/submissions").glob("*.json"))) == 1
    allowed = run(study, "resubmit", "sweep_dir=runs/edited", "allow_code_change=true", "launcher.hold=false")
    assert allowed.returncode == 0 and "resubmitting 1 tasks" in allowed.stdout, allowed.stdout + allowed.stderr
    waited = run(study, "status", "sweep_dir=runs/edited", "wait=true", "interval_s=1", "max_interval_s=2")
    assert waited.returncode == 0 and "done 1 |" in waited.stdout, waited.stdout
    (row,) = (study / "runs/edited/rows").rglob("*.parquet")
    assert read_row(row)["code"] == json.loads((study / "runs/edited/code.json").read_text())[
        "two_tank/cascade_net"]
