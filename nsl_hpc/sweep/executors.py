"""Running packs with submitit: SLURM job arrays split within the cluster's limits (returns once
submitted), or local / in-process executors in the foreground with a progress bar."""

import contextlib
import io
import itertools
import logging
import os
import shutil
import signal
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import submitit
from tqdm import tqdm

from nsl_hpc.config.launchers import DebugLauncher, Launcher, LocalLauncher, SlurmLauncher
from nsl_hpc.core.errors import ConfigError, RunError, one_line
from nsl_hpc.studies import study_named
from nsl_hpc.studies.base import Pair
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.directory import process_alive
from nsl_hpc.sweep.failures import read_failures
from nsl_hpc.sweep.groups import HeldLock, held_locks, this_node
from nsl_hpc.sweep.job import JobRunner, record_group_failure
from nsl_hpc.sweep.launch_settings import LaunchSettings
from nsl_hpc.sweep.limits import ClusterLimits, read_cluster_limits
from nsl_hpc.sweep.manifest import write_run_settings
from nsl_hpc.sweep.plan import Group, Pack
from nsl_hpc.sweep.prepare import prepare_shared_data
from nsl_hpc.sweep.rows import row_states
from nsl_hpc.sweep.slurm import held_arrays, queued_jobs, refused_flag, refused_setting
from nsl_hpc.sweep.submissions import read_submissions, record_submission

LOG = logging.getLogger(__name__)

FULL_DISK_BYTES = 64 * 2**20  # a local job that ended without its result with less free than this: the disk is full


@dataclass(frozen=True)
class Submission:
    """What a launch handed to SLURM: arrays (id -> element count) and the packs left for later."""

    arrays: dict[str, int]
    left: list[Pack]
    refusal: str | None = None  # sbatch's message when it refused an array
    unaccounted: str | None = None  # why the user's job limits could not be read (limits.ClusterLimits)


def submit_to_slurm(sweep_dir: Path, packs: Sequence[Pack], launcher: SlurmLauncher, name: str,
                    limits: ClusterLimits) -> Submission:
    """Submit ``packs`` as job arrays, one time limit per array, indices from 0, within the cluster's ``limits``."""
    room = limits.max_job_count.value - queued_jobs(user_only=False)
    if limits.submit_jobs is not None:
        room = min(room, limits.submit_jobs.value - queued_jobs(user_only=True, qos=limits.submit_jobs.qos))
    if launcher.feed_minutes is not None and room < len(packs):
        room -= 1  # the feeder's (submit_feeder)
    ordered = sorted(packs, key=lambda pack: pack.time_limit_min)
    now, left = ordered[:max(room, 0)], ordered[max(room, 0):]
    chunks = array_chunks(now, limits.max_array_size.value)
    arrays: dict[str, int] = {}
    after = (held_arrays(record["array_id"] for record in read_submissions(sweep_dir))
             if launcher.max_running is not None else [])
    for index, chunk in enumerate(chunks):
        try:
            array_id = submit_array(sweep_dir, chunk, chunk[0].time_limit_min, launcher, name, limits.cluster, after)
            arrays[array_id] = len(chunk)
        except submitit.core.utils.FailedJobError as error:  # e.g. the controller is full: keep what went in
            refused = [pack for later in chunks[index:] for pack in later]
            return Submission(arrays, refused + left, one_line(error)[-300:], limits.unaccounted)
        if launcher.max_running is not None:  # one array at a time: the sweep never runs more than max_running
            after = [array_id]
    return Submission(arrays, left, unaccounted=limits.unaccounted)


def array_chunks(packs: Sequence[Pack], max_array_size: int) -> list[list[Pack]]:
    """``packs`` (sorted by time limit) cut into arrays of one time limit and at most ``max_array_size``."""
    chunks = []
    for _, same_limit in itertools.groupby(packs, key=lambda pack: pack.time_limit_min):
        group = list(same_limit)
        chunks += [group[start:start + max_array_size] for start in range(0, len(group), max_array_size)]
    return chunks


