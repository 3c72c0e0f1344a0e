"""Keyboard driving in a plain terminal: raw input, key decoding, and the driving model.

A terminal (local, over SSH, in tmux) reports key *presses* and then the keyboard's
auto-repeat, never key *releases*. A key therefore counts as held while presses keep
arriving: until ``first_repeat_s`` after the first press (the keyboard's initial repeat
delay, typically 250-660 ms), then until ``window_s`` after the latest repeat (repeats
come every 30-50 ms). A terminal repeats only the newest key, so actions held when
another key goes down stay held while that key repeats (throttle, then steer). The
pedals ramp toward their maximum while their key is held and back to zero when it is
released; the steering moves toward full lock at a limited rate while an arrow is held
and re-centres by itself when none is, with the lock reduced at speed
(``speed_ref_mps``) so that a digital key stays drivable on a motorway.

The model (:class:`KeyboardModel`) is pure: it is fed decoded keys with their arrival
time and advanced with :meth:`KeyboardModel.update`, so it is tested without a terminal.
:class:`RawTerminal` puts a tty in cbreak mode (no echo, no line buffering, Ctrl-C still
raises SIGINT) and restores it on exit.
"""

from __future__ import annotations

import math
import os
import select
import sys
import termios
import tty
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from clients.profile import ProfileError, check_mapping, number, read_profile

# ---------------------------------------------------------------------------- keys

KEY_UP, KEY_DOWN, KEY_LEFT, KEY_RIGHT = "up", "down", "left", "right"
KEY_BACKSPACE = "backspace"

_ESCAPES = {
    b"\x1b[A": KEY_UP, b"\x1b[B": KEY_DOWN, b"\x1b[C": KEY_RIGHT, b"\x1b[D": KEY_LEFT,
    b"\x1bOA": KEY_UP, b"\x1bOB": KEY_DOWN, b"\x1bOC": KEY_RIGHT, b"\x1bOD": KEY_LEFT,
}

ACTION_THROTTLE = "throttle"
ACTION_BRAKE = "brake"
ACTION_LEFT = "steer_left"
ACTION_RIGHT = "steer_right"
HELD_ACTIONS = (ACTION_THROTTLE, ACTION_BRAKE, ACTION_LEFT, ACTION_RIGHT)
"""Actions that last while their key is held."""

KEY_BINDINGS: Mapping[str, str] = {
    KEY_UP: ACTION_THROTTLE, "w": ACTION_THROTTLE, "W": ACTION_THROTTLE,
    KEY_DOWN: ACTION_BRAKE, "s": ACTION_BRAKE, "S": ACTION_BRAKE,
    KEY_LEFT: ACTION_LEFT, "a": ACTION_LEFT, "A": ACTION_LEFT,
    KEY_RIGHT: ACTION_RIGHT, "d": ACTION_RIGHT,
    "1": "gear_P", "p": "gear_P", "P": "gear_P",
    "2": "gear_R", "r": "gear_R", "R": "gear_R",
    "3": "gear_N", "n": "gear_N", "N": "gear_N",
    "4": "gear_D", "D": "gear_D",
    "h": "parking_brake", "H": "parking_brake",
    "b": "auto_hold", "B": "auto_hold",
    " ": "pause",
    "x": "reset", "X": "reset", KEY_BACKSPACE: "reset",
    "q": "quit", "Q": "quit",
}
"""Key -> action. Lower-case ``d`` steers right; Shift+D (``D``) selects drive."""

KEY_HELP_LINES = (
    "keys    hold arrows or w/a/s/d: throttle, steer, brake",
    "        gear 1 P  2 R  3 N  4 D (or p r n Shift+D)   h parking brake   b auto hold",
    "        space pause/resume   x reset   q quit",
)
KEY_HELP = "; ".join(line[8:] for line in KEY_HELP_LINES)
"""The key help in one line (``--help``)."""


def decode_keys(buffer: bytes) -> tuple[list[str], bytes]:
    """Split terminal input into key names.

    Parameters
    ----------
    buffer : bytes
        Bytes read from the terminal (possibly ending inside an escape sequence).

    Returns
    -------
    keys : list of str
        ``"up"``, ``"down"``, ``"left"``, ``"right"``, ``"backspace"``, or the character.
        Unknown escape sequences are dropped.
    rest : bytes
        An incomplete escape sequence at the end, to prepend to the next read.
    """
    keys: list[str] = []
    i = 0
    n = len(buffer)
    while i < n:
        b = buffer[i]
        if b == 0x1B:
            if i + 1 >= n:
                return keys, buffer[i:]
            if buffer[i + 1] in (0x5B, 0x4F):  # "[" or "O": CSI or SS3
                j = i + 2
                while j < n and not 0x40 <= buffer[j] <= 0x7E:
                    j += 1
                if j >= n:
                    return keys, buffer[i:]
                seq = bytes(buffer[i:j + 1])
                if seq in _ESCAPES:
                    keys.append(_ESCAPES[seq])
                i = j + 1
            else:  # a lone ESC (or Alt+key): skip the ESC
                i += 1
        elif b in (0x7F, 0x08):
            keys.append(KEY_BACKSPACE)
            i += 1
        else:
            # UTF-8 multibyte characters are not bindings: skip their bytes
            if b < 0x80:
                keys.append(chr(b))
            i += 1
    return keys, b""


