"""SUBNET (Beintema, Schoukens and Toth, Automatica 2023): an encoder estimates the state from the past, a state
transition x_{k+1} = x_k + f(x_k, u_k) (``residual``) or f(x_k, u_k) and an output map y_k = h(x_k) simulate the
future. Each of the three MLPs may add a linear map of its input to its output (``bypass``), as deepSI's
``MLP_res_net`` does for all three; the paper keeps it in h and the encoder and gives f the residual instead.
"""

import torch
from torch import nn

from nsl_hpc.config.arch import SUBNET_NETWORKS
from nsl_hpc.models.blocks import mlp


class SUBNET(nn.Module):
    """encoder: (u_{t-P..t-1}, y_{t-P..t-1}) -> x_t;  f: (n_x + 1) -> n_x;  h: n_x -> 1; every MLP has ``depth``
    hidden layers of ``width`` units (``block``), plus a bias-free Linear from its input to its output when named in
    ``bypass``; P = ``past`` samples. ``zero_bias``: every bias starts at 0 (deepSI), else PyTorch's default;
    ``zero_f_output``: f's output layer and bypass start at 0 (with the residual, x_{k+1} = x_k at initialisation)."""

    def __init__(self, state_dim: int, past: int, width: int, depth: int, block: str,
                 bypass: tuple[str, ...] = ("encoder", "h"), residual: bool = True, zero_bias: bool = False,
                 zero_f_output: bool = False):
        super().__init__()
        self.state_dim, self.past, self.residual = state_dim, past, residual
        sizes = {"encoder": (2 * past, state_dim), "f": (state_dim + 1, state_dim), "h": (state_dim, 1)}
        self.encoder = mlp(*sizes["encoder"], width, depth, block)
        self.f = mlp(*sizes["f"], width, depth, block)
        self.h = mlp(*sizes["h"], width, depth, block)
        # created after the MLPs: their initial weights are those of a model without bypass
        self.bypass = nn.ModuleDict({name: nn.Linear(*sizes[name], bias=False) for name in SUBNET_NETWORKS
                                     if name in bypass})
        if zero_bias:
            for layer in self.modules():
                if isinstance(layer, nn.Linear) and layer.bias is not None:
                    nn.init.zeros_(layer.bias)
        if zero_f_output:
            output = self.f[-1]
            assert isinstance(output, nn.Linear)
            nn.init.zeros_(output.weight)
            nn.init.zeros_(output.bias)
            if "f" in self.bypass:
                nn.init.zeros_(self.bypasses()["f"].weight)

    def network(self, name: str, z: torch.Tensor) -> torch.Tensor:
        """MLP ``name`` of inputs z (..., in), with its bypass if it has one."""
        out = self.mlps()[name](z)
        return out + self.bypass[name](z) if name in self.bypass else out

    def encode(self, past_u: torch.Tensor, past_y: torch.Tensor) -> torch.Tensor:
        """past_u, past_y (B, P), oldest first -> initial state x_t (B, n_x)."""
        return self.network("encoder", torch.cat([past_u, past_y], dim=-1))

    def step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """x_{k+1} (B, n_x) from x_k (B, n_x) and u_k (B, 1)."""
        change = self.network("f", torch.cat([x, u], dim=-1))
        return x + change if self.residual else change

    def forward(self, past_u: torch.Tensor, past_y: torch.Tensor, future_u: torch.Tensor) -> torch.Tensor:
        """Simulated outputs y_t..y_{t+T-1} (B, T) from the past (B, P) each and the inputs u_t..u_{t+T-1} (B, T)."""
        x = self.encode(past_u, past_y)
        states = []
        for k in range(future_u.shape[1]):
            states.append(x)
            x = self.step(x, future_u[:, k:k + 1])
        return self.network("h", torch.stack(states, dim=1))[..., 0]  # h of all T states at once

    def mlps(self) -> dict[str, nn.Sequential]:
        """Its MLPs by name (the lockstep path stacks them)."""
        return {"encoder": self.encoder, "f": self.f, "h": self.h}

    def bypasses(self) -> dict[str, nn.Linear]:
        """The bypass Linears by the name of their MLP."""
        return {name: layer for name, layer in self.bypass.items() if isinstance(layer, nn.Linear)}

    def counted_parameters(self) -> int:
        """p of the compute and model-size resources: f and h with their bypasses (the encoder runs once per
        sequence)."""
        counted = [self.f, self.h] + [layer for name, layer in self.bypasses().items() if name != "encoder"]
        return sum(p.numel() for module in counted for p in module.parameters())
