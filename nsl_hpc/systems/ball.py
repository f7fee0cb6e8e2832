"""Magnetic levitation; x = (position, momentum, flux), u = voltage, y = current."""

import numpy as np

from nsl_hpc.systems.port_hamiltonian import PortHamiltonianSystem, constant, diagonal

J = [[0, 1, 0], [-1, 0, 0], [0, 0, 0]]
B = [[0], [0], [1]]


class Ball(PortHamiltonianSystem):
    """H = x2^2/(2m) + x3^2/(2 L(x1)), L(x1) = 1/(0.1 + x1^2);  R = diag(0, c|x2|, 1/R_el)."""

    state_dim = 3
    input_dim = 1

    def __init__(self, m: float, R_el: float, c: float):
        self.m, self.R_el, self.c = m, R_el, c

    def hamiltonian(self, x: np.ndarray) -> np.ndarray:
        inverse_inductance = 0.1 + x[:, 0] ** 2
        return x[:, 1] ** 2 / (2 * self.m) + x[:, 2] ** 2 * inverse_inductance / 2

    def grad_hamiltonian(self, x: np.ndarray) -> np.ndarray:
        inverse_inductance = 0.1 + x[:, 0] ** 2
        return np.stack([x[:, 0] * x[:, 2] ** 2, x[:, 1] / self.m, x[:, 2] * inverse_inductance], axis=-1)

    def interconnection(self, x: np.ndarray) -> np.ndarray:
        return constant(J, len(x))

    def dissipation(self, x: np.ndarray) -> np.ndarray:
        zeros = np.zeros(len(x))
        return diagonal(np.stack([zeros, self.c * np.abs(x[:, 1]), zeros + 1 / self.R_el], axis=-1))

    def input_matrix(self, x: np.ndarray) -> np.ndarray:
        return constant(B, len(x))
