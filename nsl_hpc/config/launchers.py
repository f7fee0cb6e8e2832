"""Where a sweep's jobs run: one schema per launcher, registered as Hydra structured configs in the ``launcher``
group (``launcher=local|debug|slurm``, fields overridden with ``launcher.<field>=...``) and typed as every other
group is (``config.schema.typed``: types and ranges); ``check_runnable`` adds what depends on this machine or
would break the batch script. Site settings (a partition, an account) go in ``conf/local/default.yaml``."""

import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, cast

from nsl_hpc.config.mapping import plain
from nsl_hpc.config.schema import setting, typed
from nsl_hpc.core.errors import ConfigError, require_int

SBATCH_MEMORY = re.compile(r"[1-9][0-9]*[KMGT]?")  # sbatch --mem: megabytes, or with a unit
SBATCH_FLAG = re.compile(r"[A-Za-z][A-Za-z0-9_-]*")  # a long option's name (submitit writes _ as -)
BATCH_BREAKERS = re.compile(r"[\x00-\x1f\x7f]")  # control characters: a newline ends a line of the batch script
TIME_LIMIT = "use launcher.max_time_minutes (the plan gives each array the time its tasks need, up to that cap)"
ONE_CPU = "each task is a single-CPU job element on one node (torch's threads: the top-level threads)"
LOGS = "each job logs under <sweep_dir>/submitit"
REQUEUE = "a job is requeued at its time limit as one link of a planned chain (launcher.max_time_minutes)"
# sbatch flags the SLURM launcher sets or plans itself -> what decides them instead of launcher.extra_sbatch
PLANNED_FLAGS = {
    "time": TIME_LIMIT, "time-min": TIME_LIMIT, "array": "use launcher.max_array_size and launcher.array_parallelism",
    "cpus-per-task": ONE_CPU, "nodes": ONE_CPU, "ntasks": ONE_CPU, "ntasks-per-node": ONE_CPU,
    "mem": "use launcher.mem", "mem-per-cpu": "use launcher.mem", "output": LOGS, "error": LOGS,
    "dependency": "use launcher.max_running (the sweep's arrays then start one after another)",
    "hold": "use launcher.hold", "signal": "use launcher.signal_delay_s", "requeue": REQUEUE, "no-requeue": REQUEUE,
    "partition": "use launcher.partition", "account": "use launcher.account", "qos": "use launcher.qos",
}


@dataclass
class LocalLauncher:
    """Parallel processes on this machine (submitit's local executor), in the foreground with a progress bar.
    The embedded default."""

    name: str = setting("the launcher", default="local")
    workers: int | None = setting("processes at once; null: every CPU of this machine", default=None)

    def check_runnable(self) -> None:
        """Refuse more workers than this machine has CPUs (checked where a launch or resubmit runs them)."""
        if self.workers is not None:
            try:
                require_int("launcher.workers", self.workers, 1, len(os.sched_getaffinity(0)))
            except ConfigError as error:
                raise ConfigError(f"{error}: one single-CPU task per CPU of this machine") from None


@dataclass
class DebugLauncher:
    """In-process, one job after another (submitit's debug executor): CI dry runs and debugging."""

    name: str = setting("the launcher", default="debug")
    workers: int = setting("jobs run one after another in the launching process", 1, default=1)


