"""`python -m nsl_hpc.train` end to end: one row, idempotence, determinism, and bad input."""

import os
import subprocess
import sys

import pyarrow.parquet as pq
import pytest

from nsl_hpc.sweep.rows import read_row
from tests import preloaded

pytestmark = pytest.mark.e2e  # runs the commands end to end (make test-fast leaves it out)

TASK = ["system=ball", "arch=port_hamiltonian", "epochs=3", "data_tier=2", "width_tier=4", "depth_tier=2",
        "seed=3"]
TIMING_COLUMNS = {"train_seconds", "wall_seconds"}
ROW_COLUMNS = {
    "task_id", "system", "arch", "seed", "sweep_seed", "epochs", "data_tier", "data_size", "n_traj",
    "train_points", "width_tier", "width", "depth_tier", "depth", "batch_size", "lr", "nmae", "nmse",
    "nmae_per_column", "nmse_per_column", "nmae_scalar", "nmse_scalar", "compiled",
    "params", "stackable", "flops", "flops_paper", "test_points", "steps", "final_loss", "train_nmae",
    "mean_predictor_nmae", "status", "milestone", "repeat",
    "package_version", "code", "torch_version", "python_version", "host", *TIMING_COLUMNS,
}


def train(*args: str, cache_dir: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return preloaded.run("nsl_hpc.train", [f"cache_dir={cache_dir}", *args], timeout=300, env=env)


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


# A compiled step sums in another order than the eager one: their scores agree to this relative tolerance
# (float32; measured: 1e-6 and below after 9-18 steps).
COMPILED_RTOL = 1e-4


COMPILED_TASK = [*TASK, "arch=unstructured"]  # the cheapest to compile


@pytest.fixture
def eager_row(tmp_path, cache_dir) -> dict:
    """The row of COMPILED_TASK trained eagerly."""
    eager = train(*COMPILED_TASK, f"out_dir={tmp_path / 'eager'}", "compile=never", cache_dir=cache_dir)
    assert eager.returncode == 0, eager.stderr
    row = read_row(rows_under(tmp_path / "eager")[0])
    assert row["compiled"] is False
    return row


@pytest.mark.slow
def test_compiled_tasks_agree_with_eager_and_share_their_kernels(tmp_path, cache_dir, eager_row):
    """compile=always: two tasks compiling the same step at once into one kernel cache both finish compiled, with
    the eager task's scores to float rounding, and a third one compiles nothing anew (the cache hits)."""
    kernels = tmp_path / "kernels"
    both = [subprocess.Popen([sys.executable, "-m", "nsl_hpc.train", f"cache_dir={cache_dir}", *COMPILED_TASK,
                              f"out_dir={tmp_path / name}", "compile=always", f"compile_cache_dir={kernels}"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for name in ("a", "b")]
    for process in both:
        _, stderr = process.communicate(timeout=600)
        assert process.returncode == 0, stderr
        assert "warning" not in stderr
    for name in ("a", "b"):
        row = read_row(rows_under(tmp_path / name)[0])
        assert row["compiled"] is True and row["task_id"] == eager_row["task_id"]
        for column in ("nmae", "nmse", "final_loss"):
            assert row[column] == pytest.approx(eager_row[column], rel=COMPILED_RTOL)
    graphs = sorted((kernels / "fxgraph").rglob("*"))
    cached = train(*COMPILED_TASK, f"out_dir={tmp_path / 'cached'}", "compile=always", f"compile_cache_dir={kernels}",
                   cache_dir=cache_dir)
    assert cached.returncode == 0, cached.stderr
    assert read_row(rows_under(tmp_path / "cached")[0])["compiled"] is True
    assert graphs and sorted((kernels / "fxgraph").rglob("*")) == graphs  # nothing compiled anew: the cache hit


def test_compile_always_without_a_cpp_compiler_trains_eagerly_after_one_warning(tmp_path, cache_dir, eager_row):
    """On a node without a working C++ compiler (CXX names none), compile=always trains eagerly after one warning
    line (compiled=false), to the eager task's scores."""
    no_compiler = {**os.environ, "CXX": str(tmp_path / "no-such-c++")}
    fallback = train(*COMPILED_TASK, f"out_dir={tmp_path / 'fallback'}", "compile=always",
                     f"compile_cache_dir={tmp_path / 'fresh'}", cache_dir=cache_dir, env=no_compiler)
    assert fallback.returncode == 0, fallback.stderr
    warnings = [line for line in fallback.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and "training eagerly" in warnings[0]
    row = read_row(rows_under(tmp_path / "fallback")[0])
    assert row["compiled"] is False and row["nmae"] == pytest.approx(eager_row["nmae"], rel=COMPILED_RTOL)
    assert not (tmp_path / "fresh" / "fxgraph").exists()  # nothing was traced and compiled before the fallback


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
    ("compile=sometimes", "compile='sometimes' is unknown; choose one of: auto, always, never"),
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
