"""Post-processing a real (small) sweep: merge with corrupt, duplicate and missing shards, NSL fits,
figures, report and MLflow runs that are updated, not duplicated."""

import json
import shutil
import time
from types import SimpleNamespace

import matplotlib.image
import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest
import yaml
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure
from mlflow.tracking import MlflowClient

from nsl_hpc.analysis.cards import core_hours
from nsl_hpc.analysis.figures import draw_nsl, legend_kind, power_label
from nsl_hpc.analysis.nsl_settings import Figures
from nsl_hpc.core.seeding import stable_hash
from nsl_hpc.sweep.directory import sweep_lock
from nsl_hpc.sweep.failures import record_failure
from nsl_hpc.sweep.launch_settings import launch_settings
from nsl_hpc.sweep.layout import row_path
from nsl_hpc.sweep.manifest import read_launch_config
from nsl_hpc.sweep.merge import Vanished, read_shards
from nsl_hpc.sweep.rows import named_rows, read_row, read_task_rows, row_states, write_row_atomically
from nsl_hpc.sweep.submissions import record_submission
from tests.sweeps import TINY_GRID, manifest_ids, nsl, row_files

pytestmark = pytest.mark.e2e  # runs the commands end to end (make test-fast leaves it out)

# 24 tasks: spring / input_affine, 3 seeds x 2 epoch counts x 2 data tiers x 2 width tiers.
SMALL_GRID = ["+sweep=demo", "sweep.grid.system=[spring]", "sweep.grid.arch=[input_affine]", "sweep.grid.seed=[0,1,2]",
              "sweep.grid.epochs=[4,32]", "sweep.grid.data_tier=[2,8]", "sweep.grid.width_tier=[4,16]"]
NSLS = 6  # 1 system x 1 arch x 3 resources x 2 metrics


@pytest.fixture(scope="module")
def finished_sweep(tmp_path_factory):
    sweep_dir = tmp_path_factory.mktemp("small") / "sweep"
    result = nsl("launch", *SMALL_GRID, "launcher=local", f"sweep_dir={sweep_dir}")
    assert result.returncode == 0, result.stderr
    return sweep_dir


@pytest.fixture(scope="module")
def fitted_sweep(finished_sweep, tmp_path_factory):
    """A copy of the finished sweep, merged and fitted (one break at most, no bootstrap); tests that change it copy
    it first."""
    sweep_dir = shutil.copytree(finished_sweep, tmp_path_factory.mktemp("fitted") / "sweep")
    assert nsl("merge", f"sweep_dir={sweep_dir}").returncode == 0
    assert nsl("fit", f"sweep_dir={sweep_dir}", "nsl.max_breaks=1", "nsl.bootstrap=0").returncode == 0
    return sweep_dir


@pytest.fixture
def sweep_copy(finished_sweep, tmp_path):
    return shutil.copytree(finished_sweep, tmp_path / "sweep")


@pytest.mark.slow
def test_merge_reports_corrupt_duplicate_and_missing_shards_and_is_idempotent(sweep_copy):
    ids = manifest_ids(sweep_copy)
    corrupt, deleted, frozen, copied = (row_path(sweep_copy, ids[i]) for i in range(4))
    corrupt.write_bytes(corrupt.read_bytes()[:100])  # half-written
    deleted.unlink()
    frozen.unlink()
    record_failure(sweep_copy, ids[2], "frozen", "no heartbeat")
    write_row_atomically(read_row(copied), copied.with_name(f"{ids[3]}.copy.parquet"))  # a duplicate row of task 3
    result = nsl("merge", f"sweep_dir={sweep_copy}")
    assert result.returncode == 0, result.stderr
    assert "3 of 24 tasks (12.5%) dropped: 1 frozen, 0 failed, 2 missing" in result.stdout
    assert "1 corrupt shards moved to corrupt/" in result.stdout and corrupt.name in result.stdout
    assert not corrupt.exists() and len(list((sweep_copy / "corrupt").iterdir())) == 1  # kept aside
    assert "1 duplicate rows" in result.stdout
    results = pq.read_table(sweep_copy / "results.parquet")
    assert results.num_rows == 21 and len(set(results["task_id"].to_pylist())) == 21
    assert set(results["task_id"].to_pylist()) == set(ids) - set(ids[:3])
    assert {"system", "epochs", "data_size", "params", "nmae", "nmse", "status"} <= set(results.column_names)
    assert nsl("merge", f"sweep_dir={sweep_copy}").returncode == 0
    assert pq.read_table(sweep_copy / "results.parquet").equals(results)


