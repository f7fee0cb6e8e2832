"""Running the package's commands from a benchmark, timed."""

import subprocess
import sys
import tempfile
import time


def timed_command(*args: str) -> tuple[str, float, float]:
    """Run ``python -m <args>``: its stdout, wall seconds and peak resident memory (GiB, GNU time's); a failure
    stops the benchmark with the command's last words."""
    with tempfile.NamedTemporaryFile("r") as peak:
        started = time.perf_counter()
        done = subprocess.run(["/usr/bin/time", "-f", "%M", "-o", peak.name, sys.executable, "-m", *args],
                              capture_output=True, text=True)
        seconds = time.perf_counter() - started
        kib = int(peak.read().split()[-1])
    if done.returncode:
        sys.exit(f"{' '.join(args)} exited {done.returncode}: {done.stderr.strip()[-2000:]}")
    return done.stdout, seconds, kib / 2**20
