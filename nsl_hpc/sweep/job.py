"""What one job runs: the lockstep groups of its pack (``nsl_hpc.sweep.plan.Pack``), exactly as planned, one
after another, each in a watched child process that trains the group's tasks together (each writes its own
row) with the sizes drawn in the manifest.

A child that raises or crashes is recorded as failed (with how much training it lost); one whose heartbeat
(every 32 steps or epoch) stops for ``watchdog.heartbeat_timeout_s``, or that runs ``watchdog.overrun_factor``
times longer than its group's predicted seconds, is killed and recorded as frozen. Either way the job goes on
with its next group.

Training checkpoints (``checkpoint.every_minutes`` > 0, ``nsl_hpc.sweep.groups``): the child writes its
group's state every that many minutes and continues from it when the group runs again. On SLURM's warning
signal (a time limit ahead or a preemption; submitit calls ``checkpoint``) the runner asks the child to write
its state and stop (SIGUSR1), and the job is requeued with the running group and those it has not started: a
group longer than a job's time limit runs as a chain of requeued jobs. A SIGTERM (``scontrol requeue``, a
preemption without warning, ``scancel``) makes the child write its state and stop too; the job then ends, and
its group continues where it stopped when the job runs again or is resubmitted; asked while its models are
scored, the child writes the end of training, and the group only scores when it runs again. A group that does not
stop that way (it hangs, or it is scoring an input-output test set), and any group without checkpoints, is
recorded as timeout at the warning and the job is requeued with the groups it has not started. A child asked
before its first block ends (loading data, compiling) has nothing to write and stops at once; a warning with
nothing left to requeue ends the job as it is (``JobRunner.end_cleanly_when_nothing_is_left``).

A job trains a group only while it holds the group's lock: a second job (a resubmitted one beside a requeued
one) leaves a group that a live job trains to it.
"""

import contextlib
import ctypes
import errno
import logging
import multiprocessing
import os
import shutil
import signal
import sys
import time
from collections import Counter
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import replace
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any

import submitit

from nsl_hpc.core.checkpoint import Checkpointer, TrainingStopped, read_info, remove_checkpoint
from nsl_hpc.core.diagnostics import job_records, log_job
from nsl_hpc.studies import import_training_code, study_of
from nsl_hpc.studies.base import Pair, Study
from nsl_hpc.sweep.directory import compile_cache, process_alive, tree, unsafe_refusal
from nsl_hpc.sweep.failures import record_failure
from nsl_hpc.sweep.groups import GroupLock, checkpoint_path, this_job
from nsl_hpc.sweep.launch_settings import LaunchSettings, launch_settings
from nsl_hpc.sweep.layout import failure_path, row_path, task_log_path
from nsl_hpc.sweep.manifest import read_base_config, read_launch_config, read_manifest
from nsl_hpc.sweep.plan import Group
from nsl_hpc.sweep.rehearsal import die_if_planted
from nsl_hpc.sweep.rows import all_done, prepare_row_writes, row_states, set_aside
from nsl_hpc.sweep.task import ResolvedTask, describe, pause_if_asked, resolve_task, run_tasks, with_run

LOG = logging.getLogger(__name__)
POLL_SECONDS = 0.2
PR_SET_PDEATHSIG = 1  # prctl(2)
EXIT_STOPPED = 75  # a child's exit status after it wrote its checkpoint and stopped, as asked (EX_TEMPFAIL)
EXIT_UNSTARTED = 76  # stopped as asked before its first block ended: nothing written, nothing trained
RUNNER_SIGNALS = {signal.SIGUSR2, signal.SIGTERM, signal.SIGUSR1}  # SLURM's warning, a requeue, the runner's request


def manifest_rows(sweep_dir: Path, task_ids: Sequence[str]) -> list[dict[str, Any]]:
    """The manifest rows of ``task_ids``, in that order."""
    table = read_manifest(sweep_dir)
    position = {task_id: index for index, task_id in enumerate(table["task_id"].to_pylist())}
    return [table.slice(position[task_id], 1).to_pylist()[0] for task_id in task_ids]


