"""A sweep directory that cannot be destroyed, hijacked, run twice or silently lose a task: one test per way a
hostile but fair user lost a sweep before (the SLURM case is in tests/cluster/test_sweep_integrity_slurm.py)."""

import getpass
import multiprocessing
import os
import re
import shutil
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from mlflow.tracking import MlflowClient

from nsl_hpc.analysis.mlflow_runs import sweep_run, tracking_uri
from nsl_hpc.sweep import failures, merge, rows
from nsl_hpc.sweep.directory import unsafe_refusal
from nsl_hpc.sweep.failures import read_failures, read_record, record_failure
from nsl_hpc.sweep.groups import held_locks
from nsl_hpc.sweep.job import leave_warnings_to_the_runner
from nsl_hpc.sweep.layout import row_path
from nsl_hpc.sweep.rows import listed_row_states, read_row, read_task_rows, row_state, row_states, write_row_atomically
from tests.sweeps import TINY_GRID, manifest_ids, nsl, row_files

pytestmark = pytest.mark.e2e  # runs the commands end to end (make test-fast leaves it out)

LOCAL = [*TINY_GRID, "launcher=local"]
# tasks that train for at least ~10 s on any machine, mostly asleep (fault.kind=slow: at every heartbeat), so that a
# test can act while they run without their training taking the CPU the other tests need
LONGER = ["sweep.grid.epochs=[640]", "fault.kind=slow", "fault.heartbeat_s=0.25"]


def tree(root: Path) -> set[Path]:
    return {path for path in root.rglob("*")}


