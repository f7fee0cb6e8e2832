"""The cluster's own limits, read before launch and fitted: a QOS's MaxSubmitJobsPerUser and MaxWall, a
partition's MaxTime (the cluster enforces associations, limits and QOS: cluster/slurm.conf.template)."""

import itertools
import subprocess
import time

import pytest

from tests.cluster.requeues import wait_until_gone
from tests.sweeps import TINY_GRID, nsl

pytestmark = pytest.mark.slurm

QOS = "nsl-test"
QUICK_REHEARSAL = ["rehearsal=true", "rehearse.killed_jobs=0", "rehearse.frozen_share=0", "rehearse.failed_share=0"]


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
            "packing.enabled=false", "lockstep.enabled=false", "sweep.name=qos-limited", *QUICK_REHEARSAL]
    planned = nsl("launch", *args, "dry_run=true")
    assert planned.returncode == 0, planned.stderr
    assert f"a job runs at most 10 (QOS {limited_qos} MaxWall) minutes" in planned.stdout
    assert f"at most 3 (QOS {limited_qos} MaxSubmitJobsPerUser) jobs queued" in planned.stdout
    assert "jobs: 4 (slurm; time limits: 4 x 10 min)" in planned.stdout
    assert "submissions: 4 jobs, at most 3 queued at once" in planned.stdout
    since = time.strftime("%Y-%m-%dT%H:%M:%S")
    try:  # a job of this user outside the QOS does not count against the QOS's per-user limit
        subprocess.run(["sbatch", "--hold", "--job-name=nsl-qos-outside", "--wrap=true"], check=True,
                       capture_output=True)
        launched = nsl("launch", *args)
        assert launched.returncode == 0, launched.stderr
        assert "submitted 2 jobs in 1 arrays" in launched.stdout, launched.stdout
        assert "2 jobs (2 tasks) were not submitted: job " in launched.stdout  # the feeder took the third place
        wait_until_gone("nsl-qos-limited,nsl-qos-limited-feed")  # the feeder's array is in before it ends
    finally:
        for name in ("nsl-qos-limited", "nsl-qos-limited-feed", "nsl-qos-outside"):  # scancel takes one name
            subprocess.run(["scancel", "-n", name], check=False)
    status = nsl("status", f"sweep_dir={sweep_dir}")
    assert "4 tasks: done 4 |" in status.stdout, status.stdout  # no launch by hand
    limits = accounted(["--name", "nsl-qos-limited,nsl-qos-limited-feed", "-S", since, "-q", limited_qos, "-o",
                        "Timelimit"], 5)
    assert set(limits) == {"00:10:00"}  # 4 task jobs, 1 feeder, within MaxWall


def test_a_partitions_max_time_caps_the_time_limits_and_longer_groups_chain(slurm_cluster, tmp_path):
    sweep_dir = tmp_path / "sweep"
    args = [*TINY_GRID, "launcher=slurm", "launcher.partition=short", f"sweep_dir={sweep_dir}",
            "launcher.hold=true", "sweep.name=short-partition", "packing.time_classes_minutes=[20,60]"]
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


def test_max_running_caps_the_sweeps_running_jobs_over_all_its_arrays(slurm_cluster, tmp_path):
    sweep_dir = tmp_path / "sweep"
    args = [*TINY_GRID, "launcher=slurm", f"sweep_dir={sweep_dir}", "launcher.max_running=1",
            "launcher.max_array_size=2", "packing.enabled=false", "lockstep.enabled=false", "sweep.name=capped",
            *QUICK_REHEARSAL]
    planned = nsl("launch", *args, "dry_run=true")
    assert "running: at most 1 of the sweep's jobs at once (launcher.max_running)" in planned.stdout, planned.stdout
    try:
        launched = nsl("launch", *args, "launcher.hold=true")  # held: the first array's second-long
        assert launched.returncode == 0, launched.stderr  # jobs cannot end (and clear the dependency) before it is read
        assert "submitted 4 jobs in 2 arrays" in launched.stdout, launched.stdout
        first, second = (array.strip() for array in launched.stdout.split("arrays: ")[1].splitlines()[0].split(","))
        dependency = subprocess.run(["squeue", "-h", "-j", second, "-o", "%E"], capture_output=True, text=True,
                                    check=True).stdout
        assert f"afterany:{first}" in dependency
        throttles = subprocess.run(["scontrol", "show", "job", first], capture_output=True, text=True,
                                   check=True).stdout
        assert "ArrayTaskThrottle=1" in throttles
        subprocess.run(["scontrol", "release", first, second], check=True)
        wait_until_gone("nsl-capped")
    finally:
        subprocess.run(["scancel", "-n", "nsl-capped"], check=False)
    spans = accounted_spans(f"{first},{second}", 4)
    assert all(end <= next_start for (_, end), (next_start, _) in itertools.pairwise(spans))
    status = nsl("status", f"sweep_dir={sweep_dir}")
    assert "4 tasks: done 4 |" in status.stdout, status.stdout


def accounted_spans(job_ids: str, elements: int) -> list[tuple[str, ...]]:
    """(start, end) of each element of ``job_ids``, sorted, once accounting holds all ``elements`` ended."""
    return sorted(tuple(line.split("|")) for line in accounted(["-j", job_ids, "-o", "Start,End"], elements))


def accounted(args: list[str], jobs: int, timeout_s: float = 60) -> list[str]:
    """sacct's lines (-n -X -P ``args``) once it holds ``jobs`` jobs, none of them unfinished (accounting lags)."""
    deadline = time.time() + timeout_s
    while True:
        lines = subprocess.run(["sacct", "-n", "-X", "-P", *args], capture_output=True, text=True,
                               check=True).stdout.split()
        if len(lines) == jobs and not any("Unknown" in line for line in lines):
            return lines
        assert time.time() < deadline, f"accounting holds {lines}, not {jobs} ended jobs"
        time.sleep(2)
