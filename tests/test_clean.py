"""clean: what finished tasks no longer need goes; rows and the records of failures stay."""

import os
import signal
import subprocess
import sys
import time

import pytest

from nsl_hpc.core.checkpoint import Checkpointer, info_path
from nsl_hpc.sweep.groups import GroupLock, checkpoint_path
from nsl_hpc.sweep.rows import read_row
from tests.sweeps import ALONE, OWN_CACHE, TINY_GRID, manifest_ids, nsl, row_files

pytestmark = pytest.mark.e2e  # runs the commands end to end (make test-fast leaves it out)


def test_clean_keeps_rows_and_failures_then_removes_them_once_resolved(tmp_path):
    sweep_dir = tmp_path / "sweep"
    nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={sweep_dir}", "fault.kind=raise", "fault.seed=2", ALONE,
        OWN_CACHE)
    rows = {path: path.stat().st_mtime_ns for path in row_files(sweep_dir)}
    failure_files = sorted((sweep_dir / "failures").rglob("*.json")) + sorted((sweep_dir / "logs").rglob("*.log"))
    assert len(rows) == 3 and len(failure_files) == 2
    assert any((sweep_dir / "submitit" / "local").iterdir())

    dry = nsl("clean", f"sweep_dir={sweep_dir}", "dry_run=true")
    assert dry.returncode == 0 and "would remove" in dry.stdout
    assert any((sweep_dir / "submitit" / "local").iterdir())

    cleaned = nsl("clean", f"sweep_dir={sweep_dir}")
    assert cleaned.returncode == 0, cleaned.stderr
    assert not any((sweep_dir / "submitit" / "local").iterdir())
    assert all(path.exists() for path in failure_files)
    assert (sweep_dir / "cache").exists()  # the failed task still needs its data
    assert {path: path.stat().st_mtime_ns for path in row_files(sweep_dir)} == rows

    assert nsl("resubmit", f"sweep_dir={sweep_dir}").returncode == 0
    assert nsl("clean", f"sweep_dir={sweep_dir}").returncode == 0
    assert not any(path.exists() for path in failure_files)
    assert not (sweep_dir / "cache").exists()
    assert len(row_files(sweep_dir)) == 4 and "done 4 |" in nsl("status", f"sweep_dir={sweep_dir}").stdout
    again = nsl("clean", f"sweep_dir={sweep_dir}")
    assert again.returncode == 0 and "removed 0 files" in again.stdout


def test_clean_without_a_sweep_is_a_one_line_error(tmp_path):
    result = nsl("clean", f"sweep_dir={tmp_path}")
    assert result.returncode == 2 and result.stderr.strip().count("\n") == 0 and "no manifest.parquet" in result.stderr


def test_clean_removes_checkpoints_of_finished_groups_and_locks_no_job_renews(tmp_path):
    sweep_dir = tmp_path / "sweep"
    nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={sweep_dir}", "fault.kind=raise", "fault.seed=2", ALONE)
    done = sorted(path.stem for path in row_files(sweep_dir))
    (failed,) = set(manifest_ids(sweep_dir)) - set(done)
    finished, unfinished = (Checkpointer(checkpoint_path(sweep_dir, ids), 60, ids) for ids in (done, [failed]))
    finished.save({}, 5, 10)
    unfinished.save({}, 3, 10)
    abandoned, held = GroupLock(sweep_dir, ["gone"]), GroupLock(sweep_dir, ["trained", "now"])
    assert abandoned.acquire() is None and held.acquire() is None
    os.utime(abandoned.path, (time.time() - 3600, time.time() - 3600))
    status = nsl("status", f"sweep_dir={sweep_dir}").stdout
    assert "failed (resumed 0 times): 1 task in a group at step 3 of 10" in status, status
    assert nsl("clean", f"sweep_dir={sweep_dir}").returncode == 0
    assert not finished.path.exists() and not info_path(finished.path).exists() and not abandoned.path.exists()
    assert unfinished.path.exists() and info_path(unfinished.path).exists() and held.path.exists()


@pytest.mark.slow
def test_a_compiled_sweep_shares_its_kernel_cache_and_clean_removes_it_once_done(tmp_path):
    """compile=always: the launch says its lockstep groups compile, every row says compiled, the kernels are in
    the sweep's compile_cache (the jobs' shared cache); clean removes that cache once every task has a row."""
    sweep_dir = tmp_path / "sweep"
    launched = nsl("launch", *TINY_GRID, "sweep.grid.seed=[0]", "launcher=debug", "compile=always",
                   f"sweep_dir={sweep_dir}")  # input-affine models: compiled here only
    assert launched.returncode == 0, launched.stderr
    assert "lockstep groups compiled)" in launched.stdout
    assert [read_row(path)["compiled"] for path in row_files(sweep_dir)] == [True]
    assert any((sweep_dir / "compile_cache").rglob("fxgraph/*"))
    assert "compile_cache_dir: ${sweep_dir}/compile_cache" in (sweep_dir / "launch.yaml").read_text()  # moves along
    dry = nsl("clean", f"sweep_dir={sweep_dir}", "dry_run=true")
    assert f"{sweep_dir.resolve() / 'compile_cache'}/" in dry.stdout.splitlines()
    assert nsl("clean", f"sweep_dir={sweep_dir}").returncode == 0
    assert not (sweep_dir / "compile_cache").exists() and len(row_files(sweep_dir)) == 1


KILLED_WRITER = """
import os, signal, sys
from pathlib import Path
from nsl_hpc.core.atomic import replacing
with replacing(Path(sys.argv[1])) as temporary:
    temporary.write_bytes(b"half a checkpoint")
    os.kill(os.getpid(), signal.SIGKILL)  # as scancel's SIGKILL or a lost node: no clean-up runs
"""


def test_clean_removes_what_a_writer_killed_mid_write_left_and_keeps_a_write_in_progress(tmp_path):
    sweep_dir = tmp_path / "sweep"
    assert nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={sweep_dir}", "fault.kind=raise",
               "fault.seed=2", ALONE).returncode == 1  # one task fails: it keeps a checkpoint folder
    (failed,) = set(manifest_ids(sweep_dir)) - {path.stem for path in row_files(sweep_dir)}
    targets = [checkpoint_path(sweep_dir, [failed]), row_files(sweep_dir)[0]]
    for target in targets:
        killed = subprocess.run([sys.executable, "-c", KILLED_WRITER, str(target)], capture_output=True)
        assert killed.returncode == -signal.SIGKILL
    left = sorted(path for path in sweep_dir.rglob(".*.tmp"))
    assert len(left) == 2 and {path.parent for path in left} == {target.parent for target in targets}
    listed = nsl("clean", f"sweep_dir={sweep_dir}", "dry_run=true").stdout
    assert not any(str(path) in listed for path in left)  # just written: maybe a write in progress
    for path in left:
        os.utime(path, (time.time() - 3600, time.time() - 3600))
    listed = nsl("clean", f"sweep_dir={sweep_dir}", "dry_run=true").stdout
    assert all(str(path) in listed for path in left)
    assert nsl("clean", f"sweep_dir={sweep_dir}").returncode == 0
    assert not any(path.exists() for path in left) and len(row_files(sweep_dir)) == 3
