"""Training checkpoints: a group stopped and resumed (twice) trains exactly as it does uninterrupted, for the
input-state lockstep loop and the input-output packed loop; a group's lock keeps a second job off it; a site
time cap makes a long group a chain of jobs."""

import copy
import dataclasses
import json
import math
import multiprocessing
import os
import signal
import socket
import subprocess
import threading
import time

import pytest
import submitit
import torch

from nsl_hpc.config import compose_config
from nsl_hpc.core.checkpoint import Checkpointer, TrainingStopped, read_info, scoring_progress
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.models import build_model
from nsl_hpc.studies import pair_of
from nsl_hpc.studies.input_output import lockstep as io_lockstep
from nsl_hpc.studies.input_state.data import build_training_set
from nsl_hpc.studies.input_state.lockstep import Member, train_lockstep
from nsl_hpc.studies.input_state.scaling import Scaling
from nsl_hpc.studies.training import StepCompiler
from nsl_hpc.sweep import groups
from nsl_hpc.sweep.failures import read_failures
from nsl_hpc.sweep.groups import GroupLock, checkpoint_path
from nsl_hpc.sweep.job import EXIT_UNSTARTED, JobRunner, leave_warnings_to_the_runner, runner_signals_blocked
from nsl_hpc.sweep.launch_settings import check_run_settings, launch_settings
from nsl_hpc.sweep.manifest import read_launch_config, read_manifest
from nsl_hpc.sweep.plan import Group, make_packs
from tests.sweeps import ALONE, TINY_GRID, nsl, row_files
from tests.test_io_lockstep import members_of


def stopping(checkpoint: Checkpointer, after_blocks: int):
    """An on_progress that asks ``checkpoint`` to stop after that many blocks."""
    calls = []

    def on_progress() -> None:
        calls.append(1)
        if len(calls) == after_blocks:
            checkpoint.ask_to_stop()
    return on_progress


def interrupted(train, path, stops=(1, 1)):
    """``train(on_progress, checkpoint)`` stopped after each of ``stops`` blocks and resumed, then to the end;
    returns its result and the last checkpointer."""
    for after in stops:
        checkpoint = Checkpointer(path, every_s=3600, task_ids=["a", "b", "c"])
        with pytest.raises(TrainingStopped):
            train(stopping(checkpoint, after), checkpoint)
        assert read_info(path)["step"] > 0
    checkpoint = Checkpointer(path, every_s=3600, task_ids=["a", "b", "c"])
    return train(lambda: None, checkpoint), checkpoint


def ph_members(compose, cache, specs, arch: str = "port_hamiltonian") -> tuple[list[Member], dict]:
    """Spring lockstep members (port-Hamiltonian by default) of (epochs, width, milestones) each, and the train
    config."""
    cfg = compose("system=spring", f"arch={arch}")
    system_cfg = pair_of(cfg).system
    members = []
    for seed, (epochs, width, milestones) in enumerate(specs):
        data = build_training_set(system_cfg, seed, 1.3, cache)
        torch.manual_seed(seed)
        model = build_model(pair_of(cfg).arch, 4, 2, width=width, depth=2)
        members.append(Member(model, data, Scaling.fit(data, rescale_targets=False), epochs, 10 + seed, milestones))
    return members, pair_of(cfg).train


def lockstep_trainer(members, train_cfg, compiled: bool = False):
    """``train(on_progress, checkpoint)``: the snapshots of the members trained in lockstep (a fresh copy each),
    eagerly or compiled."""
    def train(on_progress, checkpoint=None):
        compiler = StepCompiler(compiled)
        snapshots = train_lockstep(copy.deepcopy(members), train_cfg, on_progress, checkpoint, compiler)[1]
        assert compiler.enabled == compiled
        return snapshots
    return train


def assert_same_snapshots(expected, got):
    for member_expected, member_got in zip(expected, got, strict=True):
        for snapshot, again in zip(member_expected, member_got, strict=True):
            assert snapshot.outcome == again.outcome
            assert torch.equal(snapshot.theta, again.theta)


@pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_a_lockstep_group_stopped_and_resumed_gives_its_snapshots_bit_for_bit(compiled, compose, cache, tmp_path):
    """3 models (6 batches per epoch: 72, 42 and 60 steps, blocks of 32, one kept after 4 epochs
    too), stopped after the first block, resumed, stopped after the next (a model has left), resumed to the end;
    eager, or compiled (unstructured models, the cheapest to compile: the stack keeps its shapes across a
    resume)."""
    members = ph_members(compose, cache, [(12, 6, (4,)), (7, 3, ()), (10, 6, ())],
                         "unstructured" if compiled else "port_hamiltonian")
    train = lockstep_trainer(*members, compiled)
    expected = train(lambda: None)
    (resumed, checkpoint) = interrupted(train, tmp_path / "group.pt")
    assert checkpoint.resumes == 2
    assert [[s.epochs for s in member] for member in resumed] == [[4, 12], [7], [10]]
    assert_same_snapshots(expected, resumed)


def test_a_group_over_repeated_data_stopped_and_resumed_gives_its_snapshots_bit_for_bit(compose, cache, tmp_path):
    """Each member its own passes per epoch: 1,300 samples taken twice, 11 batches per epoch (33 and 66 steps), and
    three times, 16 batches (48 steps), in blocks of 32."""
    members, train_cfg = ph_members(compose, cache, [(6, 6, (3,)), (3, 3, ())])
    members = [dataclasses.replace(member, repeat=repeat) for member, repeat in zip(members, (2, 3), strict=True)]
    train = lockstep_trainer(members, train_cfg)
    expected = train(lambda: None)
    assert [[s.outcome.steps for s in member] for member in expected] == [[33, 66], [48]]
    (resumed, _) = interrupted(train, tmp_path / "group.pt")
    assert_same_snapshots(expected, resumed)


def stopped_while_scoring(train, path) -> tuple[object, list[int]]:
    """Train to the end, then ask to stop as scoring does (``scoring_progress``): the end of training is written and
    training stops; a resumed run returns what it trained without a block. Returns that and the resumed run's
    heartbeats."""
    checkpoint = Checkpointer(path, every_s=3600, task_ids=["a", "b", "c"])
    train(lambda: None, checkpoint)
    scoring = scoring_progress(checkpoint, checkpoint.ask_to_stop)
    with pytest.raises(TrainingStopped):
        scoring()
    assert read_info(path)["step"] == read_info(path)["total_steps"] > 0
    beats: list[int] = []
    return train(lambda: beats.append(1), Checkpointer(path, every_s=3600, task_ids=["a", "b", "c"])), beats


def test_a_stop_while_scoring_keeps_the_trained_models_and_the_resumed_run_only_scores(compose, cache, tmp_path):
    """A time limit's warning after training (while the test set is scored) writes the end of training: the
    resumed group trains no block and has the same models, for both studies' loops."""
    members, train_cfg = ph_members(compose, cache, [(6, 6, (3,)), (3, 3, ())])
    train = lockstep_trainer(members, train_cfg)
    resumed, beats = stopped_while_scoring(train, tmp_path / "state.pt")
    assert beats == []
    assert_same_snapshots(train(lambda: None), resumed)

    cfg = compose("study=input_output", "system=silverbox_sim", "arch=narx")
    io_members = members_of(cfg, cache, [(700, 40, 4, 0), (400, 20, 3, 1)])

    def io_train(on_progress, checkpoint=None):
        return io_lockstep.train_lockstep(copy.deepcopy(io_members), pair_of(cfg).train, on_progress,
                                          checkpoint)[1:]

    (final, outcomes), beats = stopped_while_scoring(io_train, tmp_path / "io.pt")
    assert beats == []
    expected_final, expected_outcomes = io_train(lambda: None)
    assert outcomes == expected_outcomes and torch.equal(final, expected_final)


def stopped_once(train, path) -> None:
    """Train until the first block's checkpoint is written, then stop."""
    checkpoint = Checkpointer(path, every_s=3600, task_ids=["a", "b", "c"])
    with pytest.raises(TrainingStopped):
        train(stopping(checkpoint, 1), checkpoint)


