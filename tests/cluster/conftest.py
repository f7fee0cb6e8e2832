"""Tests on the real single-node SLURM cluster of cluster/up.sh. Without a cluster they are skipped,
except under CI=true, where a missing cluster fails them."""

import os
import shutil
import subprocess

import pytest


def cluster_answers() -> bool:
    if shutil.which("sinfo") is None:
        return False
    result = subprocess.run(["sinfo", "-h", "-o", "%T"], capture_output=True, text=True, timeout=30)
    return result.returncode == 0 and bool(result.stdout.strip())


@pytest.fixture(scope="session")
def slurm_cluster() -> None:
    """Require the cluster started by `cluster/up.sh`."""
    if cluster_answers():
        return
    message = "no SLURM cluster answers `sinfo`: start one with `sudo cluster/up.sh`"
    if os.environ.get("CI") == "true":
        pytest.fail(message)
    pytest.skip(message)

