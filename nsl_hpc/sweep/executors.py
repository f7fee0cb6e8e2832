"""Running packs with submitit: SLURM job arrays split within the cluster's limits (returns once
submitted), or local / in-process executors in the foreground with a progress bar."""

import contextlib
import itertools
import os
import shutil
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import submitit
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from nsl_hpc.errors import RunError
from nsl_hpc.studies import study_named
from nsl_hpc.sweep.job import JobRunner
from nsl_hpc.sweep.launchers import DebugLauncher, Launcher, LocalLauncher, SlurmLauncher, launcher_from
from nsl_hpc.sweep.manifest import write_run_settings
from nsl_hpc.sweep.plan import Group, Pack
from nsl_hpc.sweep.prepare import prepare_shared_data
from nsl_hpc.sweep.rows import row_path, row_state
from nsl_hpc.sweep.slurm import queued_jobs, read_limits
from nsl_hpc.sweep.submissions import record_submission


@dataclass(frozen=True)
class Submission:
    """What a launch handed to SLURM: arrays (id -> element count) and the packs left for later."""

    arrays: dict[str, int]
    left: list[Pack]
    refusal: str | None = None  # sbatch's message when it refused an array


def submit_to_slurm(sweep_dir: Path, packs: Sequence[Pack], launcher: SlurmLauncher, name: str) -> Submission:
    """Submit ``packs`` as job arrays, one time limit per array, indices from 0, within the limits."""
    limits = read_limits(launcher)
    room = limits.max_job_count - queued_jobs(user_only=False)
    if limits.max_submit_jobs is not None:
        room = min(room, limits.max_submit_jobs - queued_jobs(user_only=True))
    ordered = sorted(packs, key=lambda pack: pack.time_limit_min)
    now, left = ordered[:max(room, 0)], ordered[max(room, 0):]
    chunks = array_chunks(now, limits.max_array_size)
    arrays = {}
    for index, chunk in enumerate(chunks):
        try:
            arrays[submit_array(sweep_dir, chunk, chunk[0].time_limit_min, launcher, name)] = len(chunk)
        except submitit.core.utils.FailedJobError as error:  # e.g. the controller is full: keep what went in
            refused = [pack for later in chunks[index:] for pack in later]
            return Submission(arrays, refused + left, refusal=" ".join(str(error).split())[-300:])
    return Submission(arrays, left)


def array_chunks(packs: Sequence[Pack], max_array_size: int) -> list[list[Pack]]:
    """``packs`` (sorted by time limit) cut into arrays of one time limit and at most ``max_array_size``."""
    chunks = []
    for _, same_limit in itertools.groupby(packs, key=lambda pack: pack.time_limit_min):
        group = list(same_limit)
        chunks += [group[start:start + max_array_size] for start in range(0, len(group), max_array_size)]
    return chunks


def slurm_executor(sweep_dir: Path, time_limit_min: int, launcher: SlurmLauncher, name: str, chain: int = 1
                   ) -> submitit.SlurmExecutor:
    """The submitit executor of one array: single-CPU elements of one time limit, warned before it, each
    requeued up to ``chain`` + 2 times at its time limit (a chain of ``chain`` jobs, and some slack)."""
    executor = submitit.SlurmExecutor(folder=sweep_dir / "submitit" / "%A", max_num_timeout=chain + 2)
    executor.update_parameters(
        job_name=f"nsl-{name}", time=time_limit_min, cpus_per_task=1, ntasks_per_node=1, mem=launcher.mem,
        partition=launcher.partition, account=launcher.account, qos=launcher.qos,
        array_parallelism=launcher.array_parallelism, signal_delay_s=launcher.signal_delay_s,
        additional_parameters=dict(launcher.extra_sbatch), setup=list(launcher.setup),
        stderr_to_stdout=True)
    return executor


def submit_array(sweep_dir: Path, packs: Sequence[Pack], time_limit_min: int, launcher: SlurmLauncher,
                 name: str) -> str:
    """One array of single-CPU elements, element i running ``packs[i]``; returns the array job id."""
    executor = slurm_executor(sweep_dir, time_limit_min, launcher, name, max(pack.chain for pack in packs))
    jobs = executor.map_array(JobRunner(), [str(sweep_dir)] * len(packs), [list(pack.groups) for pack in packs])
    array_id = jobs[0].job_id.split("_")[0]  # a single element is a plain job: its id has no _<index>
    record_submission(sweep_dir, array_id, time_limit_min, [job.job_id for job in jobs],
                      [pack.task_ids for pack in packs])
    return array_id


def balance(packs: Sequence[Pack], workers: int) -> list[list[Group]]:
    """The lockstep groups of ``packs`` spread over ``workers`` lists of about equal predicted time (longest
    first)."""
    groups = [group for pack in packs for group in pack.groups]
    seconds, shares = [0.0] * min(workers, len(groups)), [[] for _ in range(min(workers, len(groups)))]
    for group in sorted(groups, key=lambda group: -group.seconds):
        lightest = seconds.index(min(seconds))
        seconds[lightest] += group.seconds
        shares[lightest].append(group)
    return shares


