"""Launch with the debug and local launchers: manifest, plan, rows, idempotent re-launch, bad input."""

import json
import re

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from nsl_hpc.config import compose_config
from nsl_hpc.config.arch import arch_settings
from nsl_hpc.studies import study_named
from nsl_hpc.studies.input_state.study import model_shape
from nsl_hpc.sweep.manifest import read_base_config
from nsl_hpc.sweep.rows import read_row
from tests.sweeps import ALONE, TINY_GRID, manifest_ids, nsl, row_files

pytestmark = pytest.mark.e2e  # runs the commands end to end (make test-fast leaves it out)


@pytest.mark.parametrize("launcher", ["debug", "local"])
def test_tiny_sweep_completes_with_one_row_per_task(launcher, tmp_path):
    sweep_dir = tmp_path / "sweep"
    result = nsl("launch", *TINY_GRID, f"launcher={launcher}", f"sweep_dir={sweep_dir}")
    assert result.returncode == 0, result.stderr
    assert "4 tasks, 0 done, 4 to run" in result.stdout and "finished: 4 ok" in result.stdout
    manifest = pq.read_table(sweep_dir / "manifest.parquet")
    expected = {"task_id", *study_named("input_state").axes, "sweep_seed", "data_size", "width", "depth", "steps",
                "flops"}
    assert expected <= set(manifest.column_names)
    rows = [read_row(path) for path in row_files(sweep_dir)]
    assert sorted(row["task_id"] for row in rows) == sorted(manifest_ids(sweep_dir))
    assert all(row["status"] == "ok" for row in rows)
    assert not list((sweep_dir / "logs").glob("*/*.log"))  # logs of finished tasks are not kept


def test_relaunch_runs_only_missing_tasks_and_never_rewrites_rows(tmp_path):
    sweep_dir = tmp_path / "sweep"
    assert nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={sweep_dir}").returncode == 0
    first, *rest = row_files(sweep_dir)
    before = {path: path.stat().st_mtime_ns for path in rest}
    first.unlink()
    again = nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={sweep_dir}")
    assert again.returncode == 0 and "3 done, 1 to run" in again.stdout
    assert first.exists() and all(path.stat().st_mtime_ns == mtime for path, mtime in before.items())
    done = nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={sweep_dir}")
    assert "nothing to run" in done.stdout


@pytest.mark.slow
def test_dry_run_writes_manifest_and_plan_only(tmp_path):
    sweep_dir = tmp_path / "sweep"
    result = nsl("launch", "+sweep=input_state", f"sweep_dir={sweep_dir}", "launcher=slurm", "dry_run=true")
    assert result.returncode == 0, result.stderr
    assert "63,504 tasks, 0 done, 63,504 to run" in result.stdout and "core-hours" in result.stdout
    assert len(manifest_ids(sweep_dir)) == 63_504
    assert not (sweep_dir / "rows").exists() and not (sweep_dir / "submissions").exists()


@pytest.mark.parametrize(("args", "message"), [
    (["+sweep=nonexistent"], "unknown sweep 'nonexistent'; choose one of: budget_io, demo, input_output, input_state,"),
    ([], "no sweep chosen: add +sweep=<name>"),
    (["+sweep=demo", "epochs=8"], "epochs is a grid axis of the sweep"),
    (["+sweep=demo", "trian.lr=1"], "trian"),
    (["+sweep=demo", "sweep.grid.epochs=[]"], "the grid has zero tasks"),
    (["+sweep=demo", "sweep.grid.data_tier=[3]"], "sweep.grid.data_tier value=3 is outside the grid"),
    (["+sweep=demo", "packing.time_classes_minutes=[0.001]"], "more than the largest of packing.time_classes"),
    (["+sweep=demo", "lockstep.size=0"], "lockstep.size=0 must be a positive integer"),
    (["+sweep=demo", "lockstep.width_buckets=[4,x]"], "lockstep.width_buckets value='x' must be a positive integer"),
    (["+sweep=demo", "lockstep.memory_mb=0"], "lockstep.memory_mb=0 must be a finite number in (0, 100000]"),
    (["+sweep=demo", "train.schedule=linear"], "train.schedule='linear' is unknown; choose one of"),
    (["+sweep=demo", "train.repeat=0"], "train.repeat=0 must be a positive integer"),
])
def test_bad_launches_fail_before_anything_is_written(args, message, tmp_path):
    sweep_dir = tmp_path / "sweep"
    result = nsl("launch", *args, f"sweep_dir={sweep_dir}", "launcher=debug")
    assert result.returncode == 2
    assert result.stderr.startswith("error: ") and message in result.stderr
    assert not (sweep_dir / "rows").exists()


