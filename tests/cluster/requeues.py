"""The queue as the cluster tests watch it: jobs leaving it, the requeued jobs SLURM holds back, a job's state in
accounting.

SLURM holds a requeued job for about two minutes (BeginTime) before it may start again; the cluster tests release
it (``scontrol update StartTime=now``) to stay short: the wait is SLURM's, not nsl_hpc's. A job released at once
can be allocated while SLURM still revokes its last run's credential, and then fails ("Killing non-startable
batch job: Job credential revoked", seen here): it is released after a few seconds."""

import contextlib
import subprocess
import threading
import time
from collections.abc import Iterator

RELEASE_AFTER_S = 5


def jobs(name: str) -> list[tuple[str, str, str]]:
    """(job id, state, reason) of the queued jobs named ``name``."""
    out = subprocess.run(["squeue", "-h", "-n", name, "-o", "%i %T %r"], capture_output=True, text=True,
                         check=True).stdout
    return [tuple(line.split(maxsplit=2)) for line in out.splitlines()]


class Releaser:
    """Releases the held requeued jobs named ``name``, each ``RELEASE_AFTER_S`` after it was first seen held;
    ``releases`` counts them."""

    def __init__(self, name: str) -> None:
        self.name, self.releases, self.held_since = name, 0, {}

    def poll(self) -> None:
        for job_id, state, reason in jobs(self.name):
            if state != "PENDING" or reason != "BeginTime":
                self.held_since.pop(job_id, None)
            elif time.time() - self.held_since.setdefault(job_id, time.time()) >= RELEASE_AFTER_S:
                subprocess.run(["scontrol", "update", f"JobId={job_id}", "StartTime=now"], check=False)
                self.held_since.pop(job_id)
                self.releases += 1


@contextlib.contextmanager
def releasing(name: str) -> Iterator[Releaser]:
    """Release the held requeued jobs named ``name`` every second in the background while the block runs."""
    releaser, done = Releaser(name), threading.Event()

    def loop() -> None:
        while not done.wait(1.0):
            releaser.poll()

    thread = threading.Thread(target=loop, daemon=True)
    thread.start()
    try:
        yield releaser
    finally:
        done.set()
        thread.join()


def wait_until_gone(name: str, timeout_s: float = 240) -> None:
    """Wait until the controller holds no job named ``name`` (names: comma-separated)."""
    deadline = time.time() + timeout_s
    while subprocess.run(["squeue", "-h", "-n", name, "-o", "%i"], capture_output=True, text=True,
                         check=True).stdout.strip():
        assert time.time() < deadline, f"{name} still queued after {timeout_s} s"
        time.sleep(2)


def sacct_state(job_id: str, wait_s: float = 60.0, env: dict[str, str] | None = None) -> str:
    """The job's state in sacct (of the cluster ``env`` names; default: this process's) once the accounting database
    has its end (slurmdbd may still say PENDING or RUNNING for a few seconds after sbatch --wait returned); ""
    where it has no record of the job within ``wait_s``."""
    deadline = time.monotonic() + wait_s
    while True:
        result = subprocess.run(["sacct", "-n", "-X", "-P", "-j", job_id, "--format=State"],
                                capture_output=True, text=True, check=True, env=env)
        state = result.stdout.strip()
        if state not in ("", "PENDING", "RUNNING") or time.monotonic() > deadline:
            return state
        time.sleep(1.0)
