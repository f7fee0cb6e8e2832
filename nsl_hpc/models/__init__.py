"""The input-state architectures, by name; ``build_model`` turns an ``arch`` config into a module.

The input-output models (NARX, SUBNET) are built by ``nsl_hpc.studies.input_output.study``.
"""

from collections.abc import Mapping
from typing import Any

from nsl_hpc.config.arch import architecture_options
from nsl_hpc.errors import ConfigError
from nsl_hpc.models.input_affine import InputAffine
from nsl_hpc.models.port_hamiltonian import PortHamiltonian
from nsl_hpc.models.state_space import StateSpaceArchitecture, StateSpaceModel
from nsl_hpc.models.unstructured import Unstructured

ARCHITECTURES: dict[str, type[StateSpaceArchitecture]] = {
    "unstructured": Unstructured,
    "input_affine": InputAffine,
    "port_hamiltonian": PortHamiltonian,
}


def build_architecture(arch_cfg: Mapping[str, Any], state_dim: int, input_dim: int, width: int
                       ) -> StateSpaceArchitecture:
    """The architecture ``arch_cfg.name`` for n = state_dim, m = input_dim, n_h = width (its config checked by
    ``config.arch``)."""
    options = architecture_options(arch_cfg)
    if arch_cfg["name"] not in ARCHITECTURES:
        raise ConfigError(f"arch {arch_cfg['name']!r} is no input-state architecture; choose one of: "
                          f"{', '.join(sorted(ARCHITECTURES))}")
    return ARCHITECTURES[arch_cfg["name"]](state_dim, input_dim, width, **options)


def build_model(arch_cfg: Mapping[str, Any], state_dim: int, input_dim: int, width: int,
                depth: int) -> StateSpaceModel:
    """The model of architecture ``arch_cfg.name`` with n_h = width, n_d = depth hidden layers per MLP."""
    return StateSpaceModel(build_architecture(arch_cfg, state_dim, input_dim, width), depth, arch_cfg["block"])