# ---------------------------------------------------------------------------- profile


@dataclass(frozen=True)
class PedalRamp:
    """Ramp rates of one pedal key (per second of full travel) and its maximum."""

    rate_per_s: float
    release_rate_per_s: float
    max: float = 1.0


@dataclass(frozen=True)
class SteerRamp:
    """Steering rates: toward lock while held, back to centre when released.

    ``speed_ref_mps``: the lock is ``max / (1 + |u| / speed_ref_mps)`` (0 = no reduction).
    """

    rate_per_s: float = 1.5
    centre_rate_per_s: float = 3.0
    max: float = 1.0
    speed_ref_mps: float = 12.0


@dataclass(frozen=True)
class HoldTiming:
    """When a key stops counting as held: ``first_repeat_s`` after a first press, then
    ``window_s`` after each repeat."""

    window_s: float = 0.12
    first_repeat_s: float = 0.6


@dataclass(frozen=True)
class KeyboardProfile:
    """Everything tunable about keyboard driving (``configs/clients/keyboard.yaml``)."""

    steer: SteerRamp = field(default_factory=SteerRamp)
    throttle: PedalRamp = field(default_factory=lambda: PedalRamp(0.8, 2.5, 1.0))
    brake: PedalRamp = field(default_factory=lambda: PedalRamp(1.2, 3.0, 1.0))
    hold: HoldTiming = field(default_factory=HoldTiming)


_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "steer": {"rate_per_s": (0.01, 100.0), "centre_rate_per_s": (0.01, 100.0),
              "max": (0.0, 1.0), "speed_ref_mps": (0.0, 1000.0)},
    "throttle": {"rate_per_s": (0.01, 100.0), "release_rate_per_s": (0.01, 100.0),
                 "max": (0.0, 1.0)},
    "brake": {"rate_per_s": (0.01, 100.0), "release_rate_per_s": (0.01, 100.0),
              "max": (0.0, 1.0)},
    "hold": {"window_s": (0.01, 2.0), "first_repeat_s": (0.01, 5.0)},
}


def load_keyboard_profile(path: str | Path | None) -> KeyboardProfile:
    """Load and validate a keyboard profile; None gives the defaults.

    Parameters
    ----------
    path : str or Path or None
        A YAML file with ``kind: keyboard`` and any of the sections ``steer``,
        ``throttle``, ``brake``, ``hold`` (omitted keys keep their defaults).

    Returns
    -------
    KeyboardProfile

    Raises
    ------
    ProfileError
        Naming the file and the key (unknown key, wrong type, out of range).
    """
    default = KeyboardProfile()
    if path is None:
        return default
    path = Path(path)
    data = read_profile(path, "keyboard")
    check_mapping(path, "", data, ("kind", *_RANGES))
    sections: dict[str, Any] = {}
    for name, ranges in _RANGES.items():
        raw = data.get(name) or {}
        check_mapping(path, name, raw, tuple(ranges))
        base = getattr(default, name)
        values = {f.name: getattr(base, f.name) for f in fields(base)}
        for key, (lo, hi) in ranges.items():
            if key in raw:
                values[key] = number(path, f"{name}.{key}", raw[key], lo, hi)
        sections[name] = type(base)(**values)
    hold = sections["hold"]
    if hold.first_repeat_s < hold.window_s:
        raise ProfileError(path, "hold.first_repeat_s",
                           f"must be at least hold.window_s ({hold.window_s:g})")
    return KeyboardProfile(**sections)


# ---------------------------------------------------------------------------- model


PEDALS = frozenset((ACTION_THROTTLE, ACTION_BRAKE))


@dataclass
class _Held:
    first_s: float
    last_s: float
    repeats: int = 0
    latched_to: str | None = None  # held while this other action's key repeats


def _approach(value: float, target: float, rate: float, dt: float) -> float:
    step = rate * dt
    if value < target:
        return min(target, value + step)
    return max(target, value - step)


