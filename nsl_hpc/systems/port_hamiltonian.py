"""Port-Hamiltonian ODEs dx/dt = (J(x) - R(x)) grad H(x) + B(x) u,  y = B(x)^T grad H(x).

Every method is vectorised over a batch: states x are (N, n), inputs u are (N, m), outputs y are (N, m).
"""

from abc import ABC, abstractmethod
from collections.abc import Sequence

import numpy as np


class PortHamiltonianSystem(ABC):
    """A benchmark system given by its Hamiltonian H and its matrices J, R, B."""

    state_dim: int
    input_dim: int

    @abstractmethod
    def hamiltonian(self, x: np.ndarray) -> np.ndarray:
        """Stored energy H(x), (N,)."""

    @abstractmethod
    def grad_hamiltonian(self, x: np.ndarray) -> np.ndarray:
        """grad H(x), (N, n)."""

    @abstractmethod
    def interconnection(self, x: np.ndarray) -> np.ndarray:
        """Skew-symmetric J(x), (N, n, n)."""

    @abstractmethod
    def dissipation(self, x: np.ndarray) -> np.ndarray:
        """Symmetric positive semi-definite R(x), (N, n, n)."""

    @abstractmethod
    def input_matrix(self, x: np.ndarray) -> np.ndarray:
        """B(x), (N, n, m)."""

    def derivative(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """dx/dt, (N, n)."""
        grad = self.grad_hamiltonian(x)[..., None]
        drift = (self.interconnection(x) - self.dissipation(x)) @ grad
        return (drift + self.input_matrix(x) @ u[..., None])[..., 0]

    def output(self, x: np.ndarray) -> np.ndarray:
        """Power-conjugate output y = B(x)^T grad H(x), (N, m)."""
        grad = self.grad_hamiltonian(x)[..., None]
        return (np.swapaxes(self.input_matrix(x), -1, -2) @ grad)[..., 0]


def diagonal(entries: np.ndarray) -> np.ndarray:
    """Batch of diagonal matrices from (N, n) entries, (N, n, n)."""
    return entries[..., :, None] * np.eye(entries.shape[-1])


def constant(matrix: Sequence[Sequence[float]], batch: int) -> np.ndarray:
    """A constant (n, k) matrix repeated over a batch, (N, n, k)."""
    return np.broadcast_to(np.asarray(matrix, dtype=float), (batch, len(matrix), len(matrix[0])))
