"""Training of K input-state models of one architecture and depth in lockstep, each as if trained alone.

Each model keeps its own initial weights, width, data (size and scaling), shuffle generator, batch order,
epoch count and learning-rate schedule: at step s model k takes its own s-th mini-batch, exactly the one it
takes when trained alone (K = 1, the single-model path). Mini-batches of different lengths are padded and
masked; a model that has finished (or diverged) gets padding only (zero loss weight, learning rate 0) until
the end of the block, then leaves the stack (a compiled step keeps it while that keeps the stack's shape:
``studies.training.stack_rows``). The loss, the gradient-norm clipping and Adam
(torch.optim.Adam's arithmetic) are computed per model, in a few operations on the (K, P) parameter rows of
``stacked``. A model is kept (``Snapshot``) after its epochs and after each of its milestones.

Everything that does not depend on the parameters is prepared for a block of steps at once: the batches'
rows (one gather), their loss weights (the batch spreads of the targets) and the learning rates. A step is
then the forward pass, a four-operation loss, the backward pass and the optimizer step.
"""

import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from nsl_hpc.config.arch import Arch
from nsl_hpc.config.targets import labelled
from nsl_hpc.core.checkpoint import Checkpointer
from nsl_hpc.core.errors import ConfigError, one_line
from nsl_hpc.models import build_model
from nsl_hpc.models.state_space import StateSpaceModel
from nsl_hpc.studies.input_state.data import Dataset
from nsl_hpc.studies.input_state.module_stack import ModuleStack
from nsl_hpc.studies.input_state.scaling import Scaling
from nsl_hpc.studies.input_state.stacked import StackedModels
from nsl_hpc.studies.metrics import ErrorSums, spreads
from nsl_hpc.studies.settings import InputStateTrain, batch_bounds, learning_rate_at
from nsl_hpc.studies.training import (
    Adam,
    BatchOrder,
    LockstepRun,
    StepCompiler,
    TrainingOutcome,
    compiled_gradient,
    drive_lockstep,
)

BLOCK_STEPS = 32  # steps prepared at once: (K, BLOCK_STEPS, batch) rows of data in memory


@dataclass(frozen=True)
class Member:
    """One model of a lockstep group, initialised, with what it trains on: ``epochs`` of a learning-rate
    schedule ``schedule_epochs`` long (0: ``epochs``), each epoch ``repeat`` passes over ``data``
    (``InputStateTrain.passes``), kept (``Snapshot``) after each of ``milestones`` epochs (and after ``epochs``)."""

    model: nn.Module  # a StateSpaceModel, or a user's module (``ModuleStack``)
    data: Dataset
    scaling: Scaling
    epochs: int
    shuffle_seed: int
    milestones: tuple[int, ...] = ()
    schedule_epochs: int = 0
    repeat: int = 1


@dataclass(frozen=True)
class Snapshot:
    """A model after ``epochs`` epochs: how training went (``outcome.steps`` steps; a model that diverged
    before has its outcome of then) and its parameters, a row (P,) of the stack's ``theta``."""

    epochs: int
    outcome: TrainingOutcome
    theta: torch.Tensor

    def as_state(self) -> list:
        return [self.epochs, self.outcome.as_state(), self.theta]

    @classmethod
    def from_state(cls, state: list) -> "Snapshot":
        return cls(state[0], TrainingOutcome.from_state(state[1]), state[2])


