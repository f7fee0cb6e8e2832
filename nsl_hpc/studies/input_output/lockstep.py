"""NARX or SUBNET models of one architecture and depth trained K at a time in lockstep, each as if alone: the
input-output fast path (K = 1 is the single-model path; ``input_state.lockstep`` is the input-state one).

Each model keeps its own initial weights, width, training prefix (and its scaling), window shuffle, iteration
count and learning-rate schedule: at iteration s model k takes the s-th mini-batch it takes in the plain loop
(``training.train_io_model``: each pass a fresh permutation of its W windows on its own generator, cut into
W // b batches of b = min(B, W)). Batches of different sizes are padded and masked (zero loss weight); a model
that has finished gets padding and learning rate 0 until the end of the block of ``BLOCK_STEPS`` iterations,
then leaves. A model whose loss is not finite at the end of a pass has diverged (as in the plain loop) and
leaves at the end of the block (a compiled step keeps such models while that keeps the stack's shape:
``studies.training.stack_rows``).

The MLPs of all K models (``model.mlps()``) are one ``stacked.StackedMLPs``: batched MLPs, weights (K, in, n_h),
zero-padded to the widest n_h, whose activations are stored feature-major, (K, n_h, B), in a stack of several
models no wider than its architecture's ``train.feature_major_width``, batch-major, (K, B, n_h), otherwise. All
parameters of a model are one row of ``theta`` (K, P): clipping and Adam are a few operations on (K, P) tensors
(``studies.training.Adam``); ``studies.training.drive_lockstep`` runs the blocks (``IOLockstep`` holds the
hooks). SUBNET's T-step rollout advances all K models at once, and the inputs' part of f's
first layer is computed for all T steps at once; compiled, it is recomputed ``train.rollout_segment`` steps at a
time (``segmented_gradient``), so a backward reads the activations of a few steps, still in cache, rather than
those of all T.
"""

import functools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import torch
from torch import nn

from nsl_hpc.core.checkpoint import Checkpointer
from nsl_hpc.models.narx import NARX
from nsl_hpc.models.subnet import SUBNET
from nsl_hpc.studies.input_output.data import Signals
from nsl_hpc.studies.input_output.stacked import Layer, StackedMLPs, split_bypass
from nsl_hpc.studies.input_output.training import SignalScaling
from nsl_hpc.studies.settings import InputOutputTrain, learning_rate_at
from nsl_hpc.studies.training import (
    Adam,
    BatchOrder,
    LockstepRun,
    StepCompiler,
    TrainingOutcome,
    compiled_gradient,
    drive_lockstep,
)

BLOCK_STEPS = 16  # iterations whose batch orders and learning rates are prepared at once (a heartbeat each)
# SUBNET's h runs on the states of at most this many (K, B, n_h) values at once, per stack: an eager one's
# temporaries of 1 MiB stay in the caches (gradient steps 8-18% faster than at 2**21); a compiled one runs h on all
# steps of a segment, or of T, in one graph whose tensors stay small enough to be reused (a (32, 256 x 150, 32)
# tensor is a fresh mapping, 3x slower).
H_CHUNK_VALUES = {"eager": 2**18, "compiled": 2**21}


@dataclass(frozen=True)
class IOMember:
    """One model of a lockstep group, initialised, with what it trains on: the training prefix ``record``, its scaling,
    ``iterations`` optimizer steps, the seed of its window shuffle and its ``horizon`` (SUBNET's simulated steps
    per window, T or fewer where the prefix is shorter than one window: ``study.horizon``; NARX: 1)."""

    model: NARX | SUBNET
    record: Signals
    scaling: SignalScaling
    iterations: int
    shuffle_seed: int
    horizon: int


