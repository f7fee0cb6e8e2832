"""A user's own module: a cascaded two-tank system and a model class for it, named in conf/ by `_target_`.

Nothing here is part of nsl_hpc; the package imports it from PYTHONPATH when a config names it.
"""

import numpy as np
import torch

from nsl_hpc.models.blocks import Head, mlp
from nsl_hpc.models.state_space import StateSpaceArchitecture
from nsl_hpc.models.tensor_layout import BATCH_MAJOR, Layout


class TwoTank:
    """Water levels h1, h2 (m) of two tanks, the first draining into the second; u: the pump's flow around
    ``bias`` (m^3/s); y = h2. A dh1/dt = q - a1 sqrt(2 g h1), A dh2/dt = a1 sqrt(2 g h1) - a2 sqrt(2 g h2)."""

    state_dim = 2
    input_dim = 1

    def __init__(self, area: float, outlet1: float, outlet2: float, bias: float, gravity: float = 9.81):
        self.area, self.outlets, self.bias, self.gravity = area, np.array([outlet1, outlet2]), bias, gravity

    def outflow(self, x: np.ndarray) -> np.ndarray:
        """Flow out of each tank (N, 2); an empty tank lets nothing out."""
        return self.outlets * np.sqrt(2 * self.gravity * np.maximum(x, 0.0))

    def derivative(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        out = self.outflow(x)
        inflow = np.stack([self.bias + u[:, 0], out[:, 0]], axis=-1)
        return (inflow - out) / self.area

    def output(self, x: np.ndarray) -> np.ndarray:
        return x[:, 1:]


class CascadeNet(StateSpaceArchitecture):
    """dx/dt = f(x) + b(x) u, y = g(x): three MLPs on the state alone (f, b of width n_h, g of width
    ``output_width``), for systems of one input. Written through ``layout`` so the lockstep training can stack it."""

    def __init__(self, state_dim: int, input_dim: int, width: int, output_width: int):
        if input_dim != 1:
            raise ValueError(f"CascadeNet takes one input, the system has {input_dim}")
        super().__init__(state_dim, input_dim, width)
        self.output_width = output_width

    def heads(self) -> list[Head]:
        return [Head("f", False, self.n, self.width), Head("b", False, self.n, self.width),
                Head("g", False, self.m, self.output_width)]

    def assemble(self, outputs, v: torch.Tensor, grad_energy, layout: Layout = BATCH_MAJOR):
        return outputs["f"] + outputs["b"] * v, outputs["g"]  # v: one feature, broadcast in either layout


class TankMLP(torch.nn.Module):
    """Any torch.nn.Module of yours: z (B, n), v (B, m) -> dz/dt (B, n), y (B, m), built with (n, m, n_h, n_d, block)
    and the config's options. The lockstep training cannot batch it with others: each trains in a group of its own."""

    def __init__(self, state_dim: int, input_dim: int, width: int, depth: int, block: str):
        super().__init__()
        self.state_dim = state_dim
        self.net = mlp(state_dim + input_dim, state_dim + input_dim, width, depth, block)

    def forward(self, z: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.net(torch.cat([z, v], dim=-1))
        return out[:, :self.state_dim], out[:, self.state_dim:]
