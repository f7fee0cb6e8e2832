"""The input-state models: ``build_model`` turns a typed ``arch`` group into a module through its ``_target_`` (the
package's ``unstructured``, ``input_affine``, ``port_hamiltonian``; a user's ``StateSpaceArchitecture``, or a
user's ``torch.nn.Module``); ``studies.input_state.lockstep.check_architecture`` tries one before any work.

The input-output models (NARX, SUBNET) are built by ``nsl_hpc.studies.input_output.study``.
"""

from torch import nn

from nsl_hpc.config.arch import Arch
from nsl_hpc.config.targets import called, labelled, located
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.models.state_space import StateSpaceArchitecture, StateSpaceModel


def build_model(arch: Arch, state_dim: int, input_dim: int, width: int, depth: int) -> nn.Module:
    """The model ``arch._target_`` builds for n = state_dim, m = input_dim, n_h = width, n_d = depth and the
    architecture's options (``Arch.keywords``): a ``StateSpaceArchitecture`` class is built with (n, m, n_h,
    options) and made a ``StateSpaceModel`` (MLP heads of n_d hidden layers of ``block``: the lockstep training
    batches them); anything else is called with (n, m, n_h, n_d, block, options) and gives a ``torch.nn.Module``
    whose forward maps z (B, n), v (B, m) to dz/dt (B, n), y (B, m) (trained one per process)."""
    builder, options = located("arch", arch), arch.keywords()
    if isinstance(builder, type) and issubclass(builder, StateSpaceArchitecture):
        architecture = called("arch", arch, builder, state_dim, input_dim, width, arg_names=("n", "m", "n_h"),
                              **options)
        return StateSpaceModel(architecture, depth, arch.block)
    module = called("arch", arch, builder, state_dim, input_dim, width, depth, arg_names=("n", "m", "n_h", "n_d"),
                    block=arch.block, **options)
    if not isinstance(module, nn.Module):
        raise ConfigError(f"{labelled('arch', arch)} built a {type(module).__name__}, not a torch.nn.Module or "
                          "StateSpaceArchitecture")
    return module


def stackable(model: nn.Module) -> bool:
    """Whether the lockstep training batches ``model`` with others (a ``StateSpaceModel``), or trains it alone."""
    return isinstance(model, StateSpaceModel)
