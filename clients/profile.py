"""Reading input profiles (``configs/clients/*.yaml``) with errors that name file and key.

Small validators in the style of the server's configuration loader (the clients read the
file with its core-free reader, ``simserver.adapters.validate``, but do not import the
loader itself: it pulls in the physics core): unknown keys are errors, numbers must be
finite and in range, and every message reads ``FILE: key 'a.b': what is wrong``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from simserver.adapters.validate import ConfigError, parse_yaml, read_config_bytes, short_repr

MAX_PROFILE_BYTES = 256 << 10
"""Largest profile read (256 KiB; the shipped ones are below 4 KiB). A profile is read
like a server configuration file (``simserver.adapters.validate``): a regular file only,
opened without blocking (a FIFO or ``/dev/zero`` is refused, not read), YAML nested at
most 64 deep, integers of at most 1 000 characters, UTF-8."""


class ProfileError(ValueError):
    """A profile that cannot be used; the message names the file and the key.

    Parameters
    ----------
    path : Path or str
        The profile file.
    key : str
        Dotted key (``"brake.dead_zone"``), or ``""`` for the whole file.
    message : str
        What is wrong.
    """

    def __init__(self, path: Path | str, key: str, message: str) -> None:
        self.path = Path(path)
        self.key = key
        where = f"{path}: key '{key}'" if key else f"{path}"
        super().__init__(f"{where}: {message}")


def read_profile(path: Path, kind: str) -> dict[str, Any]:
    """Read a profile YAML mapping and check its ``kind``.

    Parameters
    ----------
    path : Path
        The file.
    kind : str
        The expected ``kind`` value (``"keyboard"`` or ``"joystick"``).

    Returns
    -------
    dict
        The top-level mapping.

    Raises
    ------
    ProfileError
        File missing or unreadable, not YAML, not a mapping, or of another kind.
    """
    try:
        raw = read_config_bytes(path, MAX_PROFILE_BYTES)
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start})") from None
        data = parse_yaml(path, text)
    except ConfigError as exc:  # "PATH: what": the same reading rules as the server's
        message = str(exc)
        prefix = f"{path}: "
        raise ProfileError(path, "", message[len(prefix):] if message.startswith(prefix)
                           else message) from None
    if not isinstance(data, dict):
        raise ProfileError(path, "", "expected a mapping of keys at the top level")
    if data.get("kind") != kind:
        raise ProfileError(path, "kind",
                           f"expected {kind!r}, got {short_repr(data.get('kind'))}")
    return data


def check_mapping(path: Path, where: str, value: Any, allowed: Sequence[str],
                  required: Sequence[str] = ()) -> dict[str, Any]:
    """Check that ``value`` is a mapping with only ``allowed`` and all ``required`` keys.

    Raises
    ------
    ProfileError
        Naming the first unknown or missing key.
    """
    if not isinstance(value, dict):
        raise ProfileError(path, where, f"expected a mapping, got {type(value).__name__}")
    for key in value:
        if key not in allowed:
            full = f"{where}.{key}" if where else str(key)
            raise ProfileError(path, short_repr(full) if len(full) > 60 else full,
                               f"unknown key (allowed: {', '.join(allowed)})")
    for key in required:
        if key not in value:
            full = f"{where}.{key}" if where else key
            raise ProfileError(path, full, "is required")
    return value


def number(path: Path, key: str, value: Any, lo: float, hi: float) -> float:
    """A finite number in ``[lo, hi]``.

    Raises
    ------
    ProfileError
        For a non-number, a boolean, a non-finite value or one out of range.
    """
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ProfileError(path, key, f"expected a number in [{lo:g}, {hi:g}], got "
                                      f"{short_repr(value)}")
    try:
        number = float(value)
    except OverflowError:  # an integer of hundreds of digits
        number = math.inf
    if not math.isfinite(number) or not lo <= number <= hi:
        raise ProfileError(path, key, f"expected a number in [{lo:g}, {hi:g}], got "
                                      f"{short_repr(value)}")
    return number


def integer(path: Path, key: str, value: Any, lo: int, hi: int) -> int:
    """An integer in ``[lo, hi]``.

    Raises
    ------
    ProfileError
        For a non-integer (including booleans and 1.0) or one out of range.
    """
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise ProfileError(path, key, f"expected an integer in [{lo}, {hi}], got "
                                      f"{short_repr(value)}")
    return value


def boolean(path: Path, key: str, value: Any) -> bool:
    """A YAML boolean (``true``/``false``).

    Raises
    ------
    ProfileError
        For anything else.
    """
    if not isinstance(value, bool):
        raise ProfileError(path, key, f"expected true or false, got {short_repr(value)}")
    return value
