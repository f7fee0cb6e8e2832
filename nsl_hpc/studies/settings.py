"""The training settings a config names, and the step arithmetic a plan needs, without torch: the commands that
check a config, plan a sweep or read one (launch's checks, status, merge, clean, resubmit) import this module,
not the training loops (``studies.training``; torch alone is ~1.5 s of a command's start).
"""

from dataclasses import dataclass

import numpy as np

from nsl_hpc.config.arch import IO_ARCHITECTURES, STUDIES
from nsl_hpc.config.schema import setting
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.studies.metrics import NORMALIZATIONS

SCHEDULES = ("warmup_cosine", "constant")
LOSSES = ("normalised_mse", "per_column")  # input-state training losses (``input_state.lockstep.loss_weights``)
COMPILE_MODES = ("auto", "always", "never")  # ``compile``: a sweep's planner resolves auto per group
DTYPES = ("float32", "float64")


@dataclass(frozen=True)
class InputStateTrain:
    """The ``train`` group of an input-state task (conf/train/default.yaml)."""

    lr: float = setting("peak learning rate of Adam", 0, low_open=True)
    schedule: str = setting("learning-rate schedule", choices=SCHEDULES)
    warmup_fraction: float = setting("linear warm-up over this fraction of the steps", 0, 1, high_open=True)
    schedule_epochs: int | None = setting("epoch milestones: the schedule's epochs (null: off)", 1)
    grad_clip_norm: float = setting("clip the global gradient norm to this", 0, low_open=True, also="0: no clipping")
    weight_decay: float = setting("AdamW's decoupled weight decay: each step scales the parameters by 1 - lr x this "
                                  "(0: Adam)", 0)
    batch_size: int = setting("samples per mini-batch", 1)
    repeat: int = setting("R: passes over the training set per counted epoch", 1)
    repeat_by_trajectories: list[list[float]] | None = setting(
        "[[n_t, R], ...] ascending: R of the last pair whose n_t is at most the task's trajectories (the first "
        "pair's below it); null: repeat", 0, low_open=True)
    loss: str = setting("training loss", choices=LOSSES)
    loss_std_eps: float = setting("added to the batch spread that divides the loss", 0, low_open=True)
    output_weight: float = setting("weight of the output (y) term of the loss", 0)
    rescale_targets: bool = setting("true: dx/dt and y rescaled (docs/science.md)")
    dtype: str = setting("training precision", choices=DTYPES)

    def check(self) -> None:
        rule = self.repeat_by_trajectories
        if rule is None:
            return
        if self.repeat != 1:
            raise ConfigError(f"train.repeat={self.repeat} and train.repeat_by_trajectories are both set: keep one "
                              "(repeat=1 with a rule)")
        if (not rule or any(len(pair) != 2 or pair[1] != int(pair[1]) for pair in rule)
                or [n_t for n_t, _ in rule] != sorted({n_t for n_t, _ in rule})):
            raise ConfigError(f"train.repeat_by_trajectories={rule} must be [[n_t, R], ...] pairs with n_t "
                              "ascending and R a positive integer, e.g. [[1, 50], [3, 20], [10, 10], [30, 5]]")

    def passes(self, trajectories: float) -> int:
        """R, the passes over the training set per counted epoch of a task on ``trajectories`` (n_t)."""
        return passes(self.repeat, self.repeat_by_trajectories, trajectories)


@dataclass(frozen=True)
class RolloutSegment:
    """Simulated steps a compiled SUBNET step recomputes at a time, per layout of its stack (0: one graph)."""

    feature_major: int = setting("a feature-major stack's segment", 0)
    batch_major: int = setting("a batch-major stack's segment", 0)