@pytest.mark.slow
def test_fit_writes_one_row_per_nsl_and_reports_excluded_outcomes(sweep_copy):
    assert nsl("merge", f"sweep_dir={sweep_copy}").returncode == 0
    results = pq.read_table(sweep_copy / "results.parquet")
    nmae = results["nmae"].to_pylist()
    nmae[0] = 0.0  # a zero error cannot enter a log-log fit
    pq.write_table(results.set_column(results.schema.get_field_index("nmae"), "nmae", pa.array(nmae)),
                   sweep_copy / "results.parquet")
    result = nsl("fit", f"sweep_dir={sweep_copy}", "nsl.max_breaks=2", "nsl.bootstrap=20")
    assert result.returncode == 0, result.stderr
    fits = pq.read_table(sweep_copy / "nsl_fits.parquet").to_pylist()
    assert len(fits) == NSLS
    assert {(f["resource"], f["metric"]) for f in fits} == {(r, m) for r in ("compute", "data", "model")
                                                            for m in ("nmae", "nmse")}
    assert all(f["error"] is None and 0 <= f["b"] <= 2 and f["margin"] >= 0 for f in fits)
    assert all((f["outcomes"], f["excluded"]) == ((23, 1) if f["metric"] == "nmae" else (24, 0)) for f in fits)
    text = (sweep_copy / "nsl_fits.txt").read_text()
    assert text.count("(1 excluded: not ok or non-positive)") == 3
    assert text.count("L(c) = ") == 2 and text.count("L(d) = ") == 2 and text.count("L(p) = ") == 2
    assert text.count("90% (20 resamples): last slope") == NSLS and text.count("paper (Section 5.2") == 1
    for fit in fits:
        assert len(fit["bootstrap_thetas"]) == 20 and fit["last_slope_lo"] <= fit["last_slope_hi"]
        assert fit["L_at_max_lo"] <= fit["L_at_max_hi"] and fit["r_max"] > 0
    published = next(f for f in fits if (f["resource"], f["metric"]) == ("data", "nmae"))
    assert (published["paper_b"], published["paper_margin"]) == (2, 0.07) and published["paper_margin_on_ours"] > 0
    assert json.loads(published["paper_range"]) == [100, 51165] and published["r_min"] < published["r_max"]
    assert all(f["paper_b"] is None for f in fits if f is not published)

    # a card per law: what it takes to reproduce or reject it
    cards = {path.name: json.loads(path.read_text()) for path in (sweep_copy / "law_cards").glob("*.json")}
    assert len(cards) == NSLS
    card = cards["spring__input_affine__data__nmae.json"]
    launch = yaml.safe_load((sweep_copy / "launch.yaml").read_text())
    assert card["provenance"]["grid_hash"] == stable_hash(launch["sweep"]["grid"])
    assert card["law"]["b"] == published["b"] and card["margin"]["M"] == published["margin"]
    assert len(card["envelope"]["r"]) == len(card["envelope"]["e"]) == 100  # nsl.K
    assert card["b_why"].startswith(f"b={published['b']} of 0..2: ") and card["published"]["b"] == 2
    assert card["intervals"]["resamples"] == 20 and card["intervals"]["draw"] == "half"
    assert card["intervals"]["last_slope"]["lo"] <= card["law"]["slopes"][-1]
    assert card["backtest"]["M_above"] == published["backtest_margin"]
    hours = card["core_hours"]
    assert hours["tasks"] == 24 and hours["predicted"] > 0 and hours["measured"] > 0
    assert all(other["core_hours"] == hours and other["provenance"] == card["provenance"] for other in cards.values())
    # tasks submitted to SLURM: the prediction recorded at their submission (status's), not planned again
    submitted = manifest_ids(sweep_copy)[:6]
    record_submission(sweep_copy, "77", 60, ["77_0"], [submitted], [[600.0] * 6])
    launch, results = launch_settings(read_launch_config(sweep_copy)), pq.read_table(sweep_copy / "results.parquet")
    again = core_hours(sweep_copy, launch, results)
    others = results.filter(pc.invert(pc.is_in(results["task_id"], value_set=pa.array(submitted))))
    unsubmitted = core_hours(sweep_copy, launch, others)
    assert again["predicted"] == pytest.approx(1.0 + unsubmitted["predicted"], rel=1e-9)  # 6 x 600 s
    (sweep_copy / "submissions" / "77.json").unlink()
    assert nsl("fit", f"sweep_dir={sweep_copy}", "metrics=[nmae]", "nsl.bootstrap=0").returncode == 0
    assert sorted(path.name for path in (sweep_copy / "law_cards").glob("*.json")) == sorted(
        name for name in cards if "__nmae" in name)  # the cards of laws no longer fitted are gone


