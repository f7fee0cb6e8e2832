"""Which SLURM cluster a file of tests/cluster/ runs on: the first of cluster/up.sh, its second
(``CLUSTER_INSTANCE=2``, when it is up: about half of the SLURM tests' wait then passes beside the other half), or
a cluster of its own."""

import os
import shutil
import subprocess
from pathlib import Path

OWN_CLUSTER = ("tests/cluster/test_node_loss.py",)  # SLURM tests on a cluster of their own (cluster/nodes.sh)
ON_SECOND = ("tests/cluster/test_sweep_on_slurm.py", "tests/cluster/test_accounting.py",
             "tests/cluster/test_refusals.py", "tests/cluster/test_own_study_slurm.py",
             "tests/cluster/test_sweep_integrity_slurm.py", "tests/cluster/test_one_task_sbatch.py",
             "tests/cluster/test_second_cluster.py")
SECOND = "NSL_TESTS_SECOND_CLUSTER"  # the second cluster's SLURM_CONF, set for the session when it answers
SECOND_CONF = "/var/lib/nsl-cluster-2/slurm.conf"  # CLUSTER_INSTANCE=2 cluster/up.sh's


def answers(slurm_conf: str | None = None) -> bool:
    """Whether the cluster of ``slurm_conf`` (default: the environment's) answers ``sinfo`` with its nodes."""
    if shutil.which("sinfo") is None:
        return False
    env = {**os.environ, "SLURM_CONF": slurm_conf} if slurm_conf else None
    result = subprocess.run(["sinfo", "-h", "-o", "%T"], capture_output=True, text=True, timeout=30, env=env)
    return result.returncode == 0 and bool(result.stdout.strip())


def second_answers() -> bool:
    return Path(SECOND_CONF).exists() and answers(SECOND_CONF)
