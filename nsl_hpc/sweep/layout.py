"""The sweep directory's layout: the one place that names its files and folders.

    <sweep_dir>/
      manifest.parquet                    the tasks, one row each (sweep/manifest.py)
      launch.yaml, run.yaml               the launch config; the run settings a resubmit may change
      configs/<system>__<arch>.yaml       the config every task of a (system, arch) pair shares
      rows/<id[:2]>/<id>.parquet          a finished task's row: its lockstep group's file of rows, which each of
                                          the group's paths names (under out_dir, the sweep dir by default)
      rows/compacted/<part>.parquet       rows merge has moved out of their own files, many per file
      corrupt/                            rows that were not whole Parquet files of their task, set aside
      failures/<id[:2]>/<id>.json         why a task has no row (failed, frozen, timeout)
      logs/<id[:2]>/<id>.log              the output of a task's latest attempt
      checkpoints/<key[:2]>/<key>.pt      a lockstep group's training state (.json: its description, .lock: the
                                          job training it; .unreadable / .mismatched: set aside)
      submitit/<array id>/, submitit/local/<job id>/   submitit's pickled jobs and their logs
      submissions/<array id>.json         what was submitted to SLURM
      cache/                              simulated trajectories (cache_dir)
      compile_cache/                      Inductor's compiled training steps (compile_cache_dir)
      budget/round-<r>.parquet            a budgeted sweep's decisions: which tasks of round r run (sweep/decisions.py)
      budget/round_job.json               the SLURM job that launches its next round
      rehearsal/kill-<task id>            a rehearsal's job to kill (then killed-<task id>; sweep/rehearsal.py)
      .lock                               the command that changes the sweep now (launch, resubmit, clean)
      .lock.held                          ... its lock where the file system takes no flock
      results.parquet, merge_summary.json, dropped.parquet, .merge_cache.parquet   merge
      nsl_fits.parquet, nsl_fits.txt                            fit
      law_cards/<system>__<arch>__<resource>__<metric>.json    fit: a card per law (analysis/cards.py)
      report.html, comparison.md, figures/, mlflow.db, mlartifacts/   report

Ids and keys are bucketed by their first two characters, so 63k files do not share one directory.
"""

import os
from pathlib import Path

MANIFEST = "manifest.parquet"
LAUNCH_CONFIG = "launch.yaml"
RUN_SETTINGS = "run.yaml"
CONFIGS = "configs"
ROWS = "rows"
COMPACTED = "compacted"  # rows/compacted/: merge's files of many rows (sweep/rows.py)
CORRUPT = "corrupt"
FAILURES = "failures"
LOGS = "logs"
CHECKPOINTS = "checkpoints"
SUBMITIT = "submitit"
SUBMITIT_LOCAL = "local"  # submitit/local/: the local launcher's jobs
SUBMISSIONS = "submissions"
LOCK = ".lock"
LOCK_HELD = ".lock.held"  # the lock where the file system takes no flock
RESULTS = "results.parquet"
MERGE_SUMMARY = "merge_summary.json"
DROPPED = "dropped.parquet"  # the tasks merge dropped, each with its state and reason
FITS = "nsl_fits.parquet"
FITS_TEXT = "nsl_fits.txt"
LAW_CARDS = "law_cards"
REPORT = "report.html"
COMPARISON = "comparison.md"
FIGURES = "figures"
MLFLOW_DB = "mlflow.db"
MLFLOW_ARTIFACTS = "mlartifacts"
BUDGET = "budget"
REHEARSAL = "rehearsal"  # a rehearsal's own records (the jobs it killed once)
CODE = "code.json"  # the code the sweep's rows are made by: the package's version and each user module's hash
MERGE_CACHE = ".merge_cache.parquet"  # merge's read rows, so a second merge reads only new ones
ROW_CHECKS = ".row_checks.parquet"  # each own row file's state, with its inode: read once (sweep/listing.py)
FAILURE_CHECKS = ".failure_checks.parquet"  # each failure record, with its file's inode: read once
PAUSED = "paused-{point}"  # test-only: where a job paused (fault.kind=pause), for the test that signals it there

CONTROL = (SUBMITIT, LAUNCH_CONFIG, RUN_SETTINGS, CONFIGS, MANIFEST)  # what decides the code a sweep's jobs run
# what clean keeps
RECORDS = (MANIFEST, LAUNCH_CONFIG, RUN_SETTINGS, CONFIGS, CODE, ROWS, CORRUPT, SUBMISSIONS, LOCK, BUDGET, REHEARSAL,
           RESULTS, DROPPED, FITS, FITS_TEXT, LAW_CARDS, REPORT, COMPARISON, FIGURES, MLFLOW_DB, MLFLOW_ARTIFACTS,
           MERGE_CACHE, ROW_CHECKS, FAILURE_CHECKS)


def bucketed(folder: str | os.PathLike, name: str, suffix: str) -> Path:
    """``<folder>/<name[:2]>/<name><suffix>``, one Path built (status builds one per task)."""
    return Path(os.path.join(folder, name[:2], name + suffix))


def row_file(out_dir: str | os.PathLike, task_id: str) -> str:
    """``row_path`` as a string: status checks 63k rows, and a Path costs more than the check (15 us)."""
    return os.path.join(out_dir, ROWS, task_id[:2], task_id + ".parquet")


def pause_marker(sweep_dir: str | os.PathLike, point: str) -> Path:
    """Test-only: the file a job writes where it pauses (``fault.kind=pause``), before it sleeps."""
    return Path(sweep_dir) / PAUSED.format(point=point)


def row_path(out_dir: str | os.PathLike, task_id: str) -> Path:
    return Path(row_file(out_dir, task_id))


def compacted_dir(out_dir: str | os.PathLike) -> Path:
    return Path(out_dir) / ROWS / COMPACTED


def failure_path(sweep_dir: str | os.PathLike, task_id: str) -> Path:
    return bucketed(os.path.join(sweep_dir, FAILURES), task_id, ".json")


def task_log_path(sweep_dir: str | os.PathLike, task_id: str) -> Path:
    return bucketed(os.path.join(sweep_dir, LOGS), task_id, ".log")


def checkpoint_file(sweep_dir: str | os.PathLike, key: str) -> Path:
    """The checkpoint of the lockstep group whose key (a hash of its task ids) is ``key``."""
    return bucketed(Path(sweep_dir) / CHECKPOINTS, key, ".pt")


def base_config_path(sweep_dir: str | os.PathLike, system: str, arch: str) -> Path:
    return Path(sweep_dir) / CONFIGS / f"{system}__{arch}.yaml"


def submission_path(sweep_dir: str | os.PathLike, array_id: str) -> Path:
    return Path(sweep_dir) / SUBMISSIONS / f"{array_id}.json"


def local_jobs_folder(sweep_dir: str | os.PathLike) -> Path:
    """submitit's folder of the local launcher's jobs (one subfolder per job)."""
    return Path(sweep_dir) / SUBMITIT / SUBMITIT_LOCAL


def round_decisions_path(sweep_dir: str | os.PathLike, number: int) -> Path:
    """The decisions of a budgeted sweep's round ``number``."""
    return Path(sweep_dir) / BUDGET / f"round-{number:03d}.parquet"


def law_state_path(sweep_dir: str | os.PathLike, number: int) -> Path:
    """The laws' widths on the rows of a budgeted sweep's rounds up to ``number`` (analysis/widths.py)."""
    return Path(sweep_dir) / BUDGET / f"laws-{number:03d}.json"


def round_job_path(sweep_dir: str | os.PathLike) -> Path:
    return Path(sweep_dir) / BUDGET / "round_job.json"
