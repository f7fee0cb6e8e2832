"""An input-state architecture, declared once: the MLP heads it is made of and how dx/dt and y follow from
their outputs. Both training paths are built from the declaration: ``StateSpaceModel`` (one nn.Module per
model: the reference and the ground truth of the tests) and ``stacked`` (K models as batched
tensors).

Models work on standardised inputs z (n states) and v (m inputs); every tensor may carry any leading batch
dimensions, shapes below are written for one (B).
"""

from abc import ABC, abstractmethod
from collections.abc import Mapping

import torch
from torch import nn

from nsl_hpc.core.errors import ConfigError
from nsl_hpc.models.blocks import Head, mlp
from nsl_hpc.models.tensor_layout import BATCH_MAJOR, Layout

Outputs = Mapping[str, torch.Tensor]  # head name -> its output (B, out_dim)


class StateSpaceArchitecture(ABC):
    """An architecture for n = ``state_dim``, m = ``input_dim`` and hidden width n_h = ``width``.

    ``energy_head`` names the head that defines a Hamiltonian H(z) = ``energy(output)``; its gradient grad H (B, n)
    is computed by each path (autograd in the module, written out in the stacked path) and passed to ``assemble``.
    """

    energy_head: str | None = None

    def __init__(self, state_dim: int, input_dim: int, width: int):
        self.n, self.m, self.width = state_dim, input_dim, width

    def scaled_width(self, factor: float) -> int:
        """round(factor n_h) (``arch.width_factor``), refused when it rounds to zero."""
        scaled = round(factor * self.width)
        if scaled < 1:
            raise ConfigError(f"arch.width_factor={factor} gives round({factor} * {self.width}) = {scaled} units; "
                              f"use a factor of at least {0.5 / self.width}")
        return scaled

    @abstractmethod
    def heads(self) -> list[Head]:
        """The MLPs, in a fixed order."""

    @abstractmethod
    def assemble(self, outputs: Outputs, v: torch.Tensor, grad_energy: torch.Tensor | None,
                 layout: Layout = BATCH_MAJOR) -> tuple[torch.Tensor, torch.Tensor]:
        """dz/dt (B, n) and y (B, m) from the outputs of the heads (the energy head's aside), v (B, m) and
        grad H (B, n) (None without an energy head); with a feature-major ``layout`` each (B, k) is (k, B)."""

    def energy(self, output: torch.Tensor) -> torch.Tensor:
        """H (B,) from the energy head's output (B, k)."""
        raise NotImplementedError

    def energy_slope(self, output: torch.Tensor) -> torch.Tensor:
        """dH / d output (B, k)."""
        raise NotImplementedError


class StateSpaceModel(nn.Module):
    """One model: an MLP per head of ``architecture`` (``depth`` hidden layers of ``block``)."""

    def __init__(self, architecture: StateSpaceArchitecture, depth: int, block: str):
        super().__init__()
        self.architecture, self.depth, self.block = architecture, depth, block
        n, m = architecture.n, architecture.m
        self.nets = nn.ModuleDict({head.name: mlp(n + m if head.reads_input else n, head.out_dim, head.width,
                                                  depth, block) for head in architecture.heads()})
        self.reads_input = {head.name: head.reads_input for head in architecture.heads()}

    def grad_energy(self, z: torch.Tensor) -> torch.Tensor:
        """grad_z H (B, n) by autograd; differentiable (a graph) while training."""
        with torch.enable_grad():
            if not z.requires_grad:
                z = z.detach().requires_grad_(True)
            head = self.architecture.energy_head
            if head is None:
                raise TypeError(f"{type(self.architecture).__name__} has no energy head")
            energy = self.architecture.energy(self.nets[head](z))
            (grad,) = torch.autograd.grad(energy.sum(), z, create_graph=self.training)
        return grad

    def forward(self, z: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """z (B, n), v (B, m) -> dz/dt (B, n), y (B, m)."""
        zv = torch.cat([z, v], dim=-1)
        outputs = {name: net(zv if self.reads_input[name] else z) for name, net in self.nets.items()
                   if name != self.architecture.energy_head}
        grad = self.grad_energy(z) if self.architecture.energy_head else None
        return self.architecture.assemble(outputs, v, grad)
