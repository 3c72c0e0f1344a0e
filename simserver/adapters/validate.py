"""Validation of configuration values, free of the compiled core.

The five helpers every loader uses (vehicle and tire files, scenes, scenarios, the keyframe
reader of :mod:`simserver.keyframes`, the server config). They import only the standard
library and PyYAML, so a client can validate a scenario's keyframes without loading numba
or :mod:`simserver.core`. Every error is a :class:`ConfigError` whose message names the
file and the key.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import yaml

__all__ = ["ConfigError", "check_keys", "choice", "number", "read_yaml"]


class ConfigError(ValueError):
    """A configuration file is missing, unreadable or invalid; the message names file and key."""


def read_yaml(path: Path) -> dict[str, Any]:
    """Read a YAML mapping, with errors naming the file."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start})") from exc
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of keys to values at the top level")
    return data


def number(path: Path | str, key: str, value: Any, lo: float, hi: float) -> float:
    """Validate one finite number within ``[lo, hi]``; errors name file and key."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"{path}: key '{key}': expected a number, got {value!r}")
    try:
        val = float(value)
    except OverflowError:
        raise ConfigError(f"{path}: key '{key}': the number is too large") from None
    if not math.isfinite(val):
        raise ConfigError(f"{path}: key '{key}': must be finite, got {value!r}")
    if not lo <= val <= hi:
        raise ConfigError(f"{path}: key '{key}': {val:g} is outside [{lo:g}, {hi:g}]")
    return val


def choice(path: Path | str, key: str, value: Any, names: dict[str, int]) -> int:
    """Validate a named choice; errors list the accepted names."""
    if not isinstance(value, str) or value not in names:
        raise ConfigError(
            f"{path}: key '{key}': expected one of {sorted(names)}, got {value!r}"
        )
    return names[value]


def check_keys(path: Path | str, data: dict[str, Any], allowed: tuple[str, ...] | set[str],
               required: tuple[str, ...] | set[str] = ()) -> None:
    """Reject unknown keys and report missing ones, naming the file."""
    for key in data:
        if key not in allowed:
            raise ConfigError(
                f"{path}: unknown key '{key}' (allowed: {', '.join(sorted(allowed))})"
            )
    for key in required:
        if key not in data:
            raise ConfigError(f"{path}: missing key '{key}'")
