"""Input-output tasks end to end on the simulated stand-ins: one row with the documented columns and
resources, determinism, bad input refused before training, and an input_output sweep through launch,
merge and the NSL fits."""

import json
import re

import numpy as np
import pyarrow.parquet as pq
import pytest

from nsl_hpc.core.errors import ConfigError
from nsl_hpc.studies import pair_of
from nsl_hpc.studies.input_output.data import load_benchmark
from nsl_hpc.sweep.rows import read_row
from nsl_hpc.sweep.task import resolve_task, run_task, task_id
from tests.sweeps import nsl

pytestmark = pytest.mark.e2e  # runs the commands end to end (make test-fast leaves it out)

NARX_TASK = ["study=input_output", "system=wiener_hammerstein_sim", "arch=narx", "iter_multiplier=2",
             "data_tier=625", "width_tier=16", "depth=1", "seed=1"]
SUBNET_TASK = ["study=input_output", "system=silverbox_sim", "arch=subnet", "iter_multiplier=1", "data_tier=500",
               "width_tier=4", "depth=1", "seed=0"]


@pytest.mark.slow
def test_a_narx_task_writes_one_row_with_the_study_resources(compose):
    row = run_task(compose(*NARX_TASK)).row
    # a NARX without the linear path (the layout before it) keeps the id of every sweep since draws=per_task
    assert task_id(compose(*NARX_TASK, "arch.bypass=false", "arch.zero_bias=false")) == "263fa82d4ea22077"
    assert row["task_id"] == task_id(compose(*NARX_TASK)) != "263fa82d4ea22077"
    assert row["status"] == "ok" and np.isfinite([row["nmae"], row["nmse"], row["rmse_mv"]]).all()
    assert 313 <= row["train_points"] <= 625 and 8 <= row["width"] <= 16 and row["depth"] == 1
    assert row["steps"] == 2 * row["train_points"]  # n_i = m n_l
    assert row["flops"] == row["params"] * row["steps"] * 256  # c = p n_i B
    assert row["nmse"] < 0.5  # a fitted model, far better than predicting the mean (nMSE 1)
    assert row["nmse_one_step_test"] < row["nmse"]  # measured past outputs help
    again = run_task(compose(*NARX_TASK, "force=true")).row
    assert (again["nmse"], again["final_loss"]) == (row["nmse"], row["final_loss"])  # config + seed decide


def test_a_subnet_task_counts_compute_over_its_horizon_and_reports_rmse_in_mv(compose, cache):
    cfg = compose(*SUBNET_TASK, "system.subnet.horizon=30")  # T = 30 (Silverbox's 150 trains 5 times as long)
    row = run_task(cfg).row
    assert row["status"] == "ok" and row["steps"] == row["train_points"]
    assert row["flops"] == row["params"] * row["steps"] * 256 * 30  # c = p n_i B T
    measured = load_benchmark(pair_of(cfg).system, cache).tests["test"].y[50:]
    assert row["rmse_mv"] == pytest.approx(1000 * np.sqrt(row["nmse"]) * measured.std(ddof=1), rel=1e-9)
    assert (row["nmae"], row["nmse"], row["rmse_mv"]) == (
        row["nmae_free_run_test"], row["nmse_free_run_test"], row["rmse_mv_free_run_test"])
    assert "nmae_one_step_test" not in row  # SUBNET is scored in simulation only
    assert row["horizon"] == 30


def test_a_subnet_task_on_a_prefix_shorter_than_one_window_simulates_what_it_holds(compose):
    """silverbox_sim, data tier 250, seed 1: n_l = 132 < P + T = 200 samples; the task trains on its one window
    of n_l - P = 82 simulated steps and counts them in its compute."""
    row = run_task(compose(*SUBNET_TASK, "data_tier=250", "seed=1")).row
    assert row["train_points"] == 132 and row["status"] == "ok"
    assert row["horizon"] == 82
    assert row["flops"] == row["params"] * row["steps"] * 256 * 82


