"""Tests on the real single-node SLURM clusters of cluster/up.sh. Without a cluster they are skipped,
except under CI=true, where a missing cluster fails them."""

import getpass
import os
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path

import pytest

from tests import clusters
from tests.cluster.long_jobs import GROUP, outcome_rows


def cancel_earlier_test_jobs(before: datetime) -> list[str]:
    """Cancel the jobs earlier tests left in the queue (output under pytest's temp root, submitted ``before``): a run
    stopped before its cleanup, a controller state restored from a disk snapshot, an earlier module's leftovers.
    They would share this module's job names and hold its CPUs. Returns their ids."""
    root = str(Path(tempfile.gettempdir()) / f"pytest-of-{getpass.getuser()}") + os.sep
    queue = subprocess.run(["squeue", "-h", "-u", getpass.getuser(), "-O", "ArrayJobID:20,SubmitTime:25,STDOUT:1000"],
                           capture_output=True, text=True, check=True).stdout.splitlines()
    fields = [line.split(maxsplit=2) for line in queue]  # an interactive job has no STDOUT
    earlier = sorted({job for job, submitted, stdout in (three for three in fields if len(three) == 3)
                      if stdout.startswith(root) and submitted[:1].isdigit()  # not N/A
                      and datetime.fromisoformat(submitted) < before})
    if earlier:
        subprocess.run(["scancel", *earlier], check=True)
    return earlier


@pytest.fixture(scope="module")
def slurm_cluster(request) -> Iterator[dict[str, str]]:
    """The cluster of cluster/up.sh this module's tests run on, without the jobs of earlier tests: the first, or the
    second (``CLUSTER_INSTANCE=2``) for a file of ``clusters.ON_SECOND`` when it is up (tests/clusters.py). Its
    settings are the environment of this module's SLURM commands and of up.sh restarting it; yields them."""
    second = os.environ.get(clusters.SECOND)
    on_second = second is not None and request.node.nodeid in clusters.ON_SECOND
    cluster = {"CLUSTER_INSTANCE": "2", "SLURM_CONF": second} if on_second else {"CLUSTER_INSTANCE": "1"}
    saved = os.environ.get("SLURM_CONF")
    os.environ.pop("SLURM_CONF", None)
    os.environ.update(cluster)
    try:
        if not clusters.answers():
            message = "no SLURM cluster answers `sinfo`: start one with `sudo cluster/up.sh`"
            if os.environ.get("CI") == "true":
                pytest.fail(message)
            pytest.skip(message)
        cancel_earlier_test_jobs(datetime.now())
        yield cluster
    finally:
        os.environ.pop("CLUSTER_INSTANCE")
        os.environ.pop("SLURM_CONF", None)
        if saved is not None:
            os.environ["SLURM_CONF"] = saved


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The group trained uninterrupted by the local launcher, started at once (it runs beside the cluster's
    job on the other core); call it for its rows."""
    sweep_dir = tmp_path_factory.mktemp("uninterrupted") / "sweep"
    process = subprocess.Popen([sys.executable, "-m", "nsl_hpc.launch", *GROUP, "launcher=local", "launcher.workers=1",
                                f"sweep_dir={sweep_dir}"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                               text=True)

    def rows() -> dict[str, tuple]:
        output, _ = process.communicate(timeout=600)
        assert process.returncode == 0 and "finished: 2 ok" in output, output
        return outcome_rows(sweep_dir)

    yield rows
    process.kill()