def slurm_executor(sweep_dir: Path, time_limit_min: int, launcher: SlurmLauncher, name: str, chain: int = 1,
                   after: Sequence[str] = ()) -> submitit.SlurmExecutor:
    """The submitit executor of one array: single-CPU elements of one time limit, warned before it, each
    requeued up to ``chain`` + 2 times at its time limit (a chain of ``chain`` jobs, and some slack); with
    ``after``, they start once those jobs have ended (however they ended)."""
    executor = submitit.SlurmExecutor(folder=sweep_dir / layout.SUBMITIT / "%A", max_num_timeout=chain + 2)
    planned: dict[str, Any] = {"dependency": "afterany:" + ":".join(after)} if after else {}
    if launcher.hold:
        planned["hold"] = True
    executor.update_parameters(
        job_name=f"nsl-{name}", time=time_limit_min, cpus_per_task=1, ntasks_per_node=1, mem=launcher.mem,
        partition=launcher.partition, account=launcher.account, qos=launcher.qos,
        array_parallelism=min(launcher.array_parallelism, launcher.max_running or launcher.array_parallelism),
        signal_delay_s=launcher.signal_delay_s,
        additional_parameters={**launcher.sbatch_flags(), **planned}, setup=list(launcher.setup),
        stderr_to_stdout=True)
    return executor


@dataclass(frozen=True)
class SweepCommand:
    """What a sweep's own SLURM job runs: ``python -m <module> <arguments>`` in ``cwd`` (a budgeted sweep's next
    round: nsl_hpc.launch; the jobs the cluster's limits held back: nsl_hpc.resubmit); while another command holds
    the sweep (a resubmit, a clean, a launch by hand) it tries again every ``wait_s`` seconds, ``attempts`` times."""

    arguments: tuple[str, ...]
    cwd: str
    module: str = "nsl_hpc.launch"
    attempts: int = 10
    wait_s: float = 60.0

    def __call__(self) -> None:
        command = [sys.executable, "-m", self.module, *self.arguments]
        for _ in range(self.attempts):
            result = subprocess.run(command, cwd=self.cwd, check=False, stderr=subprocess.PIPE, text=True)
            print(result.stderr, end="", file=sys.stderr, flush=True)
            if result.returncode == 0:
                return
            if "is in use by" not in result.stderr:
                break
            time.sleep(self.wait_s)
        raise RunError(f"{' '.join(command)} exited with {result.returncode}")


def submit_next_round(sweep_dir: Path, arguments: Sequence[str], launcher: SlurmLauncher, name: str,
                      after: Sequence[str], minutes: int) -> str:
    """Submit the job that launches a budgeted sweep again (``arguments``: its launch's) once the jobs ``after``
    have ended; returns its id."""
    executor = slurm_executor(Path(sweep_dir), minutes, launcher, f"{name}-rounds", after=after)
    own = [argument for argument in arguments if argument.split("=", 1)[0].lstrip("+~") != "sweep_dir"]
    return str(executor.submit(SweepCommand((*own, f"sweep_dir={sweep_dir}"), os.getcwd())).job_id)


def submit_feeder(sweep_dir: Path, launcher: SlurmLauncher, name: str, after: str, minutes: int) -> str:
    """Submit the job that submits the sweep's tasks the cluster's limits held back (``resubmit
    states=[missing]``: those never submitted, or cancelled) once the array ``after`` has ended; returns its id.
    It submits another behind its own arrays while tasks are still held back."""
    executor = slurm_executor(Path(sweep_dir), minutes, launcher, f"{name}-feed", after=[after])
    command = SweepCommand((f"sweep_dir={sweep_dir}", "states=[missing]"), os.getcwd(), module="nsl_hpc.resubmit")
    return str(executor.submit(command).job_id)


def submit_array(sweep_dir: Path, packs: Sequence[Pack], time_limit_min: int, launcher: SlurmLauncher,
                 name: str, cluster: str, after: Sequence[str] = ()) -> str:
    """One array of single-CPU elements, element i running ``packs[i]``, starting once the jobs ``after`` have
    ended, on the cluster named ``cluster`` (recorded with it); returns the array job id."""
    executor = slurm_executor(sweep_dir, time_limit_min, launcher, name, max(pack.chain for pack in packs), after)
    with contextlib.redirect_stderr(io.StringIO()):  # submitit prints a refusal's sbatch lines: the error has them
        jobs = executor.map_array(JobRunner(), [str(sweep_dir)] * len(packs), [list(pack.groups) for pack in packs])
    array_id = jobs[0].job_id.split("_")[0]  # a single element is a plain job: its id has no _<index>
    record_submission(sweep_dir, array_id, time_limit_min, [job.job_id for job in jobs],
                      [pack.task_ids for pack in packs], [pack.task_seconds() for pack in packs], cluster)
    return array_id