@dataclass(frozen=True)
class InputOutputTrain:
    """The ``train`` group of an input-output task (conf/train/input_output.yaml)."""

    lr: float = setting("peak learning rate of Adam", 0, low_open=True)
    schedule: dict[str, str] = setting("per arch: warmup_cosine (a linear warm-up, then cosine decay to 0) or "
                                       "constant", choices=SCHEDULES)
    warmup_fraction: float = setting("linear warm-up over this fraction of the iterations", 0, 1, high_open=True)
    grad_clip_norm: float = setting("clip the global gradient norm to this", 0, low_open=True)
    batch_size: int = setting("B: windows per mini-batch", 1)
    dtype: str = setting("training precision", choices=DTYPES)
    feature_major_width: dict[str, int] = setting("per arch: a stack of models no wider stores activations "
                                                  "(K, n_h, B)", 0)
    rollout_segment: RolloutSegment = setting("a compiled SUBNET step's rollout segments, per stack layout")

    def check(self) -> None:
        for key in ("schedule", "feature_major_width"):
            missing = sorted(set(IO_ARCHITECTURES) - set(getattr(self, key)))
            if missing:
                raise ConfigError(f"train.{key} needs a value for {', '.join(missing)} (one per architecture: "
                                  f"{', '.join(IO_ARCHITECTURES)})")


def passes(repeat: int, rule: list[list[float]] | None, trajectories: float) -> int:
    """R of a task on ``trajectories`` (n_t): ``repeat``, or with a ``rule`` [[n_t, R], ...] (ascending) the R
    of its last pair whose n_t is at most ``trajectories``, the first pair's below it."""
    if rule is None:
        return repeat
    return int(next((r for n_t, r in reversed(rule) if n_t <= trajectories), rule[0][1]))


def batch_count(samples: int, batch_size: int) -> int:
    """Mini-batches per epoch: ceil(samples / batch_size), less one when a single sample would trail."""
    count = -(-samples // batch_size)
    return count - 1 if count > 1 and samples % batch_size == 1 else count


def batch_bounds(samples: int, batch_size: int) -> list[tuple[int, int]]:
    """[start, stop) of each of the ``batch_count`` mini-batches; a trailing single sample joins the last."""
    starts = [i * batch_size for i in range(batch_count(samples, batch_size))]
    return [(start, stop) for start, stop in zip(starts, [*starts[1:], samples], strict=True)]


def warmup_cosine(total_steps: int, warmup_fraction: float, lr: float) -> np.ndarray:
    """Learning rate of each step (total_steps,): linear warm-up from 0 over the first fraction, then cosine
    decay to 0."""
    return learning_rate_at(np.arange(total_steps), np.asarray(total_steps), "warmup_cosine", warmup_fraction, lr)


def learning_rate_at(step: np.ndarray, total_steps: np.ndarray, schedule: str, warmup_fraction: float,
                     lr: float) -> np.ndarray:
    """The learning rate of ``schedule`` (one of SCHEDULES) at steps ``step`` of schedules ``total_steps`` steps
    long (broadcast together); 0 at and after a schedule's end. warmup_cosine is the authors' LambdaLR factor
    (stepped per batch): s / (w T) while s < w T, then (1 + cos(pi (s - w T) / ((1 - w) T))) / 2."""
    if schedule == "constant":
        rate = np.full(np.broadcast(step, total_steps).shape, lr)
    else:
        warmup = warmup_fraction * np.asarray(total_steps, dtype=float)
        rising = lr * step / np.maximum(warmup, 1e-12)
        progress = (step - warmup) / np.maximum(total_steps - warmup, 1e-12)
        rate = np.where(step < warmup, rising, lr * 0.5 * (1 + np.cos(np.pi * progress)))
    return np.where(step < total_steps, rate, 0.0)


@dataclass(frozen=True)
class StudyName:
    """The ``study`` group (conf/study/<name>.yaml): the study a config belongs to."""

    name: str = setting("input_state or input_output", choices=STUDIES)


@dataclass(frozen=True)
class Metric:
    """How an input-state task's errors are normalised (conf/study/input_state.yaml)."""

    normalization: str = setting("scalar: one spread of the whole dx/dt test matrix (the authors'); per_column: "
                                 "sigma_j per column (the paper's formula)", choices=NORMALIZATIONS)


@dataclass(frozen=True)
class Runtime:
    """How a task's process runs (conf/config.yaml's top-level keys): neither changes an outcome beyond float
    rounding."""

    threads: int = setting("torch intra-op threads (SLURM tasks are single-CPU)", 1)
    compile: str = setting("lockstep training steps compiled with torch.compile: always, never, or auto (where the "
                           "planner predicts the saving exceeds the compile time)", choices=COMPILE_MODES)
