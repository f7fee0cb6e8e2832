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
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from nsl_hpc.config import plain
from nsl_hpc.config.schema import field_names, setting, typed
from nsl_hpc.core.checkpoint import Checkpointer
from nsl_hpc.core.errors import ConfigError, require_non_negative_int
from nsl_hpc.core.seeding import stable_hash
from nsl_hpc.studies import study_of
from nsl_hpc.studies.base import Pair, Study, Task
from nsl_hpc.studies.settings import Runtime
from nsl_hpc.sweep.code import code_of
from nsl_hpc.sweep.formats import package_version
from nsl_hpc.sweep.layout import pause_marker, row_path
from nsl_hpc.sweep.rehearsal import Rehearse, rehearsed_group
from nsl_hpc.sweep.rows import write_rows_atomically
from nsl_hpc.sweep.run_settings import Fault


@dataclass(frozen=True)
class TaskRun(Runtime):
    """How a task runs beside its pair's settings (conf/config.yaml's top-level keys): none changes its outcome
    but a rehearsal's."""

    out_dir: str = setting("its row goes to <out_dir>/rows/")
    force: bool = setting("recompute even when its row exists")
    task_id: str | None = setting("its id (null: the hash of every outcome-changing value)")
    compile_cache_dir: str | None = setting("Inductor's compiled kernels (null: torch's default)")
    fault: Fault = setting("test-only fault injection")
    rehearsal: bool = setting("true: nothing trains, outcomes are drawn from the planted laws")
    rehearse: Rehearse = setting("a rehearsal's planted laws and faults")


@dataclass(frozen=True)
class ResolvedTask:
    """A validated task: its study, the task as the study trains it (its pair's typed settings, coordinates, id and
    drawn sizes) and how it runs."""

    study: Study
    task: Task
    run: TaskRun

    @property
    def path(self) -> Path:
        """Where its row goes."""
        return row_path(Path(self.run.out_dir), self.task.task_id)


def resolve_task(cfg: Mapping[str, Any], sizes: Mapping[str, Any] | None = None, pair: Pair | None = None
                 ) -> ResolvedTask:
    """The task of a task config (plain or composed), its settings typed once (``Study.pair``, ``TaskRun``;
    ``pair``: those of its (system, arch), typed already) and checked, raising ConfigError before any work; its
    sizes drawn, or taken as drawn (``sizes``: a sweep's job takes them from the manifest, which is the truth)."""
    values = plain(cfg)
    study = study_of(values)
    for key in ("seed", "sweep_seed"):
        require_non_negative_int(key, values[key])
    pair = pair or study.pair(values)
    run = typed(TaskRun, {name: values[name] for name in field_names(TaskRun)}, "")
    for key in study.size_axes:
        study.check_coordinate(key, key, values[key], pair)
    coordinates = {"system": pair.system.name, "arch": pair.arch.name,
                   **{key: values[key] for key in study.task_keys}}
    sizes = dict(sizes) if sizes is not None else study.sizes(coordinates, pair)
    study.check_task(coordinates, sizes, pair)
    identity = run.task_id or task_id_from(study, study.shared_identity(pair.values), coordinates)
    return ResolvedTask(study, Task(pair, coordinates, identity, sizes, run.compile), run)


def check_settings(values: Mapping[str, Any]) -> Pair:
    """The typed settings of a task config's (system, arch) (``Study.pair``), raising ConfigError for a setting no
    task can run with: its pair's and how it runs (``TaskRun``)."""
    typed(TaskRun, {name: values[name] for name in field_names(TaskRun)}, "")
    return study_of(values).pair(values)


def task_id_from(study: Study, shared: str, values: Mapping[str, Any]) -> str:
    """A task's id from its study's ``shared_identity`` and its scalar coordinates (cheap for 63k tasks)."""
    return stable_hash([shared, *(values[key] for key in study.task_keys)])


def task_id(cfg: Mapping[str, Any]) -> str:
    """Hash of every config value that changes the task's outcome."""
    values = plain(cfg)
    study = study_of(values)
    return task_id_from(study, study.shared_identity(values), values)


def with_run(task: ResolvedTask, **changes: Any) -> ResolvedTask:
    """``task`` run with ``changes`` to its run settings (``compile``: as planned; ``fault``: cleared)."""
    run = replace(task.run, **changes)
    return ResolvedTask(task.study, replace(task.task, compile=run.compile), run)


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


def inject_fault(fault: Fault, seed: int) -> float:
    """Test-only fault injection, for tasks of seed ``fault.seed`` (every task when it is null): ``fault.kind``
    'raise' fails the task, 'hang' freezes it (no heartbeat), 'slow' returns ``fault.heartbeat_s``, the seconds
    to sleep at every heartbeat, so that training lasts at least that times its heartbeats on any machine (the
    outcome is unchanged); 0 otherwise. ``fault.once`` is applied by the job runner, which clears the fault for a
    task that already failed once."""
    if fault.kind is None or fault.seed not in (None, seed):
        return 0.0
    if fault.kind == "raise":
        raise RuntimeError(f"injected fault (fault.kind=raise, seed {seed})")
    if fault.kind == "hang":
        while True:
            time.sleep(3600)
    return float(fault.heartbeat_s) if fault.kind == "slow" else 0.0


