"""Typed owners of config groups: a group is a frozen dataclass whose fields carry their type, their range and
their documentation (``setting``); ``typed`` turns a group's plain values into it, refusing a missing or unknown
key, a value of another type or out of its range in one line that names the key. The values themselves stay in
``conf/``: a field has a default only in a group users write themselves (``budget.stop_when``). ``--help`` reads
each field's documentation (``field_docs``).
"""

import dataclasses
import math
import types
import typing
from collections.abc import Mapping
from typing import Any, TypeVar

from nsl_hpc.config.mapping import plain
from nsl_hpc.core.errors import ConfigError

T = TypeVar("T")


def setting(doc: str, low: float | None = None, high: float | None = None, *, low_open: bool = False,
            high_open: bool = False, choices: tuple = (), nonempty: bool = False, also: str = "",
            default: Any = dataclasses.MISSING, default_factory: Any = dataclasses.MISSING) -> Any:
    """A field of a typed group: ``doc`` (one line for --help), the range [low, high] of a number (an open end
    excludes it; for a list or mapping, of each of its values), the ``choices`` of a string, ``nonempty`` for a
    list or mapping that needs a value, ``also`` 'VALUE: meaning' for one number allowed outside the range (e.g.
    '0: none'). A field with a ``default`` (or ``default_factory``, a list's or a mapping's) may be left out (a
    group the user writes, not one conf/ holds)."""
    return dataclasses.field(default=default, default_factory=default_factory, metadata={
        "doc": doc, "low": low, "high": high, "low_open": low_open, "high_open": high_open, "choices": choices,
        "nonempty": nonempty, "also": also})


def typed(schema: type[T], values: Any, key: str) -> T:
    """The group ``key`` (e.g. ``watchdog``; "": a command's own top-level keys) of plain or DictConfig ``values``
    as an instance of ``schema``, or a one-line ConfigError; then the schema's own ``check()`` (rules between its
    fields), if it has one."""
    names = field_names(schema)
    if not isinstance(values, Mapping):
        raise ConfigError(f"{key}={values!r} must be a group of keys: {', '.join(names)}")
    given = plain(values)
    for name in given:
        if name not in names:
            raise ConfigError(f"{dotted(key, name)} is unknown; {key or 'the command'} has: {', '.join(names)}")
    hints = typing.get_type_hints(schema)
    built = {}
    for item in dataclasses.fields(schema):  # type: ignore[arg-type]
        if item.name in given:
            built[item.name] = checked(dotted(key, item.name), given[item.name], hints[item.name], item.metadata)
        elif item.default is dataclasses.MISSING and item.default_factory is dataclasses.MISSING:
            raise ConfigError(f"{dotted(key, item.name)} is missing ({item.metadata['doc']})")
    instance = schema(**built)
    if hasattr(instance, "check"):
        instance.check()
    return instance


def dotted(key: str, name: str) -> str:
    return f"{key}.{name}" if key else name


def field_names(schema: type) -> list[str]:
    return [item.name for item in dataclasses.fields(schema)]


def field_docs(schema: type, prefix: str) -> dict[str, str]:
    """``prefix`` -> the group's documentation (its docstring's first line), ``prefix.field`` -> each field's,
    nested groups included."""
    docs = {prefix: " ".join((schema.__doc__ or "").split("\n\n")[0].split())} if prefix else {}
    hints = typing.get_type_hints(schema)
    for item in dataclasses.fields(schema):
        if "doc" not in item.metadata:  # a plain dataclass field (the launchers'): documented in conf/
            continue
        docs[dotted(prefix, item.name)] = item.metadata["doc"]
        if dataclasses.is_dataclass(hints[item.name]):
            docs.update(field_docs(hints[item.name], dotted(prefix, item.name)))
    return docs


def checked(key: str, value: Any, kind: Any, spec: Mapping[str, Any]) -> Any:
    """``value`` of type ``kind`` within ``spec``'s range or choices (the value to build the group with)."""
    if kind is Any:
        return value
    origin, arguments = typing.get_origin(kind), typing.get_args(kind)
    if origin in (types.UnionType, typing.Union):
        if value is None and type(None) in arguments:
            return None
        (kind,) = [argument for argument in arguments if argument is not type(None)]
        return checked(key, value, kind, spec)
    if dataclasses.is_dataclass(kind):  # a group whose owner types it its own way (the arch) says so: from_values
        builder = getattr(kind, "from_values", None)
        return builder(value, key) if builder else typed(typing.cast(type, kind), value, key)
    if origin is list:
        if not isinstance(value, list) or (spec["nonempty"] and not value):
            raise ConfigError(f"{key}={value!r} must be a list" + (" of at least one value" if spec["nonempty"]
                                                                   else "") + f", e.g. {key}=[1,2]")
        return [checked(f"{key} value", item, arguments[0], spec) for item in value]
    if origin is dict:
        if not isinstance(value, Mapping) or (spec["nonempty"] and not value):
            raise ConfigError(f"{key}={value!r} must map names to values, e.g. {{narx: 1, subnet: 2}}")
        return {name: checked(f"{key}.{name}", item, arguments[1], spec) for name, item in value.items()}
    return checked_scalar(key, value, kind, spec)


def checked_scalar(key: str, value: Any, kind: type, spec: Mapping[str, Any]) -> Any:
    """``value`` as a bool, a string (within ``spec``'s choices) or a number (within its range)."""
    if kind is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}={value!r} must be true or false")
        return value
    if kind is str:
        if not isinstance(value, str) or (spec["choices"] and value not in spec["choices"]):
            allowed = ", ".join(spec["choices"])
            raise ConfigError(f"{key}={value!r} " + (f"is unknown; choose one of: {allowed}" if allowed
                                                     else "must be a string"))
        return value
    return checked_number(key, value, kind is int, spec)


def checked_number(key: str, value: Any, integer: bool, spec: Mapping[str, Any]) -> Any:
    """An int (``integer``) or a finite number within ``spec``'s [low, high], or a one-line ConfigError."""
    if spec["also"] and value == float(spec["also"].split(":")[0]) and not isinstance(value, bool):
        return value
    low, high = spec["low"], spec["high"]
    low = -math.inf if low is None else low
    high = math.inf if high is None else high
    number = not isinstance(value, bool) and isinstance(value, int if integer else int | float)
    if (not number or not math.isfinite(value) or value < low or value > high or (spec["low_open"] and value == low)
            or (spec["high_open"] and value == high)):
        also = f" (or {spec['also']})" if spec["also"] else ""
        raise ConfigError(f"{key}={value!r} must be {number_range(integer, low, high, spec)}{also}")
    return value


def number_range(integer: bool, low: float, high: float, spec: Mapping[str, Any]) -> str:
    """'a positive integer', 'an integer from 1 to 8', 'a finite number in (0, 100]'..."""
    if integer and high == math.inf and low in (0, 1):
        return "a positive integer" if low == 1 or spec["low_open"] else "a non-negative integer"
    if integer:
        return f"an integer from {low:g}" + (f" to {high:g}" if high != math.inf else " up")
    left = "(" if spec["low_open"] or low == -math.inf else "["
    right = ")" if spec["high_open"] or high == math.inf else "]"
    return f"a finite number in {left}{low:g}, {high:g}{right}"
