"""Two masses coupled by springs with nonlinear (velocity-squared) damping; x = (q1, p1, q2, p2), u in R^2 acting
on the momenta (the paper's appendix) or on the positions (the authors' code)."""

import numpy as np

from nsl_hpc.core.errors import ConfigError
from nsl_hpc.systems.port_hamiltonian import PortHamiltonianSystem, constant, diagonal

J = [[0, 1, 0, 0], [-1, 0, 1, 0], [0, -1, 0, 1], [0, 0, -1, 0]]
B = {"p": [[0, 0], [1, 0], [0, 0], [0, 1]], "q": [[1, 0], [0, 0], [0, 1], [0, 0]]}  # which rows the inputs drive


class Spring(PortHamiltonianSystem):
    """H = sum_i k_i q_i^2 / 2 + p_i^2 / (2 m_i);  R = diag(0, b1 p1^2/m1^2, 0, b2 p2^2/m2^2)."""

    state_dim = 4
    input_dim = 2

    def __init__(self, m1: float, m2: float, b1: float, b2: float, k1: float, k2: float, input_on: str = "p"):
        if input_on not in B:
            raise ConfigError(f"system.params.input_on={input_on!r}; choose one of: {', '.join(B)}")
        self.input_rows = B[input_on]
        self.m = np.array([m1, m2])
        self.b = np.array([b1, b2])
        self.k = np.array([k1, k2])

    def hamiltonian(self, x: np.ndarray) -> np.ndarray:
        q, p = x[:, 0::2], x[:, 1::2]
        return np.sum(self.k * q**2 / 2 + p**2 / (2 * self.m), axis=-1)

    def grad_hamiltonian(self, x: np.ndarray) -> np.ndarray:
        grad = np.empty_like(x)
        grad[:, 0::2] = self.k * x[:, 0::2]
        grad[:, 1::2] = x[:, 1::2] / self.m
        return grad

    def interconnection(self, x: np.ndarray) -> np.ndarray:
        return constant(J, len(x))

    def dissipation(self, x: np.ndarray) -> np.ndarray:
        entries = np.zeros_like(x)
        entries[:, 1::2] = self.b * x[:, 1::2] ** 2 / self.m**2
        return diagonal(entries)

    def input_matrix(self, x: np.ndarray) -> np.ndarray:
        return constant(self.input_rows, len(x))