def test_a_checkpoint_with_flipped_bytes_is_set_aside_and_the_group_trains_afresh(compose, cache, tmp_path, caplog):
    """64 bytes flipped at 55% of the file (torch.load alone would not notice): the resume gives the
    uninterrupted result, not one from damaged numbers, and the damaged file is kept aside."""
    train = lockstep_trainer(*ph_members(compose, cache, [(12, 6, ()), (7, 3, ()), (10, 6, ())]))
    path = tmp_path / "group.pt"
    stopped_once(train, path)
    raw = bytearray(path.read_bytes())
    at = int(0.55 * len(raw))
    raw[at:at + 64] = bytes(b ^ 0xFF for b in raw[at:at + 64])
    path.write_bytes(raw)
    checkpoint = Checkpointer(path, every_s=3600, task_ids=["a", "b", "c"])
    assert_same_snapshots(train(lambda: None), train(lambda: None, checkpoint))
    assert checkpoint.resumes == 0 and path.with_suffix(".unreadable").read_bytes() == raw
    assert "group.pt unreadable (ValueError: checksum mismatch" in caplog.text


def test_a_checkpoint_of_another_layout_is_set_aside_and_the_group_trains_afresh(compose, cache, tmp_path, caplog):
    """The same task ids trained by models of another width (a code change between resubmits): the checkpoint
    loads but does not fit; it is set aside once, with a line, and the group trains to its own result."""
    path = tmp_path / "group.pt"
    stopped_once(lockstep_trainer(*ph_members(compose, cache, [(12, 6, ()), (7, 3, ()), (10, 6, ())])), path)
    train = lockstep_trainer(*ph_members(compose, cache, [(12, 8, ()), (7, 3, ()), (10, 6, ())]))
    checkpoint = Checkpointer(path, every_s=3600, task_ids=["a", "b", "c"])
    assert_same_snapshots(train(lambda: None), train(lambda: None, checkpoint))
    assert checkpoint.resumes == 0 and path.with_suffix(".mismatched").exists()
    assert "group.pt mismatched (made for {'format': 2, 'theta': [3, " in caplog.text


@pytest.mark.parametrize(("arch", "compiled"), [
    ("narx", False), ("subnet", False),
    pytest.param("narx", True, marks=pytest.mark.slow),
])
def test_a_packed_input_output_group_stopped_and_resumed_gives_its_models_bit_for_bit(arch, compiled, compose,
                                                                                     cache, tmp_path):
    """3 models of 40, 20 and 35 iterations (blocks of 16), stopped after the first block, then after the
    second (one model has finished), then to the end; eager, or compiled (NARX: SUBNET's compiled step shares
    the loop and its state, and compiles for minutes)."""
    cfg = compose("study=input_output", "system=silverbox_sim", f"arch={arch}")
    members = members_of(cfg, cache, [(700, 40, 4, 0), (400, 20, 3, 1), (1300, 35, 5, 2)])
    train_cfg = pair_of(cfg).train

    def train(on_progress, checkpoint=None):
        compiler = StepCompiler(compiled)
        result = io_lockstep.train_lockstep(copy.deepcopy(members), train_cfg, on_progress, checkpoint, compiler)[1:]
        assert compiler.enabled == compiled
        return result

    final, outcomes = train(lambda: None)
    (final_resumed, outcomes_resumed), _ = interrupted(train, tmp_path / "group.pt")
    assert outcomes_resumed == outcomes and [outcome.steps for outcome in outcomes] == [40, 20, 35]
    assert torch.equal(final_resumed, final)


def test_a_checkpoint_of_other_tasks_or_damaged_is_not_used(tmp_path):
    path = tmp_path / "group.pt"
    Checkpointer(path, 60, ["a"]).save({"x": torch.ones(2)}, 1, 4)
    assert Checkpointer(path, 60, ["a"]).load({})["x"].sum() == 2
    assert Checkpointer(path, 60, ["b"]).load({}) is None
    path.write_bytes(b"not a checkpoint")
    assert Checkpointer(path, 60, ["a"]).load({}) is None
    assert path.with_suffix(".unreadable").exists() and not path.exists()  # kept aside, not deleted


def held_lock(sweep_dir, task_ids) -> subprocess.Popen:
    """A live process (returned) holding the lock of the group of ``task_ids`` as job 7_1 on this host."""
    holder = subprocess.Popen(["sleep", "60"])
    lock = GroupLock(sweep_dir, task_ids)
    lock.path.parent.mkdir(parents=True)
    lock.path.write_text(f'{{"job": "7_1", "host": "{socket.gethostname()}", "pid": {holder.pid}, "time": 0}}')
    return holder


