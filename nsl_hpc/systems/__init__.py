"""The simulated systems of the input-state study: ``build_system`` turns a typed ``system`` group into one through
its ``_target_`` (the package's ``spring``, ``ball``, ``motor``, or a class or function of the user's), and
``check_system`` tries one on its initial box before any work."""

from typing import Protocol, runtime_checkable

import numpy as np

from nsl_hpc.config.system import InputStateSystem
from nsl_hpc.config.targets import called, labelled, located
from nsl_hpc.core.errors import ConfigError, one_line


@runtime_checkable
class System(Protocol):
    """What a simulated system gives: its sizes and right-hand side, vectorised over a batch (x (N, n), u (N, m)).
    A port-Hamiltonian one (``PortHamiltonianSystem``) derives both from H, J, R and B."""

    state_dim: int
    input_dim: int

    def derivative(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """dx/dt = f(x, u), (N, n)."""
        ...

    def output(self, x: np.ndarray) -> np.ndarray:
        """y = g(x), (N, m)."""
        ...


def build_system(settings: InputStateSystem) -> System:
    """The system ``settings._target_`` builds from its constants ``settings.params`` (keyword arguments)."""
    system = called("system", settings, located("system", settings), **settings.params)
    if not isinstance(system, System):
        missing = [name for name in ("state_dim", "input_dim", "derivative", "output") if not hasattr(system, name)]
        raise ConfigError(f"{labelled('system', settings)} built a {type(system).__name__} without "
                          f"{', '.join(missing)} (nsl_hpc.systems.System)")
    return system


def check_system(settings: InputStateSystem, samples: int = 256) -> System:
    """The system, refused in one line unless its sizes agree with the initial box and f and g give finite values
    of the right shapes at ``samples`` states drawn from the box (its corners among them) and inputs up to three
    times the multisine's RMS."""
    system = build_system(settings)
    label = labelled("system", settings)
    box = np.asarray(settings.initial_box, dtype=float)
    if len(box) != system.state_dim:
        raise ConfigError(f"{label} has state_dim={system.state_dim}, system.initial_box has {len(box)} states")
    rng = np.random.default_rng(0)
    corners = np.stack(np.meshgrid(*box, indexing="ij"), axis=-1).reshape(-1, len(box))[:samples]
    x = np.concatenate([corners, rng.uniform(box[:, 0], box[:, 1], size=(samples, len(box)))])
    peak = 3 * settings.input.amplitude * np.sqrt(settings.input.harmonics / 2)  # 3 x its RMS
    u = rng.uniform(-peak, peak, size=(len(x), system.input_dim))
    for name, value, shape in (("derivative(x, u)", lambda: system.derivative(x, u), (len(x), system.state_dim)),
                               ("output(x)", lambda: system.output(x), (len(x), system.input_dim))):
        try:
            with np.errstate(all="ignore"):  # what is not finite is the one line below, not a warning
                result = np.asarray(value(), dtype=float)
        except Exception as error:
            raise ConfigError(f"{label}: {name} raises {type(error).__name__}: {one_line(error)[:200]}") from None
        if result.shape != shape:
            raise ConfigError(f"{label}: {name} gives shape {result.shape} for {len(x)} states, expected {shape}")
        if not np.isfinite(result).all():
            raise ConfigError(f"{label}: {name} is not finite at {int((~np.isfinite(result)).any(axis=1).sum())} of "
                              f"{len(x)} states drawn from system.initial_box (inputs up to {peak:g})")
    return system
