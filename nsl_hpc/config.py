"""The configs in ``conf/``: where they are, and composing one with ``key=value`` overrides (Hydra)."""

from collections.abc import Sequence
from pathlib import Path

from hydra import compose, initialize_config_dir
from hydra.errors import HydraException, MissingConfigException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from nsl_hpc.errors import ConfigError

PACKAGE_DIR = Path(__file__).resolve().parent


def config_dir() -> Path:
    """``conf/`` of a source checkout, or the copy a wheel carries inside the package."""
    for candidate in (PACKAGE_DIR.parent / "conf", PACKAGE_DIR / "conf"):
        if (candidate / "config.yaml").is_file():
            return candidate
    raise ConfigError(f"no conf/config.yaml next to {PACKAGE_DIR}; reinstall nsl_hpc")


def compose_config(overrides: Sequence[str], config_name: str = "config") -> DictConfig:
    """The config ``config_name`` from ``conf/`` with Hydra ``overrides`` applied, in struct mode."""
    from nsl_hpc.sweep.launchers import register_launchers  # the launcher group's schemas

    register_launchers()
    try:
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            cfg = compose(config_name, overrides=list(overrides))
        OmegaConf.resolve(cfg)
        missing = sorted(OmegaConf.missing_keys(cfg))
    except MissingConfigException as error:
        raise ConfigError(describe_missing_config(error)) from None
    except (HydraException, OmegaConfBaseException) as error:
        cause = error.__cause__  # e.g. a schema's validation error behind "Error merging override ..."
        reason = f": {str(cause).splitlines()[0]}" if isinstance(cause, OmegaConfBaseException) else ""
        raise ConfigError(one_line(str(error)) + reason) from None
    if missing:
        raise ConfigError(f"{missing[0]} is required: add {missing[0]}=<value>")
    return cfg


def describe_missing_config(error: MissingConfigException) -> str:
    """'unknown system 'foo'; choose one of: ...' from Hydra's multi-line message."""
    missing = error.missing_cfg_file or ""
    if "/" in missing and error.options:
        group, name = missing.rsplit("/", 1)
        return f"unknown {group} {name!r}; choose one of: {', '.join(error.options)}"
    return one_line(str(error))


def one_line(message: str) -> str:
    return " ".join(message.split())


def config_groups() -> dict[str, list[str]]:
    """Selectable options of each config group, e.g. {'system': ['ball', 'motor', 'spring']}."""
    from nsl_hpc.sweep.launchers import LAUNCHERS

    groups = {group.name: sorted(f.stem for f in group.glob("*.yaml"))
              for group in config_dir().iterdir() if group.is_dir() and group.name != "local"}
    groups["launcher"] = sorted(LAUNCHERS)
    return dict(sorted(groups.items()))
