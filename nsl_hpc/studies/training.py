"""What the training loops share: the outcome record, the batch order, Adam on the rows of a stack of models, the
compiled step (mini-batch bounds and the learning-rate schedules: ``studies.settings``) and the lockstep driver
(``drive_lockstep``: blocks of steps, settling, shrinking the stack, heartbeats, checkpoints). Each study trains its
models, alone or K in lockstep, through a ``LockstepRun`` of its own: ``input_state.lockstep`` (input-state models)
and ``input_output.lockstep`` (NARX and SUBNET).
"""

import functools
import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, TypeVar, cast

import numpy as np
import torch
from tqdm import tqdm

from nsl_hpc.core.checkpoint import Checkpointer

LOG = logging.getLogger(__name__)


def nonzero(scale: np.ndarray | float) -> np.ndarray:
    """A scale with zeros replaced by 1, so a constant column is centred, not blown up."""
    return np.where(scale > 0, scale, 1.0)


ADAM_BETAS, ADAM_EPS, CLIP_EPS = (0.9, 0.999), 1e-8, 1e-6  # torch.optim.Adam and clip_grad_norm_ defaults


@dataclass(frozen=True)
class TrainingOutcome:
    steps: int
    final_loss: float
    finite: bool

    def as_state(self) -> list:
        """A checkpoint's form of it (``from_state`` reads it back)."""
        return [self.steps, self.final_loss, self.finite]

    @classmethod
    def from_state(cls, state: list) -> "TrainingOutcome":
        return cls(*state)

    @classmethod
    def maybe_from_state(cls, state: list | None) -> "TrainingOutcome | None":
        """An outcome, or None (a model still training) as ``as_state`` stored it."""
        return None if state is None else cls(*state)


class BatchOrder:
    """The batches one model of a lockstep loop takes, step after step: each pass (epoch) a fresh permutation on
    its own ``generator`` (``next_pass``: the pass's batches, (batches, width) indices), then, once its
    ``remaining`` steps are taken, rows of ``fill`` (padding). Its ``state`` is what a checkpoint keeps: the
    generator's state before the current pass and how many of its batches are still to take (the pass is drawn
    again on ``load_state``), not the batches themselves."""

    generator: torch.Generator
    remaining: int
    fill: int
    width: int

    def start(self, seed: int) -> None:
        self.generator = torch.Generator().manual_seed(seed)
        self.pass_start: torch.Tensor | None = None  # the generator's state before the current pass
        self.pending = torch.empty(0, self.width, dtype=torch.long)  # the current pass's batches not yet taken

    def next_pass(self) -> torch.Tensor:
        raise NotImplementedError

    def take(self, count: int) -> torch.Tensor:
        """Indices (count, width) of the next ``count`` steps' batches."""
        wanted = min(count, self.remaining)
        parts, available = [self.pending], len(self.pending)
        while available < wanted:
            self.pass_start = self.generator.get_state()
            parts.append(self.next_pass())
            available += len(parts[-1])
        rows = torch.cat(parts)
        self.pending, self.remaining = rows[wanted:], self.remaining - wanted  # a tail of the current pass
        return torch.cat([rows[:wanted], rows.new_full((count - wanted, self.width), self.fill)])

    def state(self) -> dict:
        return {"pass_start": self.pass_start, "pending": len(self.pending), "remaining": self.remaining}

    def load_state(self, state: dict) -> None:
        self.remaining = state["remaining"]
        if state["pass_start"] is not None:
            self.pass_start = state["pass_start"]
            self.generator.set_state(self.pass_start)
            batches = self.next_pass()
            self.pending = batches[len(batches) - state["pending"]:]