class BatchPlan(BatchOrder):
    """The mini-batches of one member, step after step: each epoch a new permutation of its samples, each
    taken ``repeat`` times (the authors' ``--repeat``: the training set concatenated R times), by
    ``torch.randperm`` on its own generator, cut into ``batch_bounds`` slices, padded to ``width`` rows with the
    index ``pad``; once its ``steps`` are taken, only padding."""

    def __init__(self, samples: int, batch_size: int, epochs: int, seed: int, width: int, pad: int, repeat: int):
        bounds = batch_bounds(samples * repeat, batch_size)
        self.samples, self.repeat, self.fill, self.width = samples, repeat, pad, width
        self.steps = self.remaining = epochs * len(bounds)
        self.slots = torch.full((len(bounds), width), samples * repeat)  # position in the permutation; last: padding
        for j, (start, stop) in enumerate(bounds):
            self.slots[j, :stop - start] = torch.arange(start, stop)
        self.start(seed)

    def next_pass(self) -> torch.Tensor:
        order = torch.randperm(self.samples * self.repeat, generator=self.generator) % self.samples
        return torch.cat([order, order.new_tensor([self.fill])])[self.slots]

    def stop(self) -> None:
        """Take no more batches (the model diverged)."""
        self.remaining = 0


def loss_weights(targets: torch.Tensor, mask: torch.Tensor, outputs: int, loss: str, output_weight: float,
                 eps: float) -> torch.Tensor:
    """r (..., c, B) such that the loss of a batch is sum over c, b of ((predicted - target) r)^2. targets
    (..., c, B), feature-major: the state rows, then ``outputs`` output rows; mask (..., 1, B) of 0 / 1 (a batch
    with no unmasked sample gets r = 0).

    normalised_mse (the authors'): the mean over the unmasked entries of the state rows of
    ((predicted - target) / (s + eps))^2, s the standard deviation (ddof 1) of all those entries of the target,
    plus ``output_weight`` times the same for the output rows. per_column: the mean over the unmasked
    samples and the state rows of ((predicted - target) / s_j)^2, s_j the spread (ddof 0, at least eps) of
    target row j, plus ``output_weight`` times that mean over the output rows."""
    samples = mask.sum(dim=-1, keepdim=True).clamp_min(1.0)  # (..., 1, 1)
    states = targets.shape[-2] - outputs
    scales = []
    for block, share in ((targets[..., :states, :], 1.0), (targets[..., states:, :], output_weight)):
        entries = samples * block.shape[-2]
        if loss == "per_column":
            mean = (block * mask).sum(dim=-1, keepdim=True) / samples
            spread = (((block - mean) * mask).square().sum(dim=-1, keepdim=True) / samples).sqrt().clamp_min(eps)
        else:
            mean = (block * mask).sum(dim=(-2, -1), keepdim=True) / entries
            deviation = ((block - mean) * mask).square().sum(dim=(-2, -1), keepdim=True)
            spread = (deviation / (entries - 1).clamp_min(1.0)).sqrt() + eps
        scales.append(((share / entries).sqrt() / spread).expand(*block.shape[:-1], 1))  # (..., c_block, 1)
    return torch.cat(scales, dim=-2) * mask


def stacked_data(members: Sequence[Member], dtype: torch.dtype) -> torch.Tensor:
    """(K, N_max + 1, 2n + 2m): each member's scaled z, v, dz, y, zero-padded to the longest data set plus one
    row of zeros (the padding row of every member)."""
    parts = []
    for member in members:
        z, v = member.scaling.model_inputs(member.data, dtype)
        dz, y = member.scaling.model_targets(member.data, dtype)
        parts.append(torch.cat([z, v, dz, y], dim=1))
    rows = max(len(part) for part in parts) + 1
    return torch.stack([nn.functional.pad(part, (0, 0, 0, rows - len(part))) for part in parts])


Stack = StackedModels | ModuleStack


def stack_of(models: Sequence[nn.Module], dtype: torch.dtype, state_dim: int, input_dim: int) -> Stack:
    """``models`` (of systems of n = state_dim, m = input_dim) as one stack: batched MLP heads (``StackedModels``)
    for architectures the package can stack, else a ``ModuleStack`` of a user's modules."""
    heads = [model for model in models if isinstance(model, StateSpaceModel)]
    if len(heads) == len(models):
        return StackedModels(heads, dtype)
    return ModuleStack(list(models), dtype, state_dim, input_dim)


