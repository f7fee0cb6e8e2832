"""The exceptions a command turns into one line on stderr (a user's mistake, or the machine's), and the checks
of single values that raise them."""

import math
from collections.abc import Collection
from typing import Any


class ConfigError(ValueError):
    """A user-fixable mistake; its message is one line that names the bad value and what is allowed."""


class RunError(RuntimeError):
    """The machine or the cluster failed a command (a full disk, a SLURM command that failed); its message is
    one line that says what happened to the work and what to do."""


class SlurmError(RunError):
    """A SLURM command failed (after its retries): the cluster's trouble, not a mistake in the config."""


def one_line(message: object) -> str:
    """``message`` (an error, or its text) on one line: its whitespace runs, newlines too, as single spaces."""
    return " ".join(str(message).split())


def damaged_file(path: object, error: Exception) -> ConfigError:
    """The one-line error for a sweep file that cannot be read."""
    return ConfigError(f"{path} cannot be read ({type(error).__name__}: {one_line(error)[:120]}); the "
                       "sweep directory is damaged: restore that file, or launch the sweep into a new sweep_dir")


def require_member(key: str, value: Any, allowed: list) -> None:
    if value not in allowed:
        raise ConfigError(f"{key}={value!r} is outside the grid; allowed: {', '.join(map(str, allowed))}")


def require_positive_int(key: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ConfigError(f"{key}={value!r} must be a positive integer")


def require_non_negative_int(key: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ConfigError(f"{key}={value!r} must be a non-negative integer")


def require_number(key: str, value: Any, low: float, high: float = math.inf, low_open: bool = False,
                   high_open: bool = False) -> None:
    """A finite number in [low, high] (an open end excludes it), or a ConfigError naming ``key`` and the range."""
    number = not isinstance(value, bool) and isinstance(value, int | float) and math.isfinite(value)
    if not number or value < low or value > high or (low_open and value == low) or (high_open and value == high):
        left, right = "(" if low_open else "[", ")" if high_open or high == math.inf else "]"
        raise ConfigError(f"{key}={value!r} must be a finite number in {left}{low:g}, {high:g}{right}")


def require_int(key: str, value: Any, low: int, high: int | None = None) -> None:
    """An integer in [low, high] (no upper end when None), or a ConfigError naming ``key`` and the range."""
    if isinstance(value, bool) or not isinstance(value, int) or value < low or (high is not None and value > high):
        raise ConfigError(f"{key}={value!r} must be an integer from {low}" + (f" to {high}" if high is not None
                                                                            else " up"))


def require_choice(key: str, value: Any, allowed: Collection[Any]) -> None:
    if value not in allowed:
        raise ConfigError(f"{key}={value!r}; choose one of: {', '.join(map(str, allowed))}")
