"""A rehearsal on the real cluster: every task takes the real path (plan, arrays, jobs, watchdog, rows), trains
nothing, and meets the planted faults; status, resubmit, merge and fit account for every task, and its rows are
never a real sweep's."""

import re
import subprocess

import pyarrow.parquet as pq
import pytest

from tests.sweeps import nsl

pytestmark = pytest.mark.slurm

# the demo's 216 tasks, with faults planted often enough to strike a grid this small
REHEARSAL = ["+sweep=demo", "launcher=slurm", "rehearsal=true", "rehearse.frozen_share=0.15",
             "rehearse.failed_share=0.1", "rehearse.killed_jobs=2", "sweep.name=rehearsal",
             "packing.pack_minutes=0.1"]  # 10 jobs, 2 of them killed


def counts(status: str) -> dict[str, int]:
    """The task counts of status's last summary ('216 tasks: done 125 | running 0 | ...'; wait=true prints one a
    look)."""
    total, _, states = [line for line in status.splitlines() if " tasks: done " in line][-1].partition(" tasks: ")
    return {"tasks": int(total.replace(",", "")), **{name: int(value.replace(",", "")) for name, value in
                                                      re.findall(r"(\w+) ([\d,]+)", states)}}


def test_a_rehearsal_runs_the_real_path_and_every_task_is_accounted_for(slurm_cluster, tmp_path):
    sweep_dir = tmp_path / "rehearsal"
    try:
        launched = nsl("launch", *REHEARSAL, f"sweep_dir={sweep_dir}")
        assert launched.returncode == 0, launched.stderr
        first = counts(nsl("status", f"sweep_dir={sweep_dir}", "wait=true", "interval_s=1", "settle_s=2").stdout)
        assert first["tasks"] == 216 and first["done"] < 216
        assert first["frozen"] > 0 and first["failed"] > 0 and first["missing"] > 0  # a job killed: its rest missing
        assert first["done"] + first["frozen"] + first["failed"] + first["missing"] == 216
        resubmitted = nsl("resubmit", f"sweep_dir={sweep_dir}")
        assert resubmitted.returncode == 0, resubmitted.stderr
        second = counts(nsl("status", f"sweep_dir={sweep_dir}", "wait=true", "interval_s=1", "settle_s=2").stdout)
        # the killed jobs' rest ran (and met its own planted faults); the planted faults struck again
        assert second["missing"] == 0 and second["frozen"] >= first["frozen"] and second["failed"] >= first["failed"]
        assert second["done"] + second["frozen"] + second["failed"] == 216 and second["done"] > first["done"]
        assert len(list((sweep_dir / "rehearsal").glob("killed-*"))) == 2
        merged = nsl("merge", f"sweep_dir={sweep_dir}")
        dropped = second["frozen"] + second["failed"]
        assert f"{dropped} of 216 tasks" in merged.stdout and "each with its reason in dropped.parquet" in merged.stdout
        table = pq.read_table(sweep_dir / "dropped.parquet").to_pylist()
        assert len(table) == dropped and {row["state"] for row in table} == {"frozen", "failed"}
        assert all(row["reason"] for row in table)
        results = pq.read_table(sweep_dir / "results.parquet")
        assert results.num_rows == second["done"] and all(results["rehearsal"].to_pylist())
        fitted = nsl("fit", f"sweep_dir={sweep_dir}", "nsl.bootstrap=0", "metrics=[nmae]", "nsl.max_breaks=1")
        assert fitted.returncode == 0, fitted.stderr
        fits = pq.read_table(sweep_dir / "nsl_fits.parquet").to_pylist()
        assert all(row["rehearsal"] for row in fits)
        assert sum(row.get("planted_formula") is not None for row in fits) == 6  # the compute laws
        assert "planted (rehearsal)" in (sweep_dir / "nsl_fits.txt").read_text()
        real = nsl("launch", "+sweep=demo", "launcher=slurm", f"sweep_dir={sweep_dir}", "dry_run=true")
        assert real.returncode == 2 and "holds a different grid" in real.stderr  # rehearsal rows are never real ones
    finally:
        subprocess.run(["scancel", "-n", "nsl-rehearsal"], check=False)
