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

The MLPs of all K models (``model.mlps()``) are batched MLPs, weights (K, in, n_h), zero-padded to the widest
n_h: LayerNorm averages over each model's own units and padded entries get exactly zero gradient, so a padded
model computes and learns what it does alone. A stack of several models no wider than its architecture's
``train.feature_major_width`` stores activations feature-major, (K, n_h, B), so a LayerNorm reduces over n_h
rows of B contiguous windows rather than over rows of a few units (as the input-state chains:
``input_state.stacked``); a model alone, or wider ones, batch-major, (K, B, n_h), where torch's fused LayerNorm
and fewer operations are faster. A feature-major or compiled stack computes a LayerNorm layer from its weights
centred over each model's units (``StackedMLPs.computed``): one reduction fewer per layer. All parameters of a
model are one row of ``theta`` (K, P): clipping and Adam are a few operations on (K, P) tensors
(``studies.training.Adam``). SUBNET's T-step rollout advances all K models at once, and the inputs' part of f's
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
from torch.nn import functional

from nsl_hpc.checkpoint import Checkpointer
from nsl_hpc.models.blocks import LAYER_NORM_EPS, masked_layer_norm
from nsl_hpc.models.narx import NARX
from nsl_hpc.models.subnet import SUBNET
from nsl_hpc.studies.input_output.data import Signals
from nsl_hpc.studies.input_output.training import SignalScaling
from nsl_hpc.studies.settings import learning_rate_at
from nsl_hpc.studies.training import (
    Adam,
    BatchOrder,
    StepCompiler,
    TrainingOutcome,
    compiled_gradient,
    stack_rows,
)

BLOCK_STEPS = 16  # iterations whose batch orders and learning rates are prepared at once (a heartbeat each)
# SUBNET's h runs on the states of at most this many (K, B, n_h) values at once, per stack: an eager one's
# temporaries of 1 MiB stay in the caches (gradient steps 8-18% faster than at 2**21); a compiled one runs h on all
# steps of a segment, or of T, in one graph whose tensors stay small enough to be reused (a (32, 256 x 150, 32)
# tensor is a fresh mapping, 3x slower).
H_CHUNK_VALUES = {"eager": 2**18, "compiled": 2**21}
# A compiled batch-major stack computes a product with at most this many output columns (f's and h's last layers:
# n_x, 1) as its transpose, (K, columns, B): MKL's batched GEMM writes few long rows several times faster than many
# rows of a few columns ((8, 256, 32) x (8, 32, 4): 62 against 14 us; its weight gradient 80 against 11 us); at 16
# columns the two are even. Eagerly the transposed layouts it passes on cost more than that (K = 8, 32 x 3: 14-18%
# slower).
NARROW_OUTPUTS = 8

Layer = tuple[torch.Tensor, ...]  # weight (K, in, out), bias (K, 1, out)[, LayerNorm scale, shift (K, 1, out)]


@dataclass(frozen=True)
class IOMember:
    """One model of a lockstep group, initialised, with what it trains on: the training prefix ``record``, its scaling,
    ``iterations`` optimizer steps and the seed of its window shuffle."""

    model: NARX | SUBNET
    record: Signals
    scaling: SignalScaling
    iterations: int
    shuffle_seed: int


def mlp_shape(net: nn.Sequential) -> tuple[int, int, int, bool]:
    """(inputs, outputs, depth, LayerNorm) of an MLP of ``nsl_hpc.models.blocks.mlp``."""
    linears = [layer for layer in net if isinstance(layer, nn.Linear)]
    return (linears[0].in_features, linears[-1].out_features, len(linears) - 1,
            any(isinstance(layer, nn.LayerNorm) for layer in net))