def balance(packs: Sequence[Pack], workers: int) -> list[list[Group]]:
    """The lockstep groups of ``packs`` spread over ``workers`` lists of about equal predicted time (longest
    first)."""
    groups = [group for pack in packs for group in pack.groups]
    seconds = [0.0] * min(workers, len(groups))
    shares: list[list[Group]] = [[] for _ in seconds]
    for group in sorted(groups, key=lambda group: -group.seconds):
        lightest = seconds.index(min(seconds))
        seconds[lightest] += group.seconds
        shares[lightest].append(group)
    return shares


def run_locally(sweep_dir: Path, packs: Sequence[Pack], launcher: LocalLauncher | DebugLauncher,
                silence_s: float) -> dict[str, int]:
    """Run ``packs`` on this machine (local: parallel processes; debug: in-process) and wait, with a progress
    bar over tasks; returns counts by outcome. A local worker that stops answering (its group's lock not renewed
    for ``silence_s``: a stopped process, one stuck in the kernel) is killed and its group recorded frozen; one
    that dies has its group recorded failed; either way the other workers go on."""
    debug = isinstance(launcher, DebugLauncher)
    workers = launcher.workers or os.cpu_count() or 1
    shares = balance(packs, workers)
    task_ids = [task_id for share in shares for group in share for task_id in group.task_ids]
    folder = layout.local_jobs_folder(sweep_dir) / "%j"
    executor: submitit.Executor
    if debug:
        executor = submitit.DebugExecutor(folder=folder)
    else:
        executor = submitit.LocalExecutor(folder=folder)
        executor.update_parameters(timeout_min=int(sum(p.seconds for p in packs) * 10 / 60) + 60)
    runner = JobRunner(None if debug else os.getpid())  # workers die with this process
    jobs = executor.map_array(runner, [str(sweep_dir)] * len(shares), shares)
    counts: Counter[str] = Counter()
    try:
        with tqdm(total=len(task_ids), desc="tasks", unit="task", disable=None) as bar:
            pending = dict(zip(jobs, shares, strict=True))
            while pending:
                if not debug:
                    time.sleep(1.0)
                for job in list(pending):
                    if not debug and stop_stalled_worker(sweep_dir, pending[job], silence_s):
                        counts.update(unfinished_share(sweep_dir, pending.pop(job), "it stopped answering"))
                    elif debug or job.done():
                        counts.update(job_result(job, sweep_dir, pending.pop(job)))
                bar.n = sum(state == "done" for state in row_states(sweep_dir, task_ids).values())
                bar.refresh()
    except KeyboardInterrupt:
        for job in jobs:
            with contextlib.suppress(Exception):
                job.cancel()
        raise RunError("interrupted: the running tasks were stopped, finished rows are kept; launch again to run "
                       "the rest") from None
    return dict(counts)


def worker_locks(sweep_dir: Path, share: Sequence[Group]) -> list[HeldLock]:
    """The locks of the groups of a local worker's ``share`` (the one it trains now; none between groups)."""
    ids = {task_id for group in share for task_id in group.task_ids}
    return [lock for lock in held_locks(sweep_dir)
            if lock.host == this_node() and lock.task_ids and set(lock.task_ids) <= ids]


