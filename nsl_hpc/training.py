"""Training of one state-space model on (x, u) -> (dx/dt, y) samples, and its predictions.

Models work in standardised coordinates: z = (x - mean_x) / std_x and v = (u - mean_u) / std_u, from
training statistics. Their targets are dz/dt = dx/dt / std_x and the output conjugate to v,
y * std_u, so a port-Hamiltonian model in z is one in x as well (J, R scale by the diagonal std_x and
keep their skew / PSD structure). The loss is invariant to these per-column scalings anyway: each
column's error is divided by the spread of that column's targets in the batch.
"""

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from nsl_hpc.datasets import Dataset


@dataclass(frozen=True)
class Scaling:
    """Standard scaling fitted on training data; every array is (n,) or (m,)."""

    x_mean: np.ndarray
    x_std: np.ndarray
    u_mean: np.ndarray
    u_std: np.ndarray

    @classmethod
    def fit(cls, data: Dataset) -> "Scaling":
        def spread(a: np.ndarray) -> np.ndarray:
            std = a.std(axis=0)
            return np.where(std > 0, std, 1.0)  # a constant column is centred, not blown up

        return cls(data.x.mean(axis=0), spread(data.x), data.u.mean(axis=0), spread(data.u))

    def model_inputs(self, data: Dataset, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """z (N, n), v (N, m)."""
        return (torch.as_tensor((data.x - self.x_mean) / self.x_std, dtype=dtype),
                torch.as_tensor((data.u - self.u_mean) / self.u_std, dtype=dtype))

    def model_targets(self, data: Dataset, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """dz/dt (N, n), conjugate output (N, m)."""
        return (torch.as_tensor(data.dx / self.x_std, dtype=dtype),
                torch.as_tensor(data.y * self.u_std, dtype=dtype))


def batch_normalized_mse(predicted: torch.Tensor, target: torch.Tensor, floor: float) -> torch.Tensor:
    """Mean of ((predicted - target) / s_j)^2 with s_j the spread of target column j in this batch."""
    spread = target.std(dim=0, unbiased=False).clamp_min(floor)
    return ((predicted - target) / spread).square().mean()


def batch_bounds(samples: int, batch_size: int) -> list[tuple[int, int]]:
    """[start, stop) of each mini-batch; a trailing single sample joins the batch before it."""
    starts = list(range(0, samples, batch_size))
    if len(starts) > 1 and samples - starts[-1] == 1:
        starts.pop()
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
                shuffle_seed: int) -> TrainingOutcome:
    """Adam with warm-up + cosine schedule and gradient clipping; ``cfg`` is the ``train`` config group.

    Each epoch shuffles the samples once and walks through them in contiguous mini-batches.
    Stops early (finite=False) when the loss becomes NaN or infinite.
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
    return torch.cat(parts).double().numpy() * scaling.x_std
