"""The MLP every architecture is built from, and the declaration of an architecture's MLPs ("heads").

An MLP of depth n_d has n_d hidden layers of width n_h and a linear output layer. A hidden layer is
Linear -> LayerNorm -> SiLU (``block: layernorm_silu``, the authors' code) or Linear -> tanh
(``block: tanh``, nsl_hpc before the study's own configuration).
"""

from dataclasses import dataclass

import torch
from torch import nn

from nsl_hpc.config.arch import BLOCKS
from nsl_hpc.core.errors import ConfigError, require_choice

LAYER_NORM_EPS = 1e-5  # torch.nn.LayerNorm's default


def mlp(in_dim: int, out_dim: int, width: int, depth: int, block: str) -> nn.Sequential:
    """``depth`` hidden layers of ``width`` units, then a Linear to ``out_dim``: a flat Sequential
    [Linear, LayerNorm, SiLU, ..., Linear] (or [Linear, Tanh, ..., Linear])."""
    require_choice("arch.block", block, BLOCKS)
    if depth < 1:
        raise ConfigError(f"an MLP needs at least one hidden layer; got depth {depth}")
    layers: list[nn.Module] = []
    for index in range(depth):
        layers.append(nn.Linear(in_dim if index == 0 else width, width))
        layers += [nn.LayerNorm(width, eps=LAYER_NORM_EPS), nn.SiLU()] if block == "layernorm_silu" else [nn.Tanh()]
    layers.append(nn.Linear(width, out_dim))
    return nn.Sequential(*layers)


def masked_layer_norm(a: torch.Tensor, mask: torch.Tensor | None, inverse: torch.Tensor, dim: int = -1
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """LayerNorm without its affine part of ``a`` over each model's own units along ``dim`` (a (..., width)
    by default; a feature-major (..., width, B) with dim=-2), and 1 / the spread (size 1 along ``dim``):
    ``inverse`` is 1 / their number, ``mask`` 1 on them (None: all units are its own), both broadcasting
    against ``a``. Padded units of ``a`` must be 0; they stay 0."""
    centered = a - a.sum(dim=dim, keepdim=True) * inverse
    if mask is not None:
        centered = centered * mask
    spread = (centered.square().sum(dim=dim, keepdim=True) * inverse + LAYER_NORM_EPS).rsqrt()
    return centered * spread, spread


def parameter_count(module: nn.Module) -> int:
    """Number of trainable scalars."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


@dataclass(frozen=True)
class Head:
    """One MLP of an input-state architecture: its name, whether it reads (x, u) or x alone, its outputs and
    its hidden width."""

    name: str
    reads_input: bool
    out_dim: int
    width: int
