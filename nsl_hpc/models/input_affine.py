"""Input-affine state-space model: dz/dt = h(z) + j(z) v, y = k(z), with j(z) an n x m matrix."""

import torch
from torch import nn

from nsl_hpc.models.blocks import mlp


class InputAffine(nn.Module):
    """Three MLPs of width n_h and depth n_d: parameters ~ 3 n_d n_h^2."""

    def __init__(self, state_dim: int, input_dim: int, width: int, depth: int):
        super().__init__()
        self.n, self.m = state_dim, input_dim
        self.h = mlp(state_dim, state_dim, width, depth)
        self.j = mlp(state_dim, state_dim * input_dim, width, depth)
        self.k = mlp(state_dim, input_dim, width, depth)

    def forward(self, z: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """z (B, n), v (B, m) -> dz/dt (B, n), y (B, m)."""
        gain = self.j(z).view(-1, self.n, self.m)  # (B, n, m)
        return self.h(z) + (gain @ v.unsqueeze(-1)).squeeze(-1), self.k(z)
