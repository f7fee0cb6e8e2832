"""The reproduction's status (nsl_hpc/analysis/reproduction.py) on small merged sweeps written here: how far an
envelope of half the tasks rises, the gap readings of a slice cut at each value of a coordinate or read on the
paper's approximate parameter count, and the candidates' table keeping the committed rows of runs not on this
machine."""

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from nsl_hpc.analysis.published import published_law
from nsl_hpc.analysis.reproduction import GapReading, LawGap, LawSlice, candidates_table, gaps_table, half_task_rise

LAW = "ball/port_hamiltonian/model/nmae"


def merged(sweep_dir: Path, params: list[float], nmae: list[float], epochs: list[int]) -> Path:
    """A merged sweep of ball / port-Hamiltonian rows (results.parquet) with these outcomes."""
    sweep_dir.mkdir(parents=True)
    n = len(params)
    pq.write_table(pa.table({
        "task_id": [f"t{k}" for k in range(n)], "system": ["ball"] * n, "arch": ["port_hamiltonian"] * n,
        "status": ["ok"] * n, "params": params, "nmae": nmae, "epochs": epochs, "width": [4] * n, "depth": [2] * n,
        "flops": [1e6] * n, "train_points": [1000] * n, "mean_predictor_nmae": [0.5] * n}),
        sweep_dir / "results.parquet")
    return sweep_dir


def test_half_the_tasks_raise_the_envelope_where_its_best_outcomes_are_rare():
    """A half's envelope never lies below the whole one's; equal outcomes: no rise; an outcome alone far below the
    rest (20x): about half of the halves lie on the rest, so the average rise is near sqrt(20); three such outcomes:
    a half misses all three about one time in eight, so it rises far less; no outcome at or below the resource:
    NaN."""
    rng = np.random.default_rng(3)
    r, e = rng.uniform(1, 100, 200), rng.uniform(0.01, 1, 200)
    assert (half_task_rise(r, e, [10.0, 50.0, 100.0], 30) >= 1).all()
    r = np.arange(1.0, 41.0)
    e = np.full(40, 0.2)
    assert half_task_rise(r, e, [40.0], 20).tolist() == [1.0]
    e[17] = 0.01
    alone = half_task_rise(r, e, [40.0], 200)[0]
    assert 20 ** 0.4 < alone < 20 ** 0.6
    e[[5, 29]] = 0.01
    assert 1 <= half_task_rise(r, e, [40.0], 200)[0] < 20 ** 0.25 < alone
    assert np.isnan(half_task_rise(r, e, [0.5], 5)[0])


def test_a_gap_reading_cuts_a_slice_at_each_value_and_reads_the_papers_count(tmp_path):
    merged(tmp_path / "slice", [100.0, 300.0, 300.0], [0.2, 0.1, 0.01], [128, 128, 1024])
    gaps = {LAW: LawGap(at=[300.0], readings=[
        GapReading(slice="slice", label="cut", by="epochs", up_to=[128, 1024]),
        GapReading(slice="slice", label="paper", paper_count=True),
        GapReading(slice="absent", label="gone")])}
    table = gaps_table(gaps, tmp_path)
    law = published_law(tuple(LAW.split("/"))).law.predict(np.array([300.0]))[0]
    assert f"| cut, epochs <= 128 | slice | 2 | 0.1 | {0.1 / law:.2g}x |" in table
    assert f"| cut, epochs <= 1024 | slice | 3 | 0.01 | {0.01 / law:.2g}x |" in table
    # 4 n_d n_h^2 = 128 parameters: every outcome lies at or below 300
    assert f"| paper | slice | 3 | 0.01 | {0.01 / law:.2g}x |" in table
    assert "| gone | absent | not run |" in table


def test_a_candidate_not_on_this_machine_keeps_its_committed_row(tmp_path):
    merged(tmp_path / "model_slice", [100.0, 300.0], [0.2, 0.1], [128, 128])
    laws = {LAW: LawSlice(at=[300.0], slice="model_slice")}
    runs = {"model_slice": {"kept": ["x=1"], "absent": ["x=2"]}}
    committed = (f"**{LAW}** on `model_slice` (envelope / published law)\n\n| settings | outcomes |\n|---|---|\n"
                 "| kept (`x=1`) | 7 | 7 | 2x | 2x |\n")
    table = candidates_table(laws, tmp_path, runs, 0.95, committed)
    assert "| kept (`x=1`) | 7 | 7 | 2x | 2x |" in table
    assert "| absent (`x=2`) | not run |" in table
    assert "| default | 2 | 2 |" in table


def test_no_halves_is_no_reading():
    assert np.isnan(half_task_rise(np.arange(1.0, 5.0), np.ones(4), [4.0], 0)[0])
