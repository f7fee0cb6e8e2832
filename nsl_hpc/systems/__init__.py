"""The simulated benchmark systems, by name; ``build_system`` turns a ``system`` config into one."""

from collections.abc import Mapping
from typing import Any

from nsl_hpc.errors import ConfigError
from nsl_hpc.systems.ball import Ball
from nsl_hpc.systems.motor import Motor
from nsl_hpc.systems.port_hamiltonian import PortHamiltonianSystem
from nsl_hpc.systems.spring import Spring

SYSTEMS: dict[str, type[PortHamiltonianSystem]] = {"spring": Spring, "ball": Ball, "motor": Motor}


def build_system(name: str, params: Mapping[str, Any]) -> PortHamiltonianSystem:
    """The system called ``name`` with physical constants ``params``."""
    if name not in SYSTEMS:
        raise ConfigError(f"unknown system {name!r}; choose one of: {', '.join(sorted(SYSTEMS))}")
    return SYSTEMS[name](**params)