class StackedMLPs:
    """The MLPs of K models of one architecture, depth and block as batched MLPs; ``theta`` (K, P) holds every
    parameter, zero-padded to the widest hidden width ``width``. Their activations are stored feature-major when
    there are several models no wider than ``feature_major_width``, batch-major otherwise; a feature-major stack,
    or one whose step is ``compiled``, computes with ``centred`` LayerNorm weights; a compiled batch-major stack
    computes its products of few output columns as their transposes (``linear``)."""

    def __init__(self, models: Sequence[NARX | SUBNET], dtype: torch.dtype, feature_major_width: int = 0,
                 compiled: bool = False):
        first = models[0].mlps()
        self.shapes = {name: mlp_shape(net) for name, net in first.items()}
        if any({name: mlp_shape(net) for name, net in model.mlps().items()} != self.shapes for model in models):
            raise ValueError(f"models trained together need one architecture, depth and block ({type(models[0])}, "
                             f"MLPs {self.shapes}); widths may differ")
        own = [cast(nn.Linear, next(iter(model.mlps().values()))[0]).out_features for model in models]
        self.width = max(own)
        self.alone = len(models) == 1
        self.feature_major = not self.alone and self.width <= feature_major_width  # for the group's whole life
        # LayerNorm layers compute from centred weights (``computed``), except eager batch-major stacks: torch's
        # fused LayerNorm is faster there
        self.centred = self.feature_major or compiled
        self.compiled = compiled
        # an activation's dimensions of the units and of the B windows
        self.features, self.samples = (-2, -1) if self.feature_major else (-1, -2)
        size = sum(rows * columns for name in self.shapes for layer in self.tensor_shapes(name)
                   for rows, columns in layer)
        self.use_theta(torch.zeros(len(models), size, dtype=dtype))
        mask = torch.zeros_like(self.theta)
        with torch.no_grad():
            for k, model in enumerate(models):
                self.load(k, model, mask)
        self.gradient_mask = mask  # (K, P): 0 on padding
        units = torch.tensor(own, dtype=dtype)
        # mask (K, 1, width) of each model's own units, 1 / their number (K, 1, 1): every model built from
        self.model_units = (torch.arange(self.width) < units[:, None]).to(dtype)[:, None], (1.0 / units)[:, None, None]
        self.train_models(torch.arange(len(models)))

    def train_models(self, models: torch.Tensor) -> None:
        """The rows of ``theta`` hold ``models`` (K',), indices of the models the stack was built from."""
        self.models = models
        mask, inverse = self.model_units
        self.padded = bool((mask[models] == 0).any())  # some model training is narrower than ``width``
        self.units = (mask[models] if self.padded else None, inverse[models])

    def tensor_shapes(self, name: str) -> list[list[tuple[int, int]]]:
        """(rows, columns) of each tensor of each layer of MLP ``name``."""
        inputs, outputs, depth, layer_norm = self.shapes[name]
        norm = [(1, self.width)] * 2 if layer_norm else []
        return [*([[(fan_in, self.width), (1, self.width), *norm]
                   for fan_in in [inputs] + [self.width] * (depth - 1)]),
                [(self.width, outputs), (1, outputs)]]

    def layers(self, theta: torch.Tensor) -> dict[str, list[Layer]]:
        """Per MLP, per layer, views (K, rows, columns) of its tensors in ``theta`` (K, P)."""
        views, offset = {}, 0
        for name in self.shapes:
            layers = []
            for shapes in self.tensor_shapes(name):
                tensors = []
                for rows, columns in shapes:
                    tensors.append(theta[:, offset:offset + rows * columns].view(-1, rows, columns))
                    offset += rows * columns
                layers.append(tuple(tensors))
            views[name] = layers
        return views

    def computed(self, theta: torch.Tensor | None = None) -> dict[str, list[Layer]]:
        """The layers as the stack computes with them: ``trained``, or views of ``theta`` (K, P); when ``centred``,
        each LayerNorm layer's weight and bias centred over each model's own units (padding stays 0). The mean over
        a model's units of x W + b is x (W 1 / n) + mean(b), so the LayerNorm of x W + b is x W_c + b_c over its
        root mean square: one reduction fewer per hidden layer, forward and backward; only rounding differs."""
        layers = self.trained if theta is None else self.layers(theta)
        if not self.centred:
            return dict(layers)
        mask, inverse = self.units
        return {name: [tuple(self.centre(tensor, mask, inverse) for tensor in layer[:2]) + layer[2:]
                       if len(layer) == 4 else layer for layer in mlp] for name, mlp in layers.items()}

    @staticmethod
    def centre(tensor: torch.Tensor, mask: torch.Tensor | None, inverse: torch.Tensor) -> torch.Tensor:
        """A weight (K, in, width) or bias (K, 1, width) less its mean over each model's own units (``mask``
        (K, 1, width), None: all; ``inverse`` (K, 1, 1): 1 / their number); padded columns, 0, stay 0."""
        centred = tensor - tensor.sum(dim=-1, keepdim=True) * inverse
        return centred if mask is None else centred * mask

    def use_theta(self, theta: torch.Tensor) -> None:
        """Hold the parameters in ``theta`` (K, P); the trained layers are leaf views into it."""
        self.theta = theta
        self.trained = self.layers(theta)
        self.parameters = [tensor.requires_grad_(True) for layers in self.trained.values() for layer in layers
                           for tensor in layer]

    def load(self, k: int, model: NARX | SUBNET, mask: torch.Tensor) -> None:
        """Copy the parameters of ``model`` into row k; set its entries of ``mask`` (K, P) to 1."""
        masks = self.layers(mask)
        for name, net in model.mlps().items():
            linears = [layer for layer in net if isinstance(layer, nn.Linear)]
            norms = [layer for layer in net if isinstance(layer, nn.LayerNorm)] + [None] * len(linears)
            for tensors, mask_tensors, linear, norm in zip(self.trained[name], masks[name], linears, norms,
                                                           strict=False):
                values = [linear.weight.T, linear.bias[None]]
                if norm is not None:
                    values += [norm.weight[None], norm.bias[None]]
                for tensor, tensor_mask, value in zip(tensors, mask_tensors, values, strict=True):
                    tensor[k, :value.shape[0], :value.shape[1]] = value
                    tensor_mask[k, :value.shape[0], :value.shape[1]] = 1.0

    def keep(self, rows: torch.Tensor) -> None:
        """Keep only the models of ``rows`` (K',): ``theta`` becomes a new (K', P) tensor."""
        self.use_theta(self.theta.detach()[rows])
        self.gradient_mask = self.gradient_mask[rows]
        self.train_models(self.models[rows])

    def parameter_gradient(self, loss: torch.Tensor) -> torch.Tensor:
        """d loss / d parameters (K, P), exactly 0 on padding entries."""
        grads = torch.autograd.grad(loss, self.parameters, materialize_grads=True)
        return torch.cat([grad.reshape(len(self.theta), -1) for grad in grads], dim=1).mul_(self.gradient_mask)

    def orient(self, tensor: torch.Tensor) -> torch.Tensor:
        """A parameter tensor (K, rows, columns) as the stack's layout multiplies or adds it: transposed when
        feature-major (a weight (K, out, in), a bias or LayerNorm affine (K, out, 1))."""
        return tensor.mT if self.feature_major else tensor

    def oriented(self, layers: Mapping[str, list[Layer]]) -> dict[str, list[Layer]]:
        """``layers`` (as ``layers`` gives them) with every tensor oriented: what ``run`` takes."""
        return {name: [tuple(self.orient(tensor) for tensor in layer) for layer in mlp] for name, mlp in layers.items()}

    def activations(self, x: torch.Tensor) -> torch.Tensor:
        """Inputs x (K, in, B) in the stack's layout: as they are, or (K, B, in) batch-major."""
        return x if self.feature_major else x.mT

    def run(self, x: torch.Tensor, layers: list[Layer], first: torch.Tensor | None = None) -> torch.Tensor:
        """Output of one MLP, its ``layers`` oriented, for inputs x, or from its first layer's pre-activation
        ``first`` (then x is not read); activations in the stack's layout: (K, features, B) or (K, B, features)."""
        for weight, bias, *norm in layers[:-1]:
            a = self.linear(x, weight, bias) if first is None else first
            first, x = None, self.activate(a, norm)
        weight, bias = layers[-1]
        return self.linear(x, weight, bias)

    def linear(self, x: torch.Tensor, weight: torch.Tensor, added: torch.Tensor) -> torch.Tensor:
        """An oriented ``weight`` applied to x plus ``added`` (an oriented bias, or a pre-activation part); a
        compiled batch-major stack computes a product of at most ``NARROW_OUTPUTS`` columns as its transpose."""
        if self.feature_major:
            return torch.baddbmm(added, weight, x)
        if self.compiled and weight.shape[-1] <= NARROW_OUTPUTS:
            return torch.baddbmm(added.mT, weight.mT, x.mT).mT
        return torch.baddbmm(added, x, weight)

    def activate(self, a: torch.Tensor, norm: list[torch.Tensor]) -> torch.Tensor:
        """A hidden layer's activation of its pre-activation a: tanh, or LayerNorm over each model's own units
        with its oriented scale and shift, then SiLU. When ``centred`` a is already centred (``computed``) and
        the LayerNorm divides it by its root mean square; else (batch-major, eager) torch's fused LayerNorm where
        every model uses all units (with the affine part for a model alone, as its module), or the masked
        formula of ``masked_layer_norm``."""
        if not norm:
            return torch.tanh(a)
        scale, shift = norm
        if self.centred:  # padded units of a are 0
            mean_square = a.square().sum(dim=self.features, keepdim=True) * self.units[1]
            normalized = a * (mean_square + LAYER_NORM_EPS).rsqrt()
        elif self.alone:
            return functional.silu(functional.layer_norm(a, a.shape[-1:], scale.view(-1), shift.view(-1),
                                                         LAYER_NORM_EPS))
        elif self.padded:
            normalized, _ = masked_layer_norm(a, self.units[0], self.units[1])
        else:  # every model as wide as the stack: torch's fused LayerNorm without its affine part
            normalized = functional.layer_norm(a, a.shape[-1:], eps=LAYER_NORM_EPS)
        return functional.silu(torch.addcmul(shift, normalized, scale))


