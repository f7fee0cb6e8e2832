"""Training of K input-state models of one shape in lockstep, each as if it were trained alone.

Each model keeps its own initial weights, data (size and scaling), shuffle generator, batch order, epoch
count and learning-rate schedule: at step s model k takes its own s-th mini-batch, exactly the one it takes
when trained alone (K = 1, the single-model path). Mini-batches of different lengths are padded and masked;
a model that has finished (or diverged) is masked: learning rate 0, loss ignored. The loss, the
gradient-norm clipping and Adam (torch.optim.Adam's arithmetic) are computed per model, in a few operations
on the (K, P) parameter rows of ``nsl_hpc.stacked``.
"""

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from nsl_hpc.datasets import Dataset
from nsl_hpc.stacked import StackedModels
from nsl_hpc.training import Scaling, TrainingOutcome, batch_bounds, warmup_cosine

ADAM_BETAS, ADAM_EPS, CLIP_EPS = (0.9, 0.999), 1e-8, 1e-6  # torch.optim.Adam and clip_grad_norm_ defaults


@dataclass(frozen=True)
class Member:
    """One model of a lockstep pack, initialised, with what it trains on."""

    model: nn.Module
    data: Dataset
    scaling: Scaling
    epochs: int
    shuffle_seed: int


class BatchPlan:
    """The mini-batches of one member: its own shuffle per epoch, padded to ``width`` indices."""

    def __init__(self, samples: int, batch_size: int, epochs: int, seed: int, width: int):
        self.samples, self.bounds = samples, batch_bounds(samples, batch_size)
        self.steps = epochs * len(self.bounds)
        self.generator = torch.Generator().manual_seed(seed)
        self.mask = torch.zeros(len(self.bounds), width)
        for j, (start, stop) in enumerate(self.bounds):
            self.mask[j, :stop - start] = 1.0
        self.epoch_indices = torch.zeros(len(self.bounds), width, dtype=torch.long)

    def new_epoch(self) -> None:
        order = torch.randperm(self.samples, generator=self.generator)
        for j, (start, stop) in enumerate(self.bounds):
            self.epoch_indices[j, :stop - start] = order[start:stop]


def masked_normalized_mse(predicted: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
                          floor: float) -> torch.Tensor:
    """Per model (K,): mean of ((predicted - target) / s_j)^2 over the unmasked samples, with s_j the spread
    (ddof 0) of target column j over them. predicted, target (K, B, c); mask (K, B, 1)."""
    count = mask.sum(dim=1, keepdim=True)  # (K, 1, 1)
    mean = (target * mask).sum(dim=1, keepdim=True) / count
    spread = (((target - mean) * mask).square().sum(dim=1, keepdim=True) / count).sqrt().clamp_min(floor)
    return (((predicted - target) / spread).square() * mask).sum(dim=(1, 2)) / (count[:, 0, 0] * target.shape[-1])


def stacked_data(members: Sequence[Member], dtype: torch.dtype) -> torch.Tensor:
    """(K, N_max, 2n + 2m): each member's scaled z, v, dz, y, zero-padded to the longest data set."""
    parts = []
    for member in members:
        z, v = member.scaling.model_inputs(member.data, dtype)
        dz, y = member.scaling.model_targets(member.data, dtype)
        parts.append(torch.cat([z, v, dz, y], dim=1))
    rows = max(len(part) for part in parts)
    return torch.stack([nn.functional.pad(part, (0, 0, 0, rows - len(part))) for part in parts])


