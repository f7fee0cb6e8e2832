"""Where a sweep's jobs run: one schema per launcher, registered as Hydra structured configs in the ``launcher``
group (``launcher=local|debug|slurm``, fields overridden with ``launcher.<field>=...``). Site settings (a
partition, an account) go in ``conf/local/default.yaml``."""

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, cast

from omegaconf import OmegaConf

from nsl_hpc.config.mapping import plain
from nsl_hpc.errors import ConfigError


@dataclass
class LocalLauncher:
    """Parallel processes on this machine (submitit's local executor), in the foreground with a progress bar.
    The embedded default."""

    name: str = "local"
    workers: int | None = None  # processes at once; None = every CPU of this machine


@dataclass
class DebugLauncher:
    """In-process, one job after another (submitit's debug executor): CI dry runs and debugging."""

    name: str = "debug"
    workers: int = 1  # jobs run one after another in the launching process


@dataclass
class SlurmLauncher:
    """SLURM job arrays of single-CPU jobs (submitit's SLURM executor); launch returns once they are submitted."""

    name: str = "slurm"
    partition: str | None = None  # --partition; None = the cluster's default
    account: str | None = None  # --account
    qos: str | None = None  # --qos
    mem: str = "2G"  # --mem of one array element (the largest task needs < 1 GB)
    array_parallelism: int = 512  # --array=0-N%K: at most K elements of one array run at once
    max_running: int | None = None  # at most this many of the sweep's jobs run at once, over all its arrays: each
    #   array's K is at most this and it starts once the sweep's arrays before it have ended (afterany); None = no cap
    signal_delay_s: int = 120  # --signal: warn a job this long before its time limit (checkpoint and requeue)
    max_time_minutes: int | None = None  # the site's cap on a job's time limit (e.g. 1440): a group predicted
    #   longer runs as a chain of jobs (the job is requeued, each run continuing from the checkpoint)
    max_array_size: int | None = None  # None = MaxArraySize from `scontrol show config`
    max_job_count: int | None = None  # None = MaxJobCount from `scontrol show config`
    max_submit_jobs: int | None = None  # None = the user's MaxSubmitJobs from sacctmgr (no limit when none is set)
    feed_minutes: int | None = 10  # jobs the submit limits hold back are submitted by a job of this time limit
    #   behind the first array (resubmit states=[missing]), and so on; None = by launching again by hand
    extra_sbatch: dict[str, Any] = field(default_factory=dict)  # any other sbatch flag, e.g. {constraint: cpu}
    setup: list[str] = field(default_factory=list)  # shell lines run before each job (e.g. module load python)


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
    try:
        return cast(Launcher, OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(schema), given)))
    except Exception as error:  # OmegaConf's validation errors: a key the schema lacks, a value of another type
        raise ConfigError(f"launcher: {' '.join(str(error).split())[:200]}") from None

