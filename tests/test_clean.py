"""clean: what finished tasks no longer need goes; rows and the records of failures stay."""

import pytest

from tests.sweeps import ALONE, TINY_GRID, nsl, row_files

pytestmark = pytest.mark.e2e  # runs the commands end to end (make test-fast leaves it out)


def test_clean_keeps_rows_and_failures_then_removes_them_once_resolved(tmp_path):
    sweep_dir = tmp_path / "sweep"
    nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={sweep_dir}", "fault.kind=raise", "fault.seed=2", ALONE)
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
