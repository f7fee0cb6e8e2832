"""NARX model: y_t = F(y_{t-1}, ..., y_{t-n_y}, u_t, ..., u_{t-n_u}) with F an MLP, plus a linear map of the
regressors (``bypass``) as deepSI's NARX builds F (its ``MLP_res_net``)."""

import torch
from torch import nn

from nsl_hpc.models.blocks import mlp


class NARX(nn.Module):
    """F: (n_y + n_u + 1) -> 1, an MLP with ``depth`` hidden layers of ``width`` units (``block``), plus a bias-free
    Linear of the regressors when ``bypass``; ``zero_bias``: every bias starts at 0 (deepSI), else PyTorch's
    default."""

    def __init__(self, past_outputs: int, past_inputs: int, width: int, depth: int, block: str,
                 bypass: bool = False, zero_bias: bool = False):
        super().__init__()
        self.past_outputs, self.past_inputs = past_outputs, past_inputs
        regressors = past_outputs + past_inputs + 1
        self.net = mlp(regressors, 1, width, depth, block)
        # created after the MLP: its initial weights are those of a model without bypass
        self.bypass = nn.Linear(regressors, 1, bias=False) if bypass else None
        if zero_bias:
            for layer in self.net:
                if isinstance(layer, nn.Linear):
                    nn.init.zeros_(layer.bias)

    def forward(self, past_y: torch.Tensor, inputs: torch.Tensor) -> torch.Tensor:
        """past_y (B, n_y) = y_{t-n_y..t-1}, inputs (B, n_u + 1) = u_{t-n_u..t} (oldest first) -> y_t (B,)."""
        z = torch.cat([past_y, inputs], dim=-1)
        out = self.net(z)
        return (out if self.bypass is None else out + self.bypass(z))[:, 0]

    def mlps(self) -> dict[str, nn.Sequential]:
        """Its MLPs by name (the lockstep path stacks them)."""
        return {"net": self.net}

    def bypasses(self) -> dict[str, nn.Linear]:
        """Its bypass by the name of its MLP (none without one)."""
        return {} if self.bypass is None else {"net": self.bypass}

    def counted_parameters(self) -> int:
        """p of the compute and model-size resources: every parameter, the bypass's included (it is part of F)."""
        return sum(p.numel() for p in self.parameters())
