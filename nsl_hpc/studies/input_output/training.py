"""The plain training loop of one input-output model on windows of a training prefix: the reference the lockstep
path (``lockstep``, which the study runs) equals and the benchmark compares with.

Signals are standardised with the training prefix's mean and standard deviation. A NARX model trains on
one-step-ahead windows (its regressors hold measured past outputs); a SUBNET on sub-sequences: the encoder
reads P past samples, the model then simulates T steps, and the loss is the mean squared simulation error.
Both draw mini-batches of B windows from a fresh shuffle of all windows each pass, and train for exactly
n_i iterations (optimizer steps).
"""

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from nsl_hpc.models.narx import NARX
from nsl_hpc.models.subnet import SUBNET
from nsl_hpc.studies.input_output.data import Signals
from nsl_hpc.studies.settings import InputOutputTrain, learning_rate_at
from nsl_hpc.studies.training import TrainingOutcome, nonzero


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


def window_loss(model: NARX | SUBNET, signals: Signals, scaling: SignalScaling, horizon: int,
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


def train_io_model(model: NARX | SUBNET, signals: Signals, scaling: SignalScaling, train: InputOutputTrain,
                   iterations: int, horizon: int, shuffle_seed: int,
                   on_progress: Callable[[], None] = lambda: None) -> TrainingOutcome:
    """Adam (``train.schedule``'s schedule over ``iterations`` steps, gradient clipping) on mini-batches of
    ``train.batch_size`` windows (all windows when there are fewer). ``on_progress`` is called after each pass over
    the windows; stops early (finite=False) on a NaN loss."""
    windows, batch_loss = window_loss(model, signals, scaling, horizon, getattr(torch, train.dtype))
    batch = min(train.batch_size, windows)
    kind = train.schedule["narx" if isinstance(model, NARX) else "subnet"]
    schedule = learning_rate_at(np.arange(iterations), np.asarray(iterations), kind, train.warmup_fraction, train.lr)
    optimizer = torch.optim.Adam(model.parameters(), lr=train.lr, foreach=True)
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
                nn.utils.clip_grad_norm_(parameters, train.grad_clip_norm, foreach=True)
                optimizer.step()
                step += 1
            progress.update(step - progress.n)
            on_progress()
            if not torch.isfinite(loss):
                return TrainingOutcome(step, loss.item(), finite=False)
    return TrainingOutcome(step, loss.item(), finite=True)
