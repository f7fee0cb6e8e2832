"""Command-line plumbing shared by every ``python -m nsl_hpc.<verb>``: compose the Hydra config from
``conf/`` with ``key=value`` overrides, answer ``--help`` and ``--cfg``, and turn user mistakes into one
line on stderr with exit status 2.
"""

import errno
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from hydra import compose, initialize_config_dir
from hydra.errors import HydraException, MissingConfigException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from nsl_hpc.errors import ConfigError, RunError

PACKAGE_DIR = Path(__file__).resolve().parent


def config_dir() -> Path:
    """``conf/`` of a source checkout, or the copy a wheel carries inside the package."""
    for candidate in (PACKAGE_DIR.parent / "conf", PACKAGE_DIR / "conf"):
        if (candidate / "config.yaml").is_file():
            return candidate
    raise ConfigError(f"no conf/config.yaml next to {PACKAGE_DIR}; reinstall nsl_hpc")


def compose_config(overrides: Sequence[str], config_name: str = "config") -> DictConfig:
    """The config ``config_name`` from ``conf/`` with Hydra ``overrides`` applied, in struct mode."""
    try:
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            cfg = compose(config_name, overrides=list(overrides))
        OmegaConf.resolve(cfg)
        missing = sorted(OmegaConf.missing_keys(cfg))
    except MissingConfigException as error:
        raise ConfigError(describe_missing_config(error)) from None
    except (HydraException, OmegaConfBaseException) as error:
        raise ConfigError(one_line(str(error))) from None
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
    groups = {}
    for group in sorted(p for p in config_dir().iterdir() if p.is_dir() and p.name != "local"):
        groups[group.name] = sorted(f.stem for f in group.glob("*.yaml"))
    return groups


def usage(doc: str, cfg: DictConfig | None) -> str:
    groups = "\n".join(f"  {name}: {', '.join(options)}" for name, options in config_groups().items())
    text = f"{doc.strip()}\n\nConfig groups (choose with group=option):\n{groups}\n"
    text += "\nAny value can be overridden with key=value (nested: train.lr=3e-4). "
    text += "--cfg prints the composed config and exits.\n"
    if cfg is not None:
        text += f"\nCurrent config:\n{OmegaConf.to_yaml(cfg)}"
    return text


def run(main: Callable[..., int | None], doc: str, argv: Sequence[str] | None = None,
        config_name: str = "config", pass_overrides: bool = False) -> None:
    """Parse ``argv`` (default ``sys.argv[1:]``), compose the config, call ``main(cfg)`` (or
    ``main(cfg, overrides)``) and exit with its status."""
    args = list(sys.argv[1:] if argv is None else argv)
    flags = {a for a in args if a.startswith("-")}
    overrides = [a for a in args if not a.startswith("-")]
    unknown = flags - {"-h", "--help", "--cfg"}
    try:
        if unknown:
            raise ConfigError(f"unknown option {sorted(unknown)[0]}; options are --help and --cfg, "
                              "everything else is key=value")
        if flags & {"-h", "--help"}:
            try:
                cfg = compose_config(overrides, config_name)
            except ConfigError:
                cfg = None
            print(usage(doc, cfg))
            sys.exit(0)
        cfg = compose_config(overrides, config_name)
        if "--cfg" in flags:
            print(OmegaConf.to_yaml(cfg), end="")
            sys.exit(0)
        sys.exit((main(cfg, overrides) if pass_overrides else main(cfg)) or 0)
    except ConfigError as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)
    except RunError as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(1)
    except OSError as error:
        if error.errno not in (errno.ENOSPC, errno.EDQUOT, errno.EROFS):
            raise
        print(f"error: {error.strerror} while writing {error.filename or 'a file'}; what was finished is kept: free "
              "space (or point the command at a writable place) and run it again", file=sys.stderr)
        sys.exit(1)
