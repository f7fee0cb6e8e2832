"""One task of a sweep: validate its config, draw its sizes, train one model, score it, write its row.

Sizes are drawn from the task's grid coordinates: d uniform in [d~/2, d~], n_t = d / 10 trajectories,
n_h an integer in [n_h~/2, n_h~], n_d an integer in [n_d~/2, n_d~]. The draws, the initial weights and the
batch order depend on (sweep_seed, system, arch, seed, data_tier, width_tier, depth_tier) and nothing
else; the epoch count is left out on purpose, so tasks that differ only in n_e train the same model on the
same data for longer.
"""

import math
import platform
import socket
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

import nsl_hpc
from nsl_hpc.cache import ArrayCache
from nsl_hpc.datasets import build_test_set, build_training_set, points_per_trajectory, training_points
from nsl_hpc.errors import ConfigError
from nsl_hpc.metrics import normalized_errors
from nsl_hpc.models import build_model
from nsl_hpc.models.blocks import parameter_count
from nsl_hpc.rows import row_path, write_row_atomically
from nsl_hpc.seeding import stable_hash, stable_seed
from nsl_hpc.systems import SYSTEMS
from nsl_hpc.training import Scaling, predict_derivative, train_model


@dataclass(frozen=True)
class TaskSpec:
    """A task's grid coordinates and the sizes drawn from them."""

    system: str
    arch: str
    seed: int
    sweep_seed: int
    epochs: int  # n_e
    data_tier: int  # d~
    width_tier: int  # n_h~
    depth_tier: int  # n_d~
    data_size: float  # d, uniform in [d~/2, d~]
    n_traj: float  # n_t = d / 10
    width: int  # n_h
    depth: int  # n_d

    def coordinates(self) -> tuple:
        """What the random draws depend on (everything but the epoch count)."""
        return (self.sweep_seed, self.system, self.arch, self.seed,
                self.data_tier, self.width_tier, self.depth_tier)


def require_member(key: str, value: Any, allowed: list) -> None:
    if value not in allowed:
        raise ConfigError(f"{key}={value!r} is outside the grid; allowed: {', '.join(map(str, allowed))}")


