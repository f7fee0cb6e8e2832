"""Command-line plumbing shared by every ``python -m nsl_hpc.<verb>``: compose the Hydra config from
``conf/`` with ``key=value`` overrides, answer ``--help`` and ``--cfg``, and turn user mistakes into one
line on stderr with exit status 2.
"""

import dataclasses
import errno
import os
import sys
import typing
from collections.abc import Callable, Sequence
from pathlib import Path

from omegaconf import OmegaConf

from nsl_hpc.config import (
    USER_CONFIG_DIR,
    ConfigDoc,
    compose_config,
    config_dir,
    config_dirs,
    config_groups,
    documented_config,
    user_config_dir,
)
from nsl_hpc.config.launchers import LAUNCHERS
from nsl_hpc.config.schema import field_docs
from nsl_hpc.core.diagnostics import log_command
from nsl_hpc.core.errors import ConfigError, RunError


def schema_docs() -> dict[str, str]:
    """Every key of a typed group -> its field's documentation (``config.schema.field_docs``), from the registry of
    config groups."""
    from nsl_hpc.registry import groups

    return {key: doc for group in groups() for owner in group.owners
            for key, doc in field_docs(owner, group.name).items()}


def usage(doc: str, config_name: str, overrides: Sequence[str] = ()) -> str:
    """A command's --help: what it does (its module docstring, with examples), then every key it reads with its
    default and one line (a typed group's field documentation, else the comment of ``conf/<config_name>.yaml`` and
    what it includes) and the config groups it selects; for a command that launches (its config selects a launcher),
    the settings of the launcher ``overrides`` choose (``launcher_usage``) and every sweep (``sweep_usage``)."""
    lines, seen, groups, docs = [doc.strip(), ""], set(), config_groups(), schema_docs()

    def describe(config: ConfigDoc) -> None:
        shown = [(key, default, docs.get(key, comment)) for key, default, comment in config.keys if key not in seen]
        if shown:
            lines.append(f"Keys (key=value) from {config.path.relative_to(config_dir())}:")
        for key, default, comment in shown:
            seen.add(key)
            left = f"{key}={default}" if default else f"{key}.*"
            lines.append(f"  {left if len(left) <= 52 else left[:49] + '...':<52} {comment}".rstrip())
        for group in config.groups:
            lines.append(f"  {group}=<{'|'.join(groups.get(group, []))}>  (config group)")
        for included in config.included:
            describe(included)

    config = documented_config(config_name)
    describe(config)
    if "launcher" in groups_of(config):  # a command that launches
        lines += ["", *launcher_usage(overrides), "", *sweep_usage()]
    lines += ["", "--cfg prints the composed config with every value and exits. --config-dir DIR (or "
              f"${USER_CONFIG_DIR}) adds your own config directory, searched after the package's: your "
              "sweep/<name>.yaml, local/default.yaml (site settings: partition, account), nsl/, system/ ..."]
    return "\n".join(lines) + "\n"


def groups_of(config: ConfigDoc) -> set[str]:
    """The config groups ``config`` and what it includes select."""
    return {*config.groups, *(group for included in config.included for group in groups_of(included))}


def launcher_usage(overrides: Sequence[str]) -> list[str]:
    """The settings of the launcher ``overrides`` choose (``launcher=<name>``, else the default local): each
    ``launcher.<field>=<default>``, its type and one line."""
    chosen = next((o.split("=", 1)[1] for o in overrides if o.startswith("launcher=")), "local")
    schema = LAUNCHERS.get(chosen)
    if schema is None:
        return [f"launcher={chosen} is unknown; launchers: {', '.join(LAUNCHERS)}"]
    lines = [f"launcher={chosen}: {' '.join((schema.__doc__ or '').split())} Its keys (launcher=<"
             f"{'|'.join(LAUNCHERS)}> --help shows another's):"]
    hints = typing.get_type_hints(schema)
    for item in dataclasses.fields(schema):
        if item.name == "name":
            continue
        default = item.default_factory() if item.default_factory is not dataclasses.MISSING else item.default
        left = f"launcher.{item.name}={'null' if default is None else default}"
        kind = str(hints[item.name]).replace("typing.", "").replace("<class '", "").replace("'>", "")
        lines.append(f"  {left:<40} ({kind}) {item.metadata.get('doc', '')}")
    return lines


