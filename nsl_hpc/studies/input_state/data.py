"""Training and test sets of a simulated system, assembled from cached trajectories.

Trajectory i of seed s is the same wherever it is used: a task with n_t trajectories takes a prefix of
the pool (system, s), so tasks of one seed share cached simulations. The test set (``system.test_set``, chosen
with ``test_set=100x10s|100x100s|1000x10s``) has a seed of its own, is simulated in one go and is the same for
every task of a system.
"""

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from nsl_hpc.config.identity import outcome_values
from nsl_hpc.config.system import InputStateSystem
from nsl_hpc.core.cache import ArrayCache
from nsl_hpc.core.seeding import stable_seed
from nsl_hpc.systems import build_system
from nsl_hpc.systems.simulation import Trajectory, draw_multisine, simulate

# Bump when the simulation code changes results, so cached trajectories are not reused.
SIMULATION_VERSION = 2


@dataclass(frozen=True)
class Dataset:
    """Samples stacked over trajectories; N rows each."""

    x: np.ndarray  # (N, n) state
    u: np.ndarray  # (N, m) input
    dx: np.ndarray  # (N, n) dx/dt
    y: np.ndarray  # (N, m) output

    def __len__(self) -> int:
        return len(self.x)

    def rows(self, start: int, stop: int) -> "Dataset":
        """Samples start to stop (views, not copies)."""
        return Dataset(self.x[start:stop], self.u[start:stop], self.dx[start:stop], self.y[start:stop])


def points_per_trajectory(system: InputStateSystem) -> int:
    """Samples in one simulated trajectory (1,000 for 10 s at 0.01 s)."""
    return round(system.simulation.duration_s / system.simulation.dt_s)


def split_trajectory_count(n_traj: float, points: int) -> tuple[int, int]:
    """n_t = a + b -> (a whole trajectories, floor(b * points) samples of trajectory a+1)."""
    whole = math.floor(n_traj)
    return whole, math.floor((n_traj - whole) * points)


def training_points(n_traj: float, points: int) -> int:
    """Number of training samples for n_t trajectories of ``points`` samples."""
    whole, partial = split_trajectory_count(n_traj, points)
    return whole * points + partial


FIELDS = ("t", "x", "u", "dx", "y")


SIMULATED_BY = ("name", "_target_", "params", "initial_box", "input", "simulation")  # what a trajectory depends on


def simulation_key(system: InputStateSystem, **where: Any) -> dict[str, Any]:
    """Cache key of simulated data: everything the simulation depends on, and ``where`` in which pool."""
    values = dataclasses.asdict(system)
    return {"version": SIMULATION_VERSION, "system": outcome_values({k: values[k] for k in SIMULATED_BY}), **where}


def load_trajectory(system: InputStateSystem, split: str, seed: int, index: int, cache: ArrayCache) -> Trajectory:
    """Trajectory ``index`` of the pool (system, split, seed), simulated once and then read from cache."""
    key = simulation_key(system, split=split, seed=seed, index=index)

    def create() -> dict[str, np.ndarray]:
        (trajectory,) = simulate_experiments(system, stable_seed("trajectory", key), 1)
        return {field: getattr(trajectory, field) for field in FIELDS}

    return Trajectory(**cache.get_or_create(key, create))


def simulate_experiments(settings: InputStateSystem, seed: int, count: int) -> list[Trajectory]:
    """``count`` experiments simulated together: x0 uniform in the initial box, a fresh multisine per
    experiment and input channel."""
    system = build_system(settings)
    rng = np.random.default_rng(seed)
    box = np.asarray(settings.initial_box, dtype=float)  # (n, 2)
    x0 = rng.uniform(box[:, 0], box[:, 1], size=(count, len(box)))
    excitation = draw_multisine(rng, count, system.input_dim, **dataclasses.asdict(settings.input))
    trajectories = simulate(system, x0, excitation, **dataclasses.asdict(settings.simulation))
    if not all(np.all(np.isfinite(trajectory.x)) for trajectory in trajectories):
        raise FloatingPointError(f"simulation of {settings.name} (seed {seed}) diverged")
    return trajectories


def stack(trajectories: list[Trajectory]) -> Dataset:
    return Dataset(*(np.concatenate([getattr(t, f) for t in trajectories]) for f in ("x", "u", "dx", "y")))


def build_training_set(system: InputStateSystem, seed: int, n_traj: float, cache: ArrayCache) -> Dataset:
    """The first n_t trajectories of seed ``seed``; a fractional part takes a prefix of the next one."""
    whole, partial = split_trajectory_count(n_traj, points_per_trajectory(system))
    parts = [load_trajectory(system, "train", seed, i, cache) for i in range(whole)]
    if partial:
        parts.append(load_trajectory(system, "train", seed, whole, cache).head(partial))
    return stack(parts)


def build_test_set(system: InputStateSystem, cache: ArrayCache) -> Dataset:
    """The fixed test set of a system (``test_set``: ``trajectories`` experiments of ``duration_s`` each from a
    seed of its own, simulated together once), shared by every task of that system: N = trajectories x
    duration_s / dt rows."""
    spec = system.test_set
    simulated = dataclasses.replace(system, simulation=dataclasses.replace(system.simulation,
                                                                            duration_s=spec.duration_s))
    key = simulation_key(simulated, split="test", seed=spec.seed, trajectories=spec.trajectories)

    def create() -> dict[str, np.ndarray]:
        trajectories = simulate_experiments(simulated, stable_seed("test set", key), spec.trajectories)
        return {field: np.concatenate([getattr(t, field) for t in trajectories]) for field in FIELDS}

    stored = cache.get_or_create(key, create)
    return Dataset(*(stored[field] for field in ("x", "u", "dx", "y")))
