"""Where every task of a sweep stands, from the manifest, the rows and failure records on disk, and one
``squeue`` and one ``sacct`` call for all of the sweep's arrays."""

import time
from collections import Counter
from collections.abc import Collection, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.compute as pc

from nsl_hpc.sweep.decisions import budget_states, without_row_state
from nsl_hpc.sweep.directory import launch_running
from nsl_hpc.sweep.failures import read_failures
from nsl_hpc.sweep.groups import running_task_ids
from nsl_hpc.sweep.manifest import read_manifest
from nsl_hpc.sweep.rows import row_states
from nsl_hpc.sweep.slurm import ACTIVE_JOB_STATES, job_states, require_cluster
from nsl_hpc.sweep.submissions import predicted_shares, read_submissions, submitted_clusters

ACCOUNTING_LAG_S = 30  # without the queue's answer, a just-submitted job may take a while to appear in sacct
STATES = ("done", "running", "pending", "failed", "frozen", "timeout", "missing", "corrupt", "skipped", "waiting")


@dataclass(frozen=True)
class SweepState:
    """Each task's state (one of STATES), the failure records behind the failed ones, the state of every array
    element of the sweep (slurm.job_states) and, when the accounting database did not answer, why."""

    states: dict[str, str]
    failures: dict[str, dict[str, Any]]
    manifest: pa.Table  # task_id, system, arch, seed, width, depth, steps, params
    element_states: dict[str, str]
    not_done: frozenset[str]  # the tasks in a state other than done
    unaccounted: str | None = None
    predicted_s: dict[str, float] = field(default_factory=dict)  # predicted seconds of the submitted not_done ones

    @cached_property
    def counts(self) -> Counter[str]:
        """How many tasks are in each state."""
        return Counter(self.states.values())

    def tasks_in(self, wanted: Collection[str]) -> list[dict[str, Any]]:
        """The manifest rows of the tasks in one of the ``wanted`` states, in the manifest's order."""
        ids = pa.array([task_id for task_id in self.not_done if self.states[task_id] in wanted] if "done" not in wanted
                       else [task_id for task_id, state in self.states.items() if state in wanted], pa.string())
        return self.manifest.filter(pc.is_in(self.manifest["task_id"], value_set=ids)).to_pylist()

    def accounting_note(self) -> str | None:
        """One line on what the states cannot tell apart without accounting; None with it."""
        if self.unaccounted is None:
            return None
        return (f"accounting did not answer ({self.unaccounted[:160]}): states come from the queue, the rows, the "
                "failure records and the group locks; a job that ended without a row or a failure record counts "
                "as missing (cancelled, out of memory, a lost node or a job never started cannot be told apart)")


def read_sweep_state(sweep_dir: Path, queue_required: bool = True) -> SweepState:
    """Classify every task: a valid row means done; else running while a live job holds its group's lock (local
    workers included); else its latest array element's state while that is active (the controller's while it
    holds the element, so a job accounting has not recorded yet is never missing); else its failure record
    written since that submission (failed, frozen, timeout); else pending while a launch or resubmit holds the
    sweep (a local one runs it later); else missing. A file where its row belongs that is no valid row makes it
    corrupt. In a budgeted sweep a missing task is skipped where its round decided not to run it, and waiting
    while its round is not decided. Without ``queue_required`` a queue that does not answer (no SLURM on this
    machine) is reported in ``unaccounted`` like the accounting database, not raised."""
    sweep_dir = Path(sweep_dir)
    manifest = read_manifest(sweep_dir, columns=["task_id", "system", "arch", "seed", "width", "depth", "steps",
                                                 "params"])
    states = row_states(sweep_dir, manifest["task_id"].to_pylist())  # then each not_done task's own state
    not_done = frozenset(task_id for task_id, row in states.items() if row != "done")
    failures = read_failures(sweep_dir)
    latest: dict[str, tuple[str, float]] = {}  # not_done task -> (array element, submission time)
    submissions = read_submissions(sweep_dir)
    require_cluster(submitted_clusters(submissions))  # another cluster's queue knows none of its jobs
    for record in submissions:
        for element, task_ids in zip(record["element_ids"], record["elements"], strict=True):
            for task_id in not_done.intersection(task_ids):
                latest[task_id] = (element, record["submitted"])
    elements = job_states((record["array_id"] for record in submissions), queue_required)
    now = time.time()
    running, launching = running_task_ids(sweep_dir), launch_running(sweep_dir)
    budgeted = budget_states(sweep_dir)
    for task_id in not_done:
        row = states[task_id]
        element, submitted = latest.get(task_id, (None, 0.0))
        if row == "missing" and task_id in running:
            states[task_id] = "running"
            continue
        states[task_id] = task_state(row, failures.get(task_id), element, submitted,
                                     elements.states.get(element or ""), now, elements.queue_answered)
        if states[task_id] == "missing":
            states[task_id] = without_row_state(budgeted, task_id, launching)
    return SweepState(states, failures, manifest, elements.states, not_done, elements.unaccounted,
                      predicted_shares(submissions, not_done))


def task_state(row: str, failure: Mapping[str, Any] | None, element: str | None, submitted: float,
               element_state: str | None, now: float, queue_answered: bool = True) -> str:
    """One task's state (of STATES) from its row's state (done, corrupt, missing), its failure record, the
    array element it was last submitted to (None: never) at time ``submitted`` (s since the epoch) and that
    element's state (slurm.job_states; None: neither queued nor in the accounting database). A submitted element
    with no state is missing once the queue has answered (the controller holds every job it accepted); without
    the queue's answer it is pending for ACCOUNTING_LAG_S after its submission."""
    if row != "missing":
        return row  # done, or corrupt: the task ran to the end and its row was damaged since
    if failure is not None and failure["time"] >= submitted:
        return failure["status"]
    if element_state in ACTIVE_JOB_STATES:
        return ACTIVE_JOB_STATES[element_state]
    if element is not None and element_state is None and not queue_answered and now - submitted < ACCOUNTING_LAG_S:
        return "pending"  # submitted, not yet in the accounting database
    return "missing"