class InputStateLockstep(LockstepRun):
    """The models still training: their rows of the stack and of Adam's moments, their data and batch plans
    (``member`` maps a row to its member's index), and what each member has so far: its snapshots, its
    outcome once settled and the epochs it is still to be kept after."""

    block_steps = BLOCK_STEPS

    def __init__(self, members: Sequence[Member], train: InputStateTrain, compiler: StepCompiler | None = None):
        self.train = train
        self.dtype = getattr(torch, train.dtype)
        self.compiler = compiler or StepCompiler(False)
        self.compiled_losses = self.compiler.wrap(self.losses)
        self.stack = stack_of([member.model for member in members], self.dtype, members[0].data.x.shape[1],
                              members[0].data.u.shape[1])
        self.optimizer = Adam(self.stack.theta, train.grad_clip_norm, train.weight_decay)
        self.data = stacked_data(members, self.dtype)
        self.pad = self.data.shape[1] - 1
        batch = train.batch_size
        width = max(max(stop - start for start, stop in batch_bounds(len(mb.data) * mb.repeat, batch))
                    for mb in members)
        self.plans = [BatchPlan(len(mb.data), batch, mb.epochs, mb.shuffle_seed, width, self.pad, mb.repeat)
                      for mb in members]
        self.totals = np.array([plan.steps for plan in self.plans])
        self.total = int(self.totals.max(initial=0))
        self.schedules = np.array([(mb.schedule_epochs or mb.epochs) * len(plan.slots)
                                   for mb, plan in zip(members, self.plans, strict=True)])
        self.member = list(range(len(members)))
        self.pending = [sorted({*member.milestones, member.epochs}) for member in members]  # epochs not yet kept
        self.due: dict[int, list[tuple[int, int]]] = {}  # step index -> (member, epochs) kept after it
        for k, plan in enumerate(self.plans):
            for epochs in self.pending[k]:
                self.due.setdefault(epochs * len(plan.slots) - 1, []).append((k, epochs))
        self.snapshots: list[list[Snapshot]] = [[] for _ in members]
        self.outcomes: list[TrainingOutcome | None] = [
            None if plan.steps else TrainingOutcome(0, math.nan, finite=True) for plan in self.plans]
        self.active: list[int] = []  # steps of each row in the current block

    @property
    def rows(self) -> int:
        return len(self.member)

    def layout(self) -> dict[str, Any]:
        return {"theta": list(self.stack.theta.shape), "data": list(self.data.shape)}

    def state(self) -> dict[str, Any]:
        """The members' progress and the stack's: the members still training, their parameters, Adam's state,
        batch orders."""
        return {"pending": self.pending, "snapshots": [[snapshot.as_state() for snapshot in member]
                                                       for member in self.snapshots],
                "outcomes": [None if outcome is None else outcome.as_state() for outcome in self.outcomes],
                "run": {"member": list(self.member), "adam": self.optimizer.state(),
                        "plans": [plan.state() for plan in self.plans]}}

    def restore(self, state: Mapping[str, Any]) -> None:
        self.pending = state["pending"]
        self.snapshots = [[Snapshot.from_state(snapshot) for snapshot in member] for member in state["snapshots"]]
        self.outcomes = [TrainingOutcome.maybe_from_state(outcome) for outcome in state["outcomes"]]
        stack = state["run"]
        if len(stack["member"]) < len(self.member):
            self.keep(stack["member"])
        self.optimizer.load_state(stack["adam"])
        for plan, plan_state in zip(self.plans, stack["plans"], strict=True):
            plan.load_state(plan_state)

    def keep(self, rows: list[int]) -> None:
        index = torch.tensor(rows, dtype=torch.long)
        self.stack.keep(index)
        self.optimizer.keep(index, self.stack.theta)
        self.data = self.data[index]
        self.plans = [self.plans[row] for row in rows]
        self.totals, self.schedules = self.totals[rows], self.schedules[rows]
        self.member = [self.member[row] for row in rows]

    def losses(self, theta: torch.Tensor | None, inputs: torch.Tensor, weighted_targets: torch.Tensor,
               weights: torch.Tensor) -> torch.Tensor:
        """Each row's loss (K,) on one step's batch (feature-major: inputs (K, n + m, W), the targets times -r and
        r (K, n + m, W): ``loss_weights``), with the stack's parameters or ``theta`` (K, P)."""
        predicted = torch.cat(self.stack.forward(inputs, theta), dim=1)
        return torch.addcmul(weighted_targets, predicted, weights).square().sum(dim=(1, 2))

    def gradient(self, inputs: torch.Tensor, weighted_targets: torch.Tensor,
                 weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Each row's loss (K,) on one step's batch and its gradient (K, P), 0 on padding. Eager: autograd
        through the stack's layer views; compiled: through the compiled losses of a (K, P) leaf sharing the
        stack's parameters."""
        if not self.compiler.enabled:
            losses = self.losses(None, inputs, weighted_targets, weights)
            return losses, self.stack.parameter_gradient(losses.sum())
        return compiled_gradient(self.compiled_losses, self.stack.theta, self.stack.gradient_mask, inputs,
                                 weighted_targets, weights)

    def train_block(self, start: int, size: int) -> torch.Tensor:
        """Steps start .. start + size - 1 of every row, each model kept (``Snapshot``) after the steps its
        epochs are due; returns their losses (size, rows)."""
        n, m, train, dtype = self.stack.n, self.stack.m, self.train, self.dtype
        self.active = [min(size, plan.remaining) for plan in self.plans]
        rows = torch.stack([plan.take(size) for plan in self.plans])  # (K, L, W)
        offsets = (torch.arange(len(self.plans)) * self.data.shape[1])[:, None, None]
        index = (rows + offsets).transpose(0, 1)  # (L, K, W) rows of the flattened data
        gathered = self.data.flatten(0, 1).index_select(0, index.reshape(-1))  # 3-4x faster than indexing
        # (L, K, 2n + 2m, W): feature-major, as the stack computes
        batches = gathered.view(*index.shape, -1).transpose(-1, -2).contiguous()
        inputs, targets = batches[:, :, :n + m], batches[:, :, n + m:]
        weights = loss_weights(targets, (rows != self.pad).transpose(0, 1).unsqueeze(-2).to(dtype), m, train.loss,
                               train.output_weight, train.loss_std_eps)
        weighted_targets = -targets * weights
        steps = np.arange(start, start + size)[:, None]
        scheduled = learning_rate_at(steps, self.schedules, train.schedule, train.warmup_fraction, train.lr)
        rates = torch.as_tensor(scheduled * (steps < self.totals), dtype=dtype).unsqueeze(-1)  # (L, K, 1)
        losses = torch.empty(size, len(self.plans), dtype=dtype)
        for i in range(size):
            step_losses, grad = self.gradient(inputs[i], weighted_targets[i], weights[i])
            self.optimizer.step(grad, rates[i])
            losses[i] = step_losses.detach()
            self.take_snapshots(start + i, losses[i])
        return losses

    def take_snapshots(self, step: int, losses: torch.Tensor) -> None:
        """Keep the models whose epochs end with ``step``, with their ``losses`` (rows,) of that step."""
        for k, epochs in self.due.get(step, ()):
            if epochs not in self.pending[k]:  # it diverged and left with its snapshots
                continue
            row = self.member.index(k)
            loss = float(losses[row])
            self.snapshots[k].append(Snapshot(epochs, TrainingOutcome(step + 1, loss, finite=math.isfinite(loss)),
                                              self.stack.theta[row].detach().clone()))
            self.pending[k].remove(epochs)

    def settle(self, start: int, size: int, losses: torch.Tensor) -> list[int]:
        """The outcomes of the models that finished or diverged in the block; before the last block, a diverged
        model's later snapshots are its last parameters."""
        for row, k in enumerate(self.member):
            if self.outcomes[k] is None and self.active[row]:
                self.outcomes[k] = settle(self.plans[row], losses[:self.active[row], row], start)
        training = [row for row, k in enumerate(self.member) if self.outcomes[k] is None]
        if len(training) < len(self.member) and start + size < self.total:
            for row, k in enumerate(self.member):
                if (outcome := self.outcomes[k]) is not None:
                    self.snapshots[k] += [Snapshot(epochs, outcome, self.stack.theta[row].detach().clone())
                                          for epochs in self.pending[k]]
                    self.pending[k] = []
        return training


def train_lockstep(members: Sequence[Member], train: InputStateTrain, on_progress: Callable[[], None] = lambda: None,
                   checkpoint: Checkpointer | None = None, compiler: StepCompiler | None = None
                   ) -> tuple[Stack, list[list[Snapshot]]]:
    """Train every member as if alone with the ``train`` settings; returns the stack and each member's
    snapshots, by epochs (the last after its ``epochs``). Models that have finished leave the stack at the
    end of a block, so the stack holds the models that trained longest. ``on_progress``, ``checkpoint``: as
    ``drive_lockstep`` takes them. With an enabled ``compiler`` the step is compiled, and the stack keeps static
    shapes (``stack_rows``)."""
    run = InputStateLockstep(members, train, compiler)
    drive_lockstep(run, on_progress, checkpoint)
    return run.stack, [[with_divergence(snapshot, outcome) for snapshot in member_snapshots]
                       for member_snapshots, outcome in zip(run.snapshots, run.outcomes, strict=True)]


def with_divergence(snapshot: Snapshot, final: TrainingOutcome | None) -> Snapshot:
    """``snapshot`` with the outcome of its model's divergence when that came at or before its steps."""
    if final is not None and not final.finite and final.steps <= snapshot.outcome.steps:
        return Snapshot(snapshot.epochs, final, snapshot.theta)
    return snapshot


def settle(plan: BatchPlan, losses: torch.Tensor, start: int) -> TrainingOutcome | None:
    """A model's outcome after a block in which its steps from ``start`` on had ``losses``: diverged (steps up to
    the first non-finite loss; its plan stops) or, when its last step was in the block, its final loss;
    None while it trains on."""
    bad = torch.nonzero(~torch.isfinite(losses))
    if len(bad):
        plan.stop()
        return TrainingOutcome(start + int(bad[0, 0]) + 1, math.nan, finite=False)
    if plan.remaining == 0:
        return TrainingOutcome(plan.steps, float(losses[-1]), finite=True)
    return None


def derivative_chunks(stack: Stack, data: Dataset, scalings: Sequence[Scaling], dtype: torch.dtype,
                      theta: torch.Tensor | None = None, models: Sequence[int] | None = None,
                      on_progress: Callable[[], None] = lambda: None, chunk: int = 4096
                      ) -> Iterator[tuple[slice, np.ndarray]]:
    """dx/dt of every model of ``stack`` or, given ``theta`` (R, P), of the ``models`` (R indices of the stack's
    members) with those parameters, a scaling per row: per chunk of ``data``'s samples, the chunk's rows and the
    predictions (R, c, n) in physical units, computed without a graph. Memory grows with R x ``chunk``, not with
    the data. ``on_progress`` is called after each chunk (a heartbeat)."""
    rows = None if models is None else torch.as_tensor(models, dtype=torch.long)
    units = np.stack([scaling.derivative_unit for scaling in scalings])[:, None, :]  # (R, 1, n)
    for start in range(0, len(data), chunk):
        part = data.rows(start, start + chunk)
        zv = torch.stack([torch.cat(scaling.model_inputs(part, dtype), dim=1).T
                          for scaling in scalings])  # (R, n + m, c)
        with torch.no_grad():
            predicted = stack.forward(zv, theta, rows)[0].transpose(1, 2).double().numpy()
        on_progress()
        yield slice(start, start + len(part)), predicted * units


def predict_derivatives(stack: Stack, data: Dataset, scalings: Sequence[Scaling], dtype: torch.dtype,
                        theta: torch.Tensor | None = None, models: Sequence[int] | None = None) -> list[np.ndarray]:
    """Every prediction of ``derivative_chunks`` at once: a (N, n) array per model."""
    parts = [predicted for _, predicted in derivative_chunks(stack, data, scalings, dtype, theta, models)]
    return list(np.concatenate(parts, axis=1))


def score_derivatives(stack: Stack, data: Dataset, scalings: Sequence[Scaling], dtype: torch.dtype,
                      theta: torch.Tensor, models: Sequence[int], normalization: str,
                      on_progress: Callable[[], None] = lambda: None) -> list[dict[str, float]]:
    """The row scores (``ErrorSums.both_ways``) of the ``models`` with parameters ``theta`` on ``data``, chunk by
    chunk: a group scores on a test set of millions of samples in the memory of one chunk."""
    test_spreads = spreads(data.dx)
    sums = [ErrorSums(test_spreads) for _ in models]
    for rows, predicted in derivative_chunks(stack, data, scalings, dtype, theta, models, on_progress):
        for model_sums, model_predicted in zip(sums, predicted, strict=True):
            model_sums.add(model_predicted - data.dx[rows])
    return [model_sums.both_ways(normalization) for model_sums in sums]


def score_mean_predictor(data: Dataset, mean: np.ndarray, normalization: str) -> dict[str, float]:
    """The row scores (``ErrorSums.both_ways``) on ``data`` of the constant prediction ``mean`` (n,): what a model
    that learned nothing but the training set's mean dx/dt scores."""
    sums = ErrorSums(spreads(data.dx))
    sums.add(mean[None, :] - data.dx)
    return sums.both_ways(normalization)


def check_architecture(arch: Arch, state_dim: int, input_dim: int, width: int, depth: int, batch: int = 8) -> None:
    """Refuse in one line an architecture whose module does not give dx/dt (B, n) and y (B, m), finite, on a sample
    batch, or whose stacked form (two models, as the lockstep training runs them) computes something else."""
    label = labelled("arch", arch)
    generator = torch.Generator().manual_seed(0)
    z = torch.randn(2, batch, state_dim, generator=generator, dtype=torch.float64)
    v = torch.randn(2, batch, input_dim, generator=generator, dtype=torch.float64)
    models = []
    for k in range(2):
        torch.manual_seed(k)
        models.append(build_model(arch, state_dim, input_dim, width, depth).double())
    try:
        outputs = [models[k](z[k], v[k]) for k in range(2)]
        stack = stack_of(models, torch.float64, state_dim, input_dim)
        stacked = stack.forward(torch.cat([z, v], dim=-1).transpose(1, 2))
    except Exception as error:
        raise ConfigError(f"{label}: its model fails on a batch of {batch} samples ({type(error).__name__}: "
                          f"{one_line(error)[:200]})") from None
    for name, index, size in (("dx/dt", 0, state_dim), ("y", 1, input_dim)):
        shape = tuple(outputs[0][index].shape)
        if shape != (batch, size):
            raise ConfigError(f"{label}: its model gives {name} of shape {shape} for a batch of {batch}, expected "
                              f"({batch}, {size})")
        if not all(torch.isfinite(output[index]).all() for output in outputs):
            raise ConfigError(f"{label}: its model gives a {name} that is not finite on a sample batch")
        if not all(torch.allclose(stacked[index][k].T, outputs[k][index], rtol=1e-9, atol=1e-9) for k in range(2)):
            raise ConfigError(f"{label}: its stacked form computes another {name} than its module (assemble must "
                              "take every tensor through its layout argument)")