class Adam:
    """torch.optim.Adam with gradient-norm clipping (clip_grad_norm_; ``clip_norm`` 0: none), per row of ``theta``
    (K, P); with ``weight_decay`` > 0, torch.optim.AdamW (the parameters scaled by 1 - lr x weight_decay before
    each update)."""

    def __init__(self, theta: torch.Tensor, clip_norm: float, weight_decay: float = 0.0):
        self.theta, self.clip_norm, self.weight_decay = theta, clip_norm, weight_decay
        self.first, self.second = torch.zeros_like(theta), torch.zeros_like(theta)
        self.steps = 0

    def keep(self, rows: torch.Tensor, theta: torch.Tensor) -> None:
        """Keep the moments of ``rows``; ``theta`` is the stack's new parameter tensor."""
        self.theta, self.first, self.second = theta, self.first[rows], self.second[rows]

    def state(self) -> dict:
        """The parameters, moments and step count (a checkpoint's part)."""
        return {"theta": self.theta.detach().clone(), "first": self.first.clone(), "second": self.second.clone(),
                "steps": self.steps}

    def load_state(self, state: dict) -> None:
        """Continue from ``state`` (of as many rows as ``theta`` has now)."""
        with torch.no_grad():
            self.theta.copy_(state["theta"])
        self.first.copy_(state["first"])
        self.second.copy_(state["second"])
        self.steps = state["steps"]

    def step(self, grad: torch.Tensor, lr: torch.Tensor) -> None:
        """One update from the parameters' gradient ``grad`` (K, P), overwritten, with learning rates ``lr``
        (K, 1)."""
        if self.clip_norm:
            norm = torch.linalg.vector_norm(grad, dim=1, keepdim=True)
            grad.mul_((self.clip_norm / (norm + CLIP_EPS)).clamp_max_(1.0))
        if self.weight_decay:
            self.theta.mul_(1.0 - lr * self.weight_decay)
        beta1, beta2 = ADAM_BETAS
        self.steps += 1
        self.first.lerp_(grad, 1 - beta1)
        self.second.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
        denominator = self.second.sqrt().div_(math.sqrt(1 - beta2 ** self.steps)).add_(ADAM_EPS)
        step_size = lr / (1 - beta1 ** self.steps)  # (K, 1)
        self.theta.addcdiv_(self.first * step_size, denominator, value=-1.0)


Step = TypeVar("Step", bound=Callable[..., Any])  # a function of tensors a StepCompiler compiles
RECOMPILE_LIMIT = 64  # compiled variants of one step function per process (a group needs at most 1 + log2 K)


class StepCompiler:
    """Whether a training loop runs its step function compiled (``torch.compile`` of the whole forward pass and
    loss, one static shape at a time, Inductor's fused kernels for it and its backward), and whether it still
    does: a compile that fails (no working C++ compiler on the node, an operation Inductor cannot lower) turns it
    off with one warning line on stderr, and the loop goes on eagerly. ``enabled`` after training is what the
    row's ``compiled`` column records."""

    def __init__(self, enabled: bool):
        self.enabled = enabled

    def wrap(self, step: Step) -> Step:
        """``step``, compiled while ``enabled`` (and a C++ compiler is found: without one the step is not traced
        and lowered first, about 8 s of CPU, only to fail)."""
        if not self.enabled:
            return step
        # imported here, not with the module: dynamo adds ~1 s to every command's and eager job's start-up
        from torch._dynamo.exc import FailOnRecompileLimitHit, TorchDynamoException
        from torch._inductor.cpp_builder import get_cpp_compiler
        from torch._inductor.exc import InvalidCxxCompiler

        try:
            get_cpp_compiler()  # Inductor's search (CXX, else its list of names); training runs on the CPU
        except InvalidCxxCompiler as error:
            self.disable(error)
            return step

        # a process may compile a step function for many groups and shapes; past the limit, fail (and train
        # eagerly, recorded as such) rather than run uncompiled while recorded compiled
        torch._dynamo.config.recompile_limit = RECOMPILE_LIMIT
        torch._dynamo.config.fail_on_recompile_limit_hit = True
        compiled = torch.compile(step, dynamic=False, fullgraph=True)

        def call(*args: torch.Tensor) -> Any:
            if self.enabled:
                try:
                    return compiled(*args)
                except (TorchDynamoException, FailOnRecompileLimitHit) as error:
                    self.disable(error)
            return step(*args)

        return cast(Step, call)

    def disable(self, error: Exception) -> None:
        """Train eagerly from here on, after one warning line naming ``error``."""
        self.enabled = False
        reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        LOG.warning("compiling the training step failed (%s); training eagerly", reason)


