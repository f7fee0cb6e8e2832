"""Unstructured state-space model: dz/dt = f(z, v), y = g(z), with f twice as wide as the other MLPs."""

import torch
from torch import nn

from nsl_hpc.errors import ConfigError
from nsl_hpc.models.blocks import mlp


class Unstructured(nn.Module):
    """f: (n + m) -> n of width round(width_factor * n_h); g: n -> m of width n_h.

    Parameters ~ (width_factor^2 + 1) n_d n_h^2 = 5 n_d n_h^2 for the default factor 2.
    """

    def __init__(self, state_dim: int, input_dim: int, width: int, depth: int, width_factor: float):
        super().__init__()
        f_width = round(width_factor * width)
        if f_width < 1:
            raise ConfigError(f"arch.width_factor={width_factor} gives f a width of round({width_factor} * "
                              f"{width}) = {f_width}; use a factor of at least {0.5 / width}")
        self.f = mlp(state_dim + input_dim, state_dim, f_width, depth)
        self.g = mlp(state_dim, input_dim, width, depth)

    def forward(self, z: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """z (B, n), v (B, m) -> dz/dt (B, n), y (B, m)."""
        return self.f(torch.cat([z, v], dim=-1)), self.g(z)