class Windows:
    """The training windows of the members' standardised records (zero-padded, (K, N)), by the index w of their
    first sample: NARX regressors y_{t-n_y..t-1}, u_{t-n_u..t} with t = w + max(n_y, n_u) and the target y_t;
    SUBNET sub-sequences u, y_{w..w+P+T-1}, T the longest of the members' horizons: a member of a shorter horizon
    T_k reads T - T_k samples more, whose errors count 0 (``step_mask``)."""

    def __init__(self, members: Sequence[IOMember], dtype: torch.dtype):
        model = members[0].model
        self.narx = isinstance(model, NARX)
        horizons = [member.horizon for member in members]
        self.horizon = max(horizons)
        if isinstance(model, NARX):
            if self.horizon != 1:
                raise ValueError(f"a NARX member trains one step ahead (horizon 1), not {self.horizon}")
            self.past = max(model.past_outputs, model.past_inputs)
        else:
            self.past, self.state_dim, self.residual = model.past, model.state_dim, model.residual
        self.counts = [len(member.record) - self.past - member.horizon + 1 for member in members]
        # (K, T, 1): 1 on each member's own steps; None when every member simulates all T
        self.step_mask = (None if min(horizons) == self.horizon else
                          (torch.arange(self.horizon) < torch.tensor(horizons)[:, None])[..., None])
        records = [member.scaling.normalise(member.record) for member in members]
        samples = max(len(member.record) + self.horizon - member.horizon for member in members)
        as_rows = lambda signals: torch.stack([  # noqa: E731
            nn.functional.pad(torch.as_tensor(signal, dtype=dtype), (0, samples - len(signal))) for signal in signals])
        self.u, self.y = as_rows(u for u, _ in records), as_rows(y for _, y in records)
        self.signals: torch.Tensor | None = None  # NARX: (y, u) concatenated (K, 2 N')
        if isinstance(model, NARX):  # positions in (y, u) concatenated of a window's regressors
            self.offsets = torch.cat([torch.arange(self.past - model.past_outputs, self.past),
                                      samples + torch.arange(self.past - model.past_inputs, self.past + 1)])
        else:
            self.offsets = torch.arange(self.past + self.horizon)
        if self.narx:
            self.signals = torch.cat([self.y, self.u], dim=1)

    def keep(self, rows: torch.Tensor) -> None:
        self.u, self.y = self.u[rows], self.y[rows]
        if self.signals is not None:
            self.signals = self.signals[rows]
        if self.step_mask is not None:
            self.step_mask = self.step_mask[rows]

    def index(self, starts: torch.Tensor) -> torch.Tensor:
        """Positions (K, len(offsets) B) of the samples at ``offsets`` after each of ``starts`` (K, B)."""
        return (starts[:, None] + self.offsets[:, None]).flatten(1)

    def gather(self, signal: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        """signal (K, N') at the positions ``index`` (K, len(offsets) B), feature-major: (K, len(offsets), B)."""
        return signal.gather(1, index).view(len(index), len(self.offsets), -1)

    def losses(self, nets: StackedMLPs, starts: torch.Tensor, weights: torch.Tensor,
               theta: torch.Tensor | None = None) -> torch.Tensor:
        """The loss (K,) of each model on its windows ``starts`` (K, B): the sum of ``weights`` (K, B) times the
        squared error of each window (NARX: one step ahead; SUBNET: summed over its T simulated steps), with
        the trained parameters or ``theta`` (K, P)."""
        stored = nets.computed(theta)
        layers = nets.oriented(stored)
        if self.signals is not None:  # NARX
            regressors = nets.activations(self.gather(self.signals, self.index(starts)))
            predicted = nets.run(regressors, layers["net"]).flatten(1)  # (K, B)
            target = self.y.gather(1, starts + self.past)
            return ((predicted - target).square() * weights).sum(dim=1)
        u, y = self.sequences(starts)
        x = self.encode(nets, layers, u, y)
        return self.simulate(nets, stored, layers, x, u[:, self.past:], y[:, self.past:], weights, self.step_mask)[0]

    def sequences(self, starts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """SUBNET's sub-sequences u, y (K, P + T, B) of the windows ``starts`` (K, B)."""
        index = self.index(starts)
        return self.gather(self.u, index), self.gather(self.y, index)

    def encode(self, nets: StackedMLPs, layers: Mapping[str, list[Layer]], u: torch.Tensor,
               y: torch.Tensor) -> torch.Tensor:
        """SUBNET's initial states of windows u, y (K, P + ..., B), from their first P samples: (K, n_x, B) or
        (K, B, n_x)."""
        return nets.run(nets.activations(torch.cat([u[:, :self.past], y[:, :self.past]], dim=1)), layers["encoder"])

    def simulate(self, nets: StackedMLPs, stored: Mapping[str, list[Layer]], layers: Mapping[str, list[Layer]],
                 x: torch.Tensor, u: torch.Tensor, y: torch.Tensor, weights: torch.Tensor,
                 step_mask: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """SUBNET's loss (K,) over the S steps of inputs u and targets y (K, S, B) simulated from states x (the
        errors of steps where ``step_mask`` (K, S, 1) is 0 left out; None: none), and the state after them."""
        models, batch = weights.shape
        states, x = self.rollout(nets, stored, layers, x, u)
        horizon = len(states)
        chunk = H_CHUNK_VALUES["compiled" if nets.compiled else "eager"]
        steps = max(1, chunk // (models * batch * nets.width))  # h of this many steps at once
        simulated = torch.cat([nets.run(torch.cat(states[k:k + steps], dim=nets.samples), layers["h"])
                               .view(models, -1, batch) for k in range(0, horizon, steps)], dim=1)  # (K, S, B)
        errors = simulated - y if step_mask is None else torch.where(step_mask, simulated - y, 0.0)
        return (errors.square().sum(dim=1) * weights).sum(dim=1), x

    def rollout(self, nets: StackedMLPs, stored: Mapping[str, list[Layer]], layers: Mapping[str, list[Layer]],
                x: torch.Tensor, u: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor]:
        """SUBNET's states over the S steps of inputs u (K, S, B) from states x: the S states its steps start
        from, and the state after them."""
        f, bypass = split_bypass(stored["f"])
        weight, bias, *_ = f[0]
        w_x, w_u, bias = (nets.orient(tensor) for tensor in (weight[:, :self.state_dim], weight[:, self.state_dim:],
                                                              bias))
        inputs = u.unsqueeze(nets.features)
        from_inputs = torch.addcmul(bias[:, None], inputs, w_u[:, None])  # (K, S, width, B) or (K, S, B, width):
        # u's part, every step; and of the bypass, (K, S, n_x, B) or (K, S, B, n_x)
        if bypass is not None:
            b_x, b_u = nets.orient(bypass[:, :self.state_dim]), nets.orient(bypass[:, self.state_dim:])
            bypass_inputs = (inputs * b_u[:, None]).unbind(1)
        states = []
        for s, from_input in enumerate(from_inputs.unbind(1)):  # unbind: one backward for all S (a slice's
            states.append(x)                                    # zero-fills all S)
            bypassed = None if bypass is None else nets.linear(x, b_x, bypass_inputs[s])
            change = nets.run(x, layers["f"], first=nets.linear(x, w_x, from_input), bypassed=bypassed)
            x = x + change if self.residual else change
        return states, x


class WindowOrder(BatchOrder):
    """The windows one member trains on, iteration after iteration: each pass a fresh ``torch.randperm`` of its
    ``windows`` (its own generator) cut into windows // b batches of b = min(B, windows); -1 pads a batch to
    ``width`` and fills the iterations after its last."""

    def __init__(self, windows: int, batch: int, iterations: int, seed: int, width: int):
        self.windows, self.batch, self.width, self.fill = windows, batch, width, -1
        self.per_pass, self.remaining = windows // batch, iterations
        self.start(seed)

    def next_pass(self) -> torch.Tensor:
        order = torch.randperm(self.windows, generator=self.generator)[:self.per_pass * self.batch]
        return nn.functional.pad(order.view(self.per_pass, self.batch), (0, self.width - self.batch), value=-1)


def settle(losses: np.ndarray, start: int, iterations: int, per_pass: int) -> TrainingOutcome | None:
    """The outcome of a model after this block's ``losses`` (its iterations start + 1 ..): diverged at the end
    of a pass with a non-finite loss, finished after ``iterations``, or None (still training)."""
    for i, loss in enumerate(losses[:max(0, iterations - start)].tolist()):
        taken = start + i + 1
        if (taken % per_pass == 0 or taken == iterations) and not math.isfinite(loss):
            return TrainingOutcome(taken, loss, finite=False)
        if taken == iterations:
            return TrainingOutcome(taken, loss, finite=True)
    return None


class IOLockstep(LockstepRun):
    """The models still training (``rows``: each row's member index, fillers of a static shape included), their
    stack, Adam's moments, windows and window orders, and each member's outcome and parameters once settled
    (``final``, (K, P))."""

    block_steps = BLOCK_STEPS

    def __init__(self, members: Sequence[IOMember], train: InputOutputTrain, compiler: StepCompiler | None = None):
        self.train = train
        self.dtype = getattr(torch, train.dtype)
        self.compiler = compiler or StepCompiler(False)
        self.windows = Windows(members, self.dtype)
        narx = self.windows.narx
        self.schedule = train.schedule["narx" if narx else "subnet"]
        self.nets = StackedMLPs([member.model for member in members], self.dtype,
                                train.feature_major_width["narx" if narx else "subnet"], self.compiler.enabled)
        self.optimizer = Adam(self.nets.theta, train.grad_clip_norm)
        segments = train.rollout_segment
        segment = 0 if narx else segments.feature_major if self.nets.feature_major else segments.batch_major
        self.compiled_gradient_of = step_gradient(self.windows, self.nets, self.compiler, segment)
        batches = [min(train.batch_size, count) for count in self.windows.counts]
        self.orders = [WindowOrder(count, batch, member.iterations, member.shuffle_seed, max(batches))
                       for count, batch, member in zip(self.windows.counts, batches, members, strict=True)]
        self.totals = np.array([member.iterations for member in members])
        self.total = int(self.totals.max(initial=0))
        self.shares = torch.tensor([1.0 / (batch * member.horizon)
                                    for batch, member in zip(batches, members, strict=True)], dtype=self.dtype)
        self.final = self.nets.theta.detach().clone()
        self.outcomes: list[TrainingOutcome | None] = [None if total else TrainingOutcome(0, math.nan, finite=True)
                                                       for total in self.totals]
        self.member = list(range(len(members)))
        if len(live := [k for k, outcome in enumerate(self.outcomes) if outcome is None]) < len(members):
            self.keep(live)

    @property
    def rows(self) -> int:
        return len(self.member)

    def layout(self) -> dict[str, Any]:
        return {"theta": list(self.nets.theta.shape), "windows": self.windows.counts}

    def state(self) -> dict[str, Any]:
        return {"final": self.final, "adam": self.optimizer.state(), "rows": self.member,
                "orders": [order.state() for order in self.orders],
                "outcomes": [None if outcome is None else outcome.as_state() for outcome in self.outcomes]}

    def restore(self, state: Mapping[str, Any]) -> None:
        self.final = state["final"]
        self.outcomes = [TrainingOutcome.maybe_from_state(outcome) for outcome in state["outcomes"]]
        for order, order_state in zip(self.orders, state["orders"], strict=True):
            order.load_state(order_state)
        if len(state["rows"]) < len(self.member):
            self.keep([self.member.index(k) for k in state["rows"]])
        self.optimizer.load_state(state["adam"])

    def keep(self, rows: list[int]) -> None:
        index = torch.tensor(rows, dtype=torch.long)
        self.nets.keep(index)
        self.optimizer.keep(index, self.nets.theta)
        self.windows.keep(index)
        self.member = [self.member[row] for row in rows]

    def train_block(self, start: int, size: int) -> torch.Tensor:
        rows, dtype = self.member, self.dtype
        starts = torch.stack([self.orders[k].take(size) for k in rows], dim=1)  # (L, K', width)
        weights = (starts >= 0).to(dtype) * self.shares[rows][:, None]
        steps = np.arange(start, start + size)[:, None]
        scheduled = learning_rate_at(steps, self.totals[rows], self.schedule, self.train.warmup_fraction,
                                     self.train.lr)
        rates = torch.as_tensor(scheduled, dtype=dtype).unsqueeze(-1)  # (L, K', 1): 0 after a model's last step
        losses = torch.empty(size, len(rows), dtype=dtype)
        for i in range(size):
            if self.compiler.enabled:
                step_losses, grad = self.compiled_gradient_of(self.nets.theta, self.nets.gradient_mask,
                                                              starts[i].clamp_min(0), weights[i])
            else:
                step_losses = self.windows.losses(self.nets, starts[i].clamp_min(0), weights[i])
                grad = self.nets.parameter_gradient(step_losses.sum())
            self.optimizer.step(grad, rates[i])
            losses[i] = step_losses.detach()
        return losses

    def settle(self, start: int, size: int, losses: torch.Tensor) -> list[int]:
        """The outcomes (and parameters) of the models that finished or diverged in the block."""
        for row, k in enumerate(self.member):
            if self.outcomes[k] is None:
                self.outcomes[k] = settle(losses[:, row].double().numpy(), start, int(self.totals[k]),
                                          self.orders[k].per_pass)
                if self.outcomes[k] is not None:
                    self.final[k] = self.nets.theta[row].detach()
        return [row for row, k in enumerate(self.member) if self.outcomes[k] is None]


def train_lockstep(members: Sequence[IOMember], train: InputOutputTrain,
                   on_progress: Callable[[], None] = lambda: None, checkpoint: Checkpointer | None = None,
                   compiler: StepCompiler | None = None) -> tuple[StackedMLPs, torch.Tensor, list[TrainingOutcome]]:
    """Train every member as if alone with the ``train`` settings; returns the group, each member's trained
    parameters (K, P) (rows of its ``theta`` layout) and outcomes. ``on_progress``, ``checkpoint``: as
    ``drive_lockstep`` takes them. With an enabled ``compiler`` the step is compiled, and the stack keeps static
    shapes (``stack_rows``)."""
    run = IOLockstep(members, train, compiler)
    drive_lockstep(run, on_progress, checkpoint)
    return run.nets, run.final, cast(list[TrainingOutcome], run.outcomes)  # every model has settled


def step_gradient(windows: Windows, nets: StackedMLPs, compiler: StepCompiler,
                  segment: int) -> Callable[..., tuple[torch.Tensor, torch.Tensor]]:
    """``gradient(theta, mask, starts, weights)``: the losses (K,) of a compiled step and their gradient (K, P),
    0 where ``mask`` is; with ``segment`` > 0 (SUBNET) the rollout is compiled and recomputed that many steps
    at a time (``segmented_gradient``), else the step is one compiled function (``compiled_step``)."""
    if segment:
        return functools.partial(segmented_gradient, windows,
                                 compiler.wrap(functools.partial(encode_step, windows, nets)),
                                 compiler.wrap(functools.partial(advance_step, windows, nets)),
                                 compiler.wrap(functools.partial(simulate_step, windows, nets)), segment)
    return functools.partial(compiled_gradient, compiler.wrap(functools.partial(compiled_step, windows, nets)))


def compiled_step(windows: Windows, nets: StackedMLPs, theta: torch.Tensor, starts: torch.Tensor,
                  weights: torch.Tensor) -> torch.Tensor:
    """``Windows.losses`` with parameters ``theta``: the function a ``StepCompiler`` compiles."""
    return windows.losses(nets, starts, weights, theta)


def encode_step(windows: Windows, nets: StackedMLPs, theta: torch.Tensor, u: torch.Tensor,
                y: torch.Tensor) -> torch.Tensor:
    """``Windows.encode`` with parameters ``theta``: a function a ``StepCompiler`` compiles."""
    return windows.encode(nets, nets.oriented(nets.computed(theta)), u, y)


def advance_step(windows: Windows, nets: StackedMLPs, theta: torch.Tensor, x: torch.Tensor,
                 u: torch.Tensor) -> torch.Tensor:
    """The state after SUBNET's steps of inputs u from states x, with parameters ``theta`` (``Windows.rollout``;
    no output map, no loss): a function a ``StepCompiler`` compiles."""
    stored = nets.computed(theta)
    return windows.rollout(nets, stored, nets.oriented(stored), x, u)[1]


def simulate_step(windows: Windows, nets: StackedMLPs, theta: torch.Tensor, x: torch.Tensor, u: torch.Tensor,
                  y: torch.Tensor, weights: torch.Tensor, step_mask: torch.Tensor | None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """``Windows.simulate`` with parameters ``theta``: a function a ``StepCompiler`` compiles."""
    stored = nets.computed(theta)
    return windows.simulate(nets, stored, nets.oriented(stored), x, u, y, weights, step_mask)


def segmented_gradient(windows: Windows, encode: Callable[..., torch.Tensor], advance: Callable[..., torch.Tensor],
                       simulate: Callable[..., Any], segment: int, theta: torch.Tensor, mask: torch.Tensor,
                       starts: torch.Tensor, weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """SUBNET's losses (K,) and their gradient (K, P) (0 where ``mask`` is), the rollout recomputed ``segment``
    steps at a time: a forward pass without gradients (``advance``: states only) keeps the states where segments
    start, then each segment, last first, runs again and back-propagates, so a backward reads the activations of
    one segment only."""
    u, y = windows.sequences(starts)
    past = windows.past
    leaf = theta.detach().requires_grad_(True)
    first = encode(leaf, u, y)
    bounds = list(range(past, past + windows.horizon, segment))
    states = [first.detach()]
    with torch.no_grad():
        for start in bounds[:-1]:
            states.append(advance(leaf, states[-1], u[:, start:start + segment]))
    grad, losses, upstream = torch.zeros_like(theta), torch.zeros(len(theta), dtype=theta.dtype), None
    for start, state in zip(reversed(bounds), reversed(states), strict=True):
        state = state.requires_grad_(True)
        steps = None if windows.step_mask is None else windows.step_mask[:, start - past:start - past + segment]
        segment_losses, end = simulate(leaf, state, u[:, start:start + segment], y[:, start:start + segment],
                                       weights, steps)
        outputs: list[torch.Tensor] = [segment_losses.sum()]
        upstreams: list[torch.Tensor | None] = [None]
        if upstream is not None:
            outputs.append(end)
            upstreams.append(upstream)
        theta_grad, upstream = torch.autograd.grad(outputs, [leaf, state], upstreams)
        grad += theta_grad
        losses += segment_losses.detach()
    (theta_grad,) = torch.autograd.grad(first, leaf, upstream)
    return losses, grad.add_(theta_grad).mul_(mask)
