"""`python -m nsl_hpc.train` end to end: one row, idempotence, determinism, and bad input."""

import subprocess
import sys

import pyarrow.parquet as pq
import pytest

from nsl_hpc.sweep.rows import read_row

pytestmark = pytest.mark.e2e  # runs the commands end to end (make test-fast leaves it out)

TASK = ["system=ball", "arch=port_hamiltonian", "epochs=3", "data_tier=2", "width_tier=4", "depth_tier=2",
        "seed=3"]
TIMING_COLUMNS = {"train_seconds", "wall_seconds"}
ROW_COLUMNS = {
    "task_id", "system", "arch", "seed", "sweep_seed", "epochs", "data_tier", "data_size", "n_traj",
    "train_points", "width_tier", "width", "depth_tier", "depth", "batch_size", "lr", "nmae", "nmse",
    "nmae_per_column", "nmse_per_column", "nmae_scalar", "nmse_scalar",
    "params", "flops", "flops_paper", "test_points", "steps", "final_loss", "status", "milestone", "package_version",
    "torch_version",
    "python_version", "host", *TIMING_COLUMNS,
}


def train(*args: str, cache_dir: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "nsl_hpc.train", f"cache_dir={cache_dir}", *args],
                          capture_output=True, text=True, timeout=300)


def rows_under(out_dir):
    return sorted(out_dir.rglob("*.parquet"))


def test_one_task_writes_one_complete_row(tmp_path, cache_dir):
    result = train(*TASK, f"out_dir={tmp_path}", cache_dir=cache_dir)
    assert result.returncode == 0, result.stderr
    (path,) = rows_under(tmp_path)
    assert pq.read_metadata(path).num_rows == 1
    row = read_row(path)
    assert set(row) == ROW_COLUMNS
    assert (row["system"], row["arch"], row["seed"], row["epochs"]) == ("ball", "port_hamiltonian", 3, 3)
    assert 1.0 <= row["data_size"] <= 2.0 and row["n_traj"] == pytest.approx(row["data_size"] / 10)
    assert row["train_points"] == int(row["n_traj"] * 1000)
    assert 2 <= row["width"] <= 4 and 1 <= row["depth"] <= 2
    assert row["flops"] == row["params"] * row["epochs"] * row["train_points"]
    assert row["status"] == "ok" and row["nmae"] > 0 and row["nmse"] > 0
    assert row["batch_size"] == 256 and row["lr"] == 1e-3
    assert path.stem == row["task_id"] and path.parent.name == row["task_id"][:2]
    assert row["task_id"] in result.stdout
    assert not [p for p in tmp_path.rglob("*") if p.name.startswith(".")]  # no temporary files


def test_same_config_and_seed_give_the_same_row(tmp_path, cache_dir):
    first, second = tmp_path / "a", tmp_path / "b"
    for out in (first, second):
        assert train(*TASK, f"out_dir={out}", cache_dir=cache_dir).returncode == 0
    row_a, row_b = (read_row(rows_under(out)[0]) for out in (first, second))
    for column in TIMING_COLUMNS:
        row_a.pop(column), row_b.pop(column)
    assert row_a == row_b


def test_existing_row_is_skipped_unless_forced(tmp_path, cache_dir):
    assert train(*TASK, f"out_dir={tmp_path}", cache_dir=cache_dir).returncode == 0
    (path,) = rows_under(tmp_path)
    written = path.stat().st_mtime_ns
    skipped = train(*TASK, f"out_dir={tmp_path}", cache_dir=cache_dir)
    assert skipped.returncode == 0 and "skipped" in skipped.stdout
    assert path.stat().st_mtime_ns == written
    forced = train(*TASK, f"out_dir={tmp_path}", "force=true", cache_dir=cache_dir)
    assert forced.returncode == 0 and path.stat().st_mtime_ns != written
    assert rows_under(tmp_path) == [path]


def test_different_seeds_draw_different_sizes(tmp_path, cache_dir):
    for seed in range(4):
        task = [*TASK[:-1], f"seed={seed}"]
        assert train(*task, "width_tier=16", f"out_dir={tmp_path}", cache_dir=cache_dir).returncode == 0
    rows = [read_row(p) for p in rows_under(tmp_path)]
    assert len({row["data_size"] for row in rows}) == 4
    assert len({row["task_id"] for row in rows}) == 4


@pytest.mark.parametrize(("override", "message"), [
    ("system=pendulum", "unknown system 'pendulum'; choose one of: ball, motor, silverbox, silverbox_sim, spring"),
    ("arch=transformer", "unknown arch 'transformer'; choose one of: input_affine, narx, port_hamiltonian, "
                         "subnet, unstructured"),
    ("system=silverbox_sim", "system=silverbox_sim belongs to the input_output study, not input_state; "
                             "add study=input_output"),
    ("epochs=0", "epochs=0 must be a positive integer"),
    ("epochs=-4", "epochs=-4 must be a positive integer"),
    ("data_tier=1024", "data_tier=1024 is outside the grid; allowed: 2, 4, 8, 16, 32, 64, 128, 256, 512"),
    ("width_tier=3", "width_tier=3 is outside the grid"),
    ("depth_tier=8", "depth_tier=8 is outside the grid"),
    ("arch.width_factor=0.1", None),  # only unstructured has the key: an unknown key for pH
    ("learning_rate=0.1", "learning_rate"),
])
def test_bad_input_fails_fast_with_one_line(override, message, tmp_path, cache_dir):
    out_dir = tmp_path / "out"
    result = train(*TASK, override, f"out_dir={out_dir}", cache_dir=cache_dir)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ")
    assert message is None or message in lines[0]
    assert "Traceback" not in result.stderr
    assert not out_dir.exists()


def test_width_that_rounds_to_zero_fails_before_work(tmp_path, cache_dir):
    result = train("arch=unstructured", "arch.width_factor=0.2", "width_tier=2", f"out_dir={tmp_path / 'o'}",
                   cache_dir=cache_dir)
    assert result.returncode == 2 and "width_factor=0.2" in result.stderr
    assert not (tmp_path / "o").exists()


def test_unwritable_output_dir_fails_before_work(tmp_path, cache_dir):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    result = train(*TASK, f"out_dir={blocker / 'rows'}", cache_dir=cache_dir)
    assert result.returncode == 2
    assert result.stderr.startswith("error: out_dir=") and "not writable" in result.stderr
    assert blocker.read_text() == "not a directory"


def test_help_lists_groups_and_keys():
    result = subprocess.run([sys.executable, "-m", "nsl_hpc.train", "--help"], capture_output=True, text=True)
    assert result.returncode == 0
    for text in ("python -m nsl_hpc.train", "system=<ball|motor|silverbox", "epochs=64", "data_tier=8"):
        assert text in result.stdout
