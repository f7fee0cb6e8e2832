"""The training-speed benchmark's settings (conf/bench.yaml), typed once where ``python -m nsl_hpc.bench`` reads its
config (``bench_settings``) and passed to its parts as one ``BenchSettings``."""

from dataclasses import dataclass
from typing import Any

from nsl_hpc.config.mapping import plain
from nsl_hpc.config.schema import field_names, setting, typed
from nsl_hpc.config.system import InputStateSystem
from nsl_hpc.studies.settings import InputStateTrain

PARTS = ("input_state", "input_output", "compiled")


@dataclass(frozen=True)
class Size:
    """A model's size: hidden width n_h and depth n_d."""

    width: int = setting("hidden width n_h", 1)
    depth: int = setting("hidden layers n_d", 1)


@dataclass(frozen=True)
class TypicalTask:
    """The task whose phases are timed one by one (interpreter, imports, data, training, scoring, writing)."""

    arch: str = setting("its architecture")
    width: int = setting("its n_h", 1)
    depth: int = setting("its n_d", 1)
    n_traj: float = setting("its training trajectories", 0, low_open=True)
    epochs: int = setting("its epochs", 1)


@dataclass(frozen=True)
class Projection:
    """The (width, depth) grid on which the input-state per-step costs are measured, then interpolated per task."""

    widths: list[int] = setting("n_h values measured", 1, nonempty=True)
    depths: list[int] = setting("n_d values measured", 1, nonempty=True)
    steps: int = setting("optimizer steps per measurement", 1)


@dataclass(frozen=True)
class IoProjection:
    """The grid of the input-output per-iteration costs, per architecture."""

    widths: dict[str, list[int]] = setting("arch -> n_h values measured", 1, nonempty=True)
    depths: list[int] = setting("n_d values measured", 1, nonempty=True)
    iterations: dict[str, int] = setting("arch -> iterations per measurement", 1, nonempty=True)


@dataclass(frozen=True)
class IoBench:
    """The input-output rows (``nsl_hpc.bench.input_output``)."""

    system: str = setting("the system of the speed rows (a stand-in needs no measured files)")
    data_dir: str = setting("the measured records: the study's manifest and test lengths")
    train_points: int = setting("training prefix of the speed rows (samples)", 1)
    archs: list[str] = setting("the architectures measured", nonempty=True)
    iterations: dict[str, int] = setting("arch -> iterations per timed loop", 1, nonempty=True)
    repeats: int = setting("the fastest of this many runs", 1)
    sizes: dict[str, dict[str, Size]] = setting("arch -> size name -> (n_h, n_d)", nonempty=True)
    projection: IoProjection = setting("the per-iteration cost grid")


@dataclass(frozen=True)
class CompiledBench:
    """Compiled against eager steps (``nsl_hpc.bench.compiled``), each shape in two fresh processes."""

    blocks: int = setting("timed blocks of steps, after the first (it compiles)", 1)
    shapes: dict[str, list[list[int]]] = setting("arch -> [[n_h, n_d, K], ...]", 1, nonempty=True)
    profile: list[Any] = setting("[arch, n_h, n_d, K]: the shape whose step is profiled", nonempty=True)


@dataclass(frozen=True)
class BenchSettings:
    """What the benchmark measures; its input-state rows train on the task config's ``system`` and ``train`` groups
    (typed by their own owners, documented under them)."""

    system: InputStateSystem
    train: InputStateTrain
    parts: list[str] = setting("which tables to measure", choices=PARTS, nonempty=True)
    out: str | None = setting("write the headline figures as JSON here (null: nowhere)")
    readme: str | None = setting("replace the block between this file's bench markers with each table")
    steps: int = setting("optimizer steps per timed loop", 1)
    repeats: int = setting("the fastest of this many interleaved runs of each loop", 1)
    pack_size: int = setting("K, models trained in lockstep", 1)
    n_traj: float = setting("training trajectories of the speed table", 0, low_open=True)
    archs: list[str] = setting("the input-state architectures measured", nonempty=True)
    sizes: dict[str, Size] = setting("size name -> (n_h, n_d): the study's smallest and largest", nonempty=True)
    matmul_size: int = setting("the dense-matmul peak's square matrices", 1)
    typical_task: TypicalTask = setting("the task timed phase by phase")
    projection: Projection = setting("the per-step cost grid of the input-state projection")
    largest_task: list[str] = setting("train's key=value arguments of the largest input-state task", nonempty=True)
    io: IoBench = setting("the input-output rows")
    compiled: CompiledBench = setting("compiled against eager steps")


def bench_settings(config: Any) -> BenchSettings:
    """The benchmark's composed config (conf/bench.yaml), typed (one-line ConfigError)."""
    values = plain(config)
    return typed(BenchSettings, {name: values[name] for name in field_names(BenchSettings)}, "")
