"""Config values as plain Python: what the code below the commands works on."""

from collections.abc import Mapping
from typing import Any

from omegaconf import OmegaConf

from nsl_hpc.core.errors import ConfigError


def plain(node: Any, resolve: bool = True) -> dict[str, Any]:
    """A config mapping (a DictConfig, or any mapping) as a plain dict, its interpolations resolved unless not
    ``resolve``."""
    values = OmegaConf.to_container(node, resolve=resolve) if OmegaConf.is_config(node) else dict(node)
    if not isinstance(values, dict):
        raise ConfigError(f"expected a mapping of settings, got {type(values).__name__}")
    return {str(key): value for key, value in values.items()}


def flatten(config: Mapping[str, Any], prefix: str = "") -> dict[str, str]:
    """{'a': {'b': 1}} -> {'a.b': '1'}; lists as their text."""
    flat = {}
    for key, value in config.items():
        if isinstance(value, Mapping):
            flat.update(flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = str(value)
    return flat
