"""Did the models learn: a pair of deliberately broken models (NARX with one hidden unit, whose LayerNorm makes its
output a constant) is flagged by fit and report, a pair of models that learn is not."""

import pyarrow.parquet as pq
import pytest

from tests.sweeps import nsl

pytestmark = pytest.mark.e2e

GRID = ["+sweep=io_demo", "tiers.width=[1,4,16]", "train.batch_size=64",
        # broken: n_h = 1 (width tier 1 draws 1), a constant output
        "sweep.grid.0.seed=[0,1]", "sweep.grid.0.iter_multiplier=[1]", "sweep.grid.0.data_tier=[500]",
        "sweep.grid.0.width_tier=[1]",
        # learning: n_h 8-16, 4 n_l iterations
        "sweep.grid.1.seed=[0,1]", "sweep.grid.1.iter_multiplier=[4]", "sweep.grid.1.data_tier=[625]",
        "sweep.grid.1.width_tier=[16]", "sweep.grid.2.seed=[0]", "sweep.grid.2.data_tier=[625]",
        "sweep.grid.2.width_tier=[4]", "system.subnet.horizon=20"]


@pytest.mark.slow
def test_a_pair_of_constant_models_is_flagged_and_a_pair_that_learns_is_not(tmp_path):
    sweep_dir = tmp_path / "sweep"
    launched = nsl("launch", *GRID, "launcher=local", f"sweep_dir={sweep_dir}")
    assert launched.returncode == 0, launched.stdout + launched.stderr
    assert nsl("merge", f"sweep_dir={sweep_dir}").returncode == 0
    results = pq.read_table(sweep_dir / "results.parquet").to_pylist()
    broken = [row for row in results if row["system"] == "silverbox_sim"]
    assert {row["width"] for row in broken} == {1}
    assert all(row["output_spread"] < 1e-6 and row["free_run_finite"] for row in broken)  # a constant output
    assert all(row["nmae"] > 0.95 * row["mean_predictor_nmae"] for row in broken)
    learning = [row for row in results if (row["system"], row["arch"]) == ("wiener_hammerstein_sim", "narx")]
    assert all(row["nmae"] < 0.95 * row["mean_predictor_nmae"] for row in learning)
    assert all(0 < row["validation_nmae"] < 1 for row in learning)

    every_task = "nsl.learning.above_quantile=0"  # a grid of 2 tasks per pair: all count
    fitted = nsl("fit", f"sweep_dir={sweep_dir}", every_task, "nsl.bootstrap=0", "nsl.max_breaks=1")
    assert fitted.returncode == 0, fitted.stderr
    lines = {line.split(":")[0]: line for line in fitted.stdout.splitlines() if " / " in line.split(":")[0]}
    assert lines["silverbox_sim / narx"].endswith("NOT LEARNING")
    assert "2 of 2 tasks (100%)" in lines["silverbox_sim / narx"]
    assert "0 of 2 tasks (0%)" in lines["wiener_hammerstein_sim / narx"]
    assert not lines["wiener_hammerstein_sim / narx"].endswith("NOT LEARNING")

    reported = nsl("report", f"sweep_dir={sweep_dir}", every_task, "nsl.bootstrap=0",
                   "nsl.max_breaks=1", "figures.formats=[png]", "mlflow.enabled=false")
    assert reported.returncode == 0, reported.stderr
    page = (sweep_dir / "report.html").read_text()
    assert "Did the models learn?" in page
    assert '<tr style="color:#b00"><td>silverbox_sim</td><td>narx</td>' in page  # flagged
    assert "<tr><td>wiener_hammerstein_sim</td><td>narx</td>" in page  # not flagged
