"""Names and configs shared by several test modules."""

from omegaconf import OmegaConf

from nsl_hpc.config import compose_config

SYSTEM_NAMES = ["spring", "ball", "motor"]
ARCH_NAMES = ["unstructured", "input_affine", "port_hamiltonian"]


def system_config(name: str, *overrides: str) -> dict:
    """The plain-dict ``system`` config group of system ``name``."""
    return OmegaConf.to_container(compose_config([*overrides, f"system={name}"]).system, resolve=True)