def train_lockstep(members: Sequence[Member], cfg: Mapping[str, Any],
                   on_epoch: Callable[[], None] = lambda: None) -> tuple[StackedModels, list[TrainingOutcome]]:
    """Train every member as if alone (``cfg`` is the ``train`` group); returns the trained
    stack and each member's outcome. ``on_epoch`` is called whenever some member finishes an epoch."""
    dtype = getattr(torch, cfg["dtype"])
    stack = StackedModels([member.model for member in members], dtype)
    theta, count = stack.theta, len(members)
    n, m = stack.n, stack.m
    data = stacked_data(members, dtype)
    flat_data, rows = data.flatten(0, 1), data.shape[1]
    width = max(max(stop - start for start, stop in batch_bounds(len(mb.data), cfg["batch_size"])) for mb in members)
    plans = [BatchPlan(len(mb.data), cfg["batch_size"], mb.epochs, mb.shuffle_seed, width) for mb in members]
    total = max(plan.steps for plan in plans)
    schedule = torch.zeros(total, count, 1, dtype=dtype)  # lr of each model before each step; 0 once done
    for k, plan in enumerate(plans):
        schedule[:plan.steps, k, 0] = torch.as_tensor(warmup_cosine(plan.steps, cfg["warmup_fraction"], cfg["lr"]))
    offsets = (torch.arange(count) * rows)[:, None]
    first, second = torch.zeros_like(theta), torch.zeros_like(theta)
    beta1, beta2 = ADAM_BETAS
    done = [False] * count
    outcomes: list[TrainingOutcome | None] = [None] * count
    last_loss = torch.full((count,), math.nan, dtype=dtype)
    for step in tqdm(range(total), desc="steps", unit="step", disable=None, leave=False, mininterval=1.0):
        rows_idx, masks, epoch_end = [], [], False
        for k, plan in enumerate(plans):
            j = step % len(plan.bounds) if not done[k] else 0
            if j == 0 and not done[k]:
                plan.new_epoch()
            rows_idx.append(plan.epoch_indices[j])
            masks.append(plan.mask[j] * (not done[k]))
        batch = flat_data[torch.stack(rows_idx) + offsets]  # (K, B, 2n + 2m)
        mask = torch.stack(masks).to(dtype).unsqueeze(-1)  # (K, B, 1)
        z, v, dz, y = batch.split([n, m, n, m], dim=-1)
        predicted_dz, predicted_y = stack.forward(z, v)
        active = mask.amax(dim=1)  # (K, 1): 1 while a model trains
        safe_mask = torch.where(active[:, :, None] > 0, mask, torch.ones_like(mask))  # finished: any finite loss
        losses = masked_normalized_mse(predicted_dz, dz, safe_mask, cfg["loss_std_floor"]) + cfg["output_weight"] * \
            masked_normalized_mse(predicted_y, y, safe_mask, cfg["loss_std_floor"])
        grads = torch.autograd.grad((losses * active[:, 0]).sum(), stack.parameters)
        with torch.no_grad():
            grad = torch.cat([g.reshape(count, -1) for g in grads], dim=1)
            norm = grad.square().sum(dim=1, keepdim=True).sqrt()
            grad.mul_((cfg["grad_clip_norm"] / (norm + CLIP_EPS)).clamp_max(1.0))
            first.lerp_(grad, 1 - beta1)
            second.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
            bias1, bias2 = 1 - beta1 ** (step + 1), 1 - beta2 ** (step + 1)
            denominator = (second.sqrt() / math.sqrt(bias2)).add_(ADAM_EPS)
            theta.addcdiv_(first * (schedule[step] / bias1), denominator, value=-1.0)
        last_loss = torch.where(active[:, 0] > 0, losses.detach(), last_loss)
        for k, plan in enumerate(plans):
            if not done[k] and (step + 1) % len(plan.bounds) == 0:
                epoch_end = True
                loss = float(last_loss[k])
                if step + 1 == plan.steps or not math.isfinite(loss):
                    outcomes[k] = TrainingOutcome(step + 1, loss, finite=math.isfinite(loss))
                    done[k] = True
                    schedule[step + 1:, k] = 0.0
        if epoch_end:
            on_epoch()
        if all(done):
            break
    return stack, outcomes


def predict_derivatives(stack: StackedModels, data: Dataset, scalings: Sequence[Scaling], dtype: torch.dtype,
                        chunk: int = 4096) -> list[np.ndarray]:
    """dx/dt (N, n) of every model of ``stack`` on the same ``data``, in physical units, without a graph."""
    inputs = [scaling.model_inputs(data, dtype) for scaling in scalings]
    z, v = torch.stack([pair[0] for pair in inputs]), torch.stack([pair[1] for pair in inputs])
    with torch.no_grad():
        parts = [stack.forward(z[:, i:i + chunk], v[:, i:i + chunk])[0]
                 for i in range(0, len(data), chunk)]
    predicted = torch.cat(parts, dim=1).double().numpy()
    return [predicted[k] * scaling.derivative_rms * scaling.x_std for k, scaling in enumerate(scalings)]
