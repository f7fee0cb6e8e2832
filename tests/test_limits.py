"""The cluster's limits as SLURM writes them, the sweep directory's file system, and the sweep's lock where the
file system takes no flock (Lustre without its flock mount option, some NFS setups)."""

import errno
import fcntl
import os
import subprocess
import sys

import pytest

from nsl_hpc.core.errors import ConfigError
from nsl_hpc.sweep.directory import sweep_lock, sweep_lock_holder
from nsl_hpc.sweep.limits import ClusterLimits, Limit, cpus_of, describe_fit, slurm_minutes, smallest
from nsl_hpc.sweep.plan import Group, Pack
from nsl_hpc.sweep.slurm import refused_setting
from nsl_hpc.sweep.storage import Storage, predicted_files, read_storage


@pytest.mark.parametrize(("text", "minutes"), [
    ("UNLIMITED", None), ("INFINITE", None), ("", None), ("90", 90), ("30:00", 30), ("1:30:00", 90),
    ("2-00:00:00", 2880), ("1-12", 2160), ("1-01:30", 1530), ("00:10:00", 10),
])
def test_slurm_times_are_read_in_minutes(text, minutes):
    assert slurm_minutes(text) == minutes


def test_the_smallest_limit_binds_and_a_cpu_count_is_read_from_tres():
    assert cpus_of("cpu=64,mem=100G") == 64 and cpus_of("mem=100G,cpu=8") == 8 and cpus_of("mem=1G") is None
    qos, partition = Limit(60, "QOS normal MaxWall"), Limit(15, "partition short MaxTime")
    assert smallest(qos, None, partition) == partition and smallest(None, None) is None
    assert str(partition) == "15 (partition short MaxTime)"


def limits(submit: int | None = None) -> ClusterLimits:
    return ClusterLimits(Limit(1001, "MaxArraySize"), Limit(10000, "MaxJobCount"), "debug", Limit(15, "partition x"),
                         None if submit is None else Limit(submit, "QOS q MaxSubmitJobsPerUser"), None, "q")


def test_a_sweep_with_more_files_than_free_inodes_is_refused_before_submission(tmp_path):
    packs = [Pack((Group(("a", "b"), 10.0),), 10.0, 20), Pack((Group(("c",), 10.0),), 10.0, 20)]
    needed = predicted_files(3, 2, 2)
    roomy = Storage(tmp_path, "lustre", 2**40, needed, None)
    lines = describe_fit(limits(submit=1), roomy, packs, 3, checkpoints=True)
    assert f"files: up to {needed:,} at once, of {needed:,} inodes free" in lines
    assert lines[-1] == ("submissions: 2 jobs, at most 1 queued at once: launch (or resubmit) again as jobs end to "
                         "submit the rest (launcher.feed_minutes=null)")
    fed = describe_fit(limits(submit=1), roomy, packs, 3, checkpoints=True, feed_minutes=10)
    assert fed[-1].endswith("a job of 10 minutes behind the first array submits the rest as jobs end, and so on "
                            "until all are in (launcher.feed_minutes)")
    full = Storage(tmp_path, "lustre", 2**40, needed - 1, None)
    with pytest.raises(ConfigError, match=f"writes up to {needed:,} files .* has {needed - 1:,} inodes free"):
        describe_fit(limits(), full, packs, 3, checkpoints=True)
    chained = [Pack((Group(("a",), 3600.0),), 3600.0, 15, chain=12)]
    with pytest.raises(ConfigError, match=r"1 jobs need longer than the cluster allows, 15 \(partition x\) minutes"):
        describe_fit(limits(), roomy, chained, 1, checkpoints=False)


def test_the_file_system_of_a_sweep_directory_is_read(tmp_path):
    storage = read_storage(tmp_path)
    assert storage.path == tmp_path.resolve() and storage.flock is None and storage.free_bytes > 0
    assert storage.fs_type != "unknown" and (storage.free_inodes is None or storage.free_inodes > 0)
    assert not list(tmp_path.iterdir())  # the flock probe is gone


@pytest.fixture
def no_flock(monkeypatch):
    """A file system that answers flock with ENOSYS, as Lustre mounted without -o flock does."""
    def refuse(*_args):
        raise OSError(errno.ENOSYS, os.strerror(errno.ENOSYS))

    monkeypatch.setattr(fcntl, "flock", refuse)


def test_without_flock_the_sweep_lock_is_a_file_created_exclusively(no_flock, tmp_path):
    with sweep_lock(tmp_path, "launch"):
        held = (tmp_path / ".lock.held").read_text()
        assert held.startswith(f"launch (pid {os.getpid()} on ")
        busy = r"is in use by launch \(pid .*if it ended without removing .*\.lock\.held"
        with pytest.raises(ConfigError, match=busy), sweep_lock(tmp_path, "resubmit"):
            pass
    assert not (tmp_path / ".lock.held").exists() and sweep_lock_holder(tmp_path) is None
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    (tmp_path / ".lock.held").write_text(f"clean (pid {gone.stdout.strip()} on {os.uname().nodename}, since x)\n")
    with sweep_lock(tmp_path, "launch"):  # its holder's process of this host is gone: taken over
        assert (tmp_path / ".lock.held").read_text().startswith("launch")
    (tmp_path / ".lock.held").write_text("clean (pid 1 on another-node, since x)\n")
    with pytest.raises(ConfigError, match=r"in use by clean \(pid 1 on another-node"), sweep_lock(tmp_path, "launch"):
        pass


# What sbatch (Slurm 22.05) says for each cause of a refusal -> the setting the launch's one line names.
@pytest.mark.parametrize(("message", "setting"), [
    ("Invalid account or account/partition combination specified", "launcher.account"),
    ("Invalid partition name specified", "launcher.partition"),
    ("Invalid qos specification", "launcher.qos"),
    ("Invalid feature specification", "launcher.extra_sbatch"),
    ("Requested time limit is invalid (missing or exceeds some limit)", "launcher.max_time_minutes"),
    ("Invalid job array specification", "launcher.max_array_size"),
    ("Requested node configuration is not available", "launcher.extra_sbatch"),
    ("Node count specification invalid", "launcher.extra_sbatch"),
    ("Job violates accounting/QOS policy (job submit limit, user's size and/or time limits)", None),
])
def test_each_sbatch_refusal_names_its_own_setting(message, setting):
    assert refused_setting(f"sbatch: error: Batch job submission failed: {message}", user_queued=3) == setting
