"""Game controllers and steering wheels: profiles, the axis mapping, and SDL devices.

A joystick profile (``configs/clients/gamepad.yaml``, ``configs/clients/wheel.yaml``) says
which SDL axis is the steering, the throttle and the brake, with dead zones, inversion,
response curves and the pedals' raw range, and which buttons select a gear, toggle the
parking brake, reset, pause or quit. :func:`load_joystick_profile` validates it with
errors naming the file and the key.

The mapping is pure: :func:`map_axes` and :class:`ButtonEdges` read any object with the
small :class:`InputDevice` interface. Three implement it:

- :class:`PygameJoystick`, a real device through pygame (SDL2);
- the same class on an SDL *virtual* joystick (:class:`VirtualJoystick`, attached through
  ``SDL_JoystickAttachVirtual`` in the very SDL library pygame loaded), fed by a timed
  :class:`JoystickScript`: the whole SDL event path without hardware, for demos and the
  end-to-end test;
- any scripted object with the same five members (the unit tests use one).

pygame is optional (the ``joystick`` extra): only :func:`import_pygame` imports it.

SDL axis conventions: values in [-1, 1]; a stick or wheel reads negative to the left and
positive to the right, so the steer command (positive = left, ISO 8855) is the negated
shaped axis unless ``invert`` is set. Pedals and triggers differ between devices (rest at
-1 or +1 or 0), which is why a pedal names its raw value when ``released`` and when
``pressed``.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any, Protocol

from clients.ffb import FfbProfile, parse_ffb_profile
from clients.profile import (
    ProfileError,
    boolean,
    check_mapping,
    integer,
    number,
    read_profile,
    short_repr,
)

PYGAME_VERSION = "2.6.1"
"""The pygame release these clients are tested with (the ``joystick`` extra pins it)."""

BUTTON_ACTIONS: Mapping[str, str] = {
    "gear_p": "gear_P",
    "gear_r": "gear_R",
    "gear_n": "gear_N",
    "gear_d": "gear_D",
    "gear_next": "gear_next",
    "gear_prev": "gear_prev",
    "parking_brake": "parking_brake",
    "auto_hold": "auto_hold",
    "reset": "reset",
    "pause": "pause",
    "quit": "quit",
}
"""Profile key under ``buttons`` -> driver action (``gear_next`` moves P->R->N->D)."""

MAX_AXES = 64
MAX_BUTTONS = 128


class JoystickError(RuntimeError):
    """A joystick that cannot be opened or used (no pygame, no device, device lost)."""


# ---------------------------------------------------------------------------- profile


@dataclass(frozen=True)
class SteerAxis:
    """The steering axis.

    Attributes
    ----------
    axis : int
        SDL axis index.
    invert : bool
        Set for a device whose axis is positive to the *left*.
    dead_zone : float
        Fraction of half travel around the centre that reads 0 (sticks drift).
    gamma : float
        Response exponent: the output is ``sign(x) |x|^gamma`` after the dead zone
        (above 1 gives finer control near the centre).
    scale : float
        Steer command at full axis travel (1 = full lock).
    """

    axis: int
    invert: bool = False
    dead_zone: float = 0.0
    gamma: float = 1.0
    scale: float = 1.0


@dataclass(frozen=True)
class PedalAxis:
    """A pedal or trigger axis.

    Attributes
    ----------
    axis : int
        SDL axis index.
    released, pressed : float
        Raw axis values with the pedal up and floored (either order; they differ).
    dead_zone : float
        Fraction of travel from ``released`` that reads 0.
    full_at : float
        Fraction of travel that already reads 1 (a pedal that never quite reaches its
        stop still gives full braking).
    gamma : float
        Response exponent on the travel fraction.
    invert : bool
        Negate the raw value first (an alternative to swapping released/pressed).
    """

    axis: int
    released: float = -1.0
    pressed: float = 1.0
    dead_zone: float = 0.02
    full_at: float = 1.0
    gamma: float = 1.0
    invert: bool = False


@dataclass(frozen=True)
class JoystickProfile:
    """A validated joystick profile (see ``configs/clients/gamepad.yaml``).

    Attributes
    ----------
    path : Path or None
        The file it came from (for messages).
    name : str
        Free text.
    name_contains : str
        Choose among the devices whose name contains this (case-insensitive).
    index : int
        Which of the matching devices (0 = the first).
    steer : SteerAxis
    throttle, brake : PedalAxis
    buttons : Mapping[str, int]
        Driver action (values of :data:`BUTTON_ACTIONS`) -> SDL button index.
    force_feedback : FfbProfile
        The wheel's force feedback (``clients.ffb``; disabled when the key is absent).
    """

    path: Path | None
    name: str
    name_contains: str
    index: int
    steer: SteerAxis
    throttle: PedalAxis
    brake: PedalAxis
    buttons: Mapping[str, int]
    force_feedback: FfbProfile = FfbProfile(enabled=False)

    def where(self, key: str) -> str:
        """``"FILE: key 'KEY'"`` for messages about this profile."""
        return f"{self.path or '<profile>'}: key '{key}'"

    @property
    def axes_needed(self) -> int:
        """Number of axes a device must have for this profile."""
        return 1 + max(self.steer.axis, self.throttle.axis, self.brake.axis)

    @property
    def buttons_needed(self) -> int:
        """Number of buttons a device must have for this profile."""
        return 1 + max(self.buttons.values(), default=-1)


_STEER_KEYS = ("axis", "invert", "dead_zone", "gamma", "scale")
_PEDAL_KEYS = ("axis", "released", "pressed", "dead_zone", "full_at", "gamma", "invert")


def _steer(path: Path, raw: Any) -> SteerAxis:
    check_mapping(path, "steer", raw, _STEER_KEYS, required=("axis",))
    return SteerAxis(
        axis=integer(path, "steer.axis", raw["axis"], 0, MAX_AXES - 1),
        invert=boolean(path, "steer.invert", raw.get("invert", False)),
        dead_zone=number(path, "steer.dead_zone", raw.get("dead_zone", 0.0), 0.0, 0.5),
        gamma=number(path, "steer.gamma", raw.get("gamma", 1.0), 0.2, 5.0),
        scale=number(path, "steer.scale", raw.get("scale", 1.0), 0.05, 1.0),
    )


def _pedal(path: Path, name: str, raw: Any) -> PedalAxis:
    check_mapping(path, name, raw, _PEDAL_KEYS, required=("axis",))
    pedal = PedalAxis(
        axis=integer(path, f"{name}.axis", raw["axis"], 0, MAX_AXES - 1),
        released=number(path, f"{name}.released", raw.get("released", -1.0), -1.0, 1.0),
        pressed=number(path, f"{name}.pressed", raw.get("pressed", 1.0), -1.0, 1.0),
        dead_zone=number(path, f"{name}.dead_zone", raw.get("dead_zone", 0.02), 0.0, 0.5),
        full_at=number(path, f"{name}.full_at", raw.get("full_at", 1.0), 0.5, 1.0),
        gamma=number(path, f"{name}.gamma", raw.get("gamma", 1.0), 0.2, 5.0),
        invert=boolean(path, f"{name}.invert", raw.get("invert", False)),
    )
    if abs(pedal.pressed - pedal.released) < 0.1:
        raise ProfileError(path, f"{name}.pressed",
                           f"must differ from {name}.released ({pedal.released:g}) "
                           "by at least 0.1 of the raw range")
    if pedal.dead_zone >= pedal.full_at:
        raise ProfileError(path, f"{name}.dead_zone",
                           f"must be below {name}.full_at ({pedal.full_at:g})")
    return pedal


def load_joystick_profile(path: str | Path) -> JoystickProfile:
    """Load and validate a joystick profile.

    Parameters
    ----------
    path : str or Path
        YAML with ``kind: joystick``, ``steer``, ``throttle``, ``brake`` (required),
        ``device``, ``buttons``, ``force_feedback`` and ``name`` (optional).

    Returns
    -------
    JoystickProfile

    Raises
    ------
    ProfileError
        Naming the file and the key: unknown or missing keys, wrong types, values out
        of range, one axis used twice, one button bound to two actions.
    """
    path = Path(path)
    data = read_profile(path, "joystick")
    check_mapping(path, "", data, ("kind", "name", "device", "steer", "throttle", "brake",
                                   "buttons", "force_feedback"),
                  required=("steer", "throttle", "brake"))
    name = data.get("name", path.stem)
    if not isinstance(name, str):
        raise ProfileError(path, "name", f"expected a string, got {short_repr(name)}")
    device = data.get("device") or {}
    check_mapping(path, "device", device, ("name_contains", "index"))
    name_contains = device.get("name_contains", "") or ""
    if not isinstance(name_contains, str):
        raise ProfileError(path, "device.name_contains",
                           f"expected a string, got {short_repr(name_contains)}")
    index = integer(path, "device.index", device.get("index", 0), 0, 63)
    steer = _steer(path, data["steer"])
    throttle = _pedal(path, "throttle", data["throttle"])
    brake = _pedal(path, "brake", data["brake"])
    axes = {"steer": steer.axis, "throttle": throttle.axis, "brake": brake.axis}
    seen: dict[int, str] = {}
    for key, ax in axes.items():
        if ax in seen:
            raise ProfileError(path, f"{key}.axis",
                               f"axis {ax} is already used by {seen[ax]}.axis")
        seen[ax] = key
    raw_buttons = data.get("buttons") or {}
    check_mapping(path, "buttons", raw_buttons, tuple(BUTTON_ACTIONS))
    buttons: dict[str, int] = {}
    used: dict[int, str] = {}
    for key, value in raw_buttons.items():
        if value is None:
            continue
        b = integer(path, f"buttons.{key}", value, 0, MAX_BUTTONS - 1)
        if b in used:
            raise ProfileError(path, f"buttons.{key}",
                               f"button {b} is already bound to buttons.{used[b]}")
        used[b] = key
        buttons[BUTTON_ACTIONS[key]] = b
    return JoystickProfile(path=path, name=name, name_contains=name_contains, index=index,
                           steer=steer, throttle=throttle, brake=brake, buttons=buttons,
                           force_feedback=parse_ffb_profile(path, data.get("force_feedback")))


# ---------------------------------------------------------------------------- mapping


class InputDevice(Protocol):
    """What the mapping reads: a polled device with axes in [-1, 1] and buttons."""

    name: str

    def poll(self) -> None:
        """Take the device's newest values (pump events)."""

    def num_axes(self) -> int:
        """Number of axes."""

    def num_buttons(self) -> int:
        """Number of buttons."""

    def axis(self, index: int) -> float:
        """Raw value of an axis in [-1, 1]."""

    def button(self, index: int) -> bool:
        """True while a button is down."""