def test_a_live_jobs_lock_keeps_a_second_job_off_the_group_and_a_dead_ones_is_taken_over(tmp_path):
    holder = held_lock(tmp_path, ["a", "b"])
    try:
        assert GroupLock(tmp_path, ["a", "b"]).acquire() == f"job 7_1 on {socket.gethostname()}"
        assert GroupLock(tmp_path, ["b", "a"]).acquire() is None  # another group (order is training order)
    finally:
        os.kill(holder.pid, signal.SIGKILL)
        holder.wait()
    second = GroupLock(tmp_path, ["a", "b"])
    assert second.acquire() is None  # its holder is gone
    assert GroupLock(tmp_path, ["a", "b"]).acquire() == f"job {os.getpid()} on {socket.gethostname()}"
    second.release()
    assert not second.path.exists()


def test_a_requeued_job_waits_for_its_earlier_run_while_that_run_renews_the_lock(tmp_path, monkeypatch):
    """SLURM requeues the job of a lost node while that node's processes may still train: the new run of job 7_1
    (another host) waits while the earlier run renews its lock, takes the group once it is released, and takes
    over a lock its earlier run stopped renewing (issue: it took over at once and the group trained twice)."""
    monkeypatch.setattr(groups, "RENEW_S", 0.05)
    monkeypatch.setattr(groups, "STALE_S", 0.5)
    earlier = GroupLock(tmp_path, ["a", "b"])
    earlier.record = {**earlier.record, "job": "7_1", "host": "lost-node"}
    assert earlier.acquire() is None
    monkeypatch.setenv("SLURM_JOB_ID", "7_1")  # this_job() of the requeued run
    monkeypatch.setenv("SLURM_ARRAY_JOB_ID", "7")
    monkeypatch.setenv("SLURM_ARRAY_TASK_ID", "1")
    requeued = GroupLock(tmp_path, ["a", "b"])
    assert requeued.record["job"] == "7_1"

    def renew_then_release() -> None:
        for _ in range(10):  # 0.5 s of renewals, then released
            time.sleep(0.05)
            os.utime(earlier.path)
        earlier.path.unlink()

    renewing = threading.Thread(target=renew_then_release)
    started = time.monotonic()
    renewing.start()
    assert requeued.acquire() is None
    renewing.join()
    assert time.monotonic() - started >= 0.5  # it waited for the release
    assert json.loads(requeued.path.read_text())["host"] == socket.gethostname()
    requeued.release()
    assert earlier.acquire() is None  # the earlier run again, now silent: stale once not renewed for STALE_S
    os.utime(earlier.path, (time.time() - 1, time.time() - 1))
    assert GroupLock(tmp_path, ["a", "b"]).acquire() is None


def test_a_job_runner_leaves_a_group_that_a_live_job_trains_then_trains_it_once_that_job_is_gone(tmp_path):
    sweep_dir = tmp_path / "sweep"
    assert nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={sweep_dir}", "dry_run=true").returncode == 0
    settings = launch_settings(read_launch_config(sweep_dir))
    groups = [group for pack in settings.plan(read_manifest(sweep_dir).to_pylist())
              for group in pack.groups]
    held, others = len(groups[0].task_ids), 4 - len(groups[0].task_ids)
    holder = held_lock(sweep_dir, groups[0].task_ids)
    try:
        assert JobRunner()(str(sweep_dir), groups) == {"busy": held, **({"ok": others} if others else {})}
        assert len(row_files(sweep_dir)) == others
    finally:
        os.kill(holder.pid, signal.SIGKILL)
        holder.wait()
    assert JobRunner()(str(sweep_dir), groups) == {"ok": held, **({"skipped": others} if others else {})}
    assert len(row_files(sweep_dir)) == 4 and not list((sweep_dir / "checkpoints").rglob("*.*"))


