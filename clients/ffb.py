"""Force feedback: the state's steering-wheel torque on a wheel, through Linux evdev.

The server publishes ``steering_wheel_torque_nm`` in every state (the torque the car's
steering system applies to the driver's hands, + toward the left; docs/model.md section
12). :class:`ForceFeedback` turns it into the effects a force-feedback wheel plays, the
way Logitech, Thrustmaster and Fanatec wheels take them under Linux (``ff-core``, the
kernel's ``Documentation/input/ff.rst``):

- one ``FF_CONSTANT`` effect, uploaded once and then updated in place (uploaded again with
  its id) whenever its level changes, at the profile's rate (100-500 Hz): the torque
  times the profile's ``gain``, clipped to ``max_torque_nm``, in units of the wheel's
  full-scale torque ``device_torque_nm`` (level 32767);
- an ``FF_SPRING`` and an ``FF_DAMPER`` effect, the centring the profile gives, which take
  over while the server is paused, faulted or not heard from for ``timeout_s``: the
  constant force fades out and the spring and damper fade in over ``fade_s`` (and back
  when the states return), so the wheel never jumps.

The device is anything with python-evdev's ``InputDevice`` force-feedback members
(``capabilities``, ``upload_effect``, ``erase_effect``, ``write``): a real wheel opened by
:func:`open_ff_wheel`, or a stand-in that records what it was sent (the tests; this
machine has no input devices). python-evdev is optional (the ``ffb`` extra): only
:func:`import_evdev` imports it.

:class:`FfbLoop` runs the controller on a thread at the profile's rate from a state
subscriber of its own, apart from the command loop.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any, Protocol

from clients.profile import ProfileError, boolean, check_mapping, number, short_repr
from simserver.wire import protocol as proto

EVDEV_VERSION = "1.9.2"
"""The python-evdev release these clients are tested with (the ``ffb`` extra pins it)."""

LEVEL_MAX = 0x7FFF
"""Full scale of an ``FF_CONSTANT`` level and of a condition's coefficients (s16)."""
SATURATION_MAX = 0xFFFF
"""Full scale of a condition's saturation and of ``FF_GAIN`` (u16)."""
DIRECTION_LEFT = 0x4000
"""The effect's direction: 0x4000 is "left" in ff.rst's convention (0x0000 down, 0x8000
up, 0xC000 right), so a positive level pushes the rim to the left, as a positive torque
does. Drivers differ; ``invert`` flips the sign (docs/clients.md's checklist)."""

# evdev's codes (linux/input-event-codes.h), the same numbers python-evdev's ecodes holds;
# kept here so that the controller runs without the package (the tests' stand-in)
EV_FF = 0x15
FF_CONSTANT = 0x52
FF_SPRING = 0x53
FF_DAMPER = 0x55
FF_GAIN = 0x60
FF_AUTOCENTER = 0x61

FFB_KEYS = ("enabled", "device", "gain", "max_torque_nm", "device_torque_nm", "invert",
            "rate_hz", "spring", "damper", "timeout_s", "fade_s")


class FfbError(RuntimeError):
    """A force-feedback wheel that cannot be opened or used."""