def _clip(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else hi if x > hi else x


def steer_value(spec: SteerAxis, raw: float) -> float:
    """Steer command in [-1, 1] (+ = left) from a raw axis value.

    Parameters
    ----------
    spec : SteerAxis
        Dead zone, gamma, scale, inversion.
    raw : float
        SDL axis value (negative = left for a normal device). Non-finite reads 0.

    Returns
    -------
    float
    """
    if not math.isfinite(raw):
        return 0.0
    x = _clip(raw, -1.0, 1.0)
    mag = abs(x)
    if mag <= spec.dead_zone:
        return 0.0
    mag = (mag - spec.dead_zone) / (1.0 - spec.dead_zone)
    mag = mag ** spec.gamma
    value = math.copysign(mag * spec.scale, x)
    return _clip(value if spec.invert else -value, -1.0, 1.0)


def pedal_value(spec: PedalAxis, raw: float) -> float:
    """Pedal command in [0, 1] from a raw axis value.

    The travel fraction ``(raw - released) / (pressed - released)`` is clipped to
    [0, 1], mapped so that ``dead_zone`` reads 0 and ``full_at`` reads 1, then shaped by
    ``gamma``. Non-finite reads 0.
    """
    if not math.isfinite(raw):
        return 0.0
    x = -raw if spec.invert else raw
    travel = _clip((x - spec.released) / (spec.pressed - spec.released), 0.0, 1.0)
    frac = _clip((travel - spec.dead_zone) / (spec.full_at - spec.dead_zone), 0.0, 1.0)
    return frac ** spec.gamma


def map_axes(profile: JoystickProfile, device: InputDevice) -> tuple[float, float, float]:
    """``(steer, throttle, brake)`` from a device's current axes (pure).

    Parameters
    ----------
    profile : JoystickProfile
    device : InputDevice
        Already polled.

    Returns
    -------
    tuple of float
        Steer in [-1, 1] (+ left), throttle and brake in [0, 1].
    """
    return (
        steer_value(profile.steer, device.axis(profile.steer.axis)),
        pedal_value(profile.throttle, device.axis(profile.throttle.axis)),
        pedal_value(profile.brake, device.axis(profile.brake.axis)),
    )


class ButtonEdges:
    """Actions whose button went down since the previous call (rising edges only).

    Parameters
    ----------
    profile : JoystickProfile
    """

    def __init__(self, profile: JoystickProfile) -> None:
        self.profile = profile
        self._down: dict[str, bool] = {}

    def actions(self, device: InputDevice) -> list[str]:
        """Actions to run now; a held button fires once."""
        out = []
        for action, b in self.profile.buttons.items():
            down = bool(device.button(b))
            if down and not self._down.get(action, False):
                out.append(action)
            self._down[action] = down
        return out


def check_device(profile: JoystickProfile, device: InputDevice) -> None:
    """Check that the device has every axis and button the profile uses.

    Raises
    ------
    JoystickError
        Naming the profile file, the key and the device.
    """
    n_axes, n_buttons = device.num_axes(), device.num_buttons()
    for key, spec in (("steer", profile.steer), ("throttle", profile.throttle),
                      ("brake", profile.brake)):
        if spec.axis >= n_axes:
            raise JoystickError(f"{profile.where(key + '.axis')}: axis {spec.axis} does not "
                                f"exist on {device.name!r} (it has {n_axes} axes, 0-"
                                f"{n_axes - 1}); see --probe")
    for action, b in profile.buttons.items():
        if b >= n_buttons:
            key = next(k for k, v in BUTTON_ACTIONS.items() if v == action)
            raise JoystickError(f"{profile.where('buttons.' + key)}: button {b} does not "
                                f"exist on {device.name!r} (it has {n_buttons} buttons)")


# ---------------------------------------------------------------------------- pygame


def import_pygame() -> ModuleType:
    """Import pygame with SDL set up for a headless joystick reader.

    The video driver defaults to ``dummy`` (no window: the clients run in terminals,
    over SSH too) and joystick events are delivered without window focus.

    Raises
    ------
    JoystickError
        When pygame is not installed (with the install command).
    """
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
    os.environ.setdefault("SDL_JOYSTICK_ALLOW_BACKGROUND_EVENTS", "1")
    try:
        import pygame
    except ImportError:
        raise JoystickError(
            "joystick mode needs pygame (SDL2): pip install 'pygame==" + PYGAME_VERSION
            + "' (the 'joystick' extra)") from None
    pygame.display.init()
    pygame.joystick.init()
    return pygame


def list_joysticks() -> list[str]:
    """Names of the joysticks SDL sees, by device index."""
    pygame = import_pygame()
    pygame.event.pump()
    return [pygame.joystick.Joystick(i).get_name()
            for i in range(pygame.joystick.get_count())]


class PygameJoystick:
    """An SDL joystick through pygame, with the :class:`InputDevice` interface.

    Parameters
    ----------
    device_index : int
        SDL device index.

    Attributes
    ----------
    lost : bool
        True once SDL reported the device removed.
    """

    def __init__(self, device_index: int) -> None:
        self._pg = import_pygame()
        self._pg.event.pump()
        self._js = self._pg.joystick.Joystick(device_index)
        self._js.init()
        self.name = self._js.get_name()
        self.instance_id = self._js.get_instance_id()
        self.lost = False

    @classmethod
    def open(cls, profile: JoystickProfile) -> PygameJoystick:
        """Open the device a profile selects (``device.name_contains``, ``device.index``).

        Raises
        ------
        JoystickError
            When no device matches (with the names SDL sees).
        """
        names = list_joysticks()
        want = profile.name_contains.lower()
        matches = [i for i, n in enumerate(names) if want in n.lower()]
        if not names:
            raise JoystickError("no joystick found: SDL sees none (is it plugged in, and "
                                "may this user read /dev/input/event*?)")
        if profile.index >= len(matches):
            raise JoystickError(
                f"{profile.where('device')}: no joystick matches name_contains="
                f"{profile.name_contains!r} index={profile.index}; SDL sees: "
                + ", ".join(f"{i}: {n!r}" for i, n in enumerate(names)))
        return cls(matches[profile.index])

    def poll(self) -> None:
        """Pump SDL events; notes the device's removal."""
        pg = self._pg
        for event in pg.event.get():  # also empties SDL's queue of axis/button events
            if event.type == pg.JOYDEVICEREMOVED and \
                    getattr(event, "instance_id", None) == self.instance_id:
                self.lost = True

    def num_axes(self) -> int:
        """Number of axes."""
        return self._js.get_numaxes()

    def num_buttons(self) -> int:
        """Number of buttons."""
        return self._js.get_numbuttons()

    def axis(self, index: int) -> float:
        """Raw axis value in [-1, 1]."""
        return float(self._js.get_axis(index))

    def button(self, index: int) -> bool:
        """True while the button is down."""
        return bool(self._js.get_button(index))


# ---------------------------------------------------------------------------- virtual


def _sdl_library(pygame: ModuleType) -> ctypes.CDLL:
    """The SDL2 shared library pygame uses (its wheel bundles one in ``pygame.libs``)."""
    base = Path(pygame.__file__).resolve().parent
    for folder in (base.parent / "pygame.libs", base):
        if folder.is_dir():
            for lib in sorted(folder.glob("libSDL2-2*.so*")):
                return ctypes.CDLL(str(lib))
    name = ctypes.util.find_library("SDL2-2.0") or ctypes.util.find_library("SDL2")
    if name is None:
        raise JoystickError("cannot find the SDL2 library pygame uses")
    return ctypes.CDLL(name)


SDL_JOYSTICK_TYPE = {"gamecontroller": 1, "wheel": 2}


class VirtualJoystick:
    """An SDL virtual joystick (``SDL_JoystickAttachVirtual``, SDL >= 2.0.14).

    Attached in the SDL library pygame loaded, so pygame lists and opens it like a
    plugged-in device. Values are set with :meth:`set_axis` and :meth:`set_button`.

    Parameters
    ----------
    n_axes, n_buttons : int
        Size of the device.
    kind : {"wheel", "gamecontroller"}
        The SDL joystick type.

    Raises
    ------
    JoystickError
        When pygame is missing or its SDL does not offer virtual joysticks.
    """

    def __init__(self, n_axes: int, n_buttons: int, kind: str = "wheel") -> None:
        pygame = import_pygame()
        sdl = _sdl_library(pygame)
        try:
            attach = sdl.SDL_JoystickAttachVirtual
        except AttributeError:
            raise JoystickError("this SDL has no virtual joysticks (needs SDL >= 2.0.14)") \
                from None
        attach.restype = ctypes.c_int
        attach.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_int]
        sdl.SDL_JoystickOpen.restype = ctypes.c_void_p
        sdl.SDL_JoystickOpen.argtypes = [ctypes.c_int]
        sdl.SDL_JoystickSetVirtualAxis.argtypes = [ctypes.c_void_p, ctypes.c_int,
                                                   ctypes.c_int16]
        sdl.SDL_JoystickSetVirtualButton.argtypes = [ctypes.c_void_p, ctypes.c_int,
                                                     ctypes.c_uint8]
        sdl.SDL_GetError.restype = ctypes.c_char_p
        before = pygame.joystick.get_count()
        index = attach(SDL_JOYSTICK_TYPE[kind], n_axes, n_buttons, 0)
        if index < 0:
            raise JoystickError(f"SDL_JoystickAttachVirtual failed: "
                                f"{sdl.SDL_GetError().decode(errors='replace')}")
        pygame.event.pump()
        if pygame.joystick.get_count() <= before:
            raise JoystickError("the virtual joystick is not visible to pygame (pygame uses "
                                "another SDL library than the one found)")
        self._sdl = sdl
        self.device_index = index
        self.n_axes = n_axes
        self.n_buttons = n_buttons
        self._handle = sdl.SDL_JoystickOpen(index)
        if not self._handle:
            raise JoystickError("cannot open the virtual joystick")

    def set_axis(self, index: int, value: float) -> None:
        """Set an axis to ``value`` in [-1, 1] (SDL stores int16)."""
        v = int(round(_clip(value, -1.0, 1.0) * 32767.0))
        self._sdl.SDL_JoystickSetVirtualAxis(self._handle, index, v)

    def set_button(self, index: int, down: bool) -> None:
        """Press or release a button."""
        self._sdl.SDL_JoystickSetVirtualButton(self._handle, index, 1 if down else 0)


