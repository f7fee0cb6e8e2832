"""Training of one state-space model on (x, u) -> (dx/dt, y) samples, and its predictions.

Models work in standardised coordinates, fitted on the training data: z = (x - mean_x) / std_x,
v = (u - mean_u) / std_u, a rescaled time in which dz/dt is O(1), and a rescaled output conjugate to v
(y std_u, divided by its RMS). A port-Hamiltonian model in these coordinates is one in x, u, t as well:
the diagonal std_x keeps J skew and R PSD, and the two scalar rescalings (of time and of energy) only
scale J, R and H. The loss is invariant to these per-column scalings anyway: each column's error is
divided by the spread of that column's targets in the batch; they matter for optimisation, which
otherwise spends its steps growing output weights to the targets' magnitude.
"""

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from nsl_hpc.datasets import Dataset


def nonzero(scale: np.ndarray | float) -> np.ndarray | float:
    """A scale with zeros replaced by 1, so a constant column is centred, not blown up."""
    return np.where(scale > 0, scale, 1.0)


@dataclass(frozen=True)
class Scaling:
    """Standard scaling fitted on training data: arrays are (n,) or (m,), the rest scalars."""

    x_mean: np.ndarray
    x_std: np.ndarray
    u_mean: np.ndarray
    u_std: np.ndarray
    derivative_rms: float  # RMS of dx/dt / std_x: the time rescaling
    output_rms: float  # RMS of y std_u: the output (energy) rescaling

    @classmethod
    def fit(cls, data: Dataset) -> "Scaling":
        x_std, u_std = nonzero(data.x.std(axis=0)), nonzero(data.u.std(axis=0))
        rms = lambda a: float(nonzero(np.sqrt(np.mean(np.square(a)))))  # noqa: E731
        return cls(data.x.mean(axis=0), x_std, data.u.mean(axis=0), u_std,
                   rms(data.dx / x_std), rms(data.y * u_std))

    def model_inputs(self, data: Dataset, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """z (N, n), v (N, m)."""
        return (torch.as_tensor((data.x - self.x_mean) / self.x_std, dtype=dtype),
                torch.as_tensor((data.u - self.u_mean) / self.u_std, dtype=dtype))

    def model_targets(self, data: Dataset, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """Rescaled dz/dt (N, n) and conjugate output (N, m)."""
        return (torch.as_tensor(data.dx / self.x_std / self.derivative_rms, dtype=dtype),
                torch.as_tensor(data.y * self.u_std / self.output_rms, dtype=dtype))


def batch_normalized_mse(predicted: torch.Tensor, target: torch.Tensor, floor: float) -> torch.Tensor:
    """Mean of ((predicted - target) / s_j)^2 with s_j the spread of target column j in this batch."""
    spread = target.std(dim=0, unbiased=False).clamp_min(floor)
    return ((predicted - target) / spread).square().mean()


def batch_count(samples: int, batch_size: int) -> int:
    """Mini-batches per epoch: ceil(samples / batch_size), less one when a single sample would trail."""
    count = -(-samples // batch_size)
    return count - 1 if count > 1 and samples % batch_size == 1 else count


def batch_bounds(samples: int, batch_size: int) -> list[tuple[int, int]]:
    """[start, stop) of each of the ``batch_count`` mini-batches; a trailing single sample joins the last."""
    starts = [i * batch_size for i in range(batch_count(samples, batch_size))]
    return [(start, stop) for start, stop in zip(starts, [*starts[1:], samples], strict=True)]


def warmup_cosine(total_steps: int, warmup_fraction: float, lr: float) -> np.ndarray:
    """Learning rate before each step: linear warm-up over the first fraction, then cosine decay to 0."""
    warmup = max(1, round(warmup_fraction * total_steps))
    step = np.arange(total_steps)
    rising = lr * (step + 1) / warmup
    progress = (step - warmup) / max(1, total_steps - warmup)
    return np.where(step < warmup, rising, lr * 0.5 * (1 + np.cos(np.pi * progress)))


@dataclass(frozen=True)
class TrainingOutcome:
    steps: int
    final_loss: float
    finite: bool


def train_model(model: nn.Module, data: Dataset, scaling: Scaling, cfg: Mapping[str, Any], epochs: int,
                shuffle_seed: int, on_epoch: Callable[[], None] = lambda: None) -> TrainingOutcome:
    """Adam with warm-up + cosine schedule and gradient clipping; ``cfg`` is the ``train`` config group.

    Each epoch shuffles the samples once and walks through them in contiguous mini-batches, then calls
    ``on_epoch`` (the heartbeat of a watched task). Stops early (finite=False) when the loss becomes NaN
    or infinite.
    """
    dtype = getattr(torch, cfg["dtype"])
    z, v = scaling.model_inputs(data, dtype)
    dz, y = scaling.model_targets(data, dtype)
    bounds = batch_bounds(len(data), cfg["batch_size"])
    schedule = warmup_cosine(epochs * len(bounds), cfg["warmup_fraction"], cfg["lr"])
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg["lr"], foreach=True)
    generator = torch.Generator().manual_seed(shuffle_seed)
    parameters = list(model.parameters())
    model.train()
    step, loss = 0, torch.tensor(math.nan)
    for _ in tqdm(range(epochs), desc="epochs", unit="ep", disable=None, leave=False):
        order = torch.randperm(len(data), generator=generator)
        zs, vs, dzs, ys = z[order], v[order], dz[order], y[order]
        for start, stop in bounds:
            optimizer.param_groups[0]["lr"] = schedule[step]
            predicted_dz, predicted_y = model(zs[start:stop], vs[start:stop])
            loss = batch_normalized_mse(predicted_dz, dzs[start:stop], cfg["loss_std_floor"])
            loss = loss + cfg["output_weight"] * batch_normalized_mse(
                predicted_y, ys[start:stop], cfg["loss_std_floor"])
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            nn.utils.clip_grad_norm_(parameters, cfg["grad_clip_norm"], foreach=True)
            optimizer.step()
            step += 1
        on_epoch()
        if not torch.isfinite(loss):
            return TrainingOutcome(step, loss.item(), finite=False)
    return TrainingOutcome(step, loss.item(), finite=True)


def predict_derivative(model: nn.Module, data: Dataset, scaling: Scaling, dtype: torch.dtype,
                       chunk: int = 8192) -> np.ndarray:
    """dx/dt predicted by ``model`` in physical units, (N, n), evaluated without a training graph."""
    model.eval()
    z, v = scaling.model_inputs(data, dtype)
    with torch.no_grad():
        parts = [model(z[i:i + chunk], v[i:i + chunk])[0] for i in range(0, len(data), chunk)]
    return torch.cat(parts).double().numpy() * scaling.derivative_rms * scaling.x_std