@dataclass(frozen=True)
class FfbProfile:
    """The ``force_feedback`` section of a joystick profile.

    Attributes
    ----------
    enabled : bool
        Drive the wheel's force feedback at all.
    device : str
        evdev node (``/dev/input/by-id/...-event-joystick``), or ``auto``: the first device
        that supports ``FF_CONSTANT``.
    gain : float
        Wheel torque per N m of the simulated steering-wheel torque.
    max_torque_nm : float
        Most torque the wheel is asked for (N m at the rim), whatever the car does.
    device_torque_nm : float
        The wheel's torque at full level (its rating, N m).
    invert : bool
        Flip the sign (a wheel whose driver takes the direction the other way).
    rate_hz : float
        Effect updates per second (100-500).
    spring, damper : float
        Centring spring and damper while the server is paused or silent, as fractions of
        the wheel's full coefficient.
    timeout_s : float
        No state for this long counts as the server gone.
    fade_s : float
        Time to fade between following the torque and the centring spring.
    """

    enabled: bool = True
    device: str = "auto"
    gain: float = 0.5
    max_torque_nm: float = 2.0
    device_torque_nm: float = 2.5
    invert: bool = False
    rate_hz: float = 250.0
    spring: float = 0.3
    damper: float = 0.1
    timeout_s: float = 0.1
    fade_s: float = 0.5

    @property
    def level_max(self) -> int:
        """The largest constant-force level ever sent: ``max_torque_nm`` in device units."""
        return int(math.floor(LEVEL_MAX * self.max_torque_nm / self.device_torque_nm))

    def level(self, torque_nm: float) -> int:
        """The constant-force level for a steering-wheel torque (N m), gain and clip applied."""
        if not math.isfinite(torque_nm):
            return 0
        sign = -1.0 if self.invert else 1.0
        raw = sign * self.gain * torque_nm * LEVEL_MAX / self.device_torque_nm
        cap = self.level_max
        return int(round(min(max(raw, -cap), cap)))


def parse_ffb_profile(path: Path, raw: Any) -> FfbProfile:
    """The ``force_feedback`` mapping of a profile file; errors name the file and the key."""
    if raw is None:
        return FfbProfile(enabled=False)
    check_mapping(path, "force_feedback", raw, FFB_KEYS)
    d = FfbProfile()
    key = "force_feedback."
    device = raw.get("device", d.device)
    if not isinstance(device, str) or not device:
        raise ProfileError(path, key + "device",
                           f"expected 'auto' or a path, got {short_repr(device)}")
    device_torque = number(path, key + "device_torque_nm",
                           raw.get("device_torque_nm", d.device_torque_nm), 0.1, 100.0)
    max_torque = number(path, key + "max_torque_nm", raw.get("max_torque_nm", d.max_torque_nm),
                        0.0, 100.0)
    if max_torque > device_torque:
        raise ProfileError(path, key + "max_torque_nm",
                           f"{max_torque:g} N m is more than the wheel gives at full level "
                           f"(device_torque_nm {device_torque:g})")
    return FfbProfile(
        enabled=boolean(path, key + "enabled", raw.get("enabled", d.enabled)),
        device=device,
        gain=number(path, key + "gain", raw.get("gain", d.gain), 0.0, 10.0),
        max_torque_nm=max_torque, device_torque_nm=device_torque,
        invert=boolean(path, key + "invert", raw.get("invert", d.invert)),
        rate_hz=number(path, key + "rate_hz", raw.get("rate_hz", d.rate_hz), 100.0, 500.0),
        spring=number(path, key + "spring", raw.get("spring", d.spring), 0.0, 1.0),
        damper=number(path, key + "damper", raw.get("damper", d.damper), 0.0, 1.0),
        timeout_s=number(path, key + "timeout_s", raw.get("timeout_s", d.timeout_s), 0.01, 5.0),
        fade_s=number(path, key + "fade_s", raw.get("fade_s", d.fade_s), 0.0, 10.0),
    )


class FfDevice(Protocol):
    """The force-feedback members of python-evdev's ``InputDevice`` this module uses."""

    def capabilities(self) -> dict[int, list]: ...

    def upload_effect(self, effect: Any) -> int: ...

    def erase_effect(self, ff_id: int) -> None: ...

    def write(self, etype: int, code: int, value: int) -> None: ...


# ------------------------------------------------------------------------ evdev side


def import_evdev() -> ModuleType:
    """python-evdev, or a clear error naming the extra to install."""
    try:
        import evdev
    except ImportError:
        raise FfbError("force feedback needs python-evdev: pip install "
                       f"'simserver[ffb]' (evdev=={EVDEV_VERSION})") from None
    return evdev


def _ff_codes(device: FfDevice) -> set[int]:
    codes = device.capabilities().get(EV_FF, [])
    return {c[1] if isinstance(c, tuple) else int(c) for c in codes}