@pytest.mark.parametrize(("override", "message"), [
    ("data_tier=300", "data_tier=300 is outside the grid; allowed: 64000, 32000"),
    ("width_tier=128", "width_tier=128 is outside the grid"),
    ("depth=4", "depth=4 is outside the grid"),
    ("iter_multiplier=0", "iter_multiplier=0 must be a positive integer"),
    ("system.subnet.horizon=600 arch.shorten_horizon=false",
     "is shorter than one subnet window of 650 samples (50 past + T=600); use a larger data_tier or "
     "arch.shorten_horizon=true"),
    ("system.data_tiers=[128000]", None),  # set below with a matching data_tier
    ("arch.past=80", "subnet reads 80 past samples, more than the 50 that initialise a test simulation"),
    ("train.rollout_segment.batch_major=-1", "train.rollout_segment.batch_major=-1 must be a non-negative integer"),
    ("train.rollout_segment=10", "train.rollout_segment=10 must be a group of keys: feature_major, batch_major"),
])
def test_bad_input_output_tasks_are_refused_before_training(override, message, compose):
    overrides = [*SUBNET_TASK, *override.split()]
    if message is None:
        overrides.append("data_tier=128000")
        message = "data_tier=128000 is larger than the training pool of silverbox_sim"
    with pytest.raises(ConfigError, match=re.escape(message)):
        resolve_task(compose(*overrides))


def test_a_system_of_the_other_study_is_refused(compose):
    with pytest.raises(ConfigError, match="system=spring belongs to the input_state study, not input_output"):
        resolve_task(compose("study=input_output", "system=spring"))


def test_missing_measured_data_fails_the_task_with_one_line(tmp_path, cache_dir):
    result = nsl("train", "study=input_output", "system=silverbox", f"data_dir={tmp_path}",
                 f"out_dir={tmp_path / 'out'}", f"cache_dir={cache_dir}")
    assert result.returncode == 2
    assert result.stderr.startswith("error: silverbox: data file ") and "SilverboxFiles.zip is missing" in result.stderr
    assert not (tmp_path / "out" / "rows").exists()


def test_a_launch_on_missing_measured_data_is_refused_before_anything_is_written(tmp_path):
    sweep_dir = tmp_path / "sweep"
    result = nsl("launch", "+sweep=input_output", f"sweep_dir={sweep_dir}", "dry_run=true",
                 f"data_dir={tmp_path / 'nowhere'}")
    assert result.returncode == 2 and "SilverboxFiles.zip is missing" in result.stderr
    assert not sweep_dir.exists()