def test_a_sweep_stored_before_a_setting_existed_reads_it_at_its_neutral_value(tmp_path):
    sweep_dir = tmp_path / "sweep"
    assert nsl("launch", *TINY_GRID, f"sweep_dir={sweep_dir}", "dry_run=true").returncode == 0
    (stored,) = (sweep_dir / "configs").glob("*.yaml")
    text = stored.read_text()
    for line in ("  repeat: 1\n", "  weight_decay: 0.0\n", "  repeat_by_trajectories: null\n"):
        assert line in text
        text = text.replace(line, "")  # as stored before these settings existed
    stored.write_text(text)
    system, arch = stored.stem.split("__")
    train = read_base_config(sweep_dir, system, arch)["train"]
    assert (train["repeat"], train["weight_decay"], train["repeat_by_trajectories"]) == (1, 0.0, None)


def test_launch_on_a_directory_of_another_grid_is_refused(tmp_path):
    sweep_dir = tmp_path / "sweep"
    assert nsl("launch", *TINY_GRID, f"sweep_dir={sweep_dir}", "dry_run=true").returncode == 0
    manifest = (sweep_dir / "manifest.parquet").read_bytes()
    other = nsl("launch", *TINY_GRID, "train.lr=0.01", f"sweep_dir={sweep_dir}", "launcher=debug")
    assert other.returncode == 2 and "holds a different grid" in other.stderr
    assert (sweep_dir / "manifest.parquet").read_bytes() == manifest and not (sweep_dir / "rows").exists()


@pytest.mark.slow
def test_failed_and_frozen_tasks_are_recorded_and_resubmitted(tmp_path):
    sweep_dir = tmp_path / "sweep"
    hang = nsl("launch", *TINY_GRID, "launcher=local", f"sweep_dir={sweep_dir}", "fault.kind=hang", "fault.seed=1",
               ALONE, "watchdog.heartbeat_timeout_s=10")
    assert hang.returncode == 1 and "1 frozen, 3 ok" in hang.stdout
    status = nsl("status", f"sweep_dir={sweep_dir}")
    assert "done 3 | running 0 | pending 0 | failed 0 | frozen 1" in status.stdout
    assert "no heartbeat for" in status.stdout
    finished = {path: path.stat().st_mtime_ns for path in row_files(sweep_dir)}
    again = nsl("resubmit", f"sweep_dir={sweep_dir}")
    assert again.returncode == 0 and "resubmitting 1 tasks" in again.stdout
    assert len(row_files(sweep_dir)) == 4
    assert all(path.stat().st_mtime_ns == mtime for path, mtime in finished.items())
    assert "done 4 |" in nsl("status", f"sweep_dir={sweep_dir}").stdout
    assert "nothing to resubmit" in nsl("resubmit", f"sweep_dir={sweep_dir}").stdout


def test_raising_task_is_recorded_failed_with_its_log(tmp_path):
    sweep_dir = tmp_path / "sweep"
    result = nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={sweep_dir}", "fault.kind=raise", "fault.seed=2",
                 ALONE)
    assert result.returncode == 1 and "1 failed, 3 ok" in result.stdout
    status = nsl("status", f"sweep_dir={sweep_dir}")
    assert "failed 1" in status.stdout and "RuntimeError: injected fault" in status.stdout
    # the job's diagnostics are log records naming their group; its first task's log holds the traceback
    assert re.search(r"^[0-9-]+ [0-9:,]+ WARNING \[job \d+\] group [0-9a-f]{16} failed: exit status 1;",
                     result.stdout, re.MULTILINE), result.stdout
    (record,) = [json.loads(path.read_text()) for path in (sweep_dir / "failures").rglob("*.json")]
    assert re.search(r"ERROR \[group [0-9a-f]{16}\] training failed\nTraceback", record["log_tail"]), record


def rows_of_local_sweep(sweep_dir, grid, extra, tasks):
    """Launch ``grid`` with the local launcher into ``sweep_dir`` (all ``tasks`` must finish ok); the launch
    output and the rows."""
    result = nsl("launch", *grid, "launcher=local", f"sweep_dir={sweep_dir}", extra)
    assert result.returncode == 0 and f"finished: {tasks} ok" in result.stdout, result.stderr
    return result.stdout, [read_row(path) for path in row_files(sweep_dir)]