def sweep_usage() -> list[str]:
    """Every sweep ``+sweep=<name>`` runs, the package's and the user's (``--config-dir``), with the first line of
    its file's comment."""
    lines = ["Sweeps (+sweep=<name>; yours: sweep/<name>.yaml in --config-dir):"]
    for folder in config_dirs():
        for path in sorted((folder / "sweep").glob("*.yaml")):
            comment = next((line.lstrip("# ").strip() for line in path.read_text().splitlines()
                            if line.startswith("#") and "@package" not in line), "")
            lines.append(f"  {path.stem:<20} {comment}" + ("" if folder == config_dir() else f"  ({folder})"))
    return lines


def take_config_dir(args: Sequence[str]) -> list[str]:
    """``args`` without ``--config-dir DIR`` (or ``--config-dir=DIR``), which names the user's config directory
    for this command and the processes it starts (``$NSL_HPC_CONFIG_DIR``; config.user_config_dir)."""
    rest, args = [], list(args)
    while args:
        arg = args.pop(0)
        if arg == "--config-dir" or arg.startswith("--config-dir="):
            value = arg.split("=", 1)[1] if "=" in arg else (args.pop(0) if args else "")
            if not value:
                raise ConfigError("--config-dir needs a directory: --config-dir ~/my_conf")
            os.environ[USER_CONFIG_DIR] = str(Path(value).expanduser().resolve())
            user_config_dir()  # refuse what is no directory before any work
        else:
            rest.append(arg)
    return rest


def run(main: Callable[..., int | None], doc: str, argv: Sequence[str] | None = None,
        config_name: str = "config", pass_overrides: bool = False, per_pair: Sequence[str] = (),
        composed_with: Sequence[str] = ()) -> None:
    """Parse ``argv`` (default ``sys.argv[1:]``), compose the config, call ``main(cfg)`` (or
    ``main(cfg, overrides)``) and exit with its status. Overrides of keys under ``per_pair`` (e.g. ``arch.``: a
    sweep's (system, arch) pairs each compose their own) are left out of this config and reach only ``main``;
    ``composed_with``: overrides applied before the user's in the config only (``main`` sees the user's)."""
    args = list(sys.argv[1:] if argv is None else argv)
    try:
        log_command(sys.stdout, sys.stderr)
        args = take_config_dir(args)
        flags = {a for a in args if a.startswith("-")}
        overrides = [a for a in args if not a.startswith("-")]
        unknown = flags - {"-h", "--help", "--cfg"}
        if unknown:
            raise ConfigError(f"unknown option {sorted(unknown)[0]}; options are --help, --cfg and --config-dir "
                              "DIR, everything else is key=value")
        if flags & {"-h", "--help"}:
            print(usage(doc, config_name, overrides), end="")
            sys.exit(0)
        shared = [o for o in overrides if not o.lstrip("+~").startswith(tuple(per_pair))]
        cfg = compose_config([*composed_with, *shared], config_name)
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
    except BrokenPipeError:  # the reader went away (| head): stop quietly, as Unix tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error when Python flushes
        sys.exit(1)
    except OSError as error:
        if error.errno not in (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES):
            raise
        print(f"error: {write_failure(error)}", file=sys.stderr)
        sys.exit(1)


def write_failure(error: OSError) -> str:
    """One line for a write the machine refused: a full disk or quota (free space), or a place that takes no
    writes (a read-only file system, no permission: run where the sweep can be written)."""
    where = error.filename or "a file"
    if error.errno in (errno.ENOSPC, errno.EDQUOT):
        return (f"{error.strerror} while writing {where}; what was finished is kept: free space (or point the "
                "command at a writable place) and run it again")
    return (f"{where} cannot be written ({error.strerror}); what was finished is kept: run the command where the "
            "sweep directory is writable (or copy it to a writable place and point sweep_dir there)")
