"""Names, configs and closed forms (the oracles the package's results are checked against) shared by several test
modules."""

from typing import Any

import numpy as np

from nsl_hpc.config import compose_config
from nsl_hpc.studies import pair_of
from nsl_hpc.studies.metrics import ErrorSums, spreads
from nsl_hpc.systems.port_hamiltonian import PortHamiltonianSystem

SYSTEM_NAMES = ["spring", "ball", "motor"]
ARCH_NAMES = ["unstructured", "input_affine", "port_hamiltonian"]


def system_settings(name: str, *overrides: str) -> Any:
    """The typed ``system`` group of system ``name`` (an input-state or, with study=input_output, an input-output
    one)."""
    return pair_of(compose_config([*overrides, f"system={name}"])).system


def mlp_parameter_count(in_dim: int, out_dim: int, width: int, depth: int, block: str) -> int:
    """Closed form of the parameter count of ``mlp(in_dim, out_dim, width, depth, block)``:
    (in+1) w + (n_d-1)(w+1) w + (w+1) out, plus 2 w per hidden layer with LayerNorm."""
    norm = 2 * width * depth if block == "layernorm_silu" else 0
    return (in_dim + 1) * width + (depth - 1) * (width + 1) * width + (width + 1) * out_dim + norm


def scores_both_ways(true: np.ndarray, predicted: np.ndarray, normalization: str) -> dict[str, float]:
    """nmae_per_column, nmse_per_column, nmae_scalar, nmse_scalar, and nmae / nmse: the pair ``normalization``
    selects, of ``predicted`` against ``true`` (K, n) in one chunk."""
    sums = ErrorSums(spreads(true))
    sums.add(predicted - true)
    return sums.both_ways(normalization)


def power_balance(system: PortHamiltonianSystem, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """dH/dt predicted by passivity: -grad H^T R grad H + y^T u, (N,)."""
    grad = system.grad_hamiltonian(x)[..., None]
    dissipated = (np.swapaxes(grad, -1, -2) @ system.dissipation(x) @ grad)[..., 0, 0]
    return -dissipated + np.sum(system.output(x) * u, axis=-1)
