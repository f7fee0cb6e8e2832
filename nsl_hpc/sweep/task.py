"""One task of a sweep: validate its config, draw its sizes, train one model, score it, write its row.

What a task's coordinates are, how its sizes are drawn and how it trains is its study's business
(``nsl_hpc.studies``); the outcome depends on the config's outcome-changing values and nothing else.
"""

import math
import os
import platform
import socket
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

import nsl_hpc
from nsl_hpc.checkpoint import Checkpointer
from nsl_hpc.config import plain
from nsl_hpc.config.arch import arch_settings
from nsl_hpc.config.schema import typed
from nsl_hpc.errors import ConfigError, require_non_negative_int
from nsl_hpc.seeding import stable_hash
from nsl_hpc.studies import study_of
from nsl_hpc.studies.base import Study
from nsl_hpc.studies.settings import Runtime
from nsl_hpc.sweep.layout import row_path
from nsl_hpc.sweep.rehearsal import Rehearse, rehearsed_group
from nsl_hpc.sweep.rows import write_row_atomically
from nsl_hpc.sweep.run_settings import Fault


@dataclass(frozen=True)
class ResolvedTask:
    """A validated task: its study, coordinates (the study's axes and sweep_seed) and drawn sizes."""

    study: Study
    coordinates: dict[str, Any]
    sizes: dict[str, Any]


def resolve_task(cfg: Mapping[str, Any], sizes: Mapping[str, Any] | None = None) -> ResolvedTask:
    """Validate the task's keys (raising ConfigError before any work) and draw its sizes, or take ``sizes``
    as drawn (a sweep's job takes them from the manifest, which is the truth; they are not drawn again)."""
    values = plain(cfg)
    study = study_of(values)
    for key in ("seed", "sweep_seed"):
        require_non_negative_int(key, values[key])
    check_settings(values)
    for key in study.size_axes:
        study.check_coordinate(key, key, values[key], values)
    coordinates = {"system": values["system"]["name"], "arch": values["arch"]["name"],
                   **{key: values[key] for key in study.task_keys}}
    sizes = dict(sizes) if sizes is not None else study.sizes(coordinates, values)
    study.check_task(coordinates, sizes, values)
    return ResolvedTask(study, coordinates, sizes)


def check_settings(values: Mapping[str, Any]) -> None:
    """Raise ConfigError for a setting no task can run with (a plain task config): its study's groups
    (``Study.settings_schemas``: train, system, ...), its ``arch`` group (``config.arch``), the test-only
    ``fault``, a rehearsal's ``rehearse``, threads and compile."""
    for group, schema in (*study_of(values).settings_schemas, ("fault", Fault), ("rehearse", Rehearse)):
        typed(schema, values[group], group)
    arch_settings(values["arch"])
    Runtime.of(values)


def task_id_from(study: Study, shared: str, values: Mapping[str, Any]) -> str:
    """A task's id from its study's ``shared_identity`` and its scalar coordinates (cheap for 63k tasks)."""
    return stable_hash([shared, *(values[key] for key in study.task_keys)])


def task_id(cfg: Mapping[str, Any]) -> str:
    """Hash of every config value that changes the task's outcome."""
    values = plain(cfg)
    study = study_of(values)
    return task_id_from(study, study.shared_identity(values), values)


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


def inject_fault(fault: Mapping[str, Any], seed: int) -> float:
    """Test-only fault injection, for tasks of seed ``fault.seed`` (every task when it is null): ``fault.kind``
    'raise' fails the task, 'hang' freezes it (no heartbeat), 'slow' returns ``fault.heartbeat_s``, the seconds
    to sleep at every heartbeat, so that training lasts at least that times its heartbeats on any machine (the
    outcome is unchanged); 0 otherwise. ``fault.once`` is applied by the job runner, which clears the fault for a
    task that already failed once."""
    if fault["kind"] is None or fault["seed"] not in (None, seed):
        return 0.0
    if fault["kind"] == "raise":
        raise RuntimeError(f"injected fault (fault.kind=raise, seed {seed})")
    if fault["kind"] == "hang":
        while True:
            time.sleep(3600)
    return float(fault["heartbeat_s"])  # slow (``Fault`` allows no other kind)


def slowed(on_progress: Callable[[], None], seconds: float) -> Callable[[], None]:
    """``on_progress`` followed by a sleep of ``seconds`` (``fault.kind=slow``)."""
    def heartbeat() -> None:
        on_progress()
        time.sleep(seconds)
    return heartbeat


def run_task(cfg: DictConfig, on_progress: Callable[[], None] = lambda: None) -> TaskResult:
    """Train and score the task described by ``cfg`` and write its row under ``cfg.out_dir``.

    ``on_progress`` is called as training goes on (a heartbeat for a job's watchdog: at least once per epoch
    or per 32 steps)."""
    return run_tasks([cfg], on_progress)[0]


