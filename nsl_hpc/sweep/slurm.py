"""The one seam to SLURM's commands: cluster limits, queue size and accounting (``sacct``)."""

import getpass
import re
import subprocess
import time
from collections.abc import Iterable
from dataclasses import dataclass

from nsl_hpc.config.launchers import SlurmLauncher
from nsl_hpc.errors import ConfigError, SlurmError


def slurm_command(*args: str, retries: int = 3, backoff_s: float = 2.0) -> str:
    """stdout of a SLURM command; retried with exponential back-off (controllers rate-limit clients)."""
    for attempt in range(retries):
        try:
            result = subprocess.run(args, capture_output=True, text=True, timeout=120)
        except FileNotFoundError:
            raise ConfigError(f"{args[0]} not found: launcher=slurm needs the SLURM client commands") from None
        if result.returncode == 0:
            return result.stdout
        if attempt + 1 < retries:
            time.sleep(backoff_s * 2**attempt)
    raise SlurmError(f"{' '.join(args[:3])} failed: {' '.join(result.stderr.split())}")


@dataclass(frozen=True)
class Limits:
    """What the cluster accepts: array indices < max_array_size; at most max_job_count jobs in the
    system and max_submit_jobs of this user (array elements count one each)."""

    max_array_size: int
    max_job_count: int
    max_submit_jobs: int | None


def read_limits(launcher: SlurmLauncher) -> Limits:
    """Limits from ``scontrol show config`` and ``sacctmgr``, unless set in the launcher config."""
    config = slurm_command("scontrol", "show", "config")

    def setting(name: str) -> int:
        match = re.search(rf"^{name}\s*=\s*(\d+)", config, flags=re.MULTILINE)
        if not match:
            raise ConfigError(f"scontrol show config has no {name}; set it in the launcher config")
        return int(match.group(1))

    max_submit = launcher.max_submit_jobs
    if max_submit is None:
        values = slurm_command("sacctmgr", "-n", "-P", "show", "assoc", f"user={getpass.getuser()}",
                               "format=MaxSubmitJobs").split()
        max_submit = min((int(v) for v in values if v.isdigit()), default=None)
    return Limits(launcher.max_array_size or setting("MaxArraySize"),
                  launcher.max_job_count or setting("MaxJobCount"), max_submit)


def queued_jobs(user_only: bool) -> int:
    """Jobs (array elements expanded) that count against a limit: this user's pending and running ones
    (MaxSubmitJobs), or every job record the controller holds (MaxJobCount: finished jobs count until
    MinJobAge purges them)."""
    args = ["squeue", "-h", "-r", "-o", "%i"] + (["-u", getpass.getuser()] if user_only else ["-t", "all"])
    return len(slurm_command(*args).split())


# sacct states of a job that has not ended -> the state of the tasks it holds
ACTIVE_JOB_STATES = {"RUNNING": "running", "COMPLETING": "running", "PENDING": "pending", "REQUEUED": "pending",
                     "CONFIGURING": "running", "RESIZING": "running", "SUSPENDED": "pending"}


def job_states(job_ids: Iterable[str]) -> dict[str, str]:
    """State of every array element of ``job_ids`` (array job ids), from one ``sacct`` call."""
    ids = ",".join(job_ids)
    if not ids:
        return {}
    output = slurm_command("sacct", "-n", "-P", "-X", "-j", ids, "--format=JobID,State")
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