class TaskConfigs:
    """The tasks of a sweep's manifest rows, each (system, arch)'s shared config read from ``configs/`` and its
    settings typed once (a config read and resolved takes 40-80 ms: a rehearsal's whole job)."""

    def __init__(self, sweep_dir: Path) -> None:
        self.sweep_dir = sweep_dir
        self.shared: dict[tuple[str, str], tuple[dict[str, Any], Study, Pair]] = {}

    def load(self, task: Mapping[str, Any]) -> tuple[dict[str, Any], Study, Pair]:
        """The shared config of the manifest row ``task``'s (system, arch), its study and typed settings."""
        key = (task["system"], task["arch"])
        if key not in self.shared:
            values = read_base_config(self.sweep_dir, *key)
            study = study_of(values)
            self.shared[key] = (values, study, study.pair(values))
        return self.shared[key]

    def of(self, task: Mapping[str, Any]) -> ResolvedTask:
        """The task of the manifest row ``task`` (a dict with the manifest's columns), with its drawn sizes (the
        manifest is the truth: they are not drawn again)."""
        values, study, pair = self.load(task)
        own = {key: task[key] for key in (*study.task_keys, "task_id")}  # system, arch: the shared groups
        return resolve_task({**values, **own}, study.sizes_in(task), pair)


def as_planned(sweep: Path, task: ResolvedTask, compiled: bool) -> ResolvedTask:
    """``task`` compiled or not as its group was planned (compile=auto resolved), its test-only fault cleared where
    it struck once already (``fault.once``)."""
    fault = task.run.fault
    if fault.once and failure_path(sweep, task.task.task_id).exists():
        fault = replace(fault, kind=None)
    return with_run(task, compile="always" if compiled else "never", fault=fault)


def checkpoint_seconds(settings: LaunchSettings) -> float:
    """How often (s of training) a group writes its checkpoint; 0: never."""
    return 60.0 * settings.checkpoint.every_minutes


def die_with_parent() -> None:
    """Have the kernel kill this process when its parent ends (Linux), so no worker outlives a killed
    launcher and no task outlives its job runner; exit now if the parent is already gone."""
    parent = os.getppid()
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:
        os._exit(1)


def leave_warnings_to_the_runner(checkpoint: Checkpointer | None) -> None:
    """In a forked task process: ignore SLURM's warning (SIGUSR2 reaches every process of the job step), take
    the default SIGCONT, and on SIGUSR1 (the runner's request) or SIGTERM write the ``checkpoint`` and stop
    (without one: SIGTERM ends the process). The fork inherits submitit's handlers; a child running them
    checkpoints and requeues the job too, racing the runner's own checkpoint ("A temporary saved file already
    exists": the job fails and its unstarted groups are lost). A stop asked before the run's first block ends
    (data loading, kernels compiling: nothing to write) ends the process at once, stopped. The runner forks with
    these signals blocked (``runner_signals_blocked``); they are taken from here on."""
    signal.signal(signal.SIGUSR2, signal.SIG_IGN)
    signal.signal(signal.SIGCONT, signal.SIG_DFL)
    if checkpoint is None:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        signal.signal(signal.SIGUSR1, signal.SIG_IGN)
    else:
        def stop(*_: Any) -> None:
            if not checkpoint.progressed:
                os._exit(EXIT_UNSTARTED)
            checkpoint.ask_to_stop()

        signal.signal(signal.SIGTERM, stop)
        signal.signal(signal.SIGUSR1, stop)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, RUNNER_SIGNALS)


@contextlib.contextmanager
def runner_signals_blocked() -> Iterator[None]:
    """SLURM's warning, SIGTERM and the runner's stop request held back while a task process is forked: the fork
    takes them only once it has its own handlers (``leave_warnings_to_the_runner``), the runner as it leaves."""
    signal.pthread_sigmask(signal.SIG_BLOCK, RUNNER_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, RUNNER_SIGNALS)