def stop_stalled_worker(sweep_dir: Path, share: Sequence[Group], silence_s: float) -> bool:
    """Kill the local worker of ``share`` if it stopped answering (its group's lock, renewed every RENEW_S, not
    renewed for ``silence_s``; a SIGKILL reaches a stopped process, and its training process dies with it) and
    record its group frozen; returns whether it did (the job is given up: a process stuck in the kernel may not
    even die)."""
    for lock in worker_locks(sweep_dir, share):
        if lock.silent_s > silence_s and process_alive(lock.pid):
            with contextlib.suppress(ProcessLookupError):
                os.kill(lock.pid, signal.SIGKILL)
            record_group_failure(sweep_dir, lock.task_ids, "frozen", f"its local worker (pid {lock.pid}) stopped "
                                 f"answering: its group's lock was not renewed for {lock.silent_s:.0f} s (a stopped "
                                 "process, or one stuck in the kernel); killed")
            lock.path.unlink(missing_ok=True)
            return True
    return False


def job_result(job: submitit.Job, sweep_dir: Path, share: Sequence[Group]) -> dict[str, int]:
    """A finished local job's counts by outcome. One that ended without a result is accounted for by
    ``unfinished_share`` (its worker killed: kill -9, the OOM killer), or, where the disk is (nearly) full, ends
    the launch with a one-line RunError: every other worker would fail the same way."""
    try:
        return job.result()
    except (submitit.core.utils.UncompletedJobError, submitit.core.utils.FailedJobError) as error:
        free = shutil.disk_usage(job.paths.folder).free
        if free < FULL_DISK_BYTES:
            raise RunError(f"a local job ended without its result ({one_line(error)[:160]}); "
                           f"{free / 2**20:.0f} MiB free where it writes: free space, then launch again (finished "
                           "rows are kept)") from None
        reason = ("it died without a result: kill -9, the OOM killer?"
                  if isinstance(error, submitit.core.utils.UncompletedJobError)
                  else f"it raised {str(error).strip().splitlines()[-1][:160]}")
    return unfinished_share(sweep_dir, share, reason)


def unfinished_share(sweep_dir: Path, share: Sequence[Group], reason: str) -> dict[str, int]:
    """Counts by outcome of a local worker's ``share`` that it did not finish: the group a dead worker held
    recorded failed (one it was killed in for not answering is recorded frozen already), the tasks without a row
    and failure record ``not run`` (missing: resubmit runs them); a line says so."""
    for lock in worker_locks(sweep_dir, share):
        if not process_alive(lock.pid):
            record_group_failure(sweep_dir, lock.task_ids, "failed", f"its local worker (pid {lock.pid}) died while "
                                 "training it (kill -9, the OOM killer?); its checkpoint, if any, is kept: resubmit "
                                 "continues from it")
            lock.path.unlink(missing_ok=True)
    failures, counts = read_failures(sweep_dir), Counter[str]()
    for task_id, state in row_states(sweep_dir, [task_id for group in share for task_id in group.task_ids]).items():
        counts["ok" if state == "done" else failures[task_id]["status"] if task_id in failures else "not run"] += 1
    tqdm.write(f"a local worker did not finish its share ({reason}): {counts['ok']:,} tasks done, "
               f"{counts['failed'] + counts['frozen']:,} recorded failed or frozen, {counts['not run']:,} not run "
               "(resubmit runs them); the other workers go on")
    return dict(counts)


def dispatch(sweep_dir: Path, packs: Sequence[Pack], launcher: Launcher, name: str, silence_s: float,
             limits: ClusterLimits | None = None) -> int:
    """Submit ``packs`` (launcher slurm; within ``limits``, read here when None) or run them here, print what
    happened; returns the exit status: 1 when a task ran here and did not finish."""
    sweep_dir = Path(sweep_dir).resolve()  # jobs find it from anywhere
    if isinstance(launcher, SlurmLauncher):
        limits = limits or read_cluster_limits(launcher)
        submission = submit_to_slurm(sweep_dir, packs, launcher, name, limits)
        elements = sum(submission.arrays.values())
        if submission.unaccounted:
            LOG.info(f"the user's job limits are unknown ({submission.unaccounted[:160]}): submitted without them (set "
                  "launcher.max_submit_jobs to stay within a submit limit)")
        if submission.refusal:
            refuse_for_setting(sweep_dir, submission, list(launcher.sbatch_flags()))
        LOG.info(f"submitted {elements:,} jobs in {len(submission.arrays)} arrays: {', '.join(submission.arrays)}")
        if submission.refusal:
            LOG.info(f"sbatch refused the next array: {submission.refusal}")
        if submission.left:
            LOG.info(held_back_line(sweep_dir, submission, launcher, name, limits))
        return 0
    counts = run_locally(sweep_dir, packs, launcher, silence_s)
    LOG.info("finished: " + ", ".join(f"{n:,} {outcome}" for outcome, n in sorted(counts.items())))
    return 0 if set(counts) <= {"ok", "skipped"} else 1


