"""Port-Hamiltonian model: dz/dt = (J(z) - R(z)) grad H(z) + B(z) v, y = B(z)^T grad H(z).

J is skew-symmetric and R symmetric positive semi-definite by construction (for every parameter value),
and H(z) = ||m(z)||^2 / 2 >= 0. grad H comes from autograd, with a graph while training so the loss can
be differentiated through it.
"""

import torch
from torch import nn

from nsl_hpc.models.blocks import mlp, positive_semidefinite, skew_symmetric


class PortHamiltonian(nn.Module):
    """Four MLPs of width n_h and depth n_d (J, R, B and H): parameters ~ 4 n_d n_h^2."""

    def __init__(self, state_dim: int, input_dim: int, width: int, depth: int):
        super().__init__()
        n, m = state_dim, input_dim
        self.n, self.m = n, m
        self.J = mlp(n, n * (n - 1) // 2, width, depth)
        self.R = mlp(n, n * (n + 1) // 2, width, depth)
        self.B = mlp(n, n * m, width, depth)
        self.H = mlp(n, n, width, depth)

    def hamiltonian(self, z: torch.Tensor) -> torch.Tensor:
        """H(z) >= 0, (B,)."""
        return 0.5 * self.H(z).square().sum(dim=-1)

    def structure(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """J(z) (B, n, n) skew, R(z) (B, n, n) PSD, B(z) (B, n, m)."""
        return (skew_symmetric(self.J(z), self.n), positive_semidefinite(self.R(z), self.n),
                self.B(z).view(-1, self.n, self.m))

    def grad_hamiltonian(self, z: torch.Tensor) -> torch.Tensor:
        """grad H(z), (B, n); differentiable when the model is in training mode."""
        with torch.enable_grad():
            if not z.requires_grad:
                z = z.detach().requires_grad_(True)
            (grad,) = torch.autograd.grad(self.hamiltonian(z).sum(), z, create_graph=self.training)
        return grad

    def forward(self, z: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """z (B, n), v (B, m) -> dz/dt (B, n), y (B, m)."""
        grad = self.grad_hamiltonian(z).unsqueeze(-1)  # (B, n, 1)
        interconnection, dissipation, gain = self.structure(z)
        dz = (interconnection - dissipation) @ grad + gain @ v.unsqueeze(-1)
        return dz.squeeze(-1), (gain.transpose(1, 2) @ grad).squeeze(-1)