def run_child(sweep_dir: Path, group: Sequence[Mapping[str, Any]], configs: TaskConfigs, compiled: bool, heartbeat,
              every_s: float) -> None:
    """Child process body: output to the first task's log, train the group (manifest rows ``group``, their
    configs from ``configs``, compiled as planned) from its checkpoint, writing one every ``every_s`` seconds (0:
    none); exit status 1 on an exception, EXIT_STOPPED once stopped as asked (EXIT_UNSTARTED before its first
    block ended)."""
    ids = [task["task_id"] for task in group]
    checkpoint = Checkpointer(checkpoint_path(sweep_dir, ids), every_s, ids) if every_s > 0 else None
    leave_warnings_to_the_runner(checkpoint)
    die_with_parent()
    log = task_log_path(sweep_dir, ids[0])
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as handle:
        os.dup2(handle.fileno(), 1)
        os.dup2(handle.fileno(), 2)
    sys.stdout = open(1, "w", buffering=1, closefd=False)  # noqa: SIM115
    sys.stderr = open(2, "w", buffering=1, closefd=False)  # noqa: SIM115
    log_job(sys.stderr, group_name(ids))
    try:
        tasks = [as_planned(sweep_dir, configs.of(task), compiled) for task in group]
        pause_if_asked(tasks[0].run.fault, tasks[0].task.coordinates["seed"], "loading", sweep_dir)
        for result in run_tasks(tasks, lambda: setattr(heartbeat, "value", time.time()), checkpoint):
            LOG.info(describe(result.row) if result.row else f"skipped: {result.path} exists")
    except TrainingStopped:
        LOG.info("stopped as asked; checkpoint written (%s)", checkpoint.path.name if checkpoint else "none")
        os._exit(EXIT_STOPPED)
    except BaseException:
        LOG.exception("training failed")
        sys.stderr.flush()
        os._exit(1)
    sys.stdout.flush()
    os._exit(0)


