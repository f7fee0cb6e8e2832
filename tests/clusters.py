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


def second_answers() -> bool:
    if not Path(SECOND_CONF).exists() or shutil.which("sinfo") is None:
        return False
    answer = subprocess.run(["sinfo", "-h", "-o", "%T"], capture_output=True, text=True, timeout=30,
                            env={**os.environ, "SLURM_CONF": SECOND_CONF})
    return answer.returncode == 0 and bool(answer.stdout.strip())
