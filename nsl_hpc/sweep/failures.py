"""Records of tasks that did not produce a row: why (failed, frozen, timeout) and the end of their log.

``<sweep_dir>/failures/<id[:2]>/<id>.json`` holds the latest failure of a task and
``<sweep_dir>/logs/<id[:2]>/<id>.log`` the output of its latest attempt (removed when the task succeeds).
A row always wins: a task with a row is done, whatever failures it had before.
"""

import json
import os
import socket
import time
from pathlib import Path
from typing import Any

import pyarrow as pa

from nsl_hpc.core.atomic import write_text
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.layout import failure_path, task_log_path
from nsl_hpc.sweep.listing import read_listed

FAILURE_STATES = ("failed", "frozen", "timeout")
RECORD_SCHEMA = pa.schema([("status", pa.string()), ("reason", pa.string()), ("host", pa.string()),
                           ("job_id", pa.string()), ("time", pa.float64()), ("log_tail", pa.string())])


def log_tail(path: Path, lines: int = 20) -> str:
    """The last ``lines`` lines of a log ('' when there is none)."""
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except FileNotFoundError:
        return ""


def record_failure(sweep_dir: Path, task_id: str, status: str, reason: str) -> None:
    """Write (replace) the failure record of a task; ``status`` is one of FAILURE_STATES."""
    assert status in FAILURE_STATES, status
    record = {"task_id": task_id, "status": status, "reason": reason, "host": socket.gethostname(),
              "job_id": os.environ.get("SLURM_JOB_ID"), "time": time.time(),
              "log_tail": log_tail(task_log_path(sweep_dir, task_id))}
    write_text(json.dumps(record), failure_path(sweep_dir, task_id))


def read_failures(sweep_dir: Path) -> dict[str, dict[str, Any]]:
    """Every failure record of a sweep by task id (unreadable records are skipped), each file read once while it
    is the same file (``listing.read_listed``)."""
    table = read_listed(os.path.join(sweep_dir, layout.FAILURES), ".json", Path(sweep_dir) / layout.FAILURE_CHECKS,
                        RECORD_SCHEMA, lambda path, _inode: read_record(path))
    return {record["task_id"]: record for record in table.drop_columns(["ino"]).to_pylist()}


def read_record(path: str) -> dict[str, Any] | None:
    """The failure record at ``path``; None where it is unreadable or no record (not a JSON object)."""
    try:
        with open(path, encoding="utf-8") as file:
            record = json.load(file)
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None
