"""The one seam to SLURM's commands: cluster limits, queue size and accounting (``sacct``)."""

import getpass
import os
import re
import subprocess
import time
from collections.abc import Iterable
from dataclasses import dataclass

from nsl_hpc.core.errors import ConfigError, SlurmError


class SlurmMissing(ConfigError):
    """This machine has no SLURM client commands."""


def slurm_command(*args: str, retries: int = 3, backoff_s: float = 2.0) -> str:
    """stdout of a SLURM command; retried with exponential back-off (controllers rate-limit clients)."""
    for attempt in range(retries):
        try:
            result = subprocess.run(args, capture_output=True, text=True, timeout=120)
        except FileNotFoundError:
            raise SlurmMissing(f"{args[0]} not found: launcher=slurm needs SLURM's client commands; run this on the "
                               "cluster's login node (or use launcher=local on this machine)") from None
        if result.returncode == 0:
            return result.stdout
        if attempt + 1 < retries:
            time.sleep(backoff_s * 2**attempt)
    lines = [line.strip() for line in result.stderr.splitlines() if line.strip()] or ["no message"]
    raise SlurmError(f"{args[0]} failed: {lines[-1].removeprefix(f'{args[0]}: ').removeprefix('error: ')}")


def cluster_name() -> str:
    """The ClusterName of the cluster this machine's SLURM commands answer for (SLURM_CONF names another's)."""
    for line in slurm_command("scontrol", "show", "config").splitlines():
        key, _, value = line.partition("=")
        if key.strip() == "ClusterName":
            return value.strip()
    return ""


def require_cluster(submitted: set[str]) -> None:
    """Refuse, in one line, to read or submit a sweep's jobs through another cluster than the one they were
    submitted to (``submitted``: their ClusterNames); nothing to check without SLURM's commands."""
    if not submitted:
        return
    try:
        here = cluster_name()
    except (SlurmMissing, SlurmError):
        return  # no cluster answers here: the queue is reported unknown where it is read
    if here and here not in submitted:
        conf = os.environ.get("SLURM_CONF")
        raise ConfigError(f"this sweep's jobs were submitted to cluster {', '.join(sorted(submitted))}, and SLURM here "
                          f"answers for cluster {here}" + (f" (SLURM_CONF={conf})" if conf else "") + ": run this "
                          f"where SLURM answers for {', '.join(sorted(submitted))} (set SLURM_CONF to its "
                          "configuration)")


def queued_jobs(user_only: bool, qos: str = "") -> int:
    """Jobs (array elements expanded) that count against a limit: this user's pending and running ones
    (MaxSubmitJobs; ``qos``: of that QOS only, for its MaxSubmitJobsPerUser), or every job record the controller
    holds (MaxJobCount: finished jobs count until MinJobAge purges them)."""
    args = ["squeue", "-h", "-r", "-o", "%i"] + (["-u", getpass.getuser()] if user_only else ["-t", "all"])
    return len(slurm_command(*args, *(["-q", qos] if qos else [])).split())


def held_arrays(array_ids: Iterable[str]) -> list[str]:
    """Those of ``array_ids`` (array job ids) the controller holds now: one of their elements is pending or running."""
    held = {line.strip() for line in slurm_command("squeue", "-h", "-u", getpass.getuser(), "-o", "%F").split()}
    return [array_id for array_id in array_ids if array_id in held]


# Every state in which SLURM still holds a job (it has not ended: sacct's and squeue's long names) -> the state of
# the tasks it holds: a job that is stopped, suspended, held for a requeue or finishing its epilog still has them
ACTIVE_JOB_STATES = {"RUNNING": "running", "COMPLETING": "running", "CONFIGURING": "running", "RESIZING": "running",
                     "SIGNALING": "running", "STAGE_OUT": "running", "STOPPED": "running", "SUSPENDED": "pending",
                     "PENDING": "pending", "REQUEUED": "pending", "REQUEUE_HOLD": "pending", "REQUEUE_FED": "pending",
                     "RESV_DEL_HOLD": "pending", "SPECIAL_EXIT": "pending"}


@dataclass(frozen=True)
class JobStates:
    """The state of every array element of some jobs: the controller's (``squeue``) while it holds them, the
    accounting database's (``sacct``) once they ended; ``unaccounted``: why sacct did not answer (accounting
    disabled or down: ended jobs then have no state), None when it did."""

    states: dict[str, str]
    unaccounted: str | None = None
    queue_answered: bool = True  # squeue answered: an element it does not hold has ended