class Windows:
    """The training windows of the members' standardised records (zero-padded to the longest, (K, N)), by
    the index w of their first sample: NARX regressors y_{t-n_y..t-1}, u_{t-n_u..t} with t = w + max(n_y, n_u)
    and the target y_t; SUBNET sub-sequences u, y_{w..w+P+T-1}."""

    def __init__(self, members: Sequence[IOMember], horizon: int, dtype: torch.dtype):
        model = members[0].model
        self.narx = isinstance(model, NARX)
        if isinstance(model, NARX):
            self.past = max(model.past_outputs, model.past_inputs)
            length = self.past + 1
        else:
            self.past, self.horizon, self.state_dim = model.past, horizon, model.state_dim
            length = model.past + horizon
        self.counts = [len(member.record) - length + 1 for member in members]
        records = [member.scaling.normalise(member.record) for member in members]
        samples = max(len(member.record) for member in members)
        as_rows = lambda signals: torch.stack([  # noqa: E731
            nn.functional.pad(torch.as_tensor(signal, dtype=dtype), (0, samples - len(signal))) for signal in signals])
        self.u, self.y = as_rows(u for u, _ in records), as_rows(y for _, y in records)
        self.signals: torch.Tensor | None = None  # NARX: (y, u) concatenated (K, 2 N')
        if isinstance(model, NARX):  # positions in (y, u) concatenated of a window's regressors
            self.offsets = torch.cat([torch.arange(self.past - model.past_outputs, self.past),
                                      samples + torch.arange(self.past - model.past_inputs, self.past + 1)])
        else:
            self.offsets = torch.arange(length)
        if self.narx:
            self.signals = torch.cat([self.y, self.u], dim=1)

    def keep(self, rows: torch.Tensor) -> None:
        self.u, self.y = self.u[rows], self.y[rows]
        if self.signals is not None:
            self.signals = self.signals[rows]

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
        return self.simulate(nets, stored, layers, x, u[:, self.past:], y[:, self.past:], weights)[0]

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
                 x: torch.Tensor, u: torch.Tensor, y: torch.Tensor, weights: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        """SUBNET's loss (K,) over the S steps of inputs u and targets y (K, S, B) simulated from states x, and
        the state after them."""
        models, batch = weights.shape
        states, x = self.rollout(nets, stored, layers, x, u)
        horizon = len(states)
        chunk = H_CHUNK_VALUES["compiled" if nets.compiled else "eager"]
        steps = max(1, chunk // (models * batch * nets.width))  # h of this many steps at once
        simulated = torch.cat([nets.run(torch.cat(states[k:k + steps], dim=nets.samples), layers["h"])
                               .view(models, -1, batch) for k in range(0, horizon, steps)], dim=1)  # (K, S, B)
        return ((simulated - y).square().sum(dim=1) * weights).sum(dim=1), x

    def rollout(self, nets: StackedMLPs, stored: Mapping[str, list[Layer]], layers: Mapping[str, list[Layer]],
                x: torch.Tensor, u: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor]:
        """SUBNET's states over the S steps of inputs u (K, S, B) from states x: the S states its steps start
        from, and the state after them."""
        weight, bias, *_ = stored["f"][0]
        w_x, w_u, bias = (nets.orient(tensor) for tensor in (weight[:, :self.state_dim], weight[:, self.state_dim:],
                                                              bias))
        from_inputs = torch.addcmul(bias[:, None], u.unsqueeze(nets.features),
                                    w_u[:, None])  # (K, S, width, B) or (K, S, B, width): u's part, every step
        states = []
        for from_input in from_inputs.unbind(1):  # unbind: one backward for all S (a slice's zero-fills all S)
            states.append(x)
            x = x + nets.run(x, layers["f"], first=nets.linear(x, w_x, from_input))
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


def train_lockstep(members: Sequence[IOMember], cfg: Mapping[str, Any], horizon: int,
                   on_progress: Callable[[], None] = lambda: None, checkpoint: Checkpointer | None = None,
                   compiler: StepCompiler | None = None) -> tuple[StackedMLPs, torch.Tensor, list[TrainingOutcome]]:
    """Train every member as if alone (``cfg`` is the ``train`` group; ``horizon``: SUBNET's T); returns the
    group, each member's trained parameters (K, P) (rows of its ``theta`` layout) and outcomes. ``on_progress``
    is called after every block of ``BLOCK_STEPS`` iterations (a heartbeat); ``checkpoint`` continues from its
    state, if any, and gets the state after each block (a resumed run gives the same outcomes, bit for bit) and,
    at the end, the state a stop during scoring writes (``Checkpointer.training_done``).
    With an enabled ``compiler`` the step is compiled, and the stack keeps static shapes (``stack_rows``)."""
    dtype = getattr(torch, cfg["dtype"])
    compiler = compiler or StepCompiler(False)
    windows = Windows(members, horizon, dtype)
    nets = StackedMLPs([member.model for member in members], dtype,
                       cfg["feature_major_width"]["narx" if windows.narx else "subnet"], compiler.enabled)
    optimizer = Adam(nets.theta, cfg["grad_clip_norm"])
    segment = 0 if windows.narx else cfg["rollout_segment"]["feature_major" if nets.feature_major else "batch_major"]
    compiled_gradient_of = step_gradient(windows, nets, compiler, segment)
    batches = [min(cfg["batch_size"], count) for count in windows.counts]
    orders = [WindowOrder(count, batch, member.iterations, member.shuffle_seed, max(batches))
              for count, batch, member in zip(windows.counts, batches, members, strict=True)]
    totals = np.array([member.iterations for member in members])
    shares = torch.tensor([1.0 / (batch * (1 if windows.narx else horizon)) for batch in batches], dtype=dtype)
    final = nets.theta.detach().clone()
    outcomes: list[TrainingOutcome | None] = [None if total else TrainingOutcome(0, math.nan, finite=True)
                                              for total in totals]
    start, total = 0, int(totals.max(initial=0))
    layout = {"theta": list(nets.theta.shape), "windows": windows.counts}
    saved = checkpoint.load(layout) if checkpoint is not None else None
    if saved is not None:
        start, final = saved["start"], saved["final"]
        outcomes = [TrainingOutcome.maybe_from_state(outcome) for outcome in saved["outcomes"]]
        for order, order_state in zip(orders, saved["orders"], strict=True):
            order.load_state(order_state)
    live = [k for k, outcome in enumerate(outcomes) if outcome is None]
    rows = saved.get("rows", live) if saved is not None else live  # the members in the stack (fillers too)
    if len(rows) < len(members):
        leave(nets, optimizer, windows, rows)
    if saved is not None:
        optimizer.load_state(saved["adam"])

    def state(start: int) -> dict[str, Any]:
        return {"start": start, "final": final, "adam": optimizer.state(), "rows": rows,
                "orders": [order.state() for order in orders],
                "outcomes": [None if outcome is None else outcome.as_state() for outcome in outcomes]}

    while live:
        size = min(BLOCK_STEPS, total - start)
        starts = torch.stack([orders[k].take(size) for k in rows], dim=1)  # (L, K', width)
        weights = (starts >= 0).to(dtype) * shares[rows][:, None]
        steps = np.arange(start, start + size)[:, None]
        scheduled = learning_rate_at(steps, totals[rows], "warmup_cosine", cfg["warmup_fraction"], cfg["lr"])
        rates = torch.as_tensor(scheduled, dtype=dtype).unsqueeze(-1)  # (L, K', 1): 0 after a model's last step
        losses = torch.empty(size, len(rows), dtype=dtype)
        for i in range(size):
            if compiler.enabled:
                step_losses, grad = compiled_gradient_of(nets.theta, nets.gradient_mask, starts[i].clamp_min(0),
                                                         weights[i])
            else:
                step_losses = windows.losses(nets, starts[i].clamp_min(0), weights[i])
                grad = nets.parameter_gradient(step_losses.sum())
            optimizer.step(grad, rates[i])
            losses[i] = step_losses.detach()
        for row, k in enumerate(rows):
            if outcomes[k] is None:
                outcomes[k] = settle(losses[:, row].double().numpy(), start, int(totals[k]), orders[k].per_pass)
                if outcomes[k] is not None:
                    final[k] = nets.theta[row].detach()
        live = [k for k in rows if outcomes[k] is None]
        kept = stack_rows([row for row, k in enumerate(rows) if outcomes[k] is None], len(rows), compiler.enabled)
        if live and len(kept) < len(rows):
            rows = [rows[row] for row in kept]
            leave(nets, optimizer, windows, kept)
        start += size
        on_progress()
        if checkpoint is not None and live:
            checkpoint.block_done(functools.partial(state, start), start, total)
    if checkpoint is not None:
        checkpoint.training_done(functools.partial(state, start), start)
    return nets, final, cast(list[TrainingOutcome], outcomes)  # every model has settled


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
                  y: torch.Tensor, weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``Windows.simulate`` with parameters ``theta``: a function a ``StepCompiler`` compiles."""
    stored = nets.computed(theta)
    return windows.simulate(nets, stored, nets.oriented(stored), x, u, y, weights)


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
        segment_losses, end = simulate(leaf, state, u[:, start:start + segment], y[:, start:start + segment],
                                       weights)
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


def leave(nets: StackedMLPs, optimizer: Adam, windows: Windows, rows: list[int]) -> None:
    """Train only these rows from now on."""
    index = torch.tensor(rows, dtype=torch.long)
    nets.keep(index)
    optimizer.keep(index, nets.theta)
    windows.keep(index)