@pytest.mark.slow
def test_predict_answers_from_the_fitted_laws_and_refuses_bad_targets(sweep_copy):
    assert nsl("predict", f"sweep_dir={sweep_copy}", "target=0.1").stderr.startswith("error: ")  # not fitted yet
    assert nsl("merge", f"sweep_dir={sweep_copy}").returncode == 0
    assert nsl("fit", f"sweep_dir={sweep_copy}", "nsl.max_breaks=1", "nsl.bootstrap=20").returncode == 0
    best = min(pq.read_table(sweep_copy / "results.parquet")["nmae"].to_pylist())
    within = nsl("predict", f"sweep_dir={sweep_copy}", f"target={2 * best}")
    assert within.returncode == 0, within.stderr
    assert "nMAE" in within.stdout and "spring / input_affine: " in within.stdout and "needs c = " in within.stdout
    assert "parameters, data from" in within.stdout or "not reachable" in within.stdout
    assert "spring / input_affine: no joint law (8 configurations" in within.stdout  # 2 epochs x 2 data x 2 widths
    joint = nsl("predict", f"sweep_dir={sweep_copy}", f"target={2 * best}", "nsl.joint.min_configurations=4",
                "nsl.joint.min_levels=2", "nsl.joint.bootstrap=10")
    assert joint.returncode == 0, joint.stderr
    lines = joint.stdout.split("at the least cost", 1)[1].splitlines()
    assert lines[1].startswith("  spring / input_affine: L = ") and "the best of 3 seeds each" in lines[1]
    assert "core-hours for 3 runs [" in lines[2]  # the law reaches twice the best outcome within the candidates
    assert lines[3].startswith("      the cheapest the sweep ran that reached it: epochs ")
    data = nsl("predict", f"sweep_dir={sweep_copy}", f"target={best / 2}", "resource=data", "metric=nmse")
    assert data.returncode == 0 and "needs d = " in data.stdout
    for args, message in ((["target=0"], "target=0 must be a finite number in (0, inf)"),
                          (["target=0.1", "metric=accuracy"], "metric='accuracy'; choose one of: nmae, nmse")):
        refused = nsl("predict", f"sweep_dir={sweep_copy}", *args)
        assert refused.returncode == 2 and refused.stderr.strip() == f"error: {message}"


