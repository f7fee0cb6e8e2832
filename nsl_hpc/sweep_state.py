"""Where every task of a sweep stands, from the manifest, the rows and failure records on disk, and
one ``sacct`` call for all of the sweep's arrays."""

import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from nsl_hpc.failures import read_failures
from nsl_hpc.manifest import read_manifest
from nsl_hpc.rows import row_path, row_state
from nsl_hpc.slurm import job_states
from nsl_hpc.submissions import read_submissions

ACCOUNTING_LAG_S = 30  # a just-submitted job may take a while to appear in sacct (slurmdbd restarts, load)
STATES = ("done", "running", "pending", "failed", "frozen", "timeout", "missing", "corrupt")
ACTIVE_JOB_STATES = {"RUNNING": "running", "COMPLETING": "running", "PENDING": "pending", "REQUEUED": "pending",
                     "CONFIGURING": "running", "RESIZING": "running", "SUSPENDED": "pending"}


@dataclass(frozen=True)
class SweepState:
    """Each task's state (one of STATES), the failure records behind the failed ones and the sacct
    state of every array element of the sweep."""

    states: dict[str, str]
    failures: dict[str, dict[str, Any]]
    manifest: list[dict[str, Any]]
    element_states: dict[str, str]

    def counts(self) -> Counter[str]:
        return Counter(self.states.values())


def read_sweep_state(sweep_dir: Path) -> SweepState:
    """Classify every task: a valid row means done; else its latest array element's state while that is active;
    else its failure record written since that submission (failed, frozen, timeout); else missing. A file
    where its row belongs that is no valid row makes it corrupt."""
    sweep_dir = Path(sweep_dir)
    manifest = read_manifest(sweep_dir, columns=["task_id", "system", "arch", "seed", "width", "depth", "steps",
                                                 "params"])
    failures = read_failures(sweep_dir)
    latest: dict[str, tuple[str, float]] = {}  # task -> (array element, submission time)
    submissions = read_submissions(sweep_dir)
    for record in submissions:
        for element, task_ids in zip(record["element_ids"], record["elements"], strict=True):
            for task_id in task_ids:
                latest[task_id] = (element, record["submitted"])
    element_states = job_states(record["array_id"] for record in submissions) if submissions else {}
    states = {}
    for task_id in manifest["task_id"].to_pylist():
        row = row_state(row_path(sweep_dir, task_id))
        if row != "missing":
            states[task_id] = row  # done, or corrupt: the task ran to the end and its row was damaged since
            continue
        element, submitted = latest.get(task_id, (None, 0.0))
        failure = failures.get(task_id)
        if failure is not None and failure["time"] >= submitted:
            states[task_id] = failure["status"]
        elif element in element_states and element_states[element] in ACTIVE_JOB_STATES:
            states[task_id] = ACTIVE_JOB_STATES[element_states[element]]
        elif element is not None and element not in element_states and time.time() - submitted < ACCOUNTING_LAG_S:
            states[task_id] = "pending"  # submitted, not yet in the accounting database
        else:
            states[task_id] = "missing"
    return SweepState(states, failures, manifest.to_pylist(), element_states)
