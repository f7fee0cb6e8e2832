"""Building blocks shared by the architectures: the MLP and the skew-symmetric / PSD converters."""

import math

import torch
from torch import nn


def mlp(in_dim: int, out_dim: int, width: int, depth: int) -> nn.Sequential:
    """tanh MLP with ``depth`` hidden-to-hidden (width x width) layers: depth + 1 tanh layers in all.

    Parameters: (in_dim + 1) width + depth (width + 1) width + (width + 1) out_dim.
    """
    layers: list[nn.Module] = [nn.Linear(in_dim, width), nn.Tanh()]
    for _ in range(depth):
        layers += [nn.Linear(width, width), nn.Tanh()]
    layers.append(nn.Linear(width, out_dim))
    return nn.Sequential(*layers)


def mlp_parameter_count(in_dim: int, out_dim: int, width: int, depth: int) -> int:
    """Closed form of the parameter count of ``mlp(in_dim, out_dim, width, depth)``."""
    return (in_dim + 1) * width + depth * (width + 1) * width + (width + 1) * out_dim


def skew_symmetric(entries: torch.Tensor, n: int) -> torch.Tensor:
    """J = U - U^T from the n(n-1)/2 strictly-upper entries of U; (B, n(n-1)/2) -> (B, n, n)."""
    rows, cols = torch.triu_indices(n, n, offset=1)
    upper = entries.new_zeros(entries.shape[0], n, n)
    upper[:, rows, cols] = entries
    return upper - upper.transpose(1, 2)


def positive_semidefinite(entries: torch.Tensor, n: int) -> torch.Tensor:
    """R = L L^T / sqrt(n) from the n(n+1)/2 lower-triangular entries of L; (B, n(n+1)/2) -> (B, n, n)."""
    rows, cols = torch.tril_indices(n, n)
    lower = entries.new_zeros(entries.shape[0], n, n)
    lower[:, rows, cols] = entries
    return lower @ lower.transpose(1, 2) / math.sqrt(n)


def parameter_count(module: nn.Module) -> int:
    """Number of trainable scalars."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
