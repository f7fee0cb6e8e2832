"""The second cluster of cluster/up.sh (``CLUSTER_INSTANCE=2``): a cluster of its own beside the first, which make
test runs half of the SLURM tests on."""

import json
import os
import subprocess

import pytest

from tests import preloaded
from tests.cluster.requeues import sacct_state
from tests.sweeps import TINY_GRID, nsl

pytestmark = pytest.mark.slurm


def test_a_job_of_the_second_cluster_runs_there_and_only_its_accounting_has_it(slurm_cluster, tmp_path):
    if slurm_cluster["CLUSTER_INSTANCE"] != "2":
        message = "the second cluster does not answer: start it with `sudo CLUSTER_INSTANCE=2 cluster/up.sh`"
        if os.environ.get("CI") == "true":
            pytest.fail(message)
        pytest.skip(message)
    submitted = subprocess.run(["sbatch", "--parsable", "--wait", f"--output={tmp_path}/%j.out", "--wrap",
                                "echo $SLURM_CLUSTER_NAME"], capture_output=True, text=True, timeout=120, check=True)
    job_id = submitted.stdout.strip()
    assert (tmp_path / f"{job_id}.out").read_text().strip() == "nsl2"
    assert int(job_id) >= 500000  # its job ids lie apart from the first's
    assert sacct_state(job_id) == "COMPLETED"
    first = {key: value for key, value in os.environ.items() if key != "SLURM_CONF"}
    assert sacct_state(job_id, wait_s=0, env=first) == ""


def test_status_and_resubmit_through_another_cluster_refuse_in_one_line(slurm_cluster, tmp_path):
    """A sweep submitted to the second cluster (nsl2) records it; status and resubmit with the first cluster's
    SLURM_CONF refuse in one line, naming both clusters, instead of calling its queued tasks missing and queueing
    them again on the first (issue)."""
    if slurm_cluster["CLUSTER_INSTANCE"] != "2":
        pytest.skip("the second cluster does not answer")
    sweep_dir = tmp_path / "sweep"
    launched = nsl("launch", *TINY_GRID, "launcher=slurm", f"sweep_dir={sweep_dir}", "launcher.hold=true",
                   "sweep.name=on-nsl2")
    assert launched.returncode == 0, launched.stderr
    try:
        assert [json.loads(path.read_text())["cluster"] for path in (sweep_dir / "submissions").glob("*.json")] == [
            "nsl2"]
        first = {key: value for key, value in os.environ.items() if key != "SLURM_CONF"}
        for verb in ("status", "resubmit"):
            refused = preloaded.run(f"nsl_hpc.{verb}", [f"sweep_dir={sweep_dir}"], timeout=300, env=first)
            assert refused.returncode == 2 and refused.stderr.count("\n") == 1, refused.stderr
            assert refused.stderr.startswith("error: this sweep's jobs were submitted to cluster nsl2, and SLURM here "
                                             "answers for cluster nsl"), refused.stderr
        assert len(list((sweep_dir / "submissions").glob("*.json"))) == 1  # nothing submitted to the first
        status = nsl("status", f"sweep_dir={sweep_dir}")
        assert status.returncode == 0 and "pending 4" in status.stdout, status.stdout + status.stderr
    finally:
        subprocess.run(["scancel", "-n", "nsl-on-nsl2"], check=False)
