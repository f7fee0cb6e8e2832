"""NARX model: y_t = F(y_{t-1}, ..., y_{t-n_y}, u_t, ..., u_{t-n_u}) with F an MLP."""

import torch
from torch import nn

from nsl_hpc.models.blocks import mlp


class NARX(nn.Module):
    """F: (n_y + n_u + 1) -> 1, an MLP with ``depth`` hidden layers of ``width`` units (``block``)."""

    def __init__(self, past_outputs: int, past_inputs: int, width: int, depth: int, block: str):
        super().__init__()
        self.past_outputs, self.past_inputs = past_outputs, past_inputs
        self.net = mlp(past_outputs + past_inputs + 1, 1, width, depth, block)

    def forward(self, past_y: torch.Tensor, inputs: torch.Tensor) -> torch.Tensor:
        """past_y (B, n_y) = y_{t-n_y..t-1}, inputs (B, n_u + 1) = u_{t-n_u..t} (oldest first) -> y_t (B,)."""
        return self.net(torch.cat([past_y, inputs], dim=-1))[:, 0]

    def mlps(self) -> dict[str, nn.Sequential]:
        """Its MLPs by name (the lockstep path stacks them)."""
        return {"net": self.net}

    def bypasses(self) -> dict[str, nn.Linear]:
        """None of its MLPs has a bypass."""
        return {}

    def counted_parameters(self) -> int:
        """p of the compute and model-size resources: every parameter."""
        return sum(p.numel() for p in self.parameters())