def launched(sweep_dir: Path, *extra: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    result = nsl("launch", *LOCAL, f'sweep_dir="{sweep_dir}"', *extra, cwd=cwd)
    assert result.returncode == 0, result.stderr
    return result


@pytest.fixture(scope="module")
def tiny_sweep(tmp_path_factory) -> Path:
    """A finished local sweep of TINY_GRID, launched once for the tests that copy it (a copy is a sweep too:
    its paths are relative to it)."""
    sweep_dir = tmp_path_factory.mktemp("tiny") / "sweep"
    launched(sweep_dir)
    return sweep_dir


def copy_of(sweep_dir: Path, target: Path) -> Path:
    shutil.copytree(sweep_dir, target, symlinks=True)
    return target


# Clean never removes rows, the manifest, configs or failure records, whatever the paths.
@pytest.mark.parametrize("cache", ["sweep_dir", "rows"])
@pytest.mark.slow
def test_clean_keeps_everything_computed_whatever_cache_dir_is_and_its_dry_run_lists_what_goes(cache, tmp_path):
    sweep_dir = tmp_path / "sweep"
    cache_dir = sweep_dir if cache == "sweep_dir" else sweep_dir / "rows"
    launched(sweep_dir, f"cache_dir={cache_dir}")
    before = tree(sweep_dir)
    dry = nsl("clean", f"sweep_dir={sweep_dir}", "dry_run=true")
    assert dry.returncode == 0, dry.stderr
    listed = [Path(line.rstrip("/")) for line in dry.stdout.splitlines() if line.startswith("/")]
    assert tree(sweep_dir) == before  # a dry run changes nothing
    assert nsl("clean", f"sweep_dir={sweep_dir}").returncode == 0
    removed = before - tree(sweep_dir)
    assert removed == {path for path in before if any(path == top or path.is_relative_to(top) for top in listed)}
    assert len(row_files(sweep_dir)) == 4 and sorted(p.stem for p in row_files(sweep_dir)) == sorted(
        manifest_ids(sweep_dir))
    for kept in ("manifest.parquet", "launch.yaml", "run.yaml", "configs"):
        assert (sweep_dir / kept).exists(), kept
    assert not [path for path in removed if path.suffix == ".parquet"]


# A corrupt or truncated row is no row: status says so, launch and resubmit run it again, the file is kept aside.
@pytest.mark.slow
def test_a_truncated_row_is_reported_rerun_and_kept_aside(tiny_sweep, tmp_path):
    sweep_dir = copy_of(tiny_sweep, tmp_path / "sweep")
    first, second = row_files(sweep_dir)[:2]
    damaged = first.read_bytes()[:100]
    first.write_bytes(damaged)
    status = nsl("status", f"sweep_dir={sweep_dir}")
    assert "done 3 |" in status.stdout and "corrupt 1" in status.stdout
    again = launched(sweep_dir)
    assert "1 to run" in again.stdout and "1 corrupt rows moved to corrupt/" in again.stdout
    assert "done 4 |" in nsl("status", f"sweep_dir={sweep_dir}").stdout
    (aside,) = (sweep_dir / "corrupt").iterdir()
    assert aside.read_bytes() == damaged and aside.name.startswith(first.name)

    second.write_bytes(b"not parquet at all")
    resubmitted = nsl("resubmit", f"sweep_dir={sweep_dir}")
    assert resubmitted.returncode == 0 and "resubmitting 1 tasks" in resubmitted.stdout, resubmitted.stderr
    assert "done 4 |" in nsl("status", f"sweep_dir={sweep_dir}").stdout
    assert len(list((sweep_dir / "corrupt").iterdir())) == 2


# A sweep directory is self-contained and relocatable.
@pytest.mark.slow
def test_a_moved_sweep_is_resubmitted_from_elsewhere_into_its_new_place(tmp_path):
    first_home, elsewhere = tmp_path / "first", tmp_path / "elsewhere"
    first_home.mkdir()
    elsewhere.mkdir()
    launched(Path("runs/tiny"), cwd=first_home)  # a relative sweep_dir, as users type it
    moved = tmp_path / "moved" / "tiny"
    moved.parent.mkdir()
    shutil.move(first_home / "runs" / "tiny", moved)
    lost = row_files(moved)[0]
    lost.unlink()
    resubmitted = nsl("resubmit", f"sweep_dir={moved}", cwd=elsewhere)
    assert resubmitted.returncode == 0 and "resubmitting 1 tasks" in resubmitted.stdout, resubmitted.stderr
    assert lost.exists() and "done 4 |" in nsl("status", f"sweep_dir={moved}", cwd=elsewhere).stdout
    assert not list(elsewhere.rglob("*.parquet")) and not (first_home / "runs" / "tiny").exists()
    assert "failed 0" in nsl("status", f"sweep_dir={moved}").stdout


# One launch, resubmit or clean at a time per sweep; the manifest is created once.
@pytest.mark.slow
def test_concurrent_launches_of_different_grids_into_one_new_directory_accept_one(tmp_path):
    for trial in range(2):
        sweep_dir = tmp_path / f"race{trial}"
        commands = [[sys.executable, "-m", "nsl_hpc.launch", *LOCAL, f"sweep_dir={sweep_dir}", "dry_run=true", seeds]
                    for seeds in ("sweep.grid.seed=[0,1]", "sweep.grid.seed=[5,6,7]")]
        runs = [subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                for command in commands]
        results = [(run.wait(timeout=120), run.stderr.read()) for run in runs]
        assert sorted(code for code, _ in results) == [0, 2], results
        refusal = next(err for code, err in results if code == 2)
        assert "is in use by" in refusal or "holds a different grid" in refusal, refusal


@pytest.mark.slow
def test_a_second_command_is_refused_naming_the_running_one(tmp_path):
    sweep_dir = tmp_path / "sweep"
    first = subprocess.Popen([sys.executable, "-m", "nsl_hpc.launch", *LOCAL, f"sweep_dir={sweep_dir}",
                              "sweep.grid.epochs=[3000]", "fault.kind=hang", "watchdog.heartbeat_timeout_s=600"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # its tasks never end
    try:
        while not (sweep_dir / "logs").exists():  # its tasks run: it holds the lock
            assert first.poll() is None, first.stderr.read()
            time.sleep(0.2)
        for verb, args in (("launch", [*LOCAL, "sweep.grid.epochs=[3000]"]), ("resubmit", []), ("clean", [])):
            refused = nsl(verb, *args, f"sweep_dir={sweep_dir}")
            assert refused.returncode == 2, (verb, refused.stdout)
            assert f"is in use by launch (pid {first.pid} on" in refused.stderr, refused.stderr
        assert nsl("status", f"sweep_dir={sweep_dir}").returncode == 0  # reading is fine
    finally:
        first.kill()
        first.wait()


# Workers die with their launcher.
def sweep_processes(sweep_dir: Path) -> list[int]:
    """Processes (other than this one) whose command line or whose submitit folder names the sweep."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and int(entry.name) != os.getpid():
            try:
                if str(sweep_dir) in (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace"):
                    found.append(int(entry.name))
            except OSError:
                continue
    return found


@pytest.mark.slow
def test_killing_the_local_launcher_stops_its_workers_and_a_relaunch_runs_the_rest(tmp_path):
    sweep_dir = tmp_path / "sweep"
    launcher = subprocess.Popen([sys.executable, "-m", "nsl_hpc.launch", *LOCAL, f"sweep_dir={sweep_dir}", *LONGER,
                                 "launcher.workers=2", "lockstep.enabled=false"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    while not any((sweep_dir / "logs").rglob("*.log")):  # a task is training
        assert launcher.poll() is None
        time.sleep(0.2)
    assert len(sweep_processes(sweep_dir)) >= 2  # the launcher's workers
    os.kill(launcher.pid, signal.SIGKILL)
    launcher.wait()
    deadline = time.time() + 20
    while sweep_processes(sweep_dir) and time.time() < deadline:
        time.sleep(0.5)
    assert not sweep_processes(sweep_dir)
    finished = len(row_files(sweep_dir))
    assert finished < 4
    again = launched(sweep_dir, *LONGER, "lockstep.enabled=false")
    assert f"{4 - finished} to run" in again.stdout and len(row_files(sweep_dir)) == 4


# Resubmit uses the launcher the user names (default: the last one used) and new watchdog and time settings.
@pytest.mark.slow
def test_resubmit_runs_on_the_last_launcher_with_the_settings_it_is_given(tmp_path):
    # tasks of 13 heartbeats slowed to >= 1.3 s on any machine: longer than a watchdog poll (0.2 s), every attempt
    sweep_dir, longer = tmp_path / "sweep", ["sweep.grid.epochs=[400]", "fault.kind=slow", "fault.heartbeat_s=0.1",
                                             "fault.once=false"]
    assert nsl("launch", *LOCAL, *longer, f"sweep_dir={sweep_dir}", "dry_run=true").returncode == 0  # ran nothing
    too_tight = ["launcher=debug", "watchdog.overrun_factor=1", "cost.startup_s=0.001", "lockstep.enabled=false",
                 "cost.step_seconds.input_affine=1e-9"]
    frozen = nsl("launch", *TINY_GRID, *longer, f"sweep_dir={sweep_dir}", *too_tight)
    assert frozen.returncode == 1 and "4 frozen" in frozen.stdout, frozen.stderr
    for bad, shown in (("time_factor=abc", "time_factor='abc'"), ("time_factor=0.5", "time_factor=0.5")):
        refused = nsl("resubmit", f"sweep_dir={sweep_dir}", bad)  # one line, before anything runs
        assert refused.returncode == 2
        assert refused.stderr.strip() == f"error: {shown} must be a finite number in [1, 1000]"
    again = nsl("resubmit", f"sweep_dir={sweep_dir}")  # the debug launcher and the same tight watchdog
    assert again.returncode == 1 and "(debug)" in again.stdout and "4 frozen" in again.stdout
    recovered = nsl("resubmit", f"sweep_dir={sweep_dir}", "launcher=local", "cost.startup_s=600")
    assert recovered.returncode == 0 and "(local)" in recovered.stdout, recovered.stderr
    assert "done 4 |" in nsl("status", f"sweep_dir={sweep_dir}").stdout
    assert "name: local" in (sweep_dir / "run.yaml").read_text()


# Nobody else can change what a sweep's jobs run.
@pytest.mark.skipif(os.geteuid() != 0, reason="giving a file to another user needs root")
def test_a_control_file_another_user_owns_is_refused_with_advice_that_fixes_ownership(tmp_path):
    owned = tmp_path / "launch.yaml"
    owned.write_text("{}")
    owned.chmod(0o644)
    os.chown(owned, 65534, 65534)  # nobody
    refusal = unsafe_refusal([owned], {})
    assert refusal is not None and "another user owns it (mode -rw-r--r--)" in refusal
    assert f"ask its owner or root to `chown -R {getpass.getuser()} {owned}`" in refusal and "chmod" not in refusal


@pytest.mark.slow
def test_control_files_others_can_write_are_refused_and_written_private(tmp_path):
    sweep_dir = tmp_path / "sweep"
    result = nsl("launch", *LOCAL, f"sweep_dir={sweep_dir}", umask=0o002)  # a group project's umask
    assert result.returncode == 0, result.stderr
    for path in [sweep_dir, *(sweep_dir / "submitit").rglob("*"), *(sweep_dir / "configs").rglob("*"),
                 sweep_dir / "launch.yaml", sweep_dir / "run.yaml", sweep_dir / "manifest.parquet"]:
        assert not path.stat().st_mode & (stat.S_IWGRP | stat.S_IWOTH), path
    (sweep_dir / "launch.yaml").chmod(0o664)
    for verb, args in (("launch", LOCAL), ("resubmit", [])):
        refused = nsl(verb, *args, f"sweep_dir={sweep_dir}")
        assert refused.returncode == 2 and "launch.yaml is not safe: the group can write it" in refused.stderr
        assert "chmod -R go-w" in refused.stderr and len(refused.stderr.splitlines()) == 1
    accepted = nsl("launch", *LOCAL, f"sweep_dir={sweep_dir}", "allow_shared_sweep_dir=true")
    assert accepted.returncode == 0 and "nothing to run" in accepted.stdout
    (sweep_dir / "launch.yaml").chmod(0o644)
    planted = sweep_dir / "compile_cache" / "planted"  # Inductor unpickles what it finds in the compile cache
    planted.parent.mkdir(exist_ok=True)
    planted.touch(mode=0o666)
    planted.chmod(0o666)
    for verb, args in (("launch", LOCAL), ("resubmit", [])):
        refused = nsl(verb, *args, f"sweep_dir={sweep_dir}")
        assert refused.returncode == 2 and f"{planted} is not safe: group and others can write it" in refused.stderr


@pytest.fixture
def tmpfs(tmp_path):
    """tmpfs(options) -> a fresh tmpfs mounted with ``options`` (needs root: skipped without), unmounted after."""
    mounts = []

    def mount(options: str) -> Path:
        point = tmp_path / f"mount{len(mounts)}"
        point.mkdir()
        if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(point)],
                                               capture_output=True).returncode:
            pytest.skip("mounting a file system needs root")
        mounts.append(point)
        return point

    yield mount
    for point in mounts:
        subprocess.run(["umount", "-l", str(point)], capture_output=True)


@pytest.mark.parametrize("where", ["a file", "/proc", "read-only"])
def test_a_sweep_dir_that_cannot_hold_a_sweep_is_one_line(where, tmp_path, tmpfs):
    if where == "a file":
        target = tmp_path / "file"
        target.write_text("x")
    elif where == "/proc":
        target = Path("/proc/nsl_hpc_sweep")
    else:
        target = tmpfs("ro,size=1m") / "sweep"
    result = nsl("launch", *LOCAL, f"sweep_dir={target}")
    assert result.returncode == 2 and "cannot hold a sweep" in result.stderr and len(result.stderr.splitlines()) == 1


@pytest.fixture
def finished_sweep(tiny_sweep, tmp_path) -> Path:
    return copy_of(tiny_sweep, tmp_path / "sweep")


@pytest.mark.parametrize("damage", ["truncated manifest", "truncated launch.yaml", "deleted configs",
                                    "truncated submission"])
def test_a_damaged_sweep_directory_is_one_line_for_every_command(damage, finished_sweep):
    sweep_dir = finished_sweep
    if damage == "truncated manifest":
        path = sweep_dir / "manifest.parquet"
        path.write_bytes(path.read_bytes()[:200])
    elif damage == "truncated launch.yaml":
        (sweep_dir / "launch.yaml").write_text("sweep:\n  grid: {system: [spring\n")
    elif damage == "deleted configs":
        shutil.rmtree(sweep_dir / "configs")
        (row_files(sweep_dir)[0]).unlink()  # so that resubmit needs a task config
    else:
        (sweep_dir / "submissions").mkdir()
        (sweep_dir / "submissions" / "123.json").write_text('{"array_id": "123", "subm')
    rows = {path.stem: read_row(path) for path in row_files(sweep_dir)}
    refusing = {"truncated manifest": {"status", "resubmit", "clean", "merge", "launch"},
                "truncated launch.yaml": {"status", "resubmit", "clean", "launch"},
                "deleted configs": {"resubmit"},  # a launch restores them: they follow from its own config
                "truncated submission": {"status", "resubmit", "clean", "merge", "launch"}}[damage]  # merge: the states
    for verb, args in (("status", []), ("resubmit", []), ("clean", ["dry_run=true"]), ("merge", []),
                       ("launch", LOCAL)):
        result = nsl(verb, *args, f"sweep_dir={sweep_dir}")
        if verb not in refusing:
            assert result.returncode == 0, (verb, result.stderr)  # it does not need that file
            continue
        assert result.returncode == 2, (damage, verb, result.stdout, result.stderr)
        assert len(result.stderr.splitlines()) == 1 and "Traceback" not in result.stderr, result.stderr
        assert "damaged" in result.stderr or "missing" in result.stderr
    assert read_task_rows(sweep_dir, rows) == rows  # where they are now: merge compacts them


def test_a_quote_in_the_sweep_path_does_not_break_the_mlflow_search(tmp_path):
    """The parent run of a sweep in a directory named with a quote is found again, not duplicated (a real
    MLflow store)."""
    sweep_dir = tmp_path / "it's a sweep"
    sweep_dir.mkdir()
    client = MlflowClient(tracking_uri(sweep_dir, None))
    experiment = client.create_experiment("quotes")
    first = sweep_run(client, experiment, sweep_dir, "tiny", {"sweep_seed": "0"})
    assert sweep_run(client, experiment, sweep_dir, "tiny", {"sweep_seed": "0"}) == first
    assert client.get_run(first).data.tags["nsl_hpc.sweep.directory"] == str(sweep_dir.resolve())


@pytest.mark.slow
def test_a_full_disk_during_a_sweep_and_during_merge_is_one_line_and_keeps_the_rows(tmp_path, tmpfs):
    mount = tmpfs("size=2m")
    sweep_dir = mount / "sweep"
    cache = [f"cache_dir={tmp_path / 'cache'}"]
    launched(sweep_dir, *cache)
    for path in row_files(sweep_dir)[:2]:
        path.unlink()  # two tasks to run again
    rows = {path: path.read_bytes() for path in row_files(sweep_dir)}
    (mount / "filler").write_bytes(bytes(shutil.disk_usage(mount).free - 16 * 1024))  # room to start, not to end
    result = nsl("launch", *LOCAL, f"sweep_dir={sweep_dir}", *cache)  # two more tasks
    assert result.returncode == 1 and len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert "a local job ended without its result" in result.stderr and "MiB free where it writes" in result.stderr
    logs = "".join(path.read_text(errors="replace") for path in (sweep_dir / "submitit").rglob("*_log.*"))
    assert "Traceback" not in logs, logs[-3000:]  # the job that could not write its failure records says so
    assert "No space left on device while writing" in logs and "have no failure record" in logs, logs[-3000:]
    merged = nsl("merge", f"sweep_dir={sweep_dir}")
    assert merged.returncode == 1 and "No space left on device" in merged.stderr, merged.stderr
    assert len(merged.stderr.strip().splitlines()) == 1
    assert {path: path.read_bytes() for path in row_files(sweep_dir) if path in rows} == rows


def warned_child(ready, leave: bool) -> None:
    if leave:
        leave_warnings_to_the_runner(checkpoint=None)
    ready.set()
    time.sleep(2)
    os._exit(0)


@pytest.mark.parametrize("leave", [False, True])
def test_a_task_process_leaves_slurms_warning_to_the_job_runner(leave, tmp_path):
    """SIGUSR2 reaches every process of a SLURM job step; a forked task process inherits submitit's handler,
    and must not run it (it raced the runner's checkpoint on a fresh clone)."""
    marker = tmp_path / "handled"
    previous = signal.signal(signal.SIGUSR2, lambda signum, frame: (marker.write_text("child"), os._exit(3)))
    try:
        context = multiprocessing.get_context("fork")
        ready = context.Event()
        child = context.Process(target=warned_child, args=(ready, leave))
        child.start()
        assert ready.wait(30)
        os.kill(child.pid, signal.SIGUSR2)
        child.join(30)
    finally:
        signal.signal(signal.SIGUSR2, previous)
    assert (child.exitcode, marker.exists()) == ((0, False) if leave else (3, True))


# A row copied over another task's path is no row of that task: status and resubmit call it corrupt.
def test_a_row_copied_over_another_tasks_path_is_corrupt_not_done(tmp_path):
    mine, other = "0123456789abcdef", "fedcba9876543210"
    write_row_atomically({"task_id": mine, "nmae": 0.1}, row_path(tmp_path, mine))
    assert row_state(row_path(tmp_path, mine)) == "done"
    assert row_state(row_path(tmp_path, other)) == "missing"
    row_path(tmp_path, other).parent.mkdir(parents=True)
    shutil.copy(row_path(tmp_path, mine), row_path(tmp_path, other))
    assert row_state(row_path(tmp_path, other)) == "corrupt"


# A lockstep group's rows are one file that each task's path names: each task's row is its own, merge reads the
# file once, and a file system without hard links gets a copy per task instead.
@pytest.mark.parametrize("links", [True, False])
def test_a_groups_rows_are_one_file_each_task_reads_its_own_and_merge_reads_it_once(links, tmp_path, monkeypatch):
    if not links:
        monkeypatch.setattr(os, "link", lambda *_: (_ for _ in ()).throw(PermissionError(1, "no hard links")))
    ids = [f"{n:x}" * 16 for n in range(1, 5)]
    paths = [row_path(tmp_path, task_id) for task_id in ids]
    rows.write_rows_atomically([{"task_id": task_id, "nmae": n / 10} for n, task_id in enumerate(ids)], paths)
    assert len({path.stat().st_ino for path in paths}) == (1 if links else 4)
    assert [row_state(path) for path in paths] == ["done"] * 4
    assert [read_row(path)["nmae"] for path in paths] == [0.0, 0.1, 0.2, 0.3]
    assert read_task_rows(tmp_path, ids[1:3]) == {ids[1]: {"task_id": ids[1], "nmae": 0.1},
                                                  ids[2]: {"task_id": ids[2], "nmae": 0.2}}
    read = []
    monkeypatch.setattr(merge, "read_parquet", lambda path, **kw: read.append(path) or rows.read_parquet(path, **kw))
    table, unreadable = merge.read_shards([str(path) for path in paths[1:]],
                                          [path.stat().st_ino for path in paths[1:]])
    assert len(read) == (1 if links else 3) and unreadable == []
    assert sorted(zip(table["task_id"].to_pylist(), table["shard"].to_pylist(), strict=True)) == [
        (task_id, str(path)) for task_id, path in zip(ids[1:], paths[1:], strict=True)]
    assert table.schema.metadata is None  # no group's ids carried into results.parquet
    footer, read = rows.row_footer, []
    monkeypatch.setattr(rows, "row_footer", lambda path: read.append(path) or footer(path))
    assert listed_row_states(tmp_path, ids) == dict.fromkeys(ids, "done")
    assert len(read) == (1 if links else 4)  # status's look reads the group's file once


# Status, launch and resubmit list the row folders and read only the row files that are not the files they read
# before (a new inode): a row written again, another file put in its place or a removed row is seen as it is now;
# a row changed in place keeps its reading there, and a look at fewer tasks (a job's) reads it.
def test_the_listed_row_states_read_only_new_files_and_see_each_file_put_in_place(tmp_path, monkeypatch):
    ids = [f"{n:02x}{'0' * 14}" for n in range(6)]
    for task_id in ids[:5]:
        write_row_atomically({"task_id": task_id, "nmae": 0.1}, row_path(tmp_path, task_id))
    read = []
    footer = rows.row_footer
    monkeypatch.setattr(rows, "row_footer", lambda path: read.append(Path(path).stem) or footer(path))
    assert listed_row_states(tmp_path, ids) == {**dict.fromkeys(ids[:5], "done"), ids[5]: "missing"}
    assert sorted(read) == ids[:5] and (tmp_path / ".row_checks.parquet").exists()
    read.clear()
    assert listed_row_states(tmp_path, ids) == {**dict.fromkeys(ids[:5], "done"), ids[5]: "missing"}
    assert read == []  # none changed: none read
    damaged = tmp_path / "damaged"
    damaged.write_bytes(row_path(tmp_path, ids[0]).read_bytes()[:100])
    os.replace(damaged, row_path(tmp_path, ids[0]))  # a truncated copy put in its place
    copied = tmp_path / "copied"
    shutil.copyfile(row_path(tmp_path, ids[2]), copied)
    os.replace(copied, row_path(tmp_path, ids[1]))  # another task's row, same size
    write_row_atomically({"task_id": ids[3], "nmae": 0.2}, row_path(tmp_path, ids[3]))  # written again
    row_path(tmp_path, ids[4]).unlink()
    states = listed_row_states(tmp_path, ids)
    assert states == {ids[0]: "corrupt", ids[1]: "corrupt", ids[2]: "done", ids[3]: "done", ids[4]: "missing",
                      ids[5]: "missing"}
    assert sorted(read) == [*ids[:2], ids[3]]
    read.clear()
    assert listed_row_states(tmp_path, ids) == states and read == []  # the new checks kept, the gone one dropped
    row_path(tmp_path, ids[2]).write_bytes(row_path(tmp_path, ids[2]).read_bytes()[:100])  # changed in place
    assert listed_row_states(tmp_path, ids)[ids[2]] == "done" and read == []
    assert row_states(tmp_path, [ids[2]]) == {ids[2]: "corrupt"}


# Failure records are read once each while they are the same file: a record written again is read again.
def test_failure_records_are_read_once_while_they_stand(tmp_path, monkeypatch):
    record_failure(tmp_path, "ab" + "0" * 14, "failed", "first")
    record_failure(tmp_path, "cd" + "0" * 14, "frozen", "no heartbeat")
    assert {task_id: record["reason"] for task_id, record in read_failures(tmp_path).items()} == {
        "ab" + "0" * 14: "first", "cd" + "0" * 14: "no heartbeat"}
    opened = []
    monkeypatch.setattr(failures, "read_record", lambda path: opened.append(path) or read_record(path))
    assert read_failures(tmp_path)["ab" + "0" * 14]["status"] == "failed" and opened == []
    record_failure(tmp_path, "ab" + "0" * 14, "timeout", "second")
    (tmp_path / "failures" / "cd" / f"{'cd' + '0' * 14}.json").unlink()
    assert {task_id: (record["status"], record["reason"]) for task_id, record in read_failures(tmp_path).items()
            } == {"ab" + "0" * 14: ("timeout", "second")}
    assert len(opened) == 1


# A rehearsal's job writes its rows without pandas (pyarrow converts the values itself): the same row.
def test_a_row_written_without_pandas_is_the_same_row(tmp_path):
    row = {"task_id": "0123456789abcdef", "nmae": 0.1, "steps": 3, "note": None, "finite": True,
           "curve": [0.5, 0.25], "compiled": False}
    write = ("import sys; from pathlib import Path; from nsl_hpc.sweep.rows import prepare_row_writes, "
             "write_row_atomically; prepare_row_writes(pandas=sys.argv[2] == 'yes'); "
             f"write_row_atomically({row!r}, Path(sys.argv[1])); print('pandas' in sys.modules)")
    imported = {}
    for pandas in ("yes", "no"):
        done = subprocess.run([sys.executable, "-c", write, str(tmp_path / f"{pandas}.parquet"), pandas],
                              capture_output=True, text=True, check=True)
        imported[pandas] = done.stdout.strip()
    assert imported == {"yes": "True", "no": "False"}
    assert read_row(tmp_path / "no.parquet") == read_row(tmp_path / "yes.parquet") == row
    assert pq.read_schema(tmp_path / "no.parquet") == pq.read_schema(tmp_path / "yes.parquet")


# A local worker killed or stopped: its group recorded, the other workers finish, the launch says what happened.
@pytest.mark.e2e
@pytest.mark.parametrize(("sent", "state", "reason"), [
    (signal.SIGKILL, "failed", "died while training it (kill -9, the OOM killer?)"),
    (signal.SIGSTOP, "frozen", "stopped answering: its group's lock was not renewed for"),
])
@pytest.mark.slow
def test_a_local_worker_killed_or_stopped_is_recorded_and_the_others_finish(sent, state, reason, tmp_path):
    """4 tasks on 2 workers, a task each at a time: the worker of the first group to take its lock gets ``sent``
    (SIGSTOP, to it and its training process: noticed after watchdog.worker_silence_s=30); its group is recorded,
    its other task is not run, the other worker's two tasks finish."""
    sweep_dir = tmp_path / "sweep"
    launch = subprocess.Popen([sys.executable, "-m", "nsl_hpc.launch", *TINY_GRID, *LONGER,
                               "launcher=local", "launcher.workers=2", "lockstep.enabled=false",
                               "watchdog.worker_silence_s=30", f"sweep_dir={sweep_dir}"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    locks = []
    while not locks:
        assert launch.poll() is None, launch.stderr.read()
        time.sleep(0.2)
        locks = [lock for lock in held_locks(sweep_dir) if lock.task_ids]
    if sent == signal.SIGSTOP:  # the worker and its training process: a stopped or stuck process tree
        children = Path(f"/proc/{locks[0].pid}/task/{locks[0].pid}/children")
        while not children.read_text().split():  # the lock is taken just before the training process starts
            time.sleep(0.05)
        for child in children.read_text().split():
            os.kill(int(child), sent)
    os.kill(locks[0].pid, sent)
    if sent == signal.SIGSTOP:  # 30 s before it is noticed: the sweep runs, and status and merge say so
        status, merged = nsl("status", f"sweep_dir={sweep_dir}").stdout, nsl("merge", f"sweep_dir={sweep_dir}").stdout
        assert re.search(r"running [12] \|", status) and "missing 0 |" in status, status
        assert "0 of 4 tasks (0.0%) dropped" in merged and "still running or queued in a running launch" in merged
    out, _ = launch.communicate(timeout=300)
    assert launch.returncode == 1
    assert f"finished: 1 {state}, 1 not run, 2 ok" in out and "the other workers go on" in out, out
    failure = read_failures(sweep_dir)[locks[0].task_ids[0]]
    assert failure["status"] == state and reason in failure["reason"]
    status = nsl("status", f"sweep_dir={sweep_dir}").stdout
    assert "done 2 |" in status and f"{state} 1 |" in status and "missing 1 |" in status


def test_a_sweep_on_a_read_only_file_system_is_one_line_that_says_so(finished_sweep, tmpfs):
    """Every command that writes into a finished sweep on a file system remounted read-only says it cannot be
    written (not to free space), in one line, and changes nothing."""
    mount = tmpfs("size=64m")
    sweep_dir = mount / "sweep"
    shutil.copytree(finished_sweep, sweep_dir)
    subprocess.run(["mount", "-o", "remount,ro", str(mount)], check=True)
    before = {path: path.stat().st_mtime_ns for path in tree(sweep_dir)}
    for verb, args in (("merge", []), ("clean", []), ("resubmit", []), ("report", ["mlflow.enabled=false"])):
        result = nsl(verb, *args, f"sweep_dir={sweep_dir}")
        assert result.returncode != 0, (verb, result.stdout)
        assert len(result.stderr.splitlines()) == 1 and "Traceback" not in result.stderr, (verb, result.stderr)
        assert "Read-only file system" in result.stderr and "free space" not in result.stderr, (verb, result.stderr)
    assert {path: path.stat().st_mtime_ns for path in tree(sweep_dir)} == before