class KeyboardModel:
    """Pedals and steering from key presses (pure: no terminal, no clock of its own).

    Parameters
    ----------
    profile : KeyboardProfile, optional
        Rates and timings.

    Attributes
    ----------
    steer, throttle, brake : float
        The current normalised inputs (steer + = left, as the protocol).
    """

    def __init__(self, profile: KeyboardProfile | None = None) -> None:
        self.profile = profile or KeyboardProfile()
        self.steer = 0.0
        self.throttle = 0.0
        self.brake = 0.0
        self._held: dict[str, _Held] = {}

    def press(self, action: str, now_s: float) -> None:
        """A press (or an auto-repeat) of a held action's key at ``now_s``.

        A terminal repeats only the last key pressed: when a new key goes down, the
        actions held at that moment are latched to it and stay held while it repeats
        (throttle held, then steering), and count as released when it is let go (the
        terminal does not resume repeating the earlier key: press it again). The two
        pedals are the exception: a pedal key going down lets go of the other pedal, as
        a foot moves from one pedal to the other (latched, the throttle stayed on under
        the brake key, and a stop was made against full throttle).
        """
        h = self._held.get(action)
        if h is None or not self.held(action, now_s):
            for other, oh in self._held.items():
                if other != action and self.held(other, now_s):
                    if action in PEDALS and other in PEDALS:
                        oh.last_s = -math.inf  # released now: its ramp lets go
                        oh.latched_to = None
                    else:
                        oh.latched_to = action
            self._held[action] = _Held(first_s=now_s, last_s=now_s)
        else:
            h.last_s = now_s
            h.repeats += 1
            h.latched_to = None

    def _own_window(self, h: _Held, now_s: float) -> bool:
        hold = self.profile.hold
        window = hold.window_s if h.repeats else hold.first_repeat_s
        return now_s - h.last_s <= window

    def held(self, action: str, now_s: float) -> bool:
        """True while ``action``'s key counts as held at ``now_s``."""
        h = self._held.get(action)
        if h is None:
            return False
        if self._own_window(h, now_s):
            return True
        latch = self._held.get(h.latched_to) if h.latched_to else None
        return latch is not None and self._own_window(latch, now_s)

    def release_all(self) -> None:
        """Forget held keys and return every input to zero (after a reset)."""
        self._held.clear()
        self.steer = self.throttle = self.brake = 0.0

    def update(self, now_s: float, dt_s: float, speed_mps: float = 0.0) -> None:
        """Advance the ramps by ``dt_s`` to ``now_s``.

        Parameters
        ----------
        now_s : float
            Current time (the clock of :meth:`press`).
        dt_s : float
            Time since the previous update (clipped to [0, 0.1] s so a stall does not
            jump a pedal).
        speed_mps : float, optional
            Vehicle speed, for the speed-dependent steering lock.
        """
        dt = min(max(dt_s, 0.0), 0.1)
        p = self.profile
        for name, ramp in ((ACTION_THROTTLE, p.throttle), (ACTION_BRAKE, p.brake)):
            value = getattr(self, name)
            if self.held(name, now_s):
                value = _approach(value, ramp.max, ramp.rate_per_s, dt)
            else:
                value = _approach(value, 0.0, ramp.release_rate_per_s, dt)
            setattr(self, name, value)
        s = p.steer
        lock = s.max
        if s.speed_ref_mps > 0.0 and math.isfinite(speed_mps):
            lock = s.max / (1.0 + abs(speed_mps) / s.speed_ref_mps)
        left, right = self.held(ACTION_LEFT, now_s), self.held(ACTION_RIGHT, now_s)
        target = lock * (float(left) - float(right))
        if target != 0.0 and target * self.steer >= 0.0 and abs(target) >= abs(self.steer):
            rate = s.rate_per_s  # turning in
        else:
            rate = max(s.centre_rate_per_s, s.rate_per_s)  # centring or reversing
        self.steer = _approach(self.steer, target, rate, dt)


# ---------------------------------------------------------------------------- terminal


class RawTerminal:
    """A tty in cbreak mode (keys unbuffered and not echoed; Ctrl-C still signals).

    Parameters
    ----------
    fd : int, optional
        The terminal's file descriptor (default: stdin).

    Raises
    ------
    OSError
        When ``fd`` is not a terminal.
    """

    def __init__(self, fd: int | None = None) -> None:
        self.fd = sys.stdin.fileno() if fd is None else fd
        if not os.isatty(self.fd):
            raise OSError(f"file descriptor {self.fd} is not a terminal")
        self._saved: list[Any] | None = None
        self._rest = b""

    def __enter__(self) -> RawTerminal:
        self._saved = termios.tcgetattr(self.fd)
        tty.setcbreak(self.fd, termios.TCSANOW)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._saved is not None:
            termios.tcsetattr(self.fd, termios.TCSADRAIN, self._saved)
            self._saved = None

    def read_keys(self) -> Iterator[str]:
        """Keys typed since the last call (never blocks)."""
        data = self._rest
        while select.select([self.fd], [], [], 0.0)[0]:
            chunk = os.read(self.fd, 1024)
            if not chunk:
                break
            data += chunk
        keys, self._rest = decode_keys(data)
        yield from keys