@pytest.mark.slow
def test_lockstep_groups_give_the_rows_of_tasks_trained_alone(tmp_path):
    """12 tasks of at most 4 shapes: trained in lockstep groups by the local launcher, each task's row holds
    what training it alone gives (to the packed tolerance of tests/test_training.py)."""
    grid = [*TINY_GRID, "sweep.grid.width_tier=[2]", "sweep.grid.seed=[0,1,2,3,4,5]", "sweep.grid.epochs=[2,3]"]
    rows = {}
    for name, extra in (("packed", "lockstep.size=16"), ("alone", ALONE)):
        _, found = rows_of_local_sweep(tmp_path / name, grid, extra, 12)
        rows[name] = {row["task_id"]: row for row in found}
    manifest = pq.read_table(tmp_path / "packed" / "manifest.parquet").to_pylist()
    assert len({(t["width"], t["depth"]) for t in manifest}) < 12  # some tasks did share a group
    assert rows["packed"].keys() == rows["alone"].keys()
    for task_id, alone in rows["alone"].items():
        packed = rows["packed"][task_id]
        assert packed["steps"] == alone["steps"]
        for key in ("nmae", "nmse", "final_loss"):
            assert packed[key] == pytest.approx(alone[key], rel=1e-4), key


@pytest.mark.slow
def test_epoch_milestone_rows_with_a_constant_learning_rate_are_the_rows_of_separate_runs(tmp_path):
    """6 tasks (3 models x epochs 2 and 4) with train.schedule_epochs=4: each model trains once, to 4 epochs,
    and writes a row after 2 and after 4, marked milestone; with a constant learning rate these rows hold what
    separate runs give."""
    grid = [*TINY_GRID, "sweep.grid.seed=[0,1,2]", "sweep.grid.epochs=[2,4]", "train.schedule=constant",
            "draws=shared_across_epochs"]
    rows = {}
    for name, extra in (("milestones", "train.schedule_epochs=4"), ("separate", ALONE)):
        output, found = rows_of_local_sweep(tmp_path / name, grid, extra, 6)
        assert name == "separate" or "6 tasks as 3 models" in output
        rows[name] = {(row["seed"], row["epochs"]): row for row in found}
    assert rows["milestones"].keys() == rows["separate"].keys() and len(rows["separate"]) == 6
    for key, separate in rows["separate"].items():
        milestone = rows["milestones"][key]
        assert milestone["milestone"] and not separate["milestone"]
        assert milestone["steps"] == separate["steps"]
        for column in ("nmae", "nmse", "final_loss"):
            assert milestone[column] == pytest.approx(separate[column], rel=1e-4), column
    refused = nsl("launch", *grid, "launcher=local", f"sweep_dir={tmp_path / 'short'}", "train.schedule_epochs=3")
    assert refused.returncode == 2
    assert "sweep.grid.epochs value=4 is more than train.schedule_epochs=3" in refused.stderr
    per_task = nsl("launch", *grid[:-1], "launcher=local", f"sweep_dir={tmp_path / 'short'}", "train.schedule_epochs=4")
    assert per_task.returncode == 2 and "add draws=shared_across_epochs (now draws=per_task)" in per_task.stderr
    assert not (tmp_path / "short").exists()


def test_the_manifest_is_what_trains_a_hand_edited_size_is_not_drawn_again(tmp_path):
    """Sizes are drawn once, at launch; jobs read them from the manifest."""
    sweep_dir = tmp_path / "sweep"
    assert nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={sweep_dir}", "dry_run=true").returncode == 0
    manifest = pq.read_table(sweep_dir / "manifest.parquet").to_pylist()
    edited = manifest[0]
    edited["width"] = edited["width"] + 3
    edited["params"], _ = model_shape(arch_settings(compose_config(["arch=input_affine"]).arch), (4, 2),
                                      edited["width"], edited["depth"])  # spring: n = 4, m = 2
    pq.write_table(pa.Table.from_pylist(manifest), sweep_dir / "manifest.parquet")
    result = nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={sweep_dir}")
    assert result.returncode == 0, result.stderr
    rows = {row["task_id"]: row for row in map(read_row, row_files(sweep_dir))}
    assert rows[edited["task_id"]]["width"] == edited["width"]
    assert rows[edited["task_id"]]["params"] == edited["params"]
    assert all(rows[task["task_id"]]["width"] == task["width"] for task in manifest)
