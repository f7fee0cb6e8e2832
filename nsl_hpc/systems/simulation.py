"""Multisine excitation and trajectory simulation with ``scipy.integrate.odeint``."""

from dataclasses import dataclass

import numpy as np
from scipy.integrate import odeint

from nsl_hpc.systems.port_hamiltonian import PortHamiltonianSystem


@dataclass(frozen=True)
class Multisine:
    """u_c(t) = sum_{k=1..N} a sin(2 pi k f0 t + phi_{c,k}) for each input channel c."""

    amplitude: float
    f0_hz: float
    phases: np.ndarray  # (m, N) radians

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """Input at times t (T,) in seconds, (T, m)."""
        harmonics = np.arange(1, self.phases.shape[1] + 1)
        angle = 2 * np.pi * self.f0_hz * np.multiply.outer(np.atleast_1d(t), harmonics)  # (T, N)
        return self.amplitude * np.sin(angle[:, None, :] + self.phases).sum(axis=-1)


@dataclass(frozen=True)
class Trajectory:
    """Samples of one simulated experiment; every array has T rows."""

    t: np.ndarray  # (T,) s
    x: np.ndarray  # (T, n) state
    u: np.ndarray  # (T, m) input
    dx: np.ndarray  # (T, n) exact dx/dt from the right-hand side
    y: np.ndarray  # (T, m) output

    def head(self, points: int) -> "Trajectory":
        """The first ``points`` samples."""
        return Trajectory(*(a[:points] for a in (self.t, self.x, self.u, self.dx, self.y)))


def draw_multisine(rng: np.random.Generator, channels: int, amplitude: float, f0_hz: float,
                   harmonics: int) -> Multisine:
    """A multisine with phases drawn uniformly in [0, 2 pi), independently per channel and harmonic."""
    return Multisine(amplitude, f0_hz, rng.uniform(0.0, 2 * np.pi, size=(channels, harmonics)))


def simulate(system: PortHamiltonianSystem, x0: np.ndarray, excitation: Multisine, duration_s: float,
             dt_s: float, rtol: float, atol: float) -> Trajectory:
    """Integrate from x0 (n,) and sample every dt_s for duration_s: T = round(duration_s / dt_s) points."""
    t = np.arange(round(duration_s / dt_s)) * dt_s

    def rhs(state: np.ndarray, time: float) -> np.ndarray:
        return system.derivative(state[None], excitation(time))[0]

    x = odeint(rhs, x0, t, rtol=rtol, atol=atol)
    u = excitation(t)
    return Trajectory(t, x, u, system.derivative(x, u), system.output(x))
