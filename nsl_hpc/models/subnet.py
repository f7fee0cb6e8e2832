"""SUBNET (Beintema, Schoukens and Toth, Automatica 2023): an encoder estimates the state from the past,
a residual state transition x_{k+1} = x_k + f(x_k, u_k) and an output map y_k = h(x_k) simulate the future.
"""

import torch
from torch import nn

from nsl_hpc.models.blocks import mlp


class SUBNET(nn.Module):
    """encoder: (u_{t-P..t-1}, y_{t-P..t-1}) -> x_t;  f: (n_x + 1) -> n_x;  h: n_x -> 1; every MLP has ``depth``
    hidden layers of ``width`` units (``block``); P = ``past`` samples."""

    def __init__(self, state_dim: int, past: int, width: int, depth: int, block: str):
        super().__init__()
        self.state_dim, self.past = state_dim, past
        self.encoder = mlp(2 * past, state_dim, width, depth, block)
        self.f = mlp(state_dim + 1, state_dim, width, depth, block)
        self.h = mlp(state_dim, 1, width, depth, block)

    def encode(self, past_u: torch.Tensor, past_y: torch.Tensor) -> torch.Tensor:
        """past_u, past_y (B, P), oldest first -> initial state x_t (B, n_x)."""
        return self.encoder(torch.cat([past_u, past_y], dim=-1))

    def forward(self, past_u: torch.Tensor, past_y: torch.Tensor, future_u: torch.Tensor) -> torch.Tensor:
        """Simulated outputs y_t..y_{t+T-1} (B, T) from the past (B, P) each and the inputs u_t..u_{t+T-1} (B, T)."""
        x = self.encode(past_u, past_y)
        states = []
        for k in range(future_u.shape[1]):
            states.append(x)
            x = x + self.f(torch.cat([x, future_u[:, k:k + 1]], dim=-1))
        return self.h(torch.stack(states, dim=1))[..., 0]  # h of all T states at once

    def mlps(self) -> dict[str, nn.Sequential]:
        """Its MLPs by name (the lockstep path stacks them)."""
        return {"encoder": self.encoder, "f": self.f, "h": self.h}

    def counted_parameters(self) -> int:
        """p of the compute and model-size resources: f and h (the encoder runs once per sequence)."""
        return sum(p.numel() for module in (self.f, self.h) for p in module.parameters())
