"""The configs in ``conf/``: where they are, and composing one with ``key=value`` overrides (Hydra)."""

import difflib
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from nsl_hpc.config.launchers import LAUNCHERS, register_launchers
from nsl_hpc.config.mapping import plain
from nsl_hpc.core.errors import ConfigError, one_line

if TYPE_CHECKING:
    from hydra.errors import MissingConfigException

PACKAGE_DIR = Path(__file__).resolve().parent.parent  # nsl_hpc/


def config_dir() -> Path:
    """``conf/`` of a source checkout, or the copy a wheel carries inside the package."""
    for candidate in (PACKAGE_DIR.parent / "conf", PACKAGE_DIR / "conf"):
        if (candidate / "config.yaml").is_file():
            return candidate
    raise ConfigError(f"no conf/config.yaml next to {PACKAGE_DIR}; reinstall nsl_hpc")


USER_CONFIG_DIR = "NSL_HPC_CONFIG_DIR"  # the environment variable that names the user's config directory


def tool_settings(name: str, argv: Sequence[str]) -> DictConfig:
    """conf/<name>.yaml (a benchmark's or tool's own file, outside Hydra's groups) with ``key=value`` overrides; a
    key it does not have, or a value that does not parse, is one line (SystemExit), before any work."""
    cfg = OmegaConf.load(config_dir() / f"{name}.yaml")
    OmegaConf.set_struct(cfg, True)
    try:
        merged = OmegaConf.merge(cfg, OmegaConf.from_dotlist(list(argv)))
    except (OmegaConfBaseException, yaml.YAMLError) as error:  # its first line names the key or the value
        raise SystemExit(f"error: {str(error).splitlines()[0]}") from None
    assert isinstance(merged, DictConfig)  # a tool's file is a mapping
    return merged


def user_config_dir() -> Path | None:
    """The user's own config directory (``--config-dir`` of any command, or $NSL_HPC_CONFIG_DIR): searched after
    the package's ``conf/`` for config groups (``sweep/<name>.yaml``, ``local/default.yaml`` for site settings,
    ``system/``, ``nsl/`` ...); None without one. Refused in one line when it is no directory."""
    value = os.environ.get(USER_CONFIG_DIR)
    if not value:
        return None
    path = Path(value).expanduser().resolve()
    if not path.is_dir():
        raise ConfigError(f"--config-dir (${USER_CONFIG_DIR}) {value!r} is no directory; name the folder that "
                          "holds your sweep/<name>.yaml and local/default.yaml")
    return path


def hydra_quoted(text: str) -> str:
    """``text`` escaped for a single-quoted string of Hydra's override grammar: a quote, and the backslashes
    just before a quote or at the end, take a backslash each."""
    return re.sub(r"(\\*)('|$)", lambda match: match[1] * 2 + ("\\'" if match[2] else ""), text)


def config_dirs() -> list[Path]:
    """The package's ``conf/`` and, after it, the user's config directory."""
    return [config_dir(), *filter(None, [user_config_dir()])]


# Mappings whose keys are the user's to add with +key=value (any sbatch flag); elsewhere + only selects a config
# group (+sweep=<name>): a key added anywhere else is one no command reads, so it is refused.
OPEN_MAPPINGS = ("launcher.extra_sbatch",)
UNKNOWN_KEY = re.compile(r"Could not override '([^']+)'.*is not in struct")


def compose_config(overrides: Sequence[str], config_name: str = "config") -> DictConfig:
    """The config ``config_name`` from ``conf/`` with Hydra ``overrides`` applied, in struct mode. A key the
    config does not have (a typo, or a ``+key`` no command reads) is a ConfigError naming the closest key."""
    for override in overrides:
        key = override.split("=", 1)[0]
        if key.startswith("+") and not key.startswith("++") and key[1:] not in config_groups() \
                and key[1:].rpartition(".")[0] not in OPEN_MAPPINGS:
            raise ConfigError(unknown_key(key[1:], [o for o in overrides if o != override], config_name)
                              + f"; + only selects a config group (+sweep=<name>) or adds a {OPEN_MAPPINGS[0]} flag")
    try:
        return composed(overrides, config_name)
    except ConfigError as error:
        unknown = UNKNOWN_KEY.search(str(error))
        if unknown is None:
            raise
        key = unknown.group(1)
        if key in OPEN_MAPPINGS:
            raise ConfigError(f"{key} takes its flags one at a time: +{key}.<flag>=<value> (e.g. "
                              f"+{key}.constraint=cpu)") from None
        raise ConfigError(unknown_key(key, [o for o in overrides if o.split("=", 1)[0] != key], config_name)) \
            from None


def unknown_key(key: str, overrides: Sequence[str], config_name: str) -> str:
    """"unknown key 'wiat' (did you mean 'wait'?)": the closest key of the config composed with ``overrides``,
    or config group."""
    try:
        keys = [*config_groups(), *dotted_keys(plain(composed(overrides, config_name), resolve=False))]
    except ConfigError:
        keys = list(config_groups())
    close = difflib.get_close_matches(key, keys, n=1, cutoff=0.6)
    return f"unknown key '{key}' ({f'did you mean {close[0]!r}?' if close else '--help lists the keys'})"


def dotted_keys(node: Any, prefix: str = "") -> list[str]:
    """Every key of a nested mapping, dotted (``train``, ``train.lr``, ...)."""
    if not isinstance(node, dict):
        return []
    return [name for key, value in node.items()
            for name in (f"{prefix}{key}", *dotted_keys(value, f"{prefix}{key}."))]


