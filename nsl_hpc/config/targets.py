"""Hydra's ``_target_`` convention: a config group names the class or function that builds its object (a system,
an architecture) by its import path, the package's own as ``nsl_hpc.systems.spring.Spring`` and a user's as
``tanks.TwoTank`` (a module on PYTHONPATH). ``located`` imports it and ``called`` builds with it, each refusing
in one line that names the config file and key; both take the group's typed settings (anything with a ``name``
and a ``_target_``: ``config.system.InputStateSystem``, ``config.arch.Arch``)."""

import hashlib
import importlib
import inspect
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol

import yaml

from nsl_hpc.core.errors import ConfigError, one_line

TARGET = "_target_"
PACKAGE_PREFIX = "nsl_hpc."  # a target inside the package: identified by the package's version, as before targets


class Built(Protocol):
    """A group's typed settings that name what builds it."""

    @property
    def name(self) -> str: ...

    @property
    def _target_(self) -> str: ...


def where(group: str, spec: Built) -> str:
    """'system/two_tank.yaml': the config file of a group option (its ``name`` is the file's stem)."""
    return f"{group}/{spec.name}.yaml"


def located(group: str, spec: Built) -> Callable[..., Any]:
    """The object ``spec._target_`` names (a dotted path: module, then attributes), or a one-line ConfigError."""
    path = spec._target_
    if not isinstance(path, str) or "." not in path:
        raise ConfigError(f"{labelled(group, spec)} must name a class or function by its "
                          "import path, e.g. my_module.MySystem")
    parts = path.split(".")
    for cut in range(len(parts) - 1, 0, -1):
        module_name = ".".join(parts[:cut])
        try:
            found: Any = importlib.import_module(module_name)
        except ModuleNotFoundError as error:
            if error.name is not None and module_name.startswith(error.name) and cut > 1:
                continue  # a shorter path may be the module (Class.method)
            raise ConfigError(f"{labelled(group, spec)} does not import "
                              f"(ModuleNotFoundError: {error}); put its folder on PYTHONPATH") from None
        except Exception as error:  # the user's module itself fails as it imports
            raise ConfigError(f"{labelled(group, spec)}: importing {module_name} raises "
                              f"{type(error).__name__}: {one_line(error)[:200]}") from None
        try:
            for attribute in parts[cut:]:
                found = getattr(found, attribute)
        except AttributeError:
            raise ConfigError(f"{labelled(group, spec)}: module {module_name} has no "
                              f"{'.'.join(parts[cut:])}") from None
        if not callable(found):
            raise ConfigError(f"{labelled(group, spec)} is no class or function")
        return found
    raise ConfigError(f"{labelled(group, spec)} does not import")


def source_of(group: str, spec: Built) -> str | None:
    """What identifies the code a target outside the package runs: the file of the module that defines it and the
    SHA-256 of its bytes ('tanks.py sha256:1a2b3c4d5e6f7a8b'; that module only, not what it imports); None for the
    package's own targets (its version identifies them) and for a group that names none (an input-output system:
    records, not code)."""
    target = getattr(spec, TARGET, None)
    if target is None or str(target).startswith(PACKAGE_PREFIX):
        return None
    module = inspect.getmodule(located(group, spec))
    path = inspect.getsourcefile(module) if module is not None else None
    if path is None:
        return f"{target} (no source file)"
    return f"{Path(path).name} sha256:{hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]}"


def called(group: str, spec: Built, builder: Callable[..., Any], *args: Any, arg_names: Sequence[str] = (),
           **kwargs: Any) -> Any:
    """``builder(*args, **kwargs)``, refused in one line where its signature does not take them (named by
    ``arg_names`` and the keywords) or where it raises."""
    label = labelled(group, spec)
    try:
        inspect.signature(builder).bind(*args, **kwargs)
    except TypeError as error:
        given = ", ".join([*(arg_names or [f"<{type(arg).__name__}>" for arg in args]), *kwargs])
        raise ConfigError(f"{label} does not take ({given}): {error}") from None
    except ValueError:  # no signature to read (a builtin): calling it tells
        pass
    try:
        return builder(*args, **kwargs)
    except Exception as error:
        raise ConfigError(f"{label} raised {type(error).__name__}: {one_line(error)[:200]}") from None


def labelled(group: str, spec: Built) -> str:
    """'system/two_tank.yaml: system._target_='tanks.TwoTank'': what a one-line refusal of a build starts with."""
    return f"{where(group, spec)}: {group}.{TARGET}={spec._target_!r}"


def package_target(group: str, name: str) -> str | None:
    """The ``_target_`` of the package's config ``conf/<group>/<name>.yaml`` (None: the package has none, or that
    option builds nothing): what a config stored before targets existed was built by."""
    from nsl_hpc.config import config_dir

    path = config_dir() / group / f"{name}.yaml"
    return yaml.safe_load(path.read_text()).get(TARGET) if path.is_file() else None

