"""Command-line plumbing shared by every ``python -m nsl_hpc.<verb>``: compose the Hydra config from
``conf/`` with ``key=value`` overrides, answer ``--help`` and ``--cfg``, and turn user mistakes into one
line on stderr with exit status 2.
"""

import errno
import sys
from collections.abc import Callable, Sequence

from omegaconf import DictConfig, OmegaConf

from nsl_hpc.config import compose_config, config_groups
from nsl_hpc.errors import ConfigError, RunError


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
