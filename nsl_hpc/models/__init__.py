"""The state-space architectures, by name; ``build_model`` turns an ``arch`` config into a module."""

from collections.abc import Mapping
from typing import Any

from torch import nn

from nsl_hpc.errors import ConfigError
from nsl_hpc.models.input_affine import InputAffine
from nsl_hpc.models.port_hamiltonian import PortHamiltonian
from nsl_hpc.models.unstructured import Unstructured

ARCHITECTURES: dict[str, type[nn.Module]] = {
    "unstructured": Unstructured,
    "input_affine": InputAffine,
    "port_hamiltonian": PortHamiltonian,
}


def build_model(arch_cfg: Mapping[str, Any], state_dim: int, input_dim: int, width: int,
                depth: int) -> nn.Module:
    """The architecture ``arch_cfg.name`` for n = state_dim, m = input_dim, n_h = width, n_d = depth."""
    name = arch_cfg["name"]
    if name not in ARCHITECTURES:
        raise ConfigError(f"unknown arch {name!r}; choose one of: {', '.join(sorted(ARCHITECTURES))}")
    options = {k: v for k, v in arch_cfg.items() if k not in ("name", "study")}
    return ARCHITECTURES[name](state_dim, input_dim, width, depth, **options)