@pytest.mark.slow
def test_an_input_output_sweep_runs_merges_and_fits(tmp_path):
    sweep_dir = tmp_path / "sweep"
    grid = ["+sweep=io_demo", "sweep.grid.0.seed=[0]", "sweep.grid.0.iter_multiplier=[1,2]",
            "sweep.grid.0.data_tier=[250,500,1000]", "sweep.grid.0.width_tier=[2,4]",
            "sweep.grid.1.seed=[0]", "sweep.grid.1.iter_multiplier=[1]", "sweep.grid.1.data_tier=[312]",
            "sweep.grid.1.width_tier=[4]", "sweep.grid.2.seed=[0,1]", "sweep.grid.2.data_tier=[312]",
            "sweep.grid.2.width_tier=[2]", "train.batch_size=32", "system.subnet.horizon=20"]
    launched = nsl("launch", *grid, "launcher=local", f"sweep_dir={sweep_dir}")
    assert launched.returncode == 0, launched.stdout + launched.stderr  # tasks that cannot run are not run
    manifest = pq.read_table(sweep_dir / "manifest.parquet")
    assert manifest.num_rows == 12 + 1 + 2
    merged = nsl("merge", f"sweep_dir={sweep_dir}")
    assert merged.returncode == 0, merged.stderr
    summary = json.loads((sweep_dir / "merge_summary.json").read_text())
    infeasible = [line for line in launched.stdout.splitlines() if "cannot run as configured" in line]
    assert summary["merged"] + summary["failed"] == 15 and summary["failed"] == (1 if infeasible else 0)
    results = pq.read_table(sweep_dir / "results.parquet")
    assert {"iter_multiplier", "depth", "rmse_mv", "flops", "train_points", "params"} <= set(results.column_names)
    reported = nsl("report", f"sweep_dir={sweep_dir}", "nsl.max_breaks=1", "nsl.bootstrap=20", "figures.formats=[png]",
                   "mlflow.enabled=false")
    assert reported.returncode == 0, reported.stderr
    fits = pq.read_table(sweep_dir / "nsl_fits.parquet").to_pylist()
    pairs = {(fit["system"], fit["arch"]) for fit in fits}
    assert pairs == {("silverbox_sim", "narx"), ("wiener_hammerstein_sim", "narx"),
                     ("wiener_hammerstein_sim", "subnet")}  # no fits for the pair no sub-grid holds
    narx = [fit for fit in fits if (fit["system"], fit["arch"]) == ("silverbox_sim", "narx")]
    assert len(narx) == 6 and all(fit["error"] is None for fit in narx)  # 3 resources x 2 metrics
    assert "sub-grid 3 of 3" in (sweep_dir / "report.html").read_text()
    assert read_row(next((sweep_dir / "rows").rglob("*.parquet")))["arch"] in ("narx", "subnet")
    subnets = results.column("arch").to_pylist().count("subnet")
    assert subnets and results.column("nmae_one_step_test").null_count == subnets  # SUBNET: free run only

    refit = nsl("fit", f"sweep_dir={sweep_dir}", "nsl.max_breaks=1", "nsl.bootstrap=0",
                "metrics=[nmae_one_step_test,rmse_mv]")
    assert refit.returncode == 0, refit.stderr
    fits = pq.read_table(sweep_dir / "nsl_fits.parquet").to_pylist()
    assert {fit["metric"] for fit in fits} == {"nmae_one_step_test", "rmse_mv"}
    one_step = [fit for fit in fits if (fit["metric"], fit["system"]) == ("nmae_one_step_test", "silverbox_sim")]
    assert one_step and all(fit["error"] is None for fit in one_step)
    bad = nsl("fit", f"sweep_dir={sweep_dir}", "metrics=[nmae_free_run_arrow]")
    assert bad.returncode != 0 and "nmae_free_run_arrow not among the sweep's scores; choose from: nmae" in bad.stderr


@pytest.mark.slow
def test_resubmit_leaves_out_tasks_that_cannot_run_and_runs_the_rest(tmp_path):
    """NARX reading 250 past samples: data tier 250 (at most 250 samples) holds no window of 251, tier 500 does.
    resubmit runs the tier-500 task whose row went missing, never the two that cannot run (before: they were
    resubmitted, and failed again with every task of their group)."""
    sweep_dir = tmp_path / "sweep"
    settings = ["+sweep=io_demo", "sweep.grid=[{arch: [narx], system: [silverbox_sim], seed: [0, 1], "
                "iter_multiplier: [1], data_tier: [250, 500], width_tier: [4], depth: [1]}]",
                "arch.past_outputs=250", "arch.past_inputs=250", "system.init_samples=300", "train.batch_size=32"]
    launched = nsl("launch", *settings, "launcher=local", f"sweep_dir={sweep_dir}")
    assert launched.returncode == 0 and "2 tasks cannot run as configured: recorded as failed" in launched.stdout
    next((sweep_dir / "rows").rglob("*.parquet")).unlink()
    again = nsl("resubmit", f"sweep_dir={sweep_dir}")
    assert again.returncode == 0, again.stdout + again.stderr
    assert "2 tasks cannot run as configured" in again.stdout and "resubmitting 1 tasks" in again.stdout
    status = nsl("status", f"sweep_dir={sweep_dir}").stdout
    assert "done 2 |" in status and "failed 2 |" in status and "shorter than one narx window" in status