@pytest.mark.slow
def test_report_figures_and_mlflow_runs_are_updated_not_duplicated(sweep_copy):
    result = nsl("report", f"sweep_dir={sweep_copy}", "nsl.max_breaks=1", "nsl.bootstrap=20",
                 "compact=false")  # a row to remove below
    assert result.returncode == 0, result.stderr
    report = (sweep_copy / "report.html").read_text()
    assert report.count("data:image/png;base64,") == NSLS + NSLS  # every NSL and the 6 overview grids
    assert "0 of 24 tasks (0.0%) dropped" in report and report.count("<td><code>L(") == NSLS
    assert "predicted by the planner, " in report and "law_cards/" in report
    assert len(list((sweep_copy / "law_cards").glob("*.json"))) == NSLS
    assert "Against the published laws" in report and "Section 5.2, Figure fig:data-nmae-aff-spring" in report
    comparison = (sweep_copy / "comparison.md").read_text().splitlines()
    assert len(comparison) == 5 and comparison[2].startswith("| spring / input_affine / data / nmae | 2 / ")
    assert comparison[4].startswith("Scores: nMAE and nMSE divide every dx/dt column by one spread")  # which
    assert comparison[4].endswith("Fits: least squares of the log residuals on Definition 1's step envelope "
                                  "(nsl.envelope=step), a residual where the law lies above it weighed 5x "
                                  "(nsl.above_weight), every segment's slope in [-10, 0.19] (a law never rises "
                                  "more than the published ones do; nsl.max_slope, nsl.max_rise); b chosen in 0..1 "
                                  "among the laws whose every segment stands on at least 5 outcomes of the "
                                  "envelope: each break must cut the margin by 30%, not counting the 5% of envelope "
                                  "points the law fits worst (nsl.min_segment_points, nsl.min_gain, "
                                  "nsl.choice_trim). A slope at -10 or on fewer outcomes of the envelope is "
                                  "undetermined (marked ?, drawn grey).")
    assert "| 1e+02-5.1e+04 / " in comparison[2] and comparison[2].endswith("fig:data-nmae-aff-spring |")
    assert "What it takes" in report and "c needed [90%]" in report
    for png in (sweep_copy / "figures").rglob("*.png"):
        image = matplotlib.image.imread(png)
        assert image.shape[0] > 300 and image.shape[1] > 300 and image.std() > 0
    pdfs = list((sweep_copy / "figures").rglob("*.pdf"))
    assert len(pdfs) == 2 * NSLS and all(pdf.read_bytes().startswith(b"%PDF") for pdf in pdfs)

    client = MlflowClient(f"sqlite:///{sweep_copy / 'mlflow.db'}")
    experiment = client.get_experiment_by_name("nsl_hpc").experiment_id
    runs = client.search_runs([experiment])
    assert len(runs) == 1 + NSLS
    parent = next(run for run in runs if run.data.tags["nsl_hpc.analysis.broken_law"] == "sweep")
    assert parent.data.metrics["merged"] == 24 and parent.data.params["sweep.name"] == "demo"
    assert {a.path for a in client.list_artifacts(parent.info.run_id)} >= {"results.parquet", "report.html"}
    child = next(run for run in runs if run.data.tags["nsl_hpc.analysis.broken_law"] == "spring/input_affine/data/nmae")
    assert child.data.metrics["paper_M"] == 0.07 and child.data.metrics["last_slope_lo"] <= child.data.metrics[
        "last_slope_hi"]

    row_path(sweep_copy, manifest_ids(sweep_copy)[0]).unlink()  # one task fewer: some laws change
    again = nsl("report", f"sweep_dir={sweep_copy}", "nsl.max_breaks=1", "nsl.bootstrap=20", "figures.formats=[png]")
    assert again.returncode == 0, again.stderr
    runs = client.search_runs([experiment])
    assert len(runs) == 1 + NSLS
    parent = next(run for run in runs if run.data.tags["nsl_hpc.analysis.broken_law"] == "sweep")
    assert parent.data.metrics["merged"] == 23 and parent.data.metrics["missing"] == 1


def test_post_processing_bad_input_is_a_one_line_error(tmp_path, finished_sweep):
    for verb in ("merge", "fit", "report"):
        result = nsl(verb, f"sweep_dir={tmp_path}")
        assert result.returncode == 2 and "no manifest.parquet" in result.stderr
        assert result.stderr.strip().count("\n") == 0
    sweep_dir = tmp_path / "empty"
    assert nsl("launch", *SMALL_GRID, f"sweep_dir={sweep_dir}", "dry_run=true").returncode == 0
    unmerged = nsl("fit", f"sweep_dir={sweep_dir}")
    assert unmerged.returncode == 2 and f"run python -m nsl_hpc.merge sweep_dir={sweep_dir} first" in unmerged.stderr
    merged = nsl("merge", f"sweep_dir={sweep_dir}")
    assert merged.returncode == 0 and "24 of 24 tasks (100.0%) dropped: 0 frozen, 0 failed, 24 missing" in merged.stdout
    empty = nsl("fit", f"sweep_dir={sweep_dir}")
    assert empty.returncode == 2 and "holds no outcomes" in empty.stderr
    for verb, bad, message in (("status", "interval_s=abc", "interval_s='abc' must be a finite number in (0, 86400]"),
                               ("status", "show_failures=-1", "show_failures=-1 must be a non-negative integer"),
                               ("resubmit", "states=[done]", "states value='done' is unknown; choose one of: failed")):
        refused = nsl(verb, f"sweep_dir={sweep_dir}", bad)
        assert refused.returncode == 2 and refused.stderr.strip().startswith(f"error: {message}"), refused.stderr
    assert len(row_files(finished_sweep)) == 24  # the module's sweep is untouched