@dataclass
class SlurmLauncher:
    """SLURM job arrays of single-CPU jobs (submitit's SLURM executor); launch returns once they are submitted."""

    name: str = setting("the launcher", default="slurm")
    partition: str | None = setting("--partition; null: the cluster's default", default=None)
    account: str | None = setting("--account", default=None)
    qos: str | None = setting("--qos", default=None)
    mem: str = setting("--mem of one array element (the largest task needs < 1 GB)", default="2G")
    array_parallelism: int = setting("--array=0-N%K: at most K elements of one array run at once", 1, default=512)
    max_running: int | None = setting(
        "at most this many of the sweep's jobs run at once, over all its arrays: each array's K is at most this and "
        "it starts once the sweep's arrays before it have ended (afterany); null: no cap", 1, default=None)
    signal_delay_s: int = setting("--signal: warn a job this long before its time limit (checkpoint and requeue)",
                                  1, default=120)
    max_time_minutes: int | None = setting(
        "the site's cap on a job's time limit (e.g. 1440): a group predicted longer runs as a chain of jobs (the job "
        "is requeued, each run continuing from the checkpoint)", 1, default=None)
    max_array_size: int | None = setting("null: MaxArraySize from `scontrol show config`", 1, default=None)
    max_job_count: int | None = setting("null: MaxJobCount from `scontrol show config`", 1, default=None)
    max_submit_jobs: int | None = setting(
        "null: the user's MaxSubmitJobs from sacctmgr (no limit when none is set)", 1, default=None)
    feed_minutes: int | None = setting(
        "jobs the submit limits hold back are submitted by a job of this time limit behind the first array "
        "(resubmit states=[missing]), and so on; null: by launching again by hand", 1, default=10)
    hold: bool = setting("submit every job held (--hold): none starts until released (scontrol release <job id>)",
                         default=False)
    extra_sbatch: dict[str, Any] = setting(
        "any sbatch flag the launcher does not set or plan itself, e.g. {constraint: cpu}; a flag set to null is not "
        "passed (resubmit drops one so)", default_factory=dict)
    setup: list[str] = setting("shell lines run before each job (e.g. module load python)", default_factory=list)

    def check_runnable(self) -> None:
        """Refuse settings sbatch would refuse or that would break the batch script (checked where a launch or
        resubmit submits them)."""
        if not SBATCH_MEMORY.fullmatch(self.mem):
            raise ConfigError(f"launcher.mem={self.mem!r} is no sbatch --mem: a positive integer with an optional "
                              "unit K, M, G or T (2G, 1500M)")
        for key in ("partition", "account", "qos", "mem"):
            check_batch_text(f"launcher.{key}", getattr(self, key), flag=True)
        for flag, value in self.extra_sbatch.items():
            if not SBATCH_FLAG.fullmatch(str(flag)):
                raise ConfigError(f"launcher.extra_sbatch.{flag} is no sbatch option name (letters, digits and -, "
                                  "as in +launcher.extra_sbatch.constraint=cpu)")
            planned = PLANNED_FLAGS.get(str(flag).replace("_", "-"))
            if planned is not None:
                raise ConfigError(f"launcher.extra_sbatch.{flag} is set by the launcher itself (it plans --{flag} "
                                  f"for every job): {planned}")
            if value is not None and not isinstance(value, str | int | float | bool):
                raise ConfigError(f"launcher.extra_sbatch.{flag}={value!r} must be one value (a string or a "
                                  f"number), as written after --{flag}=")
            check_batch_text(f"launcher.extra_sbatch.{flag}", value, flag=True)
        for line in self.setup:
            check_batch_text("launcher.setup line", line, flag=False)

    def sbatch_flags(self) -> dict[str, Any]:
        """The extra_sbatch flags sbatch gets: those not set to null."""
        return {flag: value for flag, value in self.extra_sbatch.items() if value is not None}


def check_batch_text(key: str, value: object, flag: bool) -> None:
    """Raise ConfigError for a value that would break the batch script it is written to: a control character
    (a newline starts a line of its own) anywhere, whitespace in an ``#SBATCH`` option (``flag``: sbatch splits
    the line there)."""
    if value is None or isinstance(value, bool | int | float):
        return
    text = str(value)
    bad = BATCH_BREAKERS.search(text) or (flag and re.search(r"\s", text))
    if bad:
        raise ConfigError(f"{key}={text!r} holds {bad.group()!r} at position {bad.start()}: it would break the job's "
                          f"batch script (no {'whitespace or ' if flag else ''}control characters)")


Launcher = LocalLauncher | DebugLauncher | SlurmLauncher
LAUNCHERS: dict[str, type] = {"local": LocalLauncher, "debug": DebugLauncher, "slurm": SlurmLauncher}


def register_launchers() -> None:
    """Make ``launcher=<name>`` select these schemas (Hydra's config store; idempotent)."""
    from hydra.core.config_store import ConfigStore  # imported where configs are composed (see config.composed)

    store = ConfigStore.instance()
    for name, schema in LAUNCHERS.items():
        store.store(group="launcher", name=name, node=schema)


def launcher_from(values: Mapping[str, Any]) -> Launcher:
    """The launcher a config's ``launcher`` group describes (a composed config, or one read from run.yaml)."""
    given = plain(values)
    schema = LAUNCHERS.get(str(given.get("name")))
    if schema is None:
        raise ConfigError(f"launcher.name={given.get('name')!r} is unknown; choose one of: {', '.join(LAUNCHERS)}")
    return cast(Launcher, typed(schema, given, "launcher"))

