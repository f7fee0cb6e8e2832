"""The cluster's own limits, read before launch and fitted: a QOS's MaxSubmitJobsPerUser and MaxWall, a
partition's MaxTime (the cluster enforces associations, limits and QOS: cluster/slurm.conf.template)."""

import subprocess

import pytest

from tests.sweeps import TINY_GRID, nsl

pytestmark = pytest.mark.slurm

QOS = "nsl-test"


def sacctmgr(*args: str) -> None:
    subprocess.run(["sacctmgr", "-i", *args], capture_output=True, text=True, check=True)


@pytest.fixture
def limited_qos(slurm_cluster):
    """A QOS of this user's association with at most 3 jobs queued per user and 10 minutes a job."""
    subprocess.run(["sacctmgr", "-i", "delete", "qos", QOS], capture_output=True, check=False)
    sacctmgr("add", "qos", QOS, "MaxSubmitJobsPerUser=3", "MaxWall=00:10:00")
    sacctmgr("modify", "user", "where", "name=root", "set", f"qos+={QOS}")
    yield QOS
    subprocess.run(["scancel", "-u", "root", "-q", QOS], check=False)
    sacctmgr("modify", "user", "where", "name=root", "set", f"qos-={QOS}")
    sacctmgr("delete", "qos", QOS)


def time_limits(name: str) -> list[str]:
    return subprocess.run(["squeue", "-h", "-r", "-n", name, "-o", "%l"], capture_output=True, text=True,
                          check=True).stdout.split()


def test_a_qos_submit_limit_and_max_wall_are_read_and_the_plan_fits_them(limited_qos, tmp_path):
    sweep_dir = tmp_path / "sweep"
    args = [*TINY_GRID, "launcher=slurm", f"launcher.qos={limited_qos}", f"sweep_dir={sweep_dir}",
            "+launcher.extra_sbatch.hold=true", "packing.enabled=false", "lockstep.enabled=false",
            "sweep.name=qos-limited"]
    planned = nsl("launch", *args, "dry_run=true")
    assert planned.returncode == 0, planned.stderr
    assert f"a job runs at most 10 (QOS {limited_qos} MaxWall) minutes" in planned.stdout
    assert f"at most 3 (QOS {limited_qos} MaxSubmitJobsPerUser) jobs queued" in planned.stdout
    assert "jobs: 4 (slurm; time limits: 4 x 10 min)" in planned.stdout
    assert "submissions: 4 jobs, at most 3 queued at once" in planned.stdout
    try:
        launched = nsl("launch", *args)
        assert launched.returncode == 0, launched.stderr
        assert "submitted 3 jobs in 1 arrays" in launched.stdout and "1 jobs (1 tasks) were not submitted" in \
            launched.stdout
        assert time_limits("nsl-qos-limited") == ["10:00"] * 3
    finally:
        subprocess.run(["scancel", "-n", "nsl-qos-limited"], check=False)


def test_a_partitions_max_time_caps_the_time_limits_and_longer_groups_chain(slurm_cluster, tmp_path):
    sweep_dir = tmp_path / "sweep"
    args = [*TINY_GRID, "launcher=slurm", "launcher.partition=short", f"sweep_dir={sweep_dir}",
            "+launcher.extra_sbatch.hold=true", "sweep.name=short-partition", "packing.time_classes_minutes=[20,60]"]
    planned = nsl("launch", *args, "dry_run=true")
    assert planned.returncode == 0, planned.stderr
    assert "partition short: a job runs at most 15 (partition short MaxTime) minutes" in planned.stdout
    assert "time limits: 1 x 15 min" in planned.stdout
    longer = nsl("launch", *args, "dry_run=true", "cost.step_seconds.input_affine=300")  # ~35 min predicted
    assert "run as chains of" in longer.stdout and "jobs run as chains through their checkpoints" in longer.stdout
    unknown = nsl("launch", *TINY_GRID, "launcher=slurm", "launcher.partition=nope", f"sweep_dir={tmp_path / 'x'}",
                  "dry_run=true")
    assert unknown.returncode == 2
    assert unknown.stderr.strip() == ("error: launcher.partition='nope' is no partition of this cluster; choose one "
                                      "of: debug, high, short")
    try:
        launched = nsl("launch", *args)
        assert launched.returncode == 0, launched.stderr
        assert time_limits("nsl-short-partition") == ["15:00"]
    finally:
        subprocess.run(["scancel", "-n", "nsl-short-partition"], check=False)
