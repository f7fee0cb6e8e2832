"""The code a sweep's rows are made by: the package's version and, for a system or arch of the user's (a
``_target_`` outside the package), the hash of its module's source. Every row records its (system, arch)'s
(``code``); the launch that wrote the sweep records each pair's in ``code.json``; a later launch or resubmit whose
code differs is refused in one line (rows of other code would be mixed in silently) unless told to
(``allow_code_change``), and then records the code it runs with."""

import json
from collections.abc import Mapping
from pathlib import Path

from nsl_hpc.config.targets import source_of
from nsl_hpc.core.atomic import write_text
from nsl_hpc.core.errors import ConfigError
from nsl_hpc.studies.base import Pair
from nsl_hpc.sweep import layout
from nsl_hpc.sweep.formats import package_version


def code_of(pair: Pair) -> str:
    """'nsl_hpc 0.2.0; arch cascade: tanks.py sha256:1a2b3c4d5e6f7a8b': what made a (system, arch)'s rows."""
    parts = [f"nsl_hpc {package_version() or '(source tree)'}"]
    for group, spec in (("system", pair.system), ("arch", pair.arch)):
        source = source_of(group, spec)
        if source is not None:
            parts.append(f"{group} {spec.name}: {source}")
    return "; ".join(parts)


def pair_key(system: str, arch: str) -> str:
    return f"{system}/{arch}"


def recorded_code(sweep_dir: Path) -> dict[str, str]:
    """The code of each (system, arch) the sweep's last launch or resubmit ran with ({} before the record)."""
    path = Path(sweep_dir) / layout.CODE
    if not path.exists():
        return {}
    try:
        return dict(json.loads(path.read_text()))
    except (OSError, ValueError, TypeError) as error:
        raise ConfigError(f"{path} is damaged ({type(error).__name__}): restore it from a backup, or delete it to "
                          "record the code of the next launch") from None


def require_same_code(sweep_dir: Path, pairs: Mapping[tuple[str, str], Pair], allow_change: bool) -> None:
    """Record the code of ``pairs`` in the sweep; refuse, in one line, code that differs from the code recorded
    for a pair (unless ``allow_change``: the rows' ``code`` column then says which code made each)."""
    recorded = recorded_code(sweep_dir)
    now = {pair_key(*key): code_of(pair) for key, pair in pairs.items()}
    changed = [key for key, code in now.items() if key in recorded and recorded[key] != code]
    if changed and not allow_change:
        key = changed[0]
        raise ConfigError(f"the code of {key} changed since its rows were made ({recorded[key]} -> {now[key]}): "
                          "restore it, launch into a new sweep_dir, or add allow_code_change=true to mix its rows "
                          "(each row's code column says which code made it)")
    if {**recorded, **now} != recorded:
        write_text(json.dumps({**recorded, **now}, indent=1, sort_keys=True) + "\n", Path(sweep_dir) / layout.CODE)