class JobRunner:
    """The callable submitit pickles into every job: ``JobRunner(launcher_pid)(sweep_dir, groups)`` trains the
    lockstep groups (``nsl_hpc.sweep.plan.Group``) of one pack, exactly as planned. Given the pid of a local
    launcher, the runner stops its task and exits as soon as that process is gone (the local executor's
    processes would otherwise finish the sweep as orphans)."""

    def __init__(self, launcher_pid: int | None = None, unstarted: frozenset[Group] = frozenset()) -> None:
        self.launcher_pid = launcher_pid
        self.unstarted = unstarted  # groups an earlier run of this job stopped before their first block ended
        self.running: tuple[Path, list[str], BaseProcess] | None = None
        self.current: Group | None = None  # the group being run (from before its process starts to its end)
        self.started: set[Group] = set()
        self.checkpointing, self.stop_wait_s = False, 30.0
        self.warned = False  # SLURM's warning came: checkpoint() has dealt with the running group
        self.nothing_left = False  # checkpoint() found nothing to requeue
        self.configs: TaskConfigs | None = None  # the sweep's task configs, once called

    def launcher_gone(self) -> bool:
        return self.launcher_pid is not None and not process_alive(self.launcher_pid)

    def __call__(self, sweep_dir: str, groups: Sequence[Group]) -> dict[str, int]:
        """Run the tasks of each group that have no valid row yet (a corrupt one is moved aside first) together;
        returns counts by outcome (per task): ok, skipped (a row exists), failed, frozen, busy (another job
        trains the group), stopped (asked to stop; the job ends)."""
        with job_records(sys.stdout, f"job {this_job() or os.getpid()}"):
            try:
                return self.run_groups(Path(sweep_dir), groups)
            except OSError as error:
                if error.errno not in (errno.ENOSPC, errno.EDQUOT, errno.EROFS):
                    raise
                LOG.error("%s while writing %s: the job stops, and its tasks without a row have no failure record "
                          "(none can be written there): status counts them missing, resubmit runs them once the "
                          "sweep's file system takes writes again", error.strerror, error.filename or "a file")
                sys.stdout.flush()
                os._exit(1)  # submitit's own result file cannot be written either: no traceback after the line

    def end_cleanly_when_nothing_is_left(self) -> None:
        """Wrap submitit's handler of SLURM's warning (SIGUSR2): where ``checkpoint`` leaves nothing to requeue
        (the last group finished, or stopped without checkpoints; the last row written), submitit raises
        UncompletedJobError into whatever the job was doing and SLURM records it FAILED. Caught here, the job goes
        on to its end as warned (it starts no group) and exits 0; any other reason not to requeue (requeued too
        often) still fails the job."""
        submitits = signal.getsignal(signal.SIGUSR2)
        if not callable(submitits):  # not under submitit's SLURM environment: nothing to wrap
            return

        def on_warning(signum: int, frame: Any) -> None:
            try:
                submitits(signum, frame)
            except submitit.core.utils.UncompletedJobError:
                if not self.nothing_left:
                    raise
                LOG.info("SLURM's warning came with nothing left to run: the job ends, not requeued")

        signal.signal(signal.SIGUSR2, on_warning)

    def run_groups(self, sweep: Path, groups: Sequence[Group]) -> dict[str, int]:
        launch = launch_settings(read_launch_config(sweep))
        self.configs = TaskConfigs(sweep)
        # SLURM sends SIGCONT with its warning; submitit's handler for it logs, and logging swallows the exception
        # a warning handler nested in it raises (the job would go on as if not warned)
        signal.signal(signal.SIGCONT, signal.SIG_DFL)
        self.end_cleanly_when_nothing_is_left()
        if refusal := unsafe_refusal(list(tree(compile_cache(launch.compile_cache_dir))),  # Inductor unpickles from it
                                     launch.allow_shared_sweep_dir):
            return self.refuse(sweep, groups, refusal)
        if not launch.rehearsal:  # a rehearsal trains nothing
            import_training_code()  # once, not in each group's forked process
        prepare_row_writes(pandas=not launch.rehearsal)
        self.checkpointing = checkpoint_seconds(launch) > 0
        self.stop_wait_s = (launch.signal_delay_s or 60) / 2  # SLURM's warning; local launchers: 60
        rows = manifest_rows(sweep, [task_id for group in groups for task_id in group.task_ids])
        by_id = {task["task_id"]: task for task in rows}
        first = self.configs.of(rows[0]) if rows else None

        def pause(point: str) -> None:  # test-only (fault.kind=pause): where a test sends SLURM's warning
            if first is not None:
                pause_if_asked(first.run.fault, first.task.coordinates["seed"], point, sweep)

        pause("start")
        counts: Counter[str] = Counter()
        for number, group in enumerate(groups):
            if self.launcher_gone():
                os._exit(1)
            if number == 1:
                pause("between")
            if self.warned:
                break
            self.started.add(group)
            self.current = group
            outcome = self.train_group(sweep, group, [by_id[task_id] for task_id in group.task_ids], launch, counts)
            self.current = None
            if outcome == "stopped":
                break
        if not self.warned:
            pause("end")
        return dict(counts)

    def train_group(self, sweep: Path, group: Group, tasks: Sequence[Mapping[str, Any]], launch: LaunchSettings,
                    counts: Counter[str]) -> str | None:
        """Train the ``tasks`` (manifest rows) of ``group`` that have no valid row yet (a corrupt one set aside)
        while holding its lock, adding to ``counts``; returns the outcome (ok, failed, frozen, stopped), None
        where nothing trained (every row there, or another job holds the group)."""
        states = row_states(sweep, group.task_ids)
        if done := sum(state == "done" for state in states.values()):
            counts["skipped"] += done
        for task_id, state in states.items():
            if state == "corrupt":
                set_aside(row_path(sweep, task_id))
        todo = [task for task in tasks if states[task["task_id"]] != "done"]
        if not todo:  # a job stopped between its rows and removing its checkpoint leaves one behind
            remove_checkpoint(checkpoint_path(sweep, list(group.task_ids)))
            return None
        ids = [task["task_id"] for task in todo]
        lock, name = GroupLock(sweep, ids), group_name(ids)
        holder = lock.acquire()
        if holder is not None:
            LOG.info("%s is trained by %s: left to it", name, holder)
            counts["busy"] += len(todo)
            return None
        if any(state == "done" for state in row_states(sweep, ids).values()):  # written by the run it waited for
            lock.release()
            counts["skipped"] += len(todo)
            return None
        try:
            outcome = self.run_watched(sweep, todo, group, launch, lock)
        finally:
            lock.release()
        LOG.info("%s: %s", name, outcome)
        counts[outcome] += len(todo)
        if launch.rehearsal:  # the rehearsal's lost node, after the group it was planted behind
            die_if_planted(sweep, group.task_ids[0])
        return outcome

    @staticmethod
    def refuse(sweep: Path, groups: Sequence[Group], reason: str) -> dict[str, int]:
        """Record every task of ``groups`` without a row failed for ``reason``, train none; counts by outcome."""
        ids = [task_id for task_id, state in row_states(sweep, [task_id for group in groups
                                                                 for task_id in group.task_ids]).items()
               if state != "done"]
        for task_id in ids:
            record_failure(sweep, task_id, "failed", f"not run: {reason}")
        LOG.error("not run: %s", reason)
        return {"failed": len(ids)} if ids else {}

    def run_watched(self, sweep: Path, group: Sequence[Mapping[str, Any]], planned: Group, launch: LaunchSettings,
                    lock: GroupLock) -> str:
        """Run the tasks (manifest rows) ``group`` of the lockstep group ``planned`` (its predicted seconds, compiled
        or not) in a child process under the watchdog (``launch.watchdog``), renewing ``lock``; returns ok,
        failed, frozen (the outcome of each of its tasks) or stopped."""
        assert self.configs is not None
        for task in group:  # read once in this process: the children of its later groups inherit them
            self.configs.load(task)
        predicted = launch.cost.startup_s + planned.seconds  # the job's start-up: a floor for short groups
        watchdog = launch.watchdog
        silence_s = watchdog.heartbeat_timeout_s + (compile_allowance(launch, group[0]["arch"]) if planned.compiled
                                                    else 0.0)  # no heartbeat while the first block compiles
        if launch.rehearsal:  # nothing trains or compiles: a silent group is frozen
            silence_s = launch.rehearse.heartbeat_timeout_s
        ids = [task["task_id"] for task in group]
        context = multiprocessing.get_context("fork")
        heartbeat = context.Value("d", time.time(), lock=False)
        every_s = checkpoint_seconds(launch)
        child = context.Process(target=run_child, args=(sweep, group, self.configs, planned.compiled, heartbeat,
                                                        every_s), daemon=True)
        started = time.time()
        with runner_signals_blocked():
            child.start()
        self.running = (sweep, ids, child)
        try:
            while child.is_alive():
                child.join(POLL_SECONDS)
                lock.renew()
                if self.launcher_gone():  # its task dies with it (die_with_parent)
                    os._exit(1)
                silent, elapsed = time.time() - heartbeat.value, time.time() - started
                if child.is_alive() and silent > silence_s:
                    return self.stop_frozen(child, sweep, ids, f"no heartbeat for {silent:.0f} s")
                if child.is_alive() and elapsed > watchdog.overrun_factor * predicted:
                    return self.stop_frozen(child, sweep, ids, f"ran {elapsed:.0f} s, over "
                                            f"{watchdog.overrun_factor}x its predicted {predicted:.0f} s")
        finally:
            self.running = None
        if child.exitcode == 0 and all_done(sweep, ids):
            log = task_log_path(sweep, ids[0])
            log.unlink(missing_ok=True)
            with contextlib.suppress(OSError):  # the bucket directory, once empty
                log.parent.rmdir()
            remove_checkpoint(checkpoint_path(sweep, ids))
            return "ok"
        if child.exitcode in (EXIT_STOPPED, EXIT_UNSTARTED) or self.warned:  # warned: checkpoint() recorded it
            return "stopped"
        exitcode = child.exitcode if child.exitcode is not None else -signal.SIGKILL  # None: it has not ended
        reason = (f"exit status {exitcode}" if exitcode >= 0 else f"killed by signal {signal.Signals(-exitcode).name}")
        record_group_failure(sweep, ids, "failed", f"{reason}; {lost_work(checkpoint_path(sweep, ids), started)}"
                             if every_s else reason)
        return "failed"

    @staticmethod
    def stop_frozen(child: BaseProcess, sweep: Path, ids: Sequence[str], reason: str) -> str:
        child.kill()
        child.join()
        record_group_failure(sweep, ids, "frozen", reason)
        return "frozen"

    def checkpoint(self, sweep_dir: str, groups: Sequence[Group]) -> submitit.helpers.DelayedSubmission | None:
        """On SLURM's warning signal (time limit or preemption): with checkpoints, have the running group write
        its state and stop, and requeue it with the groups not started; a group that does not stop so (it hangs,
        or it is scoring an input-output test set), and any without checkpoints, is recorded as
        timeout and not requeued (none left: no requeue, which SLURM would delay by minutes for nothing). A group
        stopped before its first block ended (loading data, compiling) is requeued once so; stopped so again in
        the requeued run, it is taken to hang and recorded timeout."""
        self.warned = True
        resumed = [self.current] if self.current is not None else []  # stopped, or not started yet
        unstarted = set(self.unstarted)
        if self.running is not None:
            sweep, ids, child = self.running
            if self.checkpointing and child.pid is not None:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(child.pid, signal.SIGUSR1)
                child.join(self.stop_wait_s)
            with contextlib.suppress(ProcessLookupError):
                child.kill()
            child.join()
            stuck = child.exitcode == EXIT_UNSTARTED and self.current in self.unstarted  # again: it hangs
            if child.exitcode not in (EXIT_STOPPED, EXIT_UNSTARTED) or stuck:
                resumed = []
                if all_done(sweep, ids):
                    remove_checkpoint(checkpoint_path(sweep, ids))  # it finished as the warning came
                record_group_failure(sweep, ids, "timeout", "the job reached its time limit while this task ran"
                                     + (" (twice before its first block of training ended)" if stuck else "")
                                     + ("; its checkpoint, if any, is kept: resubmit continues from it"
                                        if self.checkpointing else ""))
            elif child.exitcode == EXIT_UNSTARTED:
                unstarted.update(resumed)
        remaining = resumed + [group for group in groups if group not in self.started]
        if not remaining:
            self.nothing_left = True
            return None
        return submitit.helpers.DelayedSubmission(JobRunner(self.launcher_pid, frozenset(unstarted)), sweep_dir,
                                                  remaining)