def test_merge_again_reads_only_new_or_rewritten_shards_and_matches_a_fresh_merge(sweep_copy):
    ids = manifest_ids(sweep_copy)
    assert nsl("merge", f"sweep_dir={sweep_copy}", "compact=false").returncode == 0
    assert (sweep_copy / ".merge_cache.parquet").exists()
    rewritten = read_row(row_path(sweep_copy, ids[0]))
    write_row_atomically({**rewritten, "nmae": 123.0}, row_path(sweep_copy, ids[0]))
    row_path(sweep_copy, ids[1]).unlink()
    assert nsl("merge", f"sweep_dir={sweep_copy}", "compact=false").returncode == 0
    results = pq.read_table(sweep_copy / "results.parquet")
    by_id = dict(zip(results["task_id"].to_pylist(), results["nmae"].to_pylist(), strict=True))
    assert by_id[ids[0]] == 123.0 and ids[1] not in by_id and len(by_id) == 23
    (sweep_copy / ".merge_cache.parquet").write_bytes(b"not parquet")  # a broken cache is rebuilt
    assert nsl("merge", f"sweep_dir={sweep_copy}", "compact=false").returncode == 0
    assert pq.read_table(sweep_copy / "results.parquet").equals(results)
    (sweep_copy / ".merge_cache.parquet").unlink()
    assert nsl("merge", f"sweep_dir={sweep_copy}").returncode == 0  # and compacted: the same results
    assert pq.read_table(sweep_copy / "results.parquet").equals(results)


def test_merge_compacts_the_rows_and_status_launch_resubmit_and_budgets_still_find_them(finished_sweep, sweep_copy):
    ids = manifest_ids(sweep_copy)
    plain = shutil.copytree(finished_sweep, sweep_copy.parent / "plain")
    assert nsl("merge", f"sweep_dir={plain}", "compact=false").returncode == 0
    merged = nsl("merge", f"sweep_dir={sweep_copy}")
    assert "24 row files compacted into rows/compacted/" in merged.stdout, merged.stdout
    (part,) = row_files(sweep_copy)
    assert part.parent.name == "compacted" and not any(row_path(sweep_copy, task_id).exists() for task_id in ids)
    whole = pa.concat_tables([named_rows(pq.read_table(path), [str(path)])[0]
                              for path in (row_path(finished_sweep, task_id) for task_id in ids)])
    assert pq.read_table(part).sort_by("task_id").equals(whole.sort_by("task_id"))  # every column of every row
    results = pq.read_table(sweep_copy / "results.parquet")
    assert results.equals(pq.read_table(plain / "results.parquet"))
    assert "done 24 |" in nsl("status", f"sweep_dir={sweep_copy}").stdout
    assert "nothing to run: every task has a row" in nsl("launch", *SMALL_GRID, "launcher=local",
                                                         f"sweep_dir={sweep_copy}").stdout
    assert "nothing to resubmit" in nsl("resubmit", f"sweep_dir={sweep_copy}", "states=[missing,corrupt]").stdout
    assert set(row_states(sweep_copy, [*ids, "0" * 16]).values()) == {"done", "missing"}
    assert read_task_rows(sweep_copy, ids[:2]) == {row["task_id"]: row for row in whole.to_pylist()[:2]}

    # a compaction interrupted before it removed the own files leaves copies: the next merge removes them
    shutil.copy(row_path(finished_sweep, ids[5]), row_path(sweep_copy, ids[5]))
    again = nsl("merge", f"sweep_dir={sweep_copy}")
    assert "1 row files compacted" in again.stdout and "duplicate" not in again.stdout, again.stdout
    assert row_files(sweep_copy) == [part] and pq.read_table(sweep_copy / "results.parquet").equals(results)

    # a finished task's row in its own file joins a second compacted file; none while another command holds the sweep
    row_path(sweep_copy, "0" * 16).parent.mkdir(parents=True, exist_ok=True)
    write_row_atomically({**whole.to_pylist()[0], "task_id": "0" * 16}, row_path(sweep_copy, "0" * 16))
    with sweep_lock(sweep_copy, "clean"):
        held = nsl("merge", f"sweep_dir={sweep_copy}")
    assert "rows not compacted: " in held.stdout and "is in use by clean" in held.stdout, held.stdout
    assert "1 rows of tasks outside the manifest ignored" in held.stdout  # not the manifest's: never compacted
    assert len(row_files(sweep_copy)) == 2