def pause_if_asked(fault: Fault, seed: int, point: str, sweep_dir: Path) -> None:
    """Test-only (``fault.kind=pause``, for tasks of seed ``fault.seed``): at ``fault.pause_at`` (``point`` of a
    job: start, loading, between, end), the first time in the sweep, write ``<sweep_dir>/paused-<point>`` (what a
    test waits for before it signals the job) and sleep ``fault.pause_s``."""
    if fault.kind != "pause" or fault.pause_at != point or fault.seed not in (None, seed):
        return
    marker = pause_marker(sweep_dir, point)
    if marker.exists():
        return
    marker.touch()
    time.sleep(fault.pause_s)


def slowed(on_progress: Callable[[], None], seconds: float) -> Callable[[], None]:
    """``on_progress`` followed by a sleep of ``seconds`` (``fault.kind=slow``)."""
    def heartbeat() -> None:
        on_progress()
        time.sleep(seconds)
    return heartbeat


def run_task(cfg: Mapping[str, Any], on_progress: Callable[[], None] = lambda: None) -> TaskResult:
    """Train and score the task described by ``cfg`` and write its row under ``cfg.out_dir``.

    ``on_progress`` is called as training goes on (a heartbeat for a job's watchdog: at least once per epoch
    or per 32 steps)."""
    return run_tasks([resolve_task(cfg)], on_progress)[0]


def run_tasks(tasks: Sequence[ResolvedTask], on_progress: Callable[[], None] = lambda: None,
              checkpoint: Checkpointer | None = None) -> list[TaskResult]:
    """Train and score tasks of one study and shape together (in lockstep where the study can) and write
    one row per task, each the row the task would have alone (one file of them all, ``write_rows_atomically``);
    tasks whose row exists are skipped.
    ``checkpoint`` (of all of ``tasks``, used when none is skipped): training continues from it and writes it as
    it goes."""
    started = time.perf_counter()
    todo = [i for i, task in enumerate(tasks) if task.run.force or not task.path.exists()]
    results = [TaskResult(task.path, None, skipped=True) for task in tasks]
    if not todo:
        return results
    for i in todo:
        ensure_writable_dir(Path(tasks[i].run.out_dir))
    run = tasks[todo[0]].run
    if run.rehearsal:  # nothing trains: outcomes drawn from the planted laws
        outcomes = rehearsed_group(run.rehearse, [(tasks[i].task.task_id, tasks[i].task.sizes) for i in todo],
                                   on_progress)
        torch_version = "none (rehearsal)"
    else:
        outcomes, torch_version = trained_group([tasks[i] for i in todo], on_progress,
                                                checkpoint if len(todo) == len(tasks) else None)
    code = code_of(tasks[todo[0]].task.pair)  # the tasks of a group are of one (system, arch)
    rows = []
    for i, outcome in zip(todo, outcomes, strict=True):
        finite = outcome.pop("finite") and all(math.isfinite(outcome[key]) for key in ("nmae", "nmse"))
        task = tasks[i].task
        row = {
            "task_id": task.task_id,
            **task.coordinates,
            **task.sizes,
            "batch_size": task.pair.train.batch_size,
            "lr": task.pair.train.lr,
            **outcome,
            "status": "ok" if finite else "diverged",
            "wall_seconds": (time.perf_counter() - started) / len(todo),
            "package_version": package_version(),
            "code": code,
            "torch_version": torch_version,
            "python_version": platform.python_version(),
            "host": socket.gethostname(),
        }
        rows.append(row)
        results[i] = TaskResult(tasks[i].path, row, skipped=False)
    write_rows_atomically(rows, [tasks[i].path for i in todo])
    return results


def trained_group(tasks: Sequence[ResolvedTask], on_progress: Callable[[], None], checkpoint: Checkpointer | None
                  ) -> tuple[list[dict[str, Any]], str]:
    """The outcomes of training tasks of one study and shape together (``train_and_score_group``, from
    ``checkpoint``), and the torch version that trained them."""
    import torch  # here, not with the module: launch and resubmit plan with this module's checks without torch

    run = tasks[0].run
    torch.set_num_threads(run.threads)
    if run.compile_cache_dir:  # Inductor reads it when it first compiles
        os.environ["TORCHINDUCTOR_CACHE_DIR"] = str(Path(run.compile_cache_dir).resolve())
    delay = max(inject_fault(task.run.fault, task.task.coordinates["seed"]) for task in tasks)
    if delay > 0:
        on_progress = slowed(on_progress, delay)
    outcomes = tasks[0].study.train_and_score_group([task.task for task in tasks], on_progress, checkpoint)
    return outcomes, torch.__version__


def describe(row: Mapping[str, Any]) -> str:
    """One line summarising a finished task."""
    coordinates = " ".join(f"{key}={row[key]}" for key in ("seed", "epochs", "iter_multiplier") if key in row)
    return (f"{row['system']}/{row['arch']} {coordinates} N={row['train_points']} n_h={row['width']} "
            f"n_d={row['depth']}: nMAE={row['nmae']:.4g} nMSE={row['nmse']:.4g} params={row['params']} "
            f"flops={row['flops']:.3g} status={row['status']} ({row['wall_seconds']:.1f} s)")