def run_locally(sweep_dir: Path, packs: Sequence[Pack], launcher: LocalLauncher | DebugLauncher) -> dict[str, int]:
    """Run ``packs`` on this machine (local: parallel processes; debug: in-process) and wait, with a progress
    bar over tasks; returns counts by outcome."""
    debug = isinstance(launcher, DebugLauncher)
    workers = launcher.workers or os.cpu_count() or 1
    shares = balance(packs, workers)
    task_ids = [task_id for share in shares for group in share for task_id in group.task_ids]
    folder = sweep_dir / "submitit" / "local" / "%j"
    if debug:
        executor = submitit.DebugExecutor(folder=folder)
    else:
        executor = submitit.LocalExecutor(folder=folder)
        executor.update_parameters(timeout_min=int(sum(p.seconds for p in packs) * 10 / 60) + 60)
    runner = JobRunner(None if debug else os.getpid())  # workers die with this process
    jobs = executor.map_array(runner, [str(sweep_dir)] * len(shares), shares)
    counts: dict[str, int] = {}
    try:
        with tqdm(total=len(task_ids), desc="tasks", unit="task", disable=None) as bar:
            pending = list(jobs)
            while pending:
                if debug:
                    finished = [pending.pop(0)]
                else:
                    time.sleep(1.0)
                    finished = [job for job in pending if job.done()]
                    pending = [job for job in pending if not job.done()]
                for job in finished:
                    for outcome, n in job_result(job).items():
                        counts[outcome] = counts.get(outcome, 0) + n
                bar.n = sum(row_state(row_path(sweep_dir, task_id)) == "done" for task_id in task_ids)
                bar.refresh()
    except KeyboardInterrupt:
        for job in jobs:
            with contextlib.suppress(Exception):
                job.cancel()
        raise RunError("interrupted: the running tasks were stopped, finished rows are kept; launch again to run "
                       "the rest") from None
    return counts


def job_result(job: submitit.Job) -> dict[str, int]:
    """A local job's counts by outcome; a job that ended without a result (its process killed, a full disk) is a
    one-line RunError."""
    try:
        return job.result()
    except (submitit.core.utils.UncompletedJobError, submitit.core.utils.FailedJobError) as error:
        disk = shutil.disk_usage(job.paths.folder)
        raise RunError(f"a local job ended without its result ({' '.join(str(error).split())[:160]}); "
                       f"{disk.free / 2**20:.0f} MiB free where it writes: free space if that is the cause, then "
                       "launch again (finished rows are kept)") from None


def dispatch(sweep_dir: Path, packs: Sequence[Pack], launcher: Launcher, name: str) -> int:
    """Submit ``packs`` (launcher slurm) or run them here, print what happened; returns the exit status:
    1 when a task ran here and did not finish."""
    sweep_dir = Path(sweep_dir).resolve()  # jobs find it from anywhere
    if isinstance(launcher, SlurmLauncher):
        submission = submit_to_slurm(sweep_dir, packs, launcher, name)
        elements = sum(submission.arrays.values())
        print(f"submitted {elements:,} jobs in {len(submission.arrays)} arrays: {', '.join(submission.arrays)}")
        if submission.refusal:
            print(f"sbatch refused the next array: {submission.refusal}")
        if submission.left:
            print(f"the cluster's job limits hold no more now: {len(submission.left):,} jobs "
                  f"({sum(len(p.task_ids) for p in submission.left):,} tasks) were not submitted; launch "
                  "again (or resubmit) once the queue has room")
        return 0
    counts = run_locally(sweep_dir, packs, launcher)
    print("finished: " + ", ".join(f"{n:,} {outcome}" for outcome, n in sorted(counts.items())))
    return 0 if set(counts) <= {"ok", "skipped"} else 1


def limit_threads(threads: int) -> None:
    """Hold the OpenMP and BLAS pools of every job this process starts (local workers inherit its environment,
    SLURM jobs too: sbatch exports it) at ``threads``: a task's torch uses ``threads`` intra-op threads, and numpy
    would otherwise start one per core of the node, oversubscribing the job's single CPU."""
    for variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[variable] = str(threads)


def run_jobs(sweep_dir: Path, launch: DictConfig, packs: Sequence[Pack], tasks: Sequence[Mapping[str, Any]],
             configs: Mapping[tuple[str, str], Mapping[str, Any]]) -> int:
    """Run the planned ``packs`` of ``tasks`` (manifest rows) with the run settings ``launch``: the data they
    share first, the settings recorded in run.yaml, then ``dispatch``; returns its exit status."""
    prepare_shared_data(tasks, configs, study_named(launch.study.name))
    write_run_settings(sweep_dir, launch)
    limit_threads(OmegaConf.select(launch, "threads", default=1))
    return dispatch(sweep_dir, packs, launcher_from(launch.launcher), launch.sweep.name)