def open_ff_wheel(spec: str, opener: Any = None, lister: Any = None) -> FfDevice:
    """Open the force-feedback wheel ``spec`` names (a path, or ``auto``).

    ``opener(path)`` opens a device (default ``evdev.InputDevice``), ``lister()`` lists the
    candidate paths (default ``evdev.list_devices``): the tests inject a stand-in here.

    Raises
    ------
    FfbError
        No such device, no permission, or no ``FF_CONSTANT`` support.
    """
    if opener is None or lister is None:
        evdev = import_evdev()
        opener = opener or evdev.InputDevice
        lister = lister or evdev.list_devices
    paths = list(lister()) if spec == "auto" else [spec]
    problems = []
    for path in paths:
        try:
            device = opener(path)
        except OSError as exc:
            problems.append(f"{path}: {exc.strerror or exc}")
            continue
        if FF_CONSTANT in _ff_codes(device):
            return device
        problems.append(f"{path}: no FF_CONSTANT")
        close = getattr(device, "close", None)
        if close is not None:
            close()
    where = "no evdev device" if not paths else "; ".join(problems)
    raise FfbError(f"no force-feedback wheel ({spec}): {where} (docs/clients.md, "
                   "force feedback checklist)")


def _make_effect(kind: int) -> Any:
    """A zeroed ``evdev.ff.Effect`` of ``kind``, id -1 (new), infinite replay."""
    from evdev import ff

    effect = ff.Effect()
    effect.type = kind
    effect.id = -1
    effect.direction = DIRECTION_LEFT
    effect.ff_trigger = ff.Trigger(0, 0)
    effect.ff_replay = ff.Replay(0, 0)  # length 0: plays until stopped
    return effect


# ------------------------------------------------------------------------ controller


class ForceFeedback:
    """The effects of one wheel, driven from the states (module docstring).

    Parameters
    ----------
    device : FfDevice
        Opened, with ``FF_CONSTANT`` (spring and damper are used when it has them).
    profile : FfbProfile
    """

    def __init__(self, device: FfDevice, profile: FfbProfile) -> None:
        self.device = device
        self.profile = profile
        codes = _ff_codes(device)
        if FF_CONSTANT not in codes:
            raise FfbError("the wheel does not support FF_CONSTANT")
        self.follow_weight = 0.0  # 1: following the torque; 0: centring spring only
        self.level = 0
        self._torque_level = 0  # the level the newest state's torque asks for
        self.spring_coeff = -1
        self.damper_coeff = -1
        self._last_s: float | None = None
        self.uploads = 0
        if FF_GAIN in codes:
            device.write(EV_FF, FF_GAIN, SATURATION_MAX)  # the gain is applied in the level
        if FF_AUTOCENTER in codes:
            device.write(EV_FF, FF_AUTOCENTER, 0)  # the centring spring is ours
        self.constant = _make_effect(FF_CONSTANT)
        self.spring = _make_effect(FF_SPRING) if FF_SPRING in codes else None
        self.damper = _make_effect(FF_DAMPER) if FF_DAMPER in codes else None
        self._set(0, force=True)
        for effect in (self.constant, self.spring, self.damper):
            if effect is not None:
                device.write(EV_FF, effect.id, 1)  # play (the updates keep it playing)

    def _upload(self, effect: Any) -> None:
        ff_id = self.device.upload_effect(effect)
        if effect.id < 0:
            effect.id = ff_id
        self.uploads += 1

    def _set(self, level: int, force: bool = False) -> None:
        """Send the constant level and the centring for the current follow weight (only
        what changed)."""
        if force or level != self.level:
            self.constant.u.ff_constant_effect.level = level
            self._upload(self.constant)
            self.level = level
        centring = 1.0 - self.follow_weight
        p = self.profile
        for effect, share, attr in ((self.spring, p.spring, "spring_coeff"),
                                    (self.damper, p.damper, "damper_coeff")):
            if effect is None:
                continue
            coeff = int(round(LEVEL_MAX * share * centring))
            if force or coeff != getattr(self, attr):
                cond = effect.u.ff_condition_effect[0]  # axis x: the wheel
                cond.right_coeff = cond.left_coeff = coeff
                cond.right_saturation = cond.left_saturation = SATURATION_MAX
                cond.deadband = 0
                cond.center = 0
                self._upload(effect)
                setattr(self, attr, coeff)

    def live(self, now_s: float, state: Any, state_wall_s: float) -> bool:
        """Whether the state is one to follow: recent, not paused, not faulted."""
        if state is None or now_s - state_wall_s > self.profile.timeout_s:
            return False
        flags = int(state["flags"])
        return not flags & (proto.StateFlag.PAUSED | proto.StateFlag.FAULT)

    def follow(self, now_s: float, state: Any, state_wall_s: float) -> None:
        """One update: the newest state (or None) and when it arrived (``time.monotonic``).

        Fades the follow weight toward 1 while the state is live, toward 0 otherwise, at
        ``1 / fade_s`` (at most two periods' worth per update); the constant level is the
        weight times the state's torque (gain, clip), the spring and damper take the rest.
        """
        p = self.profile
        # a late update (a stalled process) fades no further than two periods would: the
        # wheel never jumps, the fade takes longer instead
        dt = 0.0 if self._last_s is None else min(max(0.0, now_s - self._last_s),
                                                   2.0 / p.rate_hz)
        self._last_s = now_s
        live = self.live(now_s, state, state_wall_s)
        target = 1.0 if live else 0.0
        if p.fade_s <= 0.0:
            self.follow_weight = target
        elif self.follow_weight < target:
            self.follow_weight = min(target, self.follow_weight + dt / p.fade_s)
        elif self.follow_weight > target:
            self.follow_weight = max(target, self.follow_weight - dt / p.fade_s)
        if state is not None:
            self._torque_level = p.level(float(state["steering_wheel_torque_nm"]))
        level = int(round(self.follow_weight * self._torque_level))
        self._set(level)

    def close(self) -> None:
        """Stop and erase the effects (the wheel goes limp, as with no program running)."""
        for effect in (self.constant, self.spring, self.damper):
            if effect is not None and effect.id >= 0:
                try:
                    self.device.write(EV_FF, effect.id, 0)
                    self.device.erase_effect(effect.id)
                except OSError:
                    pass  # the wheel was unplugged: nothing left to stop
                effect.id = -1


