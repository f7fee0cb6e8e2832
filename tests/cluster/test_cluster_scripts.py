"""cluster/up.sh itself: the node it declares has the machine's CPUs whatever the caller's environment."""

import os
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.slurm

UP = Path(__file__).resolve().parents[2] / "cluster" / "up.sh"


def test_up_declares_every_cpu_of_the_node_when_omp_num_threads_is_exported(slurm_cluster):
    """GNU nproc answers OMP_NUM_THREADS (1 in every training shell): the node was declared with 1 CPU."""
    result = subprocess.run(["bash", str(UP)], env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True,
                            text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    cpus = len(os.sched_getaffinity(0))
    assert f"{cpus} CPUs" in result.stdout
    node = subprocess.run(["scontrol", "show", "node"], capture_output=True, text=True, check=True).stdout
    assert f"CPUTot={cpus} " in node