def composed(overrides: Sequence[str], config_name: str) -> DictConfig:
    """``compose_config`` without the check of unknown keys."""
    # Hydra is imported where it composes: jobs and commands that only read a sweep's configs skip its 0.2 s
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException, MissingConfigException

    register_launchers()
    try:
        user = user_config_dir()
        search = [f"hydra.searchpath=['file://{hydra_quoted(str(user))}']"] if user else []
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            cfg = compose(config_name, overrides=[*search, *overrides])
        require_one_study(cfg)  # before the interpolations, which read keys of the system's own study
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


def require_one_study(cfg: Any) -> None:
    """Refuse a system or arch of another study than the config's ``study`` (a composed config, or its plain
    values), in one line that names the study to add."""
    if "study" not in cfg:
        return
    study = cfg["study"]["name"]
    for group in ("system", "arch"):
        member = cfg[group].get("study") if group in cfg else study
        if member != study:
            raise ConfigError(f"{group}={cfg[group]['name']} belongs to the {member} study, not {study}; "
                              f"add study={member} (or pick a {group} of the {study} study)")


def describe_missing_config(error: "MissingConfigException") -> str:
    """'unknown system 'foo'; choose one of: ...' from Hydra's multi-line message."""
    missing = error.missing_cfg_file or ""
    if "/" in missing and error.options:
        group, name = missing.rsplit("/", 1)
        return f"unknown {group} {name!r}; choose one of: {', '.join(error.options)}"
    return one_line(str(error))


def config_groups() -> dict[str, list[str]]:
    """Selectable options of each config group, e.g. {'system': ['ball', 'motor', 'spring']}."""
    groups: dict[str, list[str]] = {}
    for folder in config_dirs():
        for group in folder.iterdir():
            if group.is_dir() and group.name != "local":
                groups[group.name] = sorted({*groups.get(group.name, []), *(f.stem for f in group.glob("*.yaml"))})
    groups["launcher"] = sorted(LAUNCHERS)
    return dict(sorted(groups.items()))


KEY_LINE = re.compile(r"^(?P<indent> *)(?P<key>[A-Za-z_]\w*):(?P<value>[^#]*?)\s*(?:#\s?(?P<comment>.*))?$")
DEFAULT_LINE = re.compile(r"^\s+-\s+(?:optional\s+)?(?P<entry>[\w/]+)(?::\s*(?P<option>\w+))?")


@dataclass
class ConfigDoc:
    """What a config file of conf/ documents: its keys (dotted key, default, comment; a section's own line has no
    default), the config groups it selects, and the configs it includes."""

    path: Path
    keys: list[tuple[str, str, str]] = field(default_factory=list)
    groups: list[str] = field(default_factory=list)
    included: list["ConfigDoc"] = field(default_factory=list)


def documented_config(name: str, prefix: str = "", top: bool = True) -> ConfigDoc:
    """The ``ConfigDoc`` of ``conf/<name>.yaml``, read from its text (comments included), keys under ``prefix``.
    Its defaults list is followed: a plain config (``- config``) and a group option placed at the top level
    (``# @package _global_``, e.g. ``study: input_state``) are included, and at the ``top`` the options of its
    own groups too (``nsl: default`` as ``nsl.*``)."""
    path = config_dir() / f"{name}.yaml"
    doc, in_defaults, comment, value = ConfigDoc(path), False, "", ""
    sections: list[str] = []
    for line in path.read_text().splitlines():
        if value:  # a flow mapping or list continued on this line
            doc.keys[-1] = (doc.keys[-1][0], f"{value} {line.split('#')[0].strip()}", doc.keys[-1][2])
            value = doc.keys[-1][1] if doc.keys[-1][1].count("{") + doc.keys[-1][1].count("[") > \
                doc.keys[-1][1].count("}") + doc.keys[-1][1].count("]") else ""
            continue
        if line.startswith("#"):
            if "@package" not in line:
                comment = comment or line.lstrip("# ")
            continue
        if not line.strip():
            comment = ""
            continue
        default = DEFAULT_LINE.match(line) if in_defaults else None
        if default:
            doc_of(default["entry"].lstrip("/"), default["option"], doc, top)  # /test_set: a group from the root
            continue
        match = KEY_LINE.match(line)
        if not match:
            continue
        depth = len(match["indent"]) // 2
        in_defaults = depth == 0 and match["key"] == "defaults"
        if in_defaults:
            continue
        sections[depth:] = [match["key"]]
        key, text = prefix + ".".join(sections), match["value"].strip()
        doc.keys.append((key, text, (match["comment"] or ("" if text else comment)).strip()))
        value = text if text.count("{") + text.count("[") > text.count("}") + text.count("]") else ""
        comment = ""
    return doc


def doc_of(entry: str, option: str | None, doc: ConfigDoc, top: bool) -> None:
    """Add a defaults-list entry (``entry`` or ``entry: option``) to ``doc``: a group to ``doc.groups``, what
    ``documented_config`` includes to ``doc.included``."""
    if option is None:
        if entry != "_self_" and (config_dir() / f"{entry}.yaml").is_file():
            doc.included.append(documented_config(entry, top=False))
        return
    if entry == "local":
        return
    doc.groups.append(entry)
    option_file = config_dir() / entry / f"{option}.yaml"  # launcher's options are schemas, not files
    if not option_file.is_file():
        return
    if option_file.read_text().startswith("# @package _global_"):
        doc.included.append(documented_config(f"{entry}/{option}", top=False))
    elif top:
        doc.included.append(documented_config(f"{entry}/{option}", f"{entry}.", top=False))
