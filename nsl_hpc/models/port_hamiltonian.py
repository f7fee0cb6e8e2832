"""Port-Hamiltonian model (3c): dx/dt = (J(x) - R(x)) grad H(x) + G(x) u, y = G(x)^T grad H(x).

J = S - S^T with the n(n-1)/2 outputs of an MLP strictly above the diagonal of S (skew-symmetric for every
parameter value); R = Q Q^T / sqrt(n) with Q an n x n matrix of MLP outputs (``dissipation: square``, the
authors') or a lower-triangular one from n(n+1)/2 outputs (``lower_triangular``), positive semi-definite either
way; G an MLP with n m outputs viewed as n x m; H(x) from one more MLP (``hamiltonian``): ``abs`` |MLP(x)| >= 0
(the paper requires H >= 0; the authors' nonnegative variant), ``plain`` MLP(x) (the authors' default, H
unconstrained), ``half_square`` ||MLP(x)||^2 / 2 >= 0 with n outputs. Every MLP has width n_h.
"""

import math

import torch

from nsl_hpc.models.blocks import Head
from nsl_hpc.models.state_space import Outputs, StateSpaceArchitecture
from nsl_hpc.models.tensor_layout import BATCH_MAJOR, Layout


def entries_to_matrix(n: int, entries: str, dtype: torch.dtype) -> torch.Tensor:
    """(k, n * n): maps k entries to a flattened n x n matrix: ``strict_upper`` to S - S^T (S strictly upper,
    row-major order), ``lower`` to a lower-triangular L, ``full`` to itself."""
    if entries == "full":
        return torch.eye(n * n, dtype=dtype)
    rows, cols = torch.triu_indices(n, n, offset=1) if entries == "strict_upper" else torch.tril_indices(n, n)
    mapping = torch.zeros(len(rows), n * n, dtype=dtype)
    mapping[torch.arange(len(rows)), rows * n + cols] = 1.0
    if entries == "strict_upper":
        mapping[torch.arange(len(rows)), cols * n + rows] = -1.0
    return mapping


class PortHamiltonian(StateSpaceArchitecture):
    energy_head = "H"

    def __init__(self, state_dim: int, input_dim: int, width: int, hamiltonian: str, dissipation: str):
        super().__init__(state_dim, input_dim, width)
        self.hamiltonian, self.dissipation = hamiltonian, dissipation
        # built here, not on first use: a compiled step that filled the dict would fail its guard and compile again
        self.maps = {dtype: self.entry_maps(dtype) for dtype in (torch.float32, torch.float64)}

    def entry_maps(self, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """The maps of the J and R heads' entries to the n x n matrices' (``entries_to_matrix``)."""
        return (entries_to_matrix(self.n, "strict_upper", dtype),
                entries_to_matrix(self.n, "full" if self.dissipation == "square" else "lower", dtype))

    def heads(self) -> list[Head]:
        n, m, width = self.n, self.m, self.width
        q_entries = n * n if self.dissipation == "square" else n * (n + 1) // 2
        return [Head("J", False, n * (n - 1) // 2, width), Head("R", False, q_entries, width),
                Head("G", False, n * m, width), Head("H", False, n if self.hamiltonian == "half_square" else 1, width)]

    def energy(self, output: torch.Tensor) -> torch.Tensor:
        if self.hamiltonian == "half_square":
            return 0.5 * output.square().sum(dim=-1)
        return output[..., 0].abs() if self.hamiltonian == "abs" else output[..., 0]

    def energy_slope(self, output: torch.Tensor) -> torch.Tensor:
        if self.hamiltonian == "half_square":
            return output
        return output.sign() if self.hamiltonian == "abs" else torch.ones_like(output)

    def matrices(self, outputs: Outputs, layout: Layout = BATCH_MAJOR
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """J (n x n) skew-symmetric, R (n x n) symmetric PSD and G (n x m) per sample from the heads' outputs:
        (B, n, n) and (B, n, m) batch-major, (n, n, B) and (n, m, B) feature-major."""
        n, dtype = self.n, outputs["J"].dtype
        skew, factor = self.maps[dtype] if dtype in self.maps else self.entry_maps(dtype)
        interconnection = layout.matrix(layout.linear(outputs["J"], skew), n, n)
        q = layout.matrix(layout.linear(outputs["R"], factor), n, n)
        dissipation = layout.matmul(q, layout.transposed(q)) / math.sqrt(n)
        return interconnection, dissipation, layout.matrix(outputs["G"], n, self.m)

    def assemble(self, outputs: Outputs, v: torch.Tensor, grad_energy: torch.Tensor | None,
                 layout: Layout = BATCH_MAJOR) -> tuple[torch.Tensor, torch.Tensor]:
        if grad_energy is None:
            raise TypeError("a port-Hamiltonian model's dynamics need grad H")
        interconnection, dissipation, gain = self.matrices(outputs, layout)
        grad = layout.column(grad_energy)  # n x 1
        dz = layout.matmul(interconnection - dissipation, grad) + layout.matmul(gain, layout.column(v))
        return layout.vector(dz), layout.vector(layout.matmul(layout.transposed(gain), grad))