@pytest.mark.e2e  # launches a sweep
def test_a_finished_groups_checkpoint_goes_whether_its_job_was_stopped_after_the_rows_or_warned(tmp_path):
    """A job can stop between a group's rows and removing its checkpoint (its time ran out, or SLURM's warning
    came as the group finished): the checkpoint must not outlive the rows (status and clean would show it)."""
    sweep_dir = tmp_path / "sweep"
    assert nsl("launch", *TINY_GRID, "launcher=debug", f"sweep_dir={sweep_dir}").returncode == 0
    settings = launch_settings(read_launch_config(sweep_dir))
    groups = [group for pack in settings.plan(read_manifest(sweep_dir).to_pylist())
              for group in pack.groups]
    ids = list(groups[0].task_ids)
    path = checkpoint_path(sweep_dir, ids)
    Checkpointer(path, 60, ids).save({"x": torch.ones(1)}, 1, 4)
    assert JobRunner()(str(sweep_dir), groups)["skipped"] == 4 and not path.exists()  # a job finds the rows

    Checkpointer(path, 60, ids).save({"x": torch.ones(1)}, 1, 4)
    runner, finished = JobRunner(), multiprocessing.get_context("fork").Process(target=lambda: None)
    finished.start()
    finished.join()
    runner.checkpointing, runner.running, runner.started = True, (sweep_dir, ids, finished), set(groups)
    assert runner.checkpoint(str(sweep_dir), groups) is None and not path.exists()  # warned as it finished


def test_a_warned_job_keeps_its_timeout_record_and_stops_even_when_the_warnings_exception_is_lost(tmp_path):
    """SLURM's warning comes with a SIGCONT, whose submitit handler logs; logging swallows the exception the
    nested warning handler raises. The runner must still stop, and the hanging group it killed stays timeout
    (it was recorded failed, killed by SIGKILL)."""
    sweep_dir = tmp_path / "sweep"
    assert nsl("launch", *TINY_GRID, "sweep.grid.seed=[0,1]", ALONE, "launcher=slurm",
               f"sweep_dir={sweep_dir}", "packing.time_classes_minutes=[1]", "launcher.signal_delay_s=2",
               "checkpoint.every_minutes=0", "fault.kind=hang", "dry_run=true").returncode == 0
    settings = launch_settings(read_launch_config(sweep_dir))
    groups = [group for pack in settings.plan(read_manifest(sweep_dir).to_pylist())
              for group in pack.groups]
    assert len(groups) == 2
    runner = JobRunner()

    def warned_and_lost(*_) -> None:
        assert runner.checkpoint(str(sweep_dir), groups) is not None  # the second group is requeued
    previous = signal.signal(signal.SIGUSR2, warned_and_lost)
    timer = threading.Timer(3.0, os.kill, (os.getpid(), signal.SIGUSR2))
    timer.start()
    try:
        assert runner(str(sweep_dir), groups) == {"stopped": 1}
    finally:
        timer.cancel()
        signal.signal(signal.SIGUSR2, previous)
    failures = read_failures(sweep_dir)
    assert [record["status"] for record in failures.values()] == ["timeout"], failures
    assert set(failures) == set(groups[0].task_ids) and not row_files(sweep_dir)


def test_a_site_time_cap_makes_a_long_group_a_chain_of_jobs_and_needs_checkpoints():
    launch = compose_config(["+sweep=demo", "launcher=slurm", "launcher.max_time_minutes=60"], "launch")
    packing = check_run_settings(launch).packing_for()
    assert packing.time_classes_minutes == (20, 60)
    (short, long) = make_packs([Group(("a",), 10 * 60), Group(("b",), 3 * 3600)], packing)
    assert (short.time_limit_min, short.chain) == (60, 1)  # 30 min with the safety factor 3
    assert (long.time_limit_min, long.chain) == (60, math.ceil(3 * 3 * 60 / 60))
    launch.checkpoint.every_minutes = 0
    with pytest.raises(ConfigError, match=r"launcher\.max_time_minutes=60 needs checkpoints"):
        check_run_settings(launch)


def test_time_is_measured_over_resumes(tmp_path):
    """A resumed run's training time counts the time every run before it trained up to its last checkpoint (the
    row's train_seconds), and not the time between the runs."""
    path, started = tmp_path / "group.pt", time.monotonic()
    first = Checkpointer(path, 60, ["a"])
    time.sleep(0.05)
    first.save({}, 1, 3)
    first_s = time.monotonic() - started
    time.sleep(0.2)  # between the runs: not training
    second_started = time.monotonic()
    second = Checkpointer(path, 60, ["a"])
    second.load({})
    assert 0.05 <= second.trained_before_s <= first_s
    time.sleep(0.05)
    second.save({}, 2, 3)
    second_s = time.monotonic() - second_started
    third = Checkpointer(path, 60, ["a"])
    third.load({})
    assert second.trained_before_s + 0.05 <= third.trained_before_s <= second.trained_before_s + second_s
    assert third.resumes == 2