@dataclass(frozen=True)
class ScriptFrame:
    """Raw values set at time ``t`` (held until changed)."""

    t: float
    axes: Mapping[int, float]
    buttons: Mapping[int, bool]


@dataclass(frozen=True)
class JoystickScript:
    """Timed raw device values for :class:`VirtualJoystick` (``--virtual-joystick``).

    File format (YAML)::

        kind: joystick_script
        end_s: 6.0                       # the driver quits here
        frames:
          - {t: 0.0, axes: {0: 0.0, 1: -1.0, 2: -1.0}}
          - {t: 0.5, axes: {1: 0.6}}     # raw SDL values; unnamed axes keep theirs
          - {t: 3.0, buttons: {3: 1}}    # 1 = down, 0 = up
    """

    path: Path
    end_s: float
    frames: Sequence[ScriptFrame]

    @property
    def n_axes(self) -> int:
        """Axes the script touches (highest index + 1)."""
        return 1 + max((i for f in self.frames for i in f.axes), default=-1)

    @property
    def n_buttons(self) -> int:
        """Buttons the script touches (highest index + 1)."""
        return 1 + max((i for f in self.frames for i in f.buttons), default=-1)

    def due(self, after_s: float, until_s: float) -> list[ScriptFrame]:
        """Frames with ``after_s < t <= until_s`` (``after_s`` < 0 includes t = 0)."""
        return [f for f in self.frames if after_s < f.t <= until_s]


