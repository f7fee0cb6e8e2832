"""The cluster's own limits, read before anything is submitted: what the controller accepts (MaxArraySize,
MaxJobCount), the partition's MaxTime, and the user's association and QOS (the QOS named, the association's
default, the partition's): how many jobs it may have queued (MaxSubmitJobs, MaxSubmitJobsPerUser, GrpSubmitJobs),
running (MaxJobs, MaxJobsPerUser, GrpJobs, a cpu count in GrpTRES / MaxTRESPerUser: a job is one CPU) and how long
one may run (MaxWall). Each limit keeps where it comes from; the smallest of each kind binds. Without accounting
(AccountingStorageType=none, or slurmdbd down) the association's and QOS's limits are unknown, and say why.
"""

import getpass
import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass, replace

from nsl_hpc.config.launchers import SlurmLauncher
from nsl_hpc.core.errors import ConfigError, SlurmError
from nsl_hpc.sweep.launch_settings import LaunchSettings
from nsl_hpc.sweep.plan import Pack
from nsl_hpc.sweep.slurm import SlurmMissing, slurm_command
from nsl_hpc.sweep.storage import Storage, predicted_files

LOG = logging.getLogger(__name__)

UNLIMITED = ("", "UNLIMITED", "INFINITE", "NONE", "N/A", "(null)")


@dataclass(frozen=True)
class Limit:
    """A number the cluster allows, and where it is set (e.g. 'QOS normal MaxSubmitJobsPerUser')."""

    value: int
    source: str
    qos: str = ""  # a QOS's per-user limit: only the user's jobs of that QOS count against it ('': all the user's)

    def __str__(self) -> str:
        return f"{self.value:,} ({self.source})"


def smallest(*limits: Limit | None) -> Limit | None:
    """The binding one of ``limits`` (None: no limit)."""
    given = [limit for limit in limits if limit is not None]
    return min(given, key=lambda limit: limit.value) if given else None


@dataclass(frozen=True)
class ClusterLimits:
    """What a sweep's SLURM jobs must fit (see the module docstring); ``unaccounted``: why the association's and
    QOS's limits are unknown (None: they were read)."""

    max_array_size: Limit
    max_job_count: Limit
    partition: str
    wall_minutes: Limit | None
    submit_jobs: Limit | None
    running_jobs: Limit | None
    qos: str | None
    unaccounted: str | None = None
    max_running: int | None = None  # the sweep's own cap on its running jobs (launcher.max_running)
    cluster: str = ""  # the cluster's ClusterName, recorded with each array submitted to it

    def describe(self) -> list[str]:
        """The lines a dry run prints."""
        accounting = (f"the association's and QOS's limits are unknown: {self.unaccounted}" if self.unaccounted
                      else f"QOS {self.qos or '(none)'}")
        return [f"cluster: array indices below {self.max_array_size}, at most {self.max_job_count} jobs in the system",
                f"partition {self.partition}: a job runs at most {self.wall_minutes or 'unlimited'} minutes; "
                f"{accounting}",
                f"this user: at most {self.submit_jobs or 'unlimited'} jobs queued, {self.running_jobs or 'unlimited'} "
                "running"]


def slurm_minutes(text: str) -> int | None:
    """Minutes of a SLURM time ('UNLIMITED', '90', '1:30:00', '2-00:00:00', '30:00' as minutes:seconds), rounded
    down; None for no limit."""
    text = text.strip()
    if text in UNLIMITED:
        return None
    days, _, clock = text.rpartition("-")
    parts = [int(part) for part in clock.split(":")]
    if days:  # days-hours[:minutes[:seconds]]
        hours, minutes, seconds = [*parts, 0, 0][:3]
    elif len(parts) == 3:  # hours:minutes:seconds
        hours, minutes, seconds = parts
    else:  # minutes[:seconds]
        hours, minutes, seconds = 0, parts[0], [*parts, 0][1]
    return (int(days or 0) * 24 + hours) * 60 + minutes + seconds // 60


def cpus_of(tres: str) -> int | None:
    """The cpu count of a TRES string ('cpu=64,mem=100G'), None when it sets none."""
    match = re.search(r"(?:^|,)cpu=(\d+)", tres)
    return int(match.group(1)) if match else None


def count(value: str) -> int | None:
    return int(value) if value.strip().isdigit() else None


def key_values(line: str) -> dict[str, str]:
    """``Key=Value`` tokens of one ``scontrol -o`` line."""
    return dict(token.split("=", 1) for token in line.split() if "=" in token)


def config_values(text: str) -> dict[str, str]:
    """``Key = Value`` lines of ``scontrol show config``."""
    return {key.strip(): value.strip() for key, _, value in (line.partition("=") for line in text.splitlines())
            if value}


