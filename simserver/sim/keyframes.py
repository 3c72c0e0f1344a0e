"""Driver-input keyframes of a scenario file: parsing and sampling, free of the compiled core.

A scenario's ``inputs`` list (format in :mod:`simserver.sim.scenario`) is read by two programs:
the headless runner, which samples it into the core's input table, and the player client
(``clients/player.py``), which samples it in real time and sends the samples as commands.
Both use the functions below, so both apply the same rule, channel by channel, over the
keyframes that name the channel: ``steer``, ``throttle`` and ``brake`` are linear between
them and hold their first value before the first and their last value after the last;
``parking_brake`` and ``gear`` switch at a keyframe's time, hold their default (0, gear
``D``) until their first keyframe and their last value after it. A channel no keyframe
names keeps its default throughout.

This module imports numpy, the validation helpers of :mod:`simserver.adapters.validate` and
the gear codes of the wire protocol (:class:`simserver.wire.protocol.Gear`), never numba or
:mod:`simserver.core`: a client reading keyframes depends on the file format and the
protocol only (a test checks ``sys.modules``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from simserver.adapters.validate import ConfigError, check_keys, number, read_yaml, short_repr
from simserver.wire.protocol import Gear

MAX_DURATION_S = 3600.0
"""Longest scenario (``duration_s``): the headless runner keeps every step's sampled inputs
and every recorded row in memory (:data:`simserver.sim.scenario.MAX_SCENARIO_STEPS`)."""
CONTINUOUS_CHANNELS = {"steer": (-1.0, 1.0), "throttle": (0.0, 1.0), "brake": (0.0, 1.0)}
"""Channels interpolated linearly between keyframes, with their ranges."""
DISCRETE_CHANNELS = ("parking_brake", "gear")
"""Channels that switch at a keyframe's time."""
GEAR_CODES = {g.name: int(g) for g in Gear}
"""Gear name to code (``P`` 0, ``R`` 1, ``N`` 2, ``D`` 3; the wire protocol's codes, which a
test checks against ``core.layout.GEAR_*``)."""
INPUT_CHANNELS = ("steer", "throttle", "brake", "parking_brake", "gear")
"""The columns of :func:`input_table`, in the order of ``core.layout.INPUT_NAMES`` (checked
where the core meets this module, in :mod:`simserver.sim.scenario`)."""
CHANNEL_DEFAULTS: dict[str, float] = {"steer": 0.0, "throttle": 0.0, "brake": 0.0,
                                      "parking_brake": 0.0, "gear": float(Gear.D)}
"""A channel's value where no keyframe has set it yet (switched channels) or at all."""


def parse_keyframes(path: Path | str, raw: Any) -> list[dict[str, Any]]:
    """Validate a scenario's ``inputs`` list.

    Parameters
    ----------
    path : Path or str
        The file, for the error messages.
    raw : Any
        The value of its ``inputs`` key.

    Returns
    -------
    list of dict
        One dict per keyframe: ``t`` (s) and the channels it names, every value a float
        (``gear`` as its code).

    Raises
    ------
    ConfigError
        Naming the file and the key (``inputs[k].channel``).
    """
    if not isinstance(raw, list) or not raw:
        raise ConfigError(f"{path}: key 'inputs': expected a non-empty list of keyframes")
    frames: list[dict[str, Any]] = []
    last_t = -math.inf
    allowed = ("t", *CONTINUOUS_CHANNELS, *DISCRETE_CHANNELS)
    for k, frame in enumerate(raw):
        where = f"inputs[{k}]"
        if not isinstance(frame, dict):
            raise ConfigError(f"{path}: key '{where}': expected a mapping")
        check_keys(f"{path} ({where})", frame, allowed, required=("t",))
        parsed: dict[str, Any] = {"t": number(path, f"{where}.t", frame["t"], 0.0, 1e7)}
        if parsed["t"] < last_t:
            raise ConfigError(f"{path}: key '{where}.t': keyframes must be in time order")
        last_t = parsed["t"]
        for ch, (lo, hi) in CONTINUOUS_CHANNELS.items():
            if ch in frame:
                parsed[ch] = number(path, f"{where}.{ch}", frame[ch], lo, hi)
        if "parking_brake" in frame:
            val = frame["parking_brake"]
            if isinstance(val, bool):
                val = int(val)
            parsed["parking_brake"] = number(path, f"{where}.parking_brake", val, 0.0, 1.0)
        if "gear" in frame:
            gear = frame["gear"]
            if not isinstance(gear, str) or gear not in GEAR_CODES:
                raise ConfigError(f"{path}: key '{where}.gear': expected one of P, R, N, D, "
                                  f"got {short_repr(gear)}")
            parsed["gear"] = float(GEAR_CODES[gear])
        frames.append(parsed)
    return frames


