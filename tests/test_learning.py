"""Did the models learn: a pair of deliberately broken models (NARX with one hidden unit, whose LayerNorm makes its
output a constant, and no bypass) is flagged by fit and report, with why, a pair of models that learn is not."""

import math

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from nsl_hpc.analysis.learning import pair_learning
from nsl_hpc.analysis.nsl_settings import Learning
from tests.sweeps import nsl

GRID = ["+sweep=io_demo", "tiers.width=[1,4,16]", "train.batch_size=64",
        # NARX without the linear path of its default layout
        "arch.block=layernorm_silu", "arch.bypass=false", "arch.zero_bias=false",
        # broken: n_h = 1 (width tier 1 draws 1), a constant output; learning: n_h 8-16, 4 n_l iterations
        "sweep.grid=[{arch: [narx], system: [silverbox_sim], seed: [0, 1], iter_multiplier: [1], data_tier: [500], "
        "width_tier: [1], depth: [1]}, {arch: [narx], system: [wiener_hammerstein_sim], seed: [0, 1], "
        "iter_multiplier: [4], data_tier: [625], width_tier: [16], depth: [1]}]"]


@pytest.mark.e2e
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
    output = fitted.stdout.splitlines()
    why = output[output.index(lines["silverbox_sim / narx"]) + 1]
    assert why == ("    why: none of its better-resourced tasks learned: check the architecture's layout and the "
                   "system's data (docs/fits.md, Did the models learn)")
    assert "0 of 2 tasks (0%)" in lines["wiener_hammerstein_sim / narx"]
    assert not lines["wiener_hammerstein_sim / narx"].endswith("NOT LEARNING")

    reported = nsl("report", f"sweep_dir={sweep_dir}", every_task, "nsl.bootstrap=0",
                   "nsl.max_breaks=1", "figures.formats=[png]", "mlflow.enabled=false")
    assert reported.returncode == 0, reported.stderr
    page = (sweep_dir / "report.html").read_text()
    assert "Did the models learn?" in page
    assert '<tr style="color:#b00"><td>silverbox_sim</td><td>narx</td>' in page  # flagged
    assert "NOT LEARNING: its laws describe models that fail; none of its better-resourced tasks learned" in page
    assert "<tr><td>wiener_hammerstein_sim</td><td>narx</td>" in page  # not flagged


def rows(nmae: list[float], steps: list[int]) -> pa.Table:
    """Rows of one pair at compute = steps, against a mean predictor of 1."""
    return pa.table({"system": ["ball"] * len(nmae), "arch": ["unstructured"] * len(nmae), "status": ["ok"] * len(nmae),
                     "task_id": [f"t{k}" for k in range(len(nmae))], "nmae": nmae, "steps": steps,
                     "flops": [float(s) for s in steps], "mean_predictor_nmae": [1.0] * len(nmae)})


LEARNING = Learning(below=0.95, flag_share=0.25, resource="compute", above_quantile=0.0)


@pytest.mark.parametrize(("nmae", "steps", "why"), [
    ([1.0, 1.0, 0.2, 0.1], [8, 16, 400, 500], "the better-resourced tasks that failed trained a median of 12 "
     "optimizer steps, those that learned 450: train longer"),
    ([1.0, 1.0, 0.2, 0.1], [400, 500, 400, 500], "the better-resourced tasks that failed trained as long as those "
     "that learned (a median of 450 optimizer steps against 450): the model, not its training length, fails here"),
    ([math.nan, math.inf, math.nan, 0.1], [400, 500, 400, 500], "3 of the 3 diverged or did not finish with finite "
     "scores: lower train.lr")])
def test_a_flagged_pair_says_why_its_tasks_failed(nmae, steps, why):
    """Failures that trained at most half as many optimizer steps as the tasks that learned ask for longer training;
    as many, for another model; mostly non-finite scores, for a smaller learning rate."""
    pair = pair_learning(rows(nmae, steps), "ball", "unstructured", LEARNING, "flops")
    assert pair.flagged and pair.why.startswith(why)
    assert pair.lines()[1] == f"    why: {pair.why}"
    learning = pair_learning(rows([0.2, 0.1, 0.3, 1.0], steps), "ball", "unstructured", LEARNING, "flops")
    assert not learning.flagged and learning.lines() == [learning.lines()[0]] and learning.why == ""
