"""Multisine excitation and trajectory simulation with ``scipy.integrate.odeint``."""

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from nsl_hpc.systems import System


@dataclass(frozen=True)
class Multisine:
    """u_{e,c}(t) = sum_{k=k0..k0+N-1} a sin(2 pi k f0 t + phi_{e,c,k}) for input channel c of experiment e;
    k0 = ``first_harmonic`` (1: the paper; 0: the authors' code, whose first term is a constant a sin(phi))."""

    amplitude: float
    f0_hz: float
    phases: np.ndarray  # (E, m, N) radians
    first_harmonic: int = 1

    def __call__(self, t: np.ndarray | float) -> np.ndarray:
        """Inputs at times t (T,) in seconds (a scalar: T = 1), (T, E, m)."""
        harmonics = np.arange(self.first_harmonic, self.first_harmonic + self.phases.shape[-1])
        angle = 2 * np.pi * self.f0_hz * np.multiply.outer(np.atleast_1d(t), harmonics)  # (T, N)
        return self.amplitude * np.sin(angle[:, None, None, :] + self.phases).sum(axis=-1)


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


def draw_multisine(rng: np.random.Generator, experiments: int, channels: int, amplitude: float, f0_hz: float,
                   harmonics: int, first_harmonic: int = 1) -> Multisine:
    """Multisines with phases drawn uniformly in [0, 2 pi), independently per experiment, channel and harmonic."""
    return Multisine(amplitude, f0_hz, rng.uniform(0.0, 2 * np.pi, size=(experiments, channels, harmonics)),
                     first_harmonic)


def simulate(system: "System", x0: np.ndarray, excitation: Multisine, duration_s: float,
             dt_s: float, rtol: float, atol: float) -> list[Trajectory]:
    """Integrate E experiments from x0 (E, n), experiment e driven by channel block e of ``excitation``, and
    sample every dt_s for duration_s: T = round(duration_s / dt_s) points each. The experiments are one
    odeint call (their Jacobian is block-diagonal, passed as banded): E at once cost about what 5-15 cost
    one by one, and agree with those to ~1e-7 relative at rtol = atol = 1e-9."""
    from scipy.integrate import odeint  # 0.4 s to import: only what simulates pays it, not every command

    experiments, n = x0.shape
    t = np.arange(round(duration_s / dt_s)) * dt_s

    def rhs(state: np.ndarray, time: float) -> np.ndarray:
        return system.derivative(state.reshape(experiments, n), excitation(time)[0]).ravel()

    x = odeint(rhs, x0.ravel(), t, rtol=rtol, atol=atol, ml=n - 1, mu=n - 1).reshape(len(t), experiments, n)
    u = excitation(t)  # (T, E, m)
    return [Trajectory(t, x[:, e], u[:, e], system.derivative(x[:, e], u[:, e]), system.output(x[:, e]))
            for e in range(experiments)]
