"""The input-state models: ``build_model`` turns an ``arch`` config into a module through its ``_target_`` (the
package's ``unstructured``, ``input_affine``, ``port_hamiltonian``; a user's ``StateSpaceArchitecture``, or a
user's ``torch.nn.Module``), and ``check_architecture`` tries one on a sample batch before any work.

The input-output models (NARX, SUBNET) are built by ``nsl_hpc.studies.input_output.study``.
"""

from collections.abc import Mapping
from typing import Any

import torch
from torch import nn

from nsl_hpc.config.arch import architecture_options
from nsl_hpc.config.targets import called, located, where
from nsl_hpc.errors import ConfigError
from nsl_hpc.models.state_space import StateSpaceArchitecture, StateSpaceModel


def build_model(arch_cfg: Mapping[str, Any], state_dim: int, input_dim: int, width: int, depth: int) -> nn.Module:
    """The model ``arch_cfg._target_`` builds for n = state_dim, m = input_dim, n_h = width, n_d = depth and the
    config's options (checked by ``config.arch``): a ``StateSpaceArchitecture`` class is built with (n, m, n_h,
    options) and made a ``StateSpaceModel`` (MLP heads of n_d hidden layers of ``block``: the lockstep training
    batches them); anything else is called with (n, m, n_h, n_d, block, options) and gives a ``torch.nn.Module``
    whose forward maps z (B, n), v (B, m) to dz/dt (B, n), y (B, m) (trained one per process)."""
    builder, options = located("arch", arch_cfg), architecture_options(arch_cfg)
    if isinstance(builder, type) and issubclass(builder, StateSpaceArchitecture):
        architecture = called("arch", arch_cfg, builder, state_dim, input_dim, width, arg_names=("n", "m", "n_h"),
                              **options)
        return StateSpaceModel(architecture, depth, arch_cfg["block"])
    module = called("arch", arch_cfg, builder, state_dim, input_dim, width, depth, arg_names=("n", "m", "n_h", "n_d"),
                    block=arch_cfg["block"], **options)
    if not isinstance(module, nn.Module):
        raise ConfigError(f"{where('arch', arch_cfg)}: arch._target_={arch_cfg['_target_']!r} built a "
                          f"{type(module).__name__}, not a torch.nn.Module or StateSpaceArchitecture")
    return module


def stackable(model: nn.Module) -> bool:
    """Whether the lockstep training batches ``model`` with others (a ``StateSpaceModel``), or trains it alone."""
    return isinstance(model, StateSpaceModel)


def check_architecture(arch_cfg: Mapping[str, Any], state_dim: int, input_dim: int, width: int, depth: int,
                       batch: int = 8) -> None:
    """Refuse in one line an architecture whose module does not give dx/dt (B, n) and y (B, m), finite, on a sample
    batch, or whose stacked form (two models, as the lockstep training runs them) computes something else."""
    from nsl_hpc.studies.input_state.module_stack import ModuleStack
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
        stack = StackedModels(models, torch.float64) if stackable(models[0]) else \
            ModuleStack(models, torch.float64, state_dim, input_dim)
        stacked = stack.forward(torch.cat([z, v], dim=-1).transpose(1, 2))
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