def stop_asked_in_a_fork(blocks: int, path) -> int:
    """The exit status of a forked task process whose checkpointer ended ``blocks`` blocks, asked to stop (SIGUSR1)
    while it works on (data loading, a block compiling); it is forked with the runner's signals held back."""
    def body() -> None:
        checkpoint = Checkpointer(path, 60, ["a"])
        for _ in range(blocks):
            checkpoint.block_done(lambda: {"x": torch.ones(1)}, 1, 4)
        leave_warnings_to_the_runner(checkpoint)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:  # working, outside any block boundary
            time.sleep(0.01)
        os._exit(0 if checkpoint.stop_asked else 1)

    child = multiprocessing.get_context("fork").Process(target=body)
    with runner_signals_blocked():
        child.start()
        os.kill(child.pid, signal.SIGUSR1)  # before the fork has its handlers: held until it has them
    child.join()
    return child.exitcode


def test_a_stop_before_the_first_block_ends_the_task_process_at_once_as_stopped(tmp_path):
    """SLURM's warning can come while a group loads its data or compiles (22 s into a job): with nothing to write
    yet, the task process ends at once, stopped before training (EXIT_UNSTARTED), so the runner requeues the group
    once instead of killing it and recording timeout (a second time it is taken to hang:
    tests/cluster/test_sweep_on_slurm.py's hanging tasks); after a block it writes its checkpoint at the next
    boundary as before. The signal sent as it is forked waits for its handlers."""
    assert stop_asked_in_a_fork(0, tmp_path / "loading") == EXIT_UNSTARTED
    assert not (tmp_path / "loading").exists()
    assert stop_asked_in_a_fork(1, tmp_path / "training") == 0  # asked: it stops at the next block boundary


def test_a_warning_with_nothing_left_to_requeue_ends_the_job_as_it_is_not_failed(tmp_path):
    """The warning comes when the job's last group cannot be requeued (no checkpoints; or it finished, its row
    written): submitit raises UncompletedJobError ("checkpoint function returned None") into the job, which SLURM
    records FAILED. The runner ends as warned instead; any other reason not to requeue still fails it."""
    sweep_dir = tmp_path / "sweep"
    assert nsl("launch", *TINY_GRID, ALONE, "launcher=slurm", f"sweep_dir={sweep_dir}",
               "packing.time_classes_minutes=[1]", "launcher.signal_delay_s=2", "checkpoint.every_minutes=0",
               "fault.kind=hang", "dry_run=true").returncode == 0
    settings = launch_settings(read_launch_config(sweep_dir))
    last = [group for pack in settings.plan(read_manifest(sweep_dir).to_pylist()) for group in pack.groups][:1]
    runner = JobRunner()

    def submitit_like(*_) -> None:  # submitit's handler: no requeue is an exception into the job
        if runner.checkpoint(str(sweep_dir), last) is None:
            raise submitit.core.utils.UncompletedJobError("Job not requeued")
    previous = signal.signal(signal.SIGUSR2, submitit_like)
    timer = threading.Timer(3.0, os.kill, (os.getpid(), signal.SIGUSR2))
    timer.start()
    try:
        assert runner(str(sweep_dir), last) == {"stopped": 1}  # its one group hung: timeout, nothing left
        assert {failure["status"] for failure in read_failures(sweep_dir).values()} == {"timeout"}

        def too_often(*_) -> None:  # a group left to requeue, but submitit requeued the job too often
            raise submitit.core.utils.UncompletedJobError("Job not requeued because: timed-out too many times")
        signal.signal(signal.SIGUSR2, too_often)
        other = JobRunner()
        other.end_cleanly_when_nothing_is_left()
        with pytest.raises(submitit.core.utils.UncompletedJobError):
            signal.getsignal(signal.SIGUSR2)(signal.SIGUSR2, None)
        other.nothing_left = True
        signal.getsignal(signal.SIGUSR2)(signal.SIGUSR2, None)  # nothing left: the job goes on to its end
    finally:
        timer.cancel()
        signal.signal(signal.SIGUSR2, previous)