def job_states(job_ids: Iterable[str], queue_required: bool = True) -> JobStates:
    """State of every array element of ``job_ids`` (array job ids): one ``squeue`` call for this user's jobs and
    one ``sacct`` call, whose failure is reported, not raised; so is squeue's unless ``queue_required`` (what would
    submit a task again must know the queue). The queue is the truth for what has not ended (merged_states)."""
    ids = sorted(set(job_ids))
    if not ids:
        return JobStates({})
    try:
        accounted = parse_states(slurm_command("sacct", "-n", "-P", "-X", "-j", ",".join(ids),
                                               "--format=JobID,State", retries=2))
        unaccounted = None
    except (SlurmError, SlurmMissing) as error:
        accounted, unaccounted = {}, str(error)
    try:
        queued: dict[str, str] | None = parse_states(slurm_command("squeue", "-h", "-r", "-u", getpass.getuser(),
                                                                   "-o", "%i|%T"))
    except (SlurmError, SlurmMissing) as error:
        if queue_required:
            raise
        queued, unaccounted = None, str(error)
    return JobStates(merged_states(accounted, queued, set(ids)), unaccounted, queued is not None)


def merged_states(accounted: dict[str, str], queued: dict[str, str] | None, job_ids: set[str]) -> dict[str, str]:
    """Element -> state: the controller's (``queued``, squeue) for the elements of ``job_ids`` it holds, the
    accounting database's (``accounted``, sacct) for the others. Once the queue has answered, an element it does not
    hold has ended, so an active state sacct still gives it (a record slurmdbd has not updated) is stale and
    dropped; ``queued`` None: the queue did not answer, sacct's states stand."""
    if queued is None:
        return dict(accounted)
    ended = {element: state for element, state in accounted.items() if state not in ACTIVE_JOB_STATES}
    return ended | {element: state for element, state in queued.items() if element.split("_")[0] in job_ids}


def parse_states(output: str) -> dict[str, str]:
    """Element id -> state of ``JobID|State`` lines (sacct, squeue), array ranges expanded."""
    states = {}
    for line in output.splitlines():
        job_id, state = line.split("|")[:2]
        for element in expand_array_ids(job_id):
            states[element] = state.split()[0]  # "CANCELLED by 0" -> CANCELLED
    return states


def expand_array_ids(job_id: str) -> list[str]:
    """'12_[0-2,5%4]' -> ['12_0', '12_1', '12_2', '12_5'] (pending elements are listed as ranges)."""
    match = re.fullmatch(r"(\d+)_\[([^\]]+)\]", job_id)
    if not match:
        return [job_id]
    elements = []
    for part in match.group(2).split("%")[0].split(","):
        first, _, last = part.partition("-")
        elements += [f"{match.group(1)}_{i}" for i in range(int(first), int(last or first) + 1)]
    return elements


# What sbatch says when it refuses a job for a setting (lowercase fragment -> the launcher key to change), first
# match first: "invalid account or account/partition combination" names the account; any other refusal is for room
# (the controller's or the user's job limits) and passes once jobs end.
REFUSED_SETTINGS = (("account", "launcher.account"), ("partition", "launcher.partition"),
                    ("invalid qos", "launcher.qos"), ("array specification", "launcher.max_array_size"),
                    ("time limit", "launcher.max_time_minutes"), ("memory", "launcher.mem"),
                    ("node configuration", "launcher.extra_sbatch"), ("node count", "launcher.extra_sbatch"),
                    ("feature specification", "launcher.extra_sbatch"), ("gres", "launcher.extra_sbatch"),
                    ("unrecognized option", "launcher.extra_sbatch"), ("invalid option", "launcher.extra_sbatch"))
ROOM_REFUSALS = ("temporarily", "job submit limit", "maxsubmit", "maxjobcount", "job count")


# fragments of an sbatch refusal -> the flag of launcher.extra_sbatch it is about
REFUSED_FLAGS = (("feature specification", "constraint"), ("gres", "gres"), ("node count", "nodes"),
                 ("node configuration", "constraint"))


def refused_flag(message: str, flags: list[str]) -> str | None:
    """The flag of ``flags`` (launcher.extra_sbatch's) an sbatch refusal of one of them is about: the one it names
    (--flag), the one its reason belongs to, or the only one; None where that cannot be told."""
    named = [flag for flag in flags if re.search(rf"--{re.escape(flag.replace('_', '-'))}\b", message)]
    kinds = [flag for fragment, flag in REFUSED_FLAGS if fragment in message.lower() and flag in flags]
    candidates = named or kinds or (flags if len(flags) == 1 else [])
    return candidates[0] if candidates else None


def refused_setting(message: str, user_queued: int) -> str | None:
    """The launcher setting an sbatch refusal names, None for a refusal for room. A QOS or association policy
    refusal counts as room only while the user has jobs queued (with none, the size or time of the job broke it:
    its time limit, launcher.max_time_minutes)."""
    text = message.lower()
    if "policy" in text:
        return None if user_queued else "launcher.max_time_minutes"
    if any(fragment in text for fragment in ROOM_REFUSALS):
        return None
    return next((key for fragment, key in REFUSED_SETTINGS if fragment in text), "launcher.extra_sbatch")