def held_back_line(sweep_dir: Path, submission: Submission, launcher: SlurmLauncher, name: str,
                   limits: ClusterLimits) -> str:
    """Submit the feeder of what the cluster's job limits held back (behind the first array submitted, if
    any and unless launcher.feed_minutes is null); the line that says so."""
    held = (f"the cluster's job limits hold no more now: {len(submission.left):,} jobs "
            f"({sum(len(pack.task_ids) for pack in submission.left):,} tasks) were not submitted")
    if launcher.feed_minutes is None or not submission.arrays:
        return f"{held}; launch again (or resubmit) once the queue has room"
    minutes = min(launcher.feed_minutes, limits.wall_minutes.value if limits.wall_minutes else launcher.feed_minutes)
    first = next(iter(submission.arrays))
    try:
        feeder = submit_feeder(sweep_dir, launcher, name, first, minutes)
    except submitit.core.utils.FailedJobError as error:
        return (f"{held}, nor the job that would submit them ({one_line(error)[-160:]}); launch "
                "again (or resubmit) once the queue has room")
    return f"{held}: job {feeder} submits them once array {first} has ended, and so on until all are in"


def refuse_for_setting(sweep_dir: Path, submission: Submission, flags: list[str]) -> None:
    """Raise a ConfigError when sbatch refused an array for one of the launcher's settings (a partition, an
    account, an array size the cluster does not take; of ``flags``, launcher.extra_sbatch's, the one it is about):
    one line with its reason, what went in before, and the resubmit that runs the rest with the setting corrected.
    A refusal for room (job limits) returns."""
    assert submission.refusal is not None
    setting = refused_setting(submission.refusal, queued_jobs(user_only=True))
    if setting is None:
        return
    went_in = (f"{sum(submission.arrays.values()):,} jobs in {', '.join(submission.arrays)} went in before it"
               if submission.arrays else "nothing was submitted")
    if setting == "launcher.extra_sbatch":
        flag = refused_flag(submission.refusal, flags)
        setting = f"{setting}.{flag}" if flag else setting
        corrected = f"+launcher.extra_sbatch.{flag or '<flag>'}=<value or null>"
    else:
        corrected = f"{setting}=<value>"
    raise ConfigError(f"sbatch refused the jobs ({submission.refusal.replace('sbatch: error: ', '')}): change "
                      f"{setting}; {went_in}: python -m nsl_hpc.resubmit sweep_dir={sweep_dir} {corrected} "
                      "runs the rest")


def limit_threads(threads: int) -> None:
    """Hold the OpenMP and BLAS pools of every job this process starts (local workers inherit its environment,
    SLURM jobs too: sbatch exports it) at ``threads``: a task's torch uses ``threads`` intra-op threads, and numpy
    would otherwise start one per core of the node, oversubscribing the job's single CPU."""
    for variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[variable] = str(threads)


def run_jobs(sweep_dir: Path, settings: LaunchSettings, packs: Sequence[Pack], tasks: Sequence[Mapping[str, Any]],
             configs: Mapping[tuple[str, str], Pair], limits: ClusterLimits | None = None) -> int:
    """Run the planned ``packs`` of ``tasks`` (manifest rows) with the launch's ``settings`` (within the cluster's
    ``limits``): the data they share first (none in a rehearsal), the run settings recorded in run.yaml, then
    ``dispatch``; returns its exit status."""
    if not settings.rehearsal:  # a rehearsal's tasks read no data
        prepare_shared_data(tasks, configs, study_named(settings.study.name))
    write_run_settings(sweep_dir, settings.values)
    limit_threads(settings.threads)
    return dispatch(sweep_dir, packs, settings.launcher, settings.sweep.name, settings.watchdog.worker_silence_s,
                    limits)