def _index_mapping(path: Path, where: str, value: Any, limit: int) -> dict[int, Any]:
    """A mapping whose keys are device indices in ``[0, limit)``."""
    if not isinstance(value, dict):
        raise ProfileError(path, where,
                           f"expected a mapping of index: value, got {short_repr(value)}")
    for key in value:
        if isinstance(key, bool) or not isinstance(key, int) or not 0 <= key < limit:
            raise ProfileError(path, f"{where}.{key}",
                               f"expected an index in [0, {limit - 1}] as the key")
    return value


def load_joystick_script(path: str | Path) -> JoystickScript:
    """Load and validate a joystick script (see :class:`JoystickScript`).

    Raises
    ------
    ProfileError
        Naming the file and the key.
    """
    path = Path(path)
    data = read_profile(path, "joystick_script")
    check_mapping(path, "", data, ("kind", "end_s", "frames"), required=("end_s", "frames"))
    end_s = number(path, "end_s", data["end_s"], 0.0, 3600.0)
    raw_frames = data["frames"]
    if not isinstance(raw_frames, list) or not raw_frames:
        raise ProfileError(path, "frames", "expected a non-empty list")
    frames = []
    last = -math.inf
    for k, raw in enumerate(raw_frames):
        where = f"frames[{k}]"
        check_mapping(path, where, raw, ("t", "axes", "buttons"), required=("t",))
        t = number(path, f"{where}.t", raw["t"], 0.0, end_s)
        if t < last:
            raise ProfileError(path, f"{where}.t", "frames must be in time order")
        last = t
        axes_raw = _index_mapping(path, f"{where}.axes", raw.get("axes") or {}, MAX_AXES)
        buttons_raw = _index_mapping(path, f"{where}.buttons", raw.get("buttons") or {},
                                     MAX_BUTTONS)
        axes = {i: number(path, f"{where}.axes.{i}", v, -1.0, 1.0)
                for i, v in axes_raw.items()}
        buttons = {i: bool(integer(path, f"{where}.buttons.{i}",
                                   int(v) if isinstance(v, bool) else v, 0, 1))
                   for i, v in buttons_raw.items()}
        frames.append(ScriptFrame(t=t, axes=axes, buttons=buttons))
    return JoystickScript(path=path, end_s=end_s, frames=tuple(frames))