@pytest.mark.parametrize(("verb", "override", "message"), [
    ("fit", "nsl.envelope=foo", "nsl.envelope='foo' is unknown; choose one of: step, interpolated"),
    ("fit", "nsl.max_breaks=-1", "nsl.max_breaks=-1 must be a non-negative integer"),
    ("fit", "nsl.breaks=99", "nsl.breaks=99 must be an integer from 0 to 4"),
    ("fit", "nsl.max_breaks=10", "nsl.max_breaks=10 must be an integer from 0 to 9 (nsl.positions)"),
    ("fit", "nsl.K=x", "nsl.K='x' must be an integer from 2 up"),
    ("fit", "nsl.bootstrap=-5", "nsl.bootstrap=-5 must be a non-negative integer"),
    ("fit", "nsl.bootstrap_draw=twice", "nsl.bootstrap_draw='twice' is unknown; choose one of: half, replacement"),
    ("predict", "nsl.predict.decades=0", "nsl.predict.decades=0 must be a finite number in (0, inf)"),
    ("predict", "target=inf", "target=inf must be a finite number in (0, inf)"),
    ("predict", "nsl.bootstrap_level=2", "nsl.bootstrap_level=2 must be a finite number in (0, 1)"),
    ("predict", "nsl.joint.above_weight=0.5", "nsl.joint.above_weight=0.5 must be a finite number in [1, inf)"),
    ("report", "nsl.predict.report.metric=foo", "nsl.predict.report.metric='foo'; choose one of: nmae, nmse"),
    ("report", "figures.dpi=0", "figures.dpi=0 must be an integer from 10 to 2400"),
    ("report", "figures.formats=[pngg]", "figures.formats value='pngg'; choose one of:"),
    ("report", "mlflow.timeout_s=0", "mlflow.timeout_s=0 must be a finite number in (0, 600]"),
])
def test_a_bad_setting_is_one_line_before_any_work_and_keeps_the_fits(fitted_sweep, verb, override, message):
    fits = (fitted_sweep / "nsl_fits.parquet").read_bytes()
    extra = ["target=0.05"] if verb == "predict" and not override.startswith("target") else []
    result = nsl(verb, f"sweep_dir={fitted_sweep}", override, *extra)
    assert result.returncode == 2 and result.stderr == f"error: {result.stderr[7:]}", result.stderr
    assert message in result.stderr and len(result.stderr.splitlines()) == 1, result.stderr
    assert (fitted_sweep / "nsl_fits.parquet").read_bytes() == fits


def test_a_fit_where_no_law_can_be_fitted_keeps_the_fits_it_would_replace(fitted_sweep, tmp_path):
    sweep_copy = shutil.copytree(fitted_sweep, tmp_path / "sweep")
    fits = (sweep_copy / "nsl_fits.parquet").read_bytes()
    results = pq.read_table(sweep_copy / "results.parquet")
    pq.write_table(results.slice(0, 1), sweep_copy / "results.parquet")  # one outcome: no law can be fitted
    result = nsl("fit", f"sweep_dir={sweep_copy}", "nsl.bootstrap=0")
    assert result.returncode == 1 and "none of the 6 NSLs could be fitted" in result.stderr, result.stderr
    assert "nsl_fits.parquet is left as it was" in result.stderr
    assert (sweep_copy / "nsl_fits.parquet").read_bytes() == fits


