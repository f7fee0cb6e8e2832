"""Training of the input-output models on windows of a training prefix, and their free-run simulation.

Signals are standardised with the training prefix's mean and standard deviation. A NARX model trains on
one-step-ahead windows (its regressors hold measured past outputs); a SUBNET on sub-sequences: the encoder
reads P past samples, the model then simulates T steps, and the loss is the mean squared simulation error.
Both draw mini-batches of B windows from a fresh shuffle of all windows each pass, and train for exactly
n_i iterations (optimizer steps). Scoring simulates the test signals freely (the models' own outputs fed
back) in float64 with numpy: a step of these tiny MLPs is a few microseconds there, tens in torch.
"""

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from nsl_hpc.models.blocks import LAYER_NORM_EPS
from nsl_hpc.models.narx import NARX
from nsl_hpc.models.subnet import SUBNET
from nsl_hpc.studies.input_output.data import Signals
from nsl_hpc.studies.training import TrainingOutcome, nonzero, warmup_cosine


@dataclass(frozen=True)
class SignalScaling:
    """Standard scaling of input and output, fitted on the training prefix."""

    u_mean: float
    u_std: float
    y_mean: float
    y_std: float

    @classmethod
    def fit(cls, signals: Signals) -> "SignalScaling":
        return cls(float(signals.u.mean()), float(nonzero(signals.u.std())),
                   float(signals.y.mean()), float(nonzero(signals.y.std())))

    def normalise(self, signals: Signals) -> tuple[np.ndarray, np.ndarray]:
        """Standardised (u, y), each (N,)."""
        return (signals.u - self.u_mean) / self.u_std, (signals.y - self.y_mean) / self.y_std


def narx_windows(model: NARX, u: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every one-step window of standardised u, y (N,): past outputs (W, n_y), inputs (W, n_u + 1) and the
    target y_t (W,), for t = P..N-1 with P = max(n_y, n_u); W = N - P."""
    past = max(model.past_outputs, model.past_inputs)
    t = torch.arange(past, len(y))
    past_y = y.unfold(0, model.past_outputs, 1)[t - model.past_outputs]
    inputs = u.unfold(0, model.past_inputs + 1, 1)[t - model.past_inputs]
    return past_y, inputs, y[t]


def subnet_windows(model: SUBNET, u: torch.Tensor, y: torch.Tensor, horizon: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Views (W, P + T) of every sub-sequence of standardised u and y (N,); W = N - P - T + 1."""
    length = model.past + horizon
    return u.unfold(0, length, 1), y.unfold(0, length, 1)


def window_loss(model: nn.Module, signals: Signals, scaling: SignalScaling, horizon: int,
                dtype: torch.dtype) -> tuple[int, Callable[[torch.Tensor], torch.Tensor]]:
    """(number of windows W, loss of a batch of window indices (B,)) for ``model`` on ``signals``."""
    u, y = (torch.as_tensor(a, dtype=dtype) for a in scaling.normalise(signals))
    if isinstance(model, NARX):
        past_y, inputs, target = narx_windows(model, u, y)
        return len(target), lambda idx: (model(past_y[idx], inputs[idx]) - target[idx]).square().mean()
    u_windows, y_windows = subnet_windows(model, u, y, horizon)
    past = model.past

    def loss(idx: torch.Tensor) -> torch.Tensor:
        batch_u, batch_y = u_windows[idx], y_windows[idx]
        simulated = model(batch_u[:, :past], batch_y[:, :past], batch_u[:, past:])
        return (simulated - batch_y[:, past:]).square().mean()

    return len(u_windows), loss


def train_io_model(model: nn.Module, signals: Signals, scaling: SignalScaling, cfg: Mapping[str, Any],
                   iterations: int, horizon: int, shuffle_seed: int,
                   on_progress: Callable[[], None] = lambda: None) -> TrainingOutcome:
    """Adam (warm-up + cosine over ``iterations`` steps, gradient clipping) on mini-batches of
    ``cfg.batch_size`` windows (all windows when there are fewer); ``cfg`` is the ``train`` group.
    ``on_progress`` is called after each pass over the windows; stops early (finite=False) on a NaN loss."""
    windows, batch_loss = window_loss(model, signals, scaling, horizon, getattr(torch, cfg["dtype"]))
    batch = min(cfg["batch_size"], windows)
    schedule = warmup_cosine(iterations, cfg["warmup_fraction"], cfg["lr"])
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg["lr"], foreach=True)
    generator = torch.Generator().manual_seed(shuffle_seed)
    parameters = list(model.parameters())
    model.train()
    step, loss = 0, torch.tensor(math.nan)
    with tqdm(total=iterations, desc="iterations", unit="it", disable=None, leave=False) as progress:
        while step < iterations:
            order = torch.randperm(windows, generator=generator)
            for start in range(0, min(windows - batch + 1, (iterations - step) * batch), batch):
                optimizer.param_groups[0]["lr"] = schedule[step]
                loss = batch_loss(order[start:start + batch])
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                nn.utils.clip_grad_norm_(parameters, cfg["grad_clip_norm"], foreach=True)
                optimizer.step()
                step += 1
            progress.update(step - progress.n)
            on_progress()
            if not torch.isfinite(loss):
                return TrainingOutcome(step, loss.item(), finite=False)
    return TrainingOutcome(step, loss.item(), finite=True)


