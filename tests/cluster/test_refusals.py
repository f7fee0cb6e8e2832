"""Submissions SLURM refuses for a setting: one line with sbatch's reason and the setting to change, a non-zero
exit, and a resubmit with the setting corrected runs the tasks (issue: a refused partition exited 0 and blamed
the cluster's job limits). An array size above the cluster's is refused before anything is submitted (a
partition it lacks: tests/cluster/test_limits.py)."""

import os
import subprocess
import sys

import pytest

from tests.sweeps import TINY_GRID, nsl

pytestmark = pytest.mark.slurm


def test_a_qos_sbatch_refuses_is_one_line_and_resubmit_corrects_it(slurm_cluster, tmp_path):
    sweep_dir = tmp_path / "sweep"
    args = [*TINY_GRID, "launcher=slurm", f"sweep_dir={sweep_dir}", "launcher.hold=true",
            "sweep.name=refused"]
    refused = nsl("launch", *args, "launcher.qos=nope")
    assert refused.returncode == 2, refused.stdout + refused.stderr
    line = refused.stderr.strip()
    assert "\n" not in line and line.startswith("error: sbatch refused the jobs (")
    assert "Invalid qos specification" in line and "change launcher.qos; nothing was submitted" in line
    assert f"python -m nsl_hpc.resubmit sweep_dir={sweep_dir} launcher.qos=<value>" in line
    assert "job limits" not in refused.stdout
    try:
        corrected = nsl("resubmit", f"sweep_dir={sweep_dir}", "launcher.qos=normal")
        assert corrected.returncode == 0, corrected.stderr
        assert "resubmitting 4 tasks" in corrected.stdout and "submitted 1 jobs in 1 arrays" in corrected.stdout
        reasons = subprocess.run(["squeue", "-h", "-n", "nsl-refused", "-o", "%r"], capture_output=True, text=True,
                                 check=True).stdout.split()
        assert reasons == ["JobHeldUser"]  # the sweep's other launcher settings stay (launcher.hold)
    finally:
        subprocess.run(["scancel", "-n", "nsl-refused"], check=False)


@pytest.mark.parametrize(("override", "reason", "setting", "corrected"), [
    ("launcher.account=nope", "Invalid account", "launcher.account", "launcher.account=<value>"),
    ("+launcher.extra_sbatch.constraint=nope", "Invalid feature specification", "launcher.extra_sbatch.constraint",
     "+launcher.extra_sbatch.constraint=<value or null>"),
])
def test_each_refusal_names_its_own_setting_and_its_correction_parses(slurm_cluster, tmp_path, override, reason,
                                                                       setting, corrected):
    sweep_dir = tmp_path / "sweep"
    args = [*TINY_GRID, "launcher=slurm", f"sweep_dir={sweep_dir}", "launcher.hold=true", "sweep.name=refused-cause"]
    refused = nsl("launch", *args, override)
    assert refused.returncode == 2, refused.stdout + refused.stderr
    line = refused.stderr.strip()
    assert "\n" not in line and reason in line and f"change {setting}; nothing was submitted" in line, line
    assert f"python -m nsl_hpc.resubmit sweep_dir={sweep_dir} {corrected} runs the rest" in line
    if setting.startswith("launcher.extra_sbatch"):  # the correction the line names, as written, drops the flag
        try:
            dropped = nsl("resubmit", f"sweep_dir={sweep_dir}", "+launcher.extra_sbatch.constraint=null")
            assert dropped.returncode == 0 and "submitted 1 jobs in 1 arrays" in dropped.stdout, dropped.stderr
        finally:
            subprocess.run(["scancel", "-n", "nsl-refused-cause"], check=False)


def test_an_array_size_above_the_clusters_is_refused_before_anything_is_submitted(slurm_cluster, tmp_path):
    maximum = subprocess.run(["scontrol", "show", "config"], capture_output=True, text=True, check=True).stdout
    cluster = int(next(line.split("=")[1] for line in maximum.splitlines() if line.startswith("MaxArraySize")))
    sweep_dir = tmp_path / "sweep"
    refused = nsl("launch", *TINY_GRID, "launcher=slurm", f"sweep_dir={sweep_dir}",
                  f"launcher.max_array_size={cluster + 1}", "sweep.name=too-large")
    assert refused.returncode == 2
    assert refused.stderr.strip() == (f"error: launcher.max_array_size={cluster + 1} is above the cluster's "
                                      f"MaxArraySize={cluster}: leave it unset (null) or lower it")
    assert not (sweep_dir / "submissions").exists() or not any((sweep_dir / "submissions").iterdir())


def test_where_slurms_commands_reach_no_cluster_a_dry_run_plans_and_a_launch_writes_nothing(tmp_path):
    """SLURM's real commands with no configuration to read (SLURM_CONF names no file: scontrol's "Could not
    establish a configuration source"): the dry run prints the plan and says the limits were not read and why; a
    launch is one line and writes no sweep directory."""
    env = {**os.environ, "SLURM_CONF": str(tmp_path / "no-such-slurm.conf")}
    launch = [sys.executable, "-m", "nsl_hpc.launch", *TINY_GRID, "launcher=slurm", f"sweep_dir={tmp_path / 'sweep'}"]
    planned = subprocess.run([*launch, f"sweep_dir={tmp_path / 'planned'}", "dry_run=true"], env=env,
                             capture_output=True, text=True, timeout=300)
    assert planned.returncode == 0, planned.stderr
    said = planned.stdout + planned.stderr
    assert "the cluster's limits were not read, the plan below does not fit them: scontrol failed:" in said
    assert "dry run: nothing submitted" in planned.stdout
    refused = subprocess.run(launch, env=env, capture_output=True, text=True, timeout=300)
    assert refused.returncode == 1 and refused.stderr.startswith("error: scontrol failed:")
    assert refused.stderr.count("\n") == 1 and not (tmp_path / "sweep").exists()