@pytest.mark.parametrize(("value", "label"), [(1e5, "10\u2075"), (1.0, "10\u2070"), (2e-3, "2\u00d710\u207b\u00b3"),
                                              (7e12, "7\u00d710\u00b9\u00b2"), (0.5, "5\u00d710\u207b\u00b9")])
def test_log_tick_labels_are_powers_of_ten_in_unicode(value, label):
    assert power_label(value) == label


@pytest.mark.parametrize(("label", "kind"), [
    ("envelope (K=100, Definition 1)", "lower envelope"),
    ("undetermined: the last segment stands on 3 envelope points", "undetermined segment (no law there)"),
    ("interpolated envelope (the fitted one: the law may run below the steps)", "interpolated envelope (fitted)"),
    ("L(c) = 0.1 c^-0.2\nM = 0.05", "fitted law"), ("90% band (200 resamples)", "band"),
    ("published (b=2, M=0.04; M on ours 0.1)", "published law"), ("breaks", "breaks")])
def test_every_line_of_a_panel_has_its_entry_in_the_overview_legend(label, kind):
    """The grey dotted undetermined segments have their own entry (their label names the envelope too)."""
    assert legend_kind(label) == kind


def test_a_row_file_gone_while_merge_reads_is_no_corrupt_row(finished_sweep, tmp_path):
    """A compaction by another merge moves row files while this one reads: a file gone under it makes merge list
    the files again (read_rows), never counts as a corrupt row whose task is then dropped as missing."""
    sweep_dir = shutil.copytree(finished_sweep, tmp_path / "sweep")
    paths = [str(path) for path in row_files(sweep_dir)]
    with pytest.raises(Vanished):
        read_shards([*paths, str(sweep_dir / "rows" / "00" / "gone.parquet")])
    rows, corrupt = read_shards(paths)
    assert rows.num_rows == 24 and corrupt == []


# Report with a tracking server that does not answer: one line within mlflow.timeout_s, nothing replaced.
@pytest.mark.e2e
@pytest.mark.parametrize("uri", ["http://127.0.0.1:9", "http://10.255.255.1:5000"])  # refused; unroutable
def test_report_with_a_tracking_server_that_does_not_answer_stops_before_writing(uri, tmp_path):
    sweep_dir = tmp_path / "sweep"
    assert nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={sweep_dir}", "dry_run=true").returncode == 0
    fits = sweep_dir / "nsl_fits.parquet"
    fits.write_bytes(b"the fits of an earlier report")
    started = time.monotonic()
    result = nsl("report", f"sweep_dir={sweep_dir}", f"mlflow.tracking_uri={uri}", "mlflow.timeout_s=2")
    assert time.monotonic() - started < 60
    assert result.returncode == 1 and len(result.stderr.splitlines()) == 1, result.stderr
    assert result.stderr.startswith(f"error: no MLflow tracking server answers at {uri} (mlflow.timeout_s=2; ")
    assert fits.read_bytes() == b"the fits of an earlier report" and not (sweep_dir / "results.parquet").exists()


def test_a_diverged_outcome_is_drawn_at_the_edge_not_stretching_the_range():
    """A free run that diverged (nMAE 1e36) keeps the plotted range within figures.decades_above_envelope of the
    envelope's highest step and is drawn at its edge, named in the legend."""
    figures = Figures(formats=["png"], dpi=50, colour={}, size={}, marker_size=[3, 40], formula_width=70,
                      decades_above_envelope=2)
    r = np.geomspace(1e3, 1e6, 40)
    e = 0.5 * (r / 1e3) ** -0.3
    e[7] = 1e36
    data = {"r": r, "e": e, "c": r, "s": r}
    row = {"system": "toy", "arch": "toy", "resource": "compute", "metric": "nmae", "error": "not fitted"}
    ax = Figure().subplots()
    draw_nsl(ax, data, row, SimpleNamespace(K=100), figures, LogNorm(r.min(), r.max()), legend=False)
    assert ax.get_ylim()[1] <= 0.5 * 100 * 1.001
    labels = ax.get_legend_handles_labels()[1]
    assert any(label.startswith("1 beyond the plotted range (up to 1e+36)") for label in labels)