@dataclass(frozen=True)
class NumpyLayer:
    """One layer of an MLP in float64: weight (in, out), bias (out,) and, for a hidden layer, its activation
    (LayerNorm scale and shift (out,) then SiLU, or tanh when ``norm`` is None)."""

    weight: np.ndarray
    bias: np.ndarray
    norm: tuple[np.ndarray, np.ndarray] | None = None

    def activate(self, pre: np.ndarray) -> np.ndarray:
        """The hidden activation of the pre-activation ``pre`` (..., out)."""
        if self.norm is None:
            return np.tanh(pre)
        centered = pre - pre.mean(axis=-1, keepdims=True)
        scale, shift = self.norm
        t = centered / np.sqrt(np.mean(np.square(centered), axis=-1, keepdims=True) + LAYER_NORM_EPS) * scale + shift
        return t / (1.0 + np.exp(-t))


def numpy_layers(net: nn.Sequential) -> list[NumpyLayer]:
    """The layers of an MLP (``nsl_hpc.models.blocks.mlp``) in float64."""
    as_numpy = lambda tensor: tensor.detach().double().numpy().copy()  # noqa: E731
    layers: list[NumpyLayer] = []
    for module in net:
        if isinstance(module, nn.Linear):
            layers.append(NumpyLayer(as_numpy(module.weight).T.copy(), as_numpy(module.bias)))
        elif isinstance(module, nn.LayerNorm):
            norm = (as_numpy(module.weight), as_numpy(module.bias))
            layers[-1] = NumpyLayer(layers[-1].weight, layers[-1].bias, norm)
    return layers


def hidden(layers: list[NumpyLayer], first: np.ndarray) -> np.ndarray:
    """The MLP's output given its first layer's pre-activation ``first`` (..., width)."""
    h = layers[0].activate(first)
    for layer in layers[1:-1]:
        h = layer.activate(h @ layer.weight + layer.bias)
    return h @ layers[-1].weight + layers[-1].bias


def simulate_narx(model: NARX, u: np.ndarray, y: np.ndarray, init: int) -> np.ndarray:
    """Free-run simulation (N,) on standardised u, y (N,): y_0..y_{init-1} are given, every later output is
    predicted from the model's own past predictions. ``init`` >= max(n_y, n_u)."""
    layers = numpy_layers(model.net)
    weight, bias = layers[0].weight, layers[0].bias
    w_y, w_u = weight[:model.past_outputs], weight[model.past_outputs:]
    t = np.arange(init, len(u))
    windows = np.lib.stride_tricks.sliding_window_view(u, model.past_inputs + 1)[t - model.past_inputs]
    from_inputs = windows @ w_u + bias  # (N - init, width): the inputs' part of the first layer, all at once
    simulated = y.astype(float).copy()
    for k, index in enumerate(t.tolist()):
        first = from_inputs[k] + simulated[index - model.past_outputs:index] @ w_y
        simulated[index] = hidden(layers, first)[0]
    return simulated


def simulate_subnet(model: SUBNET, u: np.ndarray, y: np.ndarray, init: int) -> np.ndarray:
    """Free-run simulation (N,) on standardised u, y (N,): the encoder reads the ``init`` samples before index
    ``init`` (its past window, init >= P), then x_{k+1} = x_k + f(x_k, u_k), y_k = h(x_k)."""
    encoder, f, h = (numpy_layers(net) for net in (model.encoder, model.f, model.h))
    past = np.concatenate([u[init - model.past:init], y[init - model.past:init]])
    x = hidden(encoder, past @ encoder[0].weight + encoder[0].bias)
    w_x, w_u = f[0].weight[:model.state_dim], f[0].weight[model.state_dim]
    from_inputs = np.multiply.outer(u[init:], w_u) + f[0].bias  # (N - init, width)
    simulated = y.astype(float).copy()
    for k in range(len(u) - init):
        simulated[init + k] = hidden(h, x @ h[0].weight + h[0].bias)[0]
        x = x + hidden(f, from_inputs[k] + x @ w_x)
    return simulated


def simulate(model: nn.Module, signals: Signals, scaling: SignalScaling, init: int) -> np.ndarray:
    """Free-run simulated output (N,) of ``signals`` in its units; the first ``init`` samples are measured."""
    model.eval()
    u, y = scaling.normalise(signals)
    with torch.no_grad():
        run = simulate_narx if isinstance(model, NARX) else simulate_subnet
        return run(model, u, y, init) * scaling.y_std + scaling.y_mean