def run_tasks(cfgs: Sequence[Mapping[str, Any]], on_progress: Callable[[], None] = lambda: None,
              sizes: Sequence[Mapping[str, Any]] | None = None, checkpoint: Checkpointer | None = None
              ) -> list[TaskResult]:
    """Train and score tasks of one study and shape together (in lockstep where the study can) and write
    one row per task, each the row the task would have alone; tasks whose row exists are skipped.
    ``sizes``: each task's drawn sizes (``resolve_task``), drawn here when None. ``checkpoint`` (of all of
    ``cfgs``'s tasks, used when none is skipped): training continues from it and writes it as it goes."""
    started = time.perf_counter()
    tasks = [resolve_task(cfg, None if sizes is None else sizes[i]) for i, cfg in enumerate(cfgs)]
    paths = [row_path(Path(cfg["out_dir"]), cfg["task_id"] or task_id(cfg)) for cfg in cfgs]
    todo = [i for i, (cfg, path) in enumerate(zip(cfgs, paths, strict=True)) if cfg["force"] or not path.exists()]
    results = [TaskResult(path, None, skipped=True) for path in paths]
    if not todo:
        return results
    for i in todo:
        ensure_writable_dir(Path(cfgs[i]["out_dir"]))
    if cfgs[todo[0]].get("rehearsal"):  # nothing trains: outcomes drawn from the planted laws
        outcomes = rehearsed_group(plain(cfgs[todo[0]]["rehearse"]), [(paths[i].stem, tasks[i].sizes) for i in todo],
                                   on_progress)
        torch_version = "none (rehearsal)"
    else:
        outcomes, torch_version = trained_group([cfgs[i] for i in todo], [tasks[i] for i in todo],
                                                [paths[i].stem for i in todo], on_progress,
                                                checkpoint if len(todo) == len(cfgs) else None)
    for i, outcome in zip(todo, outcomes, strict=True):
        finite = outcome.pop("finite") and all(math.isfinite(outcome[key]) for key in ("nmae", "nmse"))
        row = {
            "task_id": paths[i].stem,
            **tasks[i].coordinates,
            **tasks[i].sizes,
            "batch_size": cfgs[i]["train"]["batch_size"],
            "lr": cfgs[i]["train"]["lr"],
            **outcome,
            "status": "ok" if finite else "diverged",
            "wall_seconds": (time.perf_counter() - started) / len(todo),
            "package_version": nsl_hpc.__version__,
            "torch_version": torch_version,
            "python_version": platform.python_version(),
            "host": socket.gethostname(),
        }
        write_row_atomically(row, paths[i])
        results[i] = TaskResult(paths[i], row, skipped=False)
    return results


def trained_group(configs: Sequence[Mapping[str, Any]], tasks: Sequence[ResolvedTask], ids: Sequence[str],
                  on_progress: Callable[[], None], checkpoint: Checkpointer | None) -> tuple[list[dict[str, Any]], str]:
    """The outcomes of training tasks of one study and shape together (``train_and_score_group``, from
    ``checkpoint``), and the torch version that trained them."""
    import torch  # here, not with the module: launch and resubmit plan with this module's checks without torch

    cfgs = [cfg if isinstance(cfg, DictConfig) else OmegaConf.create(dict(cfg)) for cfg in configs]
    torch.set_num_threads(cfgs[0].threads)
    if cfgs[0].get("compile_cache_dir"):  # Inductor reads it when it first compiles
        os.environ["TORCHINDUCTOR_CACHE_DIR"] = str(Path(cfgs[0].compile_cache_dir).resolve())
    delay = max(inject_fault(cfg.fault, cfg.seed) for cfg in cfgs)
    if delay > 0:
        on_progress = slowed(on_progress, delay)
    outcomes = tasks[0].study.train_and_score_group(
        [(cfg, {**task.coordinates, "task_id": task_id}, task.sizes) for cfg, task, task_id in zip(cfgs, tasks, ids,
                                                                                                 strict=True)],
        on_progress, checkpoint)
    return outcomes, torch.__version__


def describe(row: Mapping[str, Any]) -> str:
    """One line summarising a finished task."""
    coordinates = " ".join(f"{key}={row[key]}" for key in ("seed", "epochs", "iter_multiplier") if key in row)
    return (f"{row['system']}/{row['arch']} {coordinates} N={row['train_points']} n_h={row['width']} "
            f"n_d={row['depth']}: nMAE={row['nmae']:.4g} nMSE={row['nmse']:.4g} params={row['params']} "
            f"flops={row['flops']:.3g} status={row['status']} ({row['wall_seconds']:.1f} s)")