def require_positive_int(key: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ConfigError(f"{key}={value!r} must be a positive integer")


def draw_sizes(sweep_seed: int, system: str, arch: str, seed: int, data_tier: int, width_tier: int,
               depth_tier: int) -> tuple[float, int, int]:
    """(d, n_h, n_d) of a task, drawn from its grid coordinates (the epoch count excluded)."""
    rng = np.random.default_rng(stable_seed("sizes", sweep_seed, system, arch, seed, data_tier, width_tier,
                                            depth_tier))
    data_size = float(rng.uniform(data_tier / 2, data_tier))
    width = int(rng.integers(math.ceil(width_tier / 2), width_tier, endpoint=True))
    depth = int(rng.integers(math.ceil(depth_tier / 2), depth_tier, endpoint=True))
    return data_size, width, depth


def resolve_task(cfg: DictConfig) -> TaskSpec:
    """Validate the task's keys (raising ConfigError before any work) and draw its sizes."""
    if cfg.system.name not in SYSTEMS:
        raise ConfigError(f"unknown system {cfg.system.name!r}; choose one of: {', '.join(sorted(SYSTEMS))}")
    for key in ("epochs", "data_tier", "width_tier", "depth_tier"):
        require_positive_int(key, cfg[key])
    for key in ("seed", "sweep_seed"):
        if isinstance(cfg[key], bool) or not isinstance(cfg[key], int) or cfg[key] < 0:
            raise ConfigError(f"{key}={cfg[key]!r} must be a non-negative integer")
    require_member("data_tier", cfg.data_tier, list(cfg.tiers.data))
    require_member("width_tier", cfg.width_tier, list(cfg.tiers.width))
    require_member("depth_tier", cfg.depth_tier, list(cfg.tiers.depth))
    require_positive_int("train.batch_size", cfg.train.batch_size)
    if not cfg.train.lr > 0:
        raise ConfigError(f"train.lr={cfg.train.lr!r} must be positive")

    data_size, width, depth = draw_sizes(cfg.sweep_seed, cfg.system.name, cfg.arch.name, cfg.seed,
                                         cfg.data_tier, cfg.width_tier, cfg.depth_tier)
    return TaskSpec(cfg.system.name, cfg.arch.name, cfg.seed, cfg.sweep_seed, cfg.epochs, cfg.data_tier,
                    cfg.width_tier, cfg.depth_tier, data_size, data_size / cfg.data_per_trajectory,
                    width, depth)


# Every config value that changes a task's outcome (paths, threads, force and the like do not):
# the config groups shared by many tasks, and the scalars that differ between tasks of a sweep.
SHARED_OUTCOME_KEYS = ("system", "arch", "train", "data_per_trajectory")
TASK_OUTCOME_KEYS = ("sweep_seed", "seed", "epochs", "data_tier", "width_tier", "depth_tier")


def shared_identity(values: Mapping[str, Any]) -> str:
    """Hash of the shared outcome-changing groups of a plain config dict."""
    return stable_hash({key: values[key] for key in SHARED_OUTCOME_KEYS})


def task_id_from(shared: str, values: Mapping[str, Any]) -> str:
    """A task's id from its ``shared_identity`` and its scalar coordinates (cheap for 63k tasks)."""
    return stable_hash([shared, *(values[key] for key in TASK_OUTCOME_KEYS)])


def task_id(cfg: DictConfig) -> str:
    """Hash of every config value that changes the task's outcome."""
    values = OmegaConf.to_container(cfg, resolve=True)
    return task_id_from(shared_identity(values), values)


def ensure_writable_dir(path: Path) -> None:
    """Create ``path`` if needed and prove a file can be written there, or raise ConfigError."""
    probe = path / f".write-test-{socket.gethostname()}-{time.monotonic_ns()}"
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe.touch()
    except OSError as error:
        raise ConfigError(f"out_dir={str(path)!r} is not writable ({error.strerror}); "
                          "choose a directory you can write to") from None
    probe.unlink()


@dataclass(frozen=True)
class TaskResult:
    path: Path
    row: dict[str, Any] | None  # None when the task was skipped because its row exists
    skipped: bool


def inject_fault(fault: Mapping[str, Any], seed: int) -> None:
    """Test-only fault injection: ``fault.kind`` 'raise' fails the task, 'hang' freezes it (no heartbeat),
    for tasks of seed ``fault.seed`` (every task when it is null). ``fault.once`` is applied by the job
    runner, which clears the fault for a task that already failed once."""
    if fault["kind"] is None or fault["seed"] not in (None, seed):
        return
    if fault["kind"] == "raise":
        raise RuntimeError(f"injected fault (fault.kind=raise, seed {seed})")
    if fault["kind"] == "hang":
        while True:
            time.sleep(3600)
    raise ConfigError(f"fault.kind={fault['kind']!r}; allowed: null, raise, hang")


def run_task(cfg: DictConfig, on_epoch: Callable[[], None] = lambda: None) -> TaskResult:
    """Train and score the task described by ``cfg`` and write its row under ``cfg.out_dir``.

    ``on_epoch`` is called after every epoch (a heartbeat for the watchdog of a job)."""
    started = time.perf_counter()
    spec = resolve_task(cfg)
    identifier = cfg.task_id or task_id(cfg)
    system_class = SYSTEMS[spec.system]
    torch.manual_seed(stable_seed("init", *spec.coordinates()))
    model = build_model(cfg.arch, system_class.state_dim, system_class.input_dim, spec.width, spec.depth)

    out_dir = Path(cfg.out_dir)
    path = row_path(out_dir, identifier)
    if path.exists() and not cfg.force:
        return TaskResult(path, None, skipped=True)
    ensure_writable_dir(out_dir)

    torch.set_num_threads(cfg.threads)
    cache = ArrayCache(cfg.cache_dir)
    system_cfg = OmegaConf.to_container(cfg.system, resolve=True)
    train_data = build_training_set(system_cfg, spec.seed, spec.n_traj, cache)
    test_data = build_test_set(system_cfg, cache)

    inject_fault(cfg.fault, spec.seed)
    train_started = time.perf_counter()
    scaling = Scaling.fit(train_data)
    outcome = train_model(model, train_data, scaling, cfg.train, spec.epochs,
                          stable_seed("shuffle", *spec.coordinates()), on_epoch)
    train_seconds = time.perf_counter() - train_started
    metrics = normalized_errors(test_data.dx, predict_derivative(model, test_data, scaling,
                                                                 getattr(torch, cfg.train.dtype)))
    finite = outcome.finite and all(math.isfinite(v) for v in metrics.values())

    params = parameter_count(model)
    points = training_points(spec.n_traj, points_per_trajectory(system_cfg))
    row = {
        "task_id": identifier,
        **asdict(spec),
        "train_points": points,
        "batch_size": cfg.train.batch_size,
        "lr": cfg.train.lr,
        "nmae": metrics["nmae"],
        "nmse": metrics["nmse"],
        "params": params,
        "flops": float(params) * spec.epochs * points,
        "steps": outcome.steps,
        "final_loss": outcome.final_loss,
        "status": "ok" if finite else "diverged",
        "train_seconds": train_seconds,
        "wall_seconds": time.perf_counter() - started,
        "package_version": nsl_hpc.__version__,
        "torch_version": torch.__version__,
        "python_version": platform.python_version(),
        "host": socket.gethostname(),
    }
    write_row_atomically(row, path)
    return TaskResult(path, row, skipped=False)


def describe(row: Mapping[str, Any]) -> str:
    """One line summarising a finished task."""
    return (f"{row['system']}/{row['arch']} seed={row['seed']} n_e={row['epochs']} d={row['data_size']:.2f} "
            f"n_h={row['width']} n_d={row['depth']}: nMAE={row['nmae']:.4g} nMSE={row['nmse']:.4g} "
            f"params={row['params']} flops={row['flops']:.3g} status={row['status']} "
            f"({row['wall_seconds']:.1f} s)")
