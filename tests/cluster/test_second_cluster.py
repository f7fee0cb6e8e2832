"""The second cluster of cluster/up.sh (``CLUSTER_INSTANCE=2``): a cluster of its own beside the first, which make
test runs half of the SLURM tests on."""

import os
import subprocess

import pytest

from tests.cluster.requeues import sacct_state

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