def compile_allowance(launch: LaunchSettings, arch: str) -> float:
    """Seconds a compiled group of ``arch`` may go without a heartbeat beyond the watchdog's: three times its
    predicted compile time (cost.compile_s; a slower node, a cold cache)."""
    return 3.0 * float(launch.cost.compile_s.get(arch) or 0.0)


def lost_work(path: Path, started: float) -> str:
    """How much training a group that started at ``started`` (s since the epoch) lost when it ended now, given
    its checkpoint at ``path``."""
    info, now = read_info(path), time.time()
    if info is None or info["saved"] < started:
        return f"no checkpoint since it started: {now - started:.0f} s of training lost"
    return (f"{now - info['saved']:.0f} s of training lost since its last checkpoint (step {info['step']:,} of "
            f"{info['total_steps']:,}); it continues from there when run again")


def group_name(ids: Sequence[str]) -> str:
    """A lockstep group as log records name it: its first task (whose log is the group's) and how many more."""
    return f"group {ids[0]}" + (f" +{len(ids) - 1} tasks" if len(ids) > 1 else "")


def record_group_failure(sweep: Path, ids: Sequence[str], status: str, reason: str) -> None:
    """A failure record for each task of a lockstep group without a row; they share the first one's log."""
    LOG.warning("%s %s: %s", group_name(ids), status, reason)
    first_log = task_log_path(sweep, ids[0])
    for task_id, state in row_states(sweep, ids).items():
        if state == "done":
            continue
        log = task_log_path(sweep, task_id)
        if task_id != ids[0] and first_log.exists():
            log.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(first_log, log)
        group = f" (in a lockstep group of {len(ids)})" if len(ids) > 1 else ""
        record_failure(sweep, task_id, status, reason + group)