def compiled_gradient(losses_of: Callable[..., torch.Tensor], theta: torch.Tensor, mask: torch.Tensor,
                      *batch: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The losses (K,) ``losses_of(theta, *batch)`` of a step and their gradient (K, P), 0 where ``mask`` is,
    through a leaf that shares ``theta``'s storage (a compiled function differentiates whole, not through the
    stack's layer views)."""
    leaf = theta.detach().requires_grad_(True)
    losses = losses_of(leaf, *batch)
    (grad,) = torch.autograd.grad(losses.sum(), leaf)
    return losses, grad.mul_(mask)


def stack_rows(training: list[int], rows: int, static: bool) -> list[int]:
    """The rows a stack of ``rows`` keeps when only the rows ``training`` still train: those; with static shapes
    (a compiled step compiles once per shape), a power of two of rows, topped up with finished rows (learning
    rate 0, padding only: they change nothing), and all of them until that power is below ``rows``: a group
    of K compiles at most 1 + log2 K shapes."""
    if not static:
        return training
    size = 1 << (len(training) - 1).bit_length()
    if size >= rows:
        return list(range(rows))
    finished = [row for row in range(rows) if row not in set(training)]
    return sorted([*training, *finished[:size - len(training)]])


class LockstepRun:
    """K models of one study trained in lockstep, as ``drive_lockstep`` drives them: each step every row of the
    stack takes its own mini-batch and update; a model that has finished (or diverged) takes padding at learning
    rate 0 until its rows leave the stack. A study implements the hooks."""

    block_steps: int  # steps prepared and taken at once; a heartbeat, and a checkpoint's chance, after each block
    total: int  # steps of the longest-training model
    compiler: "StepCompiler"

    @property
    def rows(self) -> int:
        """Rows of the stack now (finished models that still fill a static shape included)."""
        raise NotImplementedError

    def layout(self) -> dict[str, Any]:
        """The shapes a checkpoint must have been written by (``Checkpointer.load``)."""
        raise NotImplementedError

    def state(self) -> dict[str, Any]:
        """What a checkpoint keeps besides the step the run stands at (plain containers and tensors)."""
        raise NotImplementedError

    def restore(self, state: Mapping[str, Any]) -> None:
        """Continue from ``state`` (``state()`` of a run of the same models, with its ``start``)."""
        raise NotImplementedError

    def train_block(self, start: int, size: int) -> torch.Tensor:
        """Steps start .. start + size - 1 of every row; their losses (size, rows)."""
        raise NotImplementedError

    def settle(self, start: int, size: int, losses: torch.Tensor) -> list[int]:
        """Record the outcomes the block's ``losses`` (size, rows) decide; the rows still training."""
        raise NotImplementedError

    def keep(self, rows: list[int]) -> None:
        """Train only these rows from now on."""
        raise NotImplementedError


def drive_lockstep(run: LockstepRun, on_progress: Callable[[], None] = lambda: None,
                   checkpoint: Checkpointer | None = None) -> None:
    """Train ``run`` to its end, block by block: after each, the outcomes settled, the stack shrunk to the rows
    still training (``stack_rows``: static shapes while the step is compiled), ``on_progress`` (a heartbeat) and,
    with ``checkpoint``, its state offered (written when due or when a stop was asked). A run with a checkpoint
    continues from it, bit for bit as if never stopped; at the end the checkpoint gets the state a stop during
    scoring writes (``Checkpointer.training_done``)."""
    start = 0
    saved = checkpoint.load(run.layout()) if checkpoint is not None else None
    if saved is not None:
        start = saved["start"]
        run.restore(saved)

    def state(at: int) -> dict[str, Any]:
        return {"start": at, **run.state()}

    with tqdm(total=run.total, initial=start, desc="steps", unit="step", disable=None, leave=False,
              mininterval=1.0) as bar:
        while start < run.total:
            size = min(run.block_steps, run.total - start)
            training = run.settle(start, size, run.train_block(start, size))
            start += size
            bar.update(size)
            on_progress()
            if not training or start >= run.total:
                break
            if len(rows := stack_rows(training, run.rows, run.compiler.enabled)) < run.rows:
                run.keep(rows)
            if checkpoint is not None:
                checkpoint.block_done(functools.partial(state, start), start, run.total)
    if checkpoint is not None:
        checkpoint.training_done(functools.partial(state, run.total), run.total)