def partition_settings(name: str | None) -> tuple[str, dict[str, str]]:
    """(name, fields: scontrol's) of the partition ``name`` (None: the cluster's default), refused in one line when the
    cluster has no such partition."""
    partitions = [key_values(line) for line in slurm_command("scontrol", "show", "partition", "-o").splitlines()
                  if line.strip()]
    for fields in partitions:
        if fields.get("PartitionName") == name or (name is None and fields.get("Default") == "YES"):
            return fields["PartitionName"], fields
    names = ", ".join(fields.get("PartitionName", "?") for fields in partitions)
    if name is None:
        raise ConfigError(f"the cluster has no default partition: set launcher.partition (one of: {names})")
    raise ConfigError(f"launcher.partition={name!r} is no partition of this cluster; choose one of: {names}")


def accounting_rows(user: str, account: str | None, partition: str, qos: str | None
                    ) -> tuple[dict[str, str], list[tuple[str, dict[str, str]]]]:
    """The user's association for ``account`` (None: the user's default account) and ``partition`` (one set for
    the partition wins over the account's), and the (name, settings) of every QOS a job of it runs under."""
    if account is None:
        account = slurm_command("sacctmgr", "-n", "-P", "show", "user", user, "format=DefaultAccount",
                                retries=2).strip() or None
    fields = ["Account", "Partition", "QOS", "DefaultQOS", "MaxSubmitJobs", "MaxJobs", "MaxWall", "GrpTRES",
              "GrpSubmitJobs", "GrpJobs"]
    rows = [dict(zip(fields, line.split("|"), strict=False)) for line in slurm_command(
        "sacctmgr", "-n", "-P", "show", "assoc", f"user={user}", f"format={','.join(fields)}", retries=2).splitlines()]
    rows = [row for row in rows if account is None or row["Account"] == account]
    chosen = sorted((row for row in rows if row["Partition"] in ("", partition)), key=lambda row: row["Partition"],
                    reverse=True)
    association = chosen[0] if chosen else {}
    names = [name for name in dict.fromkeys([qos or association.get("DefaultQOS") or
                                             (association.get("QOS", "").split(",")[0] or None)]) if name]
    qos_fields = ["Name", "MaxSubmitJobsPerUser", "MaxJobsPerUser", "MaxWall", "GrpTRES", "MaxTRESPerUser",
                  "GrpSubmitJobs", "GrpJobs"]
    qos_rows = []
    if names:
        for line in slurm_command("sacctmgr", "-n", "-P", "show", "qos", *names, f"format={','.join(qos_fields)}",
                                  retries=2).splitlines():
            row = dict(zip(qos_fields, line.split("|"), strict=False))
            qos_rows.append((row["Name"], row))
    return association, qos_rows


def read_cluster_limits(launcher: SlurmLauncher) -> ClusterLimits:
    """The limits a sweep submitted with ``launcher`` must fit; the launcher's own settings (max_array_size, one
    above the cluster's refused; max_job_count, max_submit_jobs) count as limits too."""
    scontrol = config_values(slurm_command("scontrol", "show", "config"))
    cluster_array = int(scontrol.get("MaxArraySize", "1001"))
    if launcher.max_array_size is not None and launcher.max_array_size > cluster_array:
        raise ConfigError(f"launcher.max_array_size={launcher.max_array_size} is above the cluster's MaxArraySize="
                          f"{cluster_array}: leave it unset (null) or lower it")
    array = smallest(Limit(cluster_array, "MaxArraySize"), own(launcher.max_array_size, "launcher.max_array_size"))
    jobs = smallest(Limit(int(scontrol.get("MaxJobCount", "10000")), "MaxJobCount"),
                    own(launcher.max_job_count, "launcher.max_job_count"))
    partition, fields = partition_settings(launcher.partition)
    wall = [minutes_limit(fields.get("MaxTime", ""), f"partition {partition} MaxTime")]
    submit = [own(launcher.max_submit_jobs, "launcher.max_submit_jobs")]
    running = [own(launcher.max_running, "launcher.max_running")]
    qos, unaccounted = launcher.qos, None
    if "none" in scontrol.get("AccountingStorageType", "").lower():
        unaccounted = "accounting is disabled (AccountingStorageType=none)"
    else:
        try:
            association, qos_rows = accounting_rows(getpass.getuser(), launcher.account, partition, launcher.qos)
        except SlurmError as error:
            unaccounted = str(error)
        else:
            qos = ", ".join(name for name, _ in qos_rows) or qos
            where = f"association {association.get('Account', '?')}"
            wall.append(minutes_limit(association.get("MaxWall", ""), f"{where} MaxWall"))
            submit += [own(count(association.get(key, "")), f"{where} {key}") for key in ("MaxSubmitJobs",
                                                                                         "GrpSubmitJobs")]
            running += [own(count(association.get(key, "")), f"{where} {key}") for key in ("MaxJobs", "GrpJobs")]
            running.append(own(cpus_of(association.get("GrpTRES", "")), f"{where} GrpTRES cpu"))
            for name, row in qos_rows:
                wall.append(minutes_limit(row["MaxWall"], f"QOS {name} MaxWall"))
                submit += [own(count(row["MaxSubmitJobsPerUser"]), f"QOS {name} MaxSubmitJobsPerUser", name),
                           own(count(row["GrpSubmitJobs"]), f"QOS {name} GrpSubmitJobs")]
                running += [own(count(row[key]), f"QOS {name} {key}") for key in ("MaxJobsPerUser", "GrpJobs")]
                running += [own(cpus_of(row[key]), f"QOS {name} {key} cpu") for key in ("GrpTRES", "MaxTRESPerUser")]
    assert array is not None and jobs is not None
    return ClusterLimits(array, jobs, partition, smallest(*wall), smallest(*submit), smallest(*running), qos,
                         unaccounted, launcher.max_running, scontrol.get("ClusterName", ""))