class FfbLoop:
    """:class:`ForceFeedback` on a thread at the profile's rate, from a state inbox.

    Parameters
    ----------
    inbox
        A state subscriber (``ZenohEndpoint.declare_state_inbox``) with ``drain_newest``.
    ffb : ForceFeedback
    states : clients.common.StateFilter, optional
        Takes only valid states in the server's order (else every decodable one).
    """

    def __init__(self, inbox: Any, ffb: ForceFeedback, states: Any = None) -> None:
        self.inbox = inbox
        self.ffb = ffb
        self.states = states  # a clients.common.StateFilter: only the server's states
        self.state: Any = None
        self.state_wall_s = -math.inf
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ffb", daemon=True)

    def start(self) -> FfbLoop:
        self._thread.start()
        return self

    def poll(self, now_s: float) -> None:
        """Take the newest state received so far (bad payloads are skipped)."""
        payloads = self.inbox.drain_newest()
        if self.states is not None:  # valid and in the server's order (docs/security.md)
            state = self.states.newest(payloads, now_s)
            if state is not None:
                self.state, self.state_wall_s = state, now_s
            return
        for payload in reversed(payloads):
            try:
                self.state = proto.decode_state(payload)
            except proto.ProtocolError:
                continue
            self.state_wall_s = now_s
            break

    def _run(self) -> None:
        period = 1.0 / self.ffb.profile.rate_hz
        next_t = time.monotonic()
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                self.poll(now)
                self.ffb.follow(now, self.state, self.state_wall_s)
                next_t += period
                if next_t < now - 5 * period:  # stalled: skip the missed updates
                    next_t = now + period
                self._stop.wait(max(0.0, next_t - time.monotonic()))  # the update rate
        except BaseException as exc:  # noqa: BLE001 - reported by stop()
            self.error = exc

    def stop(self) -> None:
        """Stop the thread and erase the effects; re-raises an error the thread hit."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self.ffb.close()
        if self.error is not None:
            raise FfbError(f"force feedback stopped: {self.error}") from self.error
