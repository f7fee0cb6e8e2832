"""Permanent-magnet synchronous motor in the rotor frame; x = (phi_d, phi_q, p), u = (v_d, v_q)."""

import numpy as np

from nsl_hpc.systems.port_hamiltonian import PortHamiltonianSystem, constant, diagonal

B = [[1, 0], [0, 1], [0, 0]]


class Motor(PortHamiltonianSystem):
    """H = (phi_d^2 + phi_q^2)/(2L) + p^2/(2 Jm); J couples fluxes and rotor; R = diag(r, r, beta)."""

    state_dim = 3
    input_dim = 2

    def __init__(self, Jm: float, L: float, beta: float, r: float, Phi: float):
        self.Jm, self.L, self.beta, self.r, self.Phi = Jm, L, beta, r, Phi

    def hamiltonian(self, x: np.ndarray) -> np.ndarray:
        return (x[:, 0] ** 2 + x[:, 1] ** 2) / (2 * self.L) + x[:, 2] ** 2 / (2 * self.Jm)

    def grad_hamiltonian(self, x: np.ndarray) -> np.ndarray:
        return np.stack([x[:, 0] / self.L, x[:, 1] / self.L, x[:, 2] / self.Jm], axis=-1)

    def interconnection(self, x: np.ndarray) -> np.ndarray:
        j = np.zeros((len(x), 3, 3))
        j[:, 0, 2] = x[:, 1]
        j[:, 1, 2] = -x[:, 0] - self.Phi
        return j - np.swapaxes(j, -1, -2)

    def dissipation(self, x: np.ndarray) -> np.ndarray:
        return diagonal(np.broadcast_to([self.r, self.r, self.beta], x.shape))

    def input_matrix(self, x: np.ndarray) -> np.ndarray:
        return constant(B, len(x))
