"""Forced Duffing oscillator, the simulated stand-in of Silverbox: m y'' + d y' + k y + k3 y^3 = u."""

import numpy as np


def simulate_duffing(u: np.ndarray, fs_hz: float, m: float, d: float, k: float, k3: float,
                     substeps: int) -> np.ndarray:
    """Output y (N,) in the units of u for the input u (N,) held constant over each sample period
    (zero-order hold), starting at rest; classical RK4 with ``substeps`` steps per sample."""
    h = 1.0 / (fs_hz * substeps)
    position, velocity = 0.0, 0.0
    y = np.empty(len(u))

    def acceleration(q: float, v: float, force: float) -> float:
        return (force - d * v - k * q - k3 * q * q * q) / m

    for i, force in enumerate(u.tolist()):
        y[i] = position
        for _ in range(substeps):
            a1 = acceleration(position, velocity, force)
            q2, v2 = position + 0.5 * h * velocity, velocity + 0.5 * h * a1
            a2 = acceleration(q2, v2, force)
            q3, v3 = position + 0.5 * h * v2, velocity + 0.5 * h * a2
            a3 = acceleration(q3, v3, force)
            q4, v4 = position + h * v3, velocity + h * a3
            a4 = acceleration(q4, v4, force)
            position += h * (velocity + 2 * v2 + 2 * v3 + v4) / 6
            velocity += h * (a1 + 2 * a2 + 2 * a3 + a4) / 6
    return y
