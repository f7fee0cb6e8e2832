"""The typed owners of the ``arch`` group (conf/arch/<name>.yaml): one schema per architecture, its options
with their types and choices (``config.schema``). ``arch_settings`` types an arch config (a user's architecture:
``OwnArch``); the models build from the instance (``nsl_hpc.models``, ``studies.input_output.study.build_io_model``)."""

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any

from nsl_hpc.config.mapping import plain
from nsl_hpc.config.schema import setting, typed
from nsl_hpc.config.targets import PACKAGE_PREFIX, TARGET
from nsl_hpc.core.errors import ConfigError

BLOCKS = ("layernorm_silu", "tanh")  # an MLP's hidden layer: Linear -> LayerNorm -> SiLU, or Linear -> tanh
STUDIES = ("input_state", "input_output")
IO_ARCHITECTURES = ("narx", "subnet")  # the input-output study's architectures (per-arch training settings)
FORMS = ("joint", "split")
HAMILTONIANS = ("abs", "plain", "half_square")
DISSIPATIONS = ("square", "lower_triangular")
SUBNET_NETWORKS = ("encoder", "f", "h")  # SUBNET's MLPs: the encoder, the state transition f and the output map h


@dataclass(frozen=True)
class Arch:
    """An architecture; its other keys are its options (keyword arguments of ``_target_``)."""

    name: str = setting("the architecture")
    _target_: str = setting("the class that builds it (input-state: a StateSpaceArchitecture of n, m, n_h and the "
                            "options)")
    study: str = setting("the study it belongs to", choices=STUDIES)
    block: str = setting("hidden layer: Linear -> LayerNorm -> SiLU, or Linear -> tanh", choices=BLOCKS)

    @classmethod
    def from_values(cls, values: Any, key: str) -> "Arch":
        """The ``arch`` group ``key`` typed by its architecture's schema (``arch_settings``)."""
        return arch_settings(values, key)

    def keywords(self) -> dict[str, Any]:
        """The options ``_target_`` takes: every setting but name, _target_, study and block."""
        return {item.name: getattr(self, item.name) for item in fields(self) if item.name not in BASE_KEYS}


@dataclass(frozen=True)
class OwnArch(Arch):
    """An architecture of yours: its options are its ``_target_``'s to check (a signature that does not take them
    is refused before any work)."""

    options: dict[str, Any] = field(default_factory=dict)  # the config's other keys

    def keywords(self) -> dict[str, Any]:
        return dict(self.options)


@dataclass(frozen=True)
class UnstructuredSettings(Arch):
    """dx/dt = f(x, u), y = g(x) (3a)."""

    form: str = setting("joint: one MLP from (x, u) to (dx/dt, y); split: f and g", choices=FORMS)
    width_factor: float = setting("f's width is this times n_h", 0, low_open=True)


@dataclass(frozen=True)
class InputAffineSettings(Arch):
    """dx/dt = h(x) + j(x) u, y = k(x) (3b)."""

    width_factor: float = setting("the MLPs' width is this times n_h", 0, low_open=True)
    feedthrough: bool = setting("true: y += D(x) u (the authors' code)")


@dataclass(frozen=True)
class PortHamiltonianSettings(Arch):
    """dx/dt = (J(x) - R(x)) grad H(x) + G(x) u, y = G(x)^T grad H(x) (3c)."""

    hamiltonian: str = setting("H = |MLP(x)|, MLP(x), or ||MLP(x)||^2 / 2", choices=HAMILTONIANS)
    dissipation: str = setting("Q an n x n output, or n(n+1)/2 lower-triangular entries", choices=DISSIPATIONS)


@dataclass(frozen=True)
class NarxSettings(Arch):
    """y_t = F(y_{t-1..t-n_y}, u_{t..t-n_u}), F an MLP (plus a linear map of its input: ``bypass``)."""

    past_outputs: int = setting("n_y", 1)
    past_inputs: int = setting("n_u", 1)
    bypass: bool = setting("F adds a bias-free linear map of the regressors to the MLP's output (deepSI's "
                           "MLP_res_net)")
    zero_bias: bool = setting("every bias starts at 0 (deepSI); false: PyTorch's default initialisation")


@dataclass(frozen=True)
class SubnetSettings(Arch):
    """SUBNET: encoder (past u, y) -> x; x_{k+1} = x_k + f(x_k, u_k) (or f(x_k, u_k)); y_k = h(x_k)."""

    past: int = setting("samples the encoder reads", 1)
    bypass: list[str] = setting("the MLPs that add a linear map of their input to their output (deepSI's "
                                "MLP_res_net)", choices=SUBNET_NETWORKS)
    residual: bool = setting("x_{k+1} = x_k + f(x_k, u_k); false: f(x_k, u_k)")
    zero_bias: bool = setting("every bias starts at 0 (deepSI); false: PyTorch's default initialisation")
    zero_f_output: bool = setting("f's output layer and bypass start at 0 (with the residual: x_{k+1} = x_k at the "
                                  "start)")
    state_dim: int | None = setting("n_x; null: the system's (system.subnet.state_dim)", 1)
    shorten_horizon: bool = setting("a training prefix shorter than P + T samples trains on its one window of "
                                    "n_l - P simulated steps (counted so in the flops); false: such a task is refused")


ARCH_SCHEMAS: dict[str, type[Arch]] = {"unstructured": UnstructuredSettings, "input_affine": InputAffineSettings,
                                       "port_hamiltonian": PortHamiltonianSettings, "narx": NarxSettings,
                                       "subnet": SubnetSettings}


BASE_KEYS = ("name", TARGET, "study", "block")  # the keys every architecture has; the others are its options


def arch_settings(arch_cfg: Mapping[str, Any], key: str = "arch") -> Arch:
    """An ``arch`` group, typed and checked by its architecture's schema (a package architecture: one of
    ``ARCH_SCHEMAS``, built by the package's class), or, for one of the user's, its common keys with the rest as
    its options (``OwnArch``)."""
    if not isinstance(arch_cfg, Mapping):
        raise ConfigError(f"{key}={arch_cfg!r} must be a group of keys: {', '.join(BASE_KEYS)}")
    schema = ARCH_SCHEMAS.get(arch_cfg.get("name", ""))
    if schema is not None and str(arch_cfg.get(TARGET, "")).startswith(PACKAGE_PREFIX):
        return typed(schema, arch_cfg, key)
    values = plain(arch_cfg)
    common = typed(Arch, {name: value for name, value in values.items() if name in BASE_KEYS}, key)
    return OwnArch(**{name: getattr(common, name) for name in BASE_KEYS},
                   options={name: value for name, value in values.items() if name not in BASE_KEYS})
