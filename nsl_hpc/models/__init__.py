"""The input-state architectures: ``build_model`` turns an ``arch`` config into a module through its ``_target_``
(the package's ``unstructured``, ``input_affine``, ``port_hamiltonian``, or a ``StateSpaceArchitecture`` of the
user's), and ``check_architecture`` tries one on a sample batch before any work.

The input-output models (NARX, SUBNET) are built by ``nsl_hpc.studies.input_output.study``.
"""

from collections.abc import Mapping
from typing import Any

import torch

from nsl_hpc.config.arch import architecture_options
from nsl_hpc.config.targets import called, located, where
from nsl_hpc.errors import ConfigError
from nsl_hpc.models.state_space import StateSpaceArchitecture, StateSpaceModel


def build_architecture(arch_cfg: Mapping[str, Any], state_dim: int, input_dim: int, width: int
                       ) -> StateSpaceArchitecture:
    """The architecture ``arch_cfg._target_`` builds for n = state_dim, m = input_dim, n_h = width and the
    config's options (checked by ``config.arch``)."""
    options = architecture_options(arch_cfg)
    built = called("arch", arch_cfg, located("arch", arch_cfg), state_dim, input_dim, width, **options)
    if not isinstance(built, StateSpaceArchitecture):
        raise ConfigError(f"{where('arch', arch_cfg)}: arch._target_={arch_cfg['_target_']!r} built a "
                          f"{type(built).__name__}, not a StateSpaceArchitecture (nsl_hpc.models.state_space: its MLP "
                          "heads and how dx/dt and y follow from them, which the lockstep training stacks)")
    return built


def build_model(arch_cfg: Mapping[str, Any], state_dim: int, input_dim: int, width: int,
                depth: int) -> StateSpaceModel:
    """The model of architecture ``arch_cfg`` with n_h = width, n_d = depth hidden layers per MLP."""
    return StateSpaceModel(build_architecture(arch_cfg, state_dim, input_dim, width), depth, arch_cfg["block"])


def check_architecture(arch_cfg: Mapping[str, Any], state_dim: int, input_dim: int, width: int, depth: int,
                       batch: int = 8) -> None:
    """Refuse in one line an architecture whose module does not give dx/dt (B, n) and y (B, m), finite, on a sample
    batch, or whose stacked form (two models, as the lockstep training runs them) computes something else."""
    from nsl_hpc.studies.input_state.stacked import StackedModels

    label = f"{where('arch', arch_cfg)}: arch._target_={arch_cfg['_target_']!r}"
    generator = torch.Generator().manual_seed(0)
    z = torch.randn(2, batch, state_dim, generator=generator, dtype=torch.float64)
    v = torch.randn(2, batch, input_dim, generator=generator, dtype=torch.float64)
    models = []
    for k in range(2):
        torch.manual_seed(k)
        models.append(build_model(arch_cfg, state_dim, input_dim, width, depth).double())
    try:
        outputs = [models[k](z[k], v[k]) for k in range(2)]
        stacked = StackedModels(models, torch.float64).forward(torch.cat([z, v], dim=-1).transpose(1, 2))
    except Exception as error:
        raise ConfigError(f"{label}: its model fails on a batch of {batch} samples ({type(error).__name__}: "
                          f"{' '.join(str(error).split())[:160]})") from None
    for name, index, size in (("dx/dt", 0, state_dim), ("y", 1, input_dim)):
        shape = tuple(outputs[0][index].shape)
        if shape != (batch, size):
            raise ConfigError(f"{label}: its model gives {name} of shape {shape} for a batch of {batch}, expected "
                              f"({batch}, {size})")
        if not all(torch.isfinite(output[index]).all() for output in outputs):
            raise ConfigError(f"{label}: its model gives a {name} that is not finite on a sample batch")
        if not all(torch.allclose(stacked[index][k].T, outputs[k][index], rtol=1e-9, atol=1e-9) for k in range(2)):
            raise ConfigError(f"{label}: its stacked form computes another {name} than its module (assemble must "
                              "take every tensor through its layout argument)")