def sample_keyframes(keyframes: Sequence[Mapping[str, Any]], times_s: np.ndarray
                     ) -> dict[str, np.ndarray]:
    """Sample parsed keyframes at ``times_s``, channel by channel.

    Parameters
    ----------
    keyframes : sequence of mapping
        As returned by :func:`parse_keyframes`.
    times_s : ndarray
        Sample times (s), ascending.

    Returns
    -------
    dict of str to ndarray
        One float64 array per name of :data:`INPUT_CHANNELS`.
    """
    times_s = np.asarray(times_s, dtype=np.float64)
    out: dict[str, np.ndarray] = {}
    for channel in INPUT_CHANNELS:
        column = np.full(times_s.size, CHANNEL_DEFAULTS[channel])
        pts = [(float(f["t"]), float(f[channel])) for f in keyframes if channel in f]
        if pts:
            t_k = np.array([p[0] for p in pts])
            v_k = np.array([p[1] for p in pts])
            if channel in CONTINUOUS_CHANNELS:
                column = np.interp(times_s, t_k, v_k)
            else:
                idx = np.searchsorted(t_k, times_s, side="right") - 1
                held = idx >= 0
                column[held] = v_k[idx[held]]
        out[channel] = column
    return out


def input_table(keyframes: Sequence[Mapping[str, Any]], times_s: np.ndarray) -> np.ndarray:
    """Sample the keyframes at ``times_s`` into an ``(n, 5)`` array, columns
    :data:`INPUT_CHANNELS` (the core's input layout)."""
    channels = sample_keyframes(keyframes, times_s)
    return np.column_stack([channels[name] for name in INPUT_CHANNELS])


@dataclass(frozen=True)
class KeyframeFile:
    """What a player needs from a scenario file: its name, duration and keyframes."""

    name: str
    duration_s: float
    keyframes: list[dict[str, Any]]


def read_keyframe_file(path: Path | str, data: Mapping[str, Any]) -> KeyframeFile:
    """Validate the ``name``, ``duration_s`` and ``inputs`` of a scenario file's contents
    ``data`` (the player and the headless runner both read them this way).

    Raises
    ------
    ConfigError
        Naming the file and the key.
    """
    for key in ("name", "duration_s", "inputs"):
        if key not in data:
            raise ConfigError(f"{path}: missing key '{key}'")
    name = data["name"]
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{path}: key 'name': expected a non-empty string")
    duration = number(path, "duration_s", data["duration_s"], 0.001, MAX_DURATION_S)
    return KeyframeFile(name=name, duration_s=duration,
                        keyframes=parse_keyframes(path, data["inputs"]))


def load_keyframe_file(path: str | Path) -> KeyframeFile:
    """Read a scenario file's ``name``, ``duration_s`` and ``inputs``.

    The other keys (vehicle, road, initial state, model) are the server's to validate when
    it loads the file as its scene; they are not read here.

    Raises
    ------
    ConfigError
        Naming the file and the key.
    """
    path = Path(path)
    return read_keyframe_file(path, read_yaml(path))