def cluster_limits(settings: LaunchSettings, dry_run: bool = False) -> ClusterLimits | None:
    """The cluster's limits a launch's SLURM jobs fit; None for the local launchers, and for a dry run on a machine
    without SLURM's commands or whose commands reach no cluster (said in a line: the plan is printed without them)."""
    launcher = settings.launcher
    if not isinstance(launcher, SlurmLauncher):
        return None
    try:
        return read_cluster_limits(launcher)
    except (SlurmMissing, SlurmError) as error:
        if not dry_run:
            raise
        LOG.info(f"  the cluster's limits were not read, the plan below does not fit them: {error}")
        return None


def own(value: int | None, source: str, qos: str = "") -> Limit | None:
    return None if value is None else Limit(value, source, qos)


def minutes_limit(text: str, source: str) -> Limit | None:
    minutes = slurm_minutes(text)
    return None if minutes is None else Limit(minutes, source)


def within_limits(settings: LaunchSettings, limits: ClusterLimits) -> LaunchSettings:
    """``settings`` with its jobs' time limits within the cluster's longest (``wall_minutes``): at most that, a
    longer group as a chain of jobs through its checkpoints (``describe_fit`` refuses one without)."""
    launcher = settings.launcher
    if not isinstance(launcher, SlurmLauncher):
        return settings
    cap = smallest(limits.wall_minutes, own(launcher.max_time_minutes, "launcher.max_time_minutes"))
    if cap is None:
        return settings
    return replace(settings, launcher=replace(launcher, max_time_minutes=cap.value))


def describe_fit(limits: ClusterLimits | None, storage: Storage, packs: Sequence[Pack], tasks: int,
                 checkpoints: bool, feed_minutes: int | None = None) -> list[str]:
    """What the cluster (``limits``; None: a local launcher) and the sweep directory allow, and how the plan of
    ``packs`` (``tasks`` tasks) fits them, the jobs the submit limit holds back submitted by a feeder job of
    ``feed_minutes`` (None: by hand); raises ConfigError where it cannot (more files than free inodes, a job
    longer than the cluster allows without ``checkpoints`` to chain it)."""
    groups = sum(len(pack.groups) for pack in packs)
    chains = sum(pack.chain > 1 for pack in packs)
    if chains and not checkpoints and limits is not None:
        raise ConfigError(f"{chains:,} jobs need longer than the cluster allows, {limits.wall_minutes} minutes: "
                          "with checkpoints (checkpoint.every_minutes > 0) each runs as a chain of jobs")
    files = predicted_files(tasks, groups, len(packs))
    if storage.free_inodes is not None and files > storage.free_inodes:
        raise ConfigError(f"the sweep writes up to {files:,} files ({tasks:,} rows, its jobs' and groups' files) but "
                          f"{storage.path} has {storage.free_inodes:,} inodes free: free some (an inode quota: "
                          "`lfs quota` / `quota`), or launch fewer tasks at a time")
    if limits is None:
        return []
    lines = [*limits.describe(), storage.describe(), f"files: up to {files:,} at once, of "
             + ("uncounted inodes" if storage.free_inodes is None else f"{storage.free_inodes:,} inodes free")]
    if limits.submit_jobs is not None and len(packs) > limits.submit_jobs.value:
        rest = (f"a job of {feed_minutes} minutes behind the first array submits the rest as jobs end, and so on "
                "until all are in (launcher.feed_minutes)" if feed_minutes is not None else
                "launch (or resubmit) again as jobs end to submit the rest (launcher.feed_minutes=null)")
        lines.append(f"submissions: {len(packs):,} jobs, at most {limits.submit_jobs.value:,} queued at once: {rest}")
    if limits.max_running is not None:
        lines.append(f"running: at most {limits.max_running:,} of the sweep's jobs at once (launcher.max_running): "
                     "its arrays run one after another")
    if limits.wall_minutes is not None and chains:
        lines.append(f"time limits: at most {limits.wall_minutes}: {chains:,} jobs run as chains through their "
                     "checkpoints")
    return lines
