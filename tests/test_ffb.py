"""Force feedback (clients/ffb.py) at the evdev boundary, driven by a real server.

This machine has no input devices, so the wheel is a recording stand-in with python-evdev
``InputDevice``'s force-feedback members (``capabilities``, ``upload_effect``,
``erase_effect``, ``write``), injected where ``open_ff_wheel`` would open the real node.
It takes the real ``evdev.ff.Effect`` structures, as bytes the way python-evdev hands
them to the kernel, and refuses what the kernel refuses (an update of an effect id it did
not hand out). Everything else is real: a server subprocess, zenoh on loopback, the
state payloads, the ``FfbLoop`` thread.

Acceptance (issue 17 item 2): the effect follows the state's steering-wheel torque within
20 ms and never exceeds the profile's maximum; pausing the server or losing it fades the
effect to the centring spring.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from clients import ffb as F
from clients.joystick import load_joystick_profile
from clients.profile import ProfileError
from simserver.testing import CONFIGS, Client, ServerProcess, wait_until
from simserver.wire import protocol as proto

evdev_ff = pytest.importorskip("evdev.ff")


class RecordingWheel:
    """A force-feedback wheel's evdev boundary that records what it is sent."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.log: list[tuple[float, str, int, int, int]] = []  # (t, what, type, id, value)
        self.effects: dict[int, int] = {}  # id -> type
        self.playing: set[int] = set()
        self.closed = False

    def capabilities(self) -> dict[int, list]:
        return {F.EV_FF: [F.FF_CONSTANT, F.FF_SPRING, F.FF_DAMPER, F.FF_GAIN,
                          F.FF_AUTOCENTER]}

    def upload_effect(self, effect) -> int:
        raw = memoryview(effect).tobytes()  # what python-evdev passes to EVIOCSFF
        e = evdev_ff.Effect.from_buffer_copy(raw)
        with self.lock:
            if e.id >= 0 and self.effects.get(e.id) != e.type:
                raise OSError(22, "Invalid argument")  # ff-core: not this file's effect
            ff_id = e.id if e.id >= 0 else len(self.effects)
            self.effects[ff_id] = e.type
            if e.type == F.FF_CONSTANT:
                value = e.u.ff_constant_effect.level
                assert e.direction == F.DIRECTION_LEFT and e.ff_replay.length == 0
            else:
                cond = e.u.ff_condition_effect[0]
                assert cond.left_coeff == cond.right_coeff
                value = cond.right_coeff
            self.log.append((time.monotonic(), "upload", e.type, ff_id, value))
        return ff_id

    def erase_effect(self, ff_id: int) -> None:
        with self.lock:
            if ff_id not in self.effects:
                raise OSError(22, "Invalid argument")
            del self.effects[ff_id]
            self.playing.discard(ff_id)
            self.log.append((time.monotonic(), "erase", -1, ff_id, 0))

    def write(self, etype: int, code: int, value: int) -> None:
        assert etype == F.EV_FF
        with self.lock:
            if code in self.effects:
                (self.playing.add if value else self.playing.discard)(code)
            self.log.append((time.monotonic(), "write", -1, code, value))

    def series(self, kind: int) -> np.ndarray:
        """(time, value) of every upload of the effect type ``kind``."""
        with self.lock:
            rows = [(t, v) for t, what, typ, _, v in self.log if what == "upload"
                    and typ == kind]
        return np.array(rows, dtype=float).reshape(-1, 2)

    def value_at(self, kind: int, t: float) -> int:
        s = self.series(kind)
        k = np.searchsorted(s[:, 0], t, side="right") - 1
        return int(s[k, 1])


PROFILE = F.FfbProfile(gain=0.5, max_torque_nm=1.5, device_torque_nm=2.5, rate_hz=250.0,
                       spring=0.4, damper=0.2, timeout_s=0.1, fade_s=0.3)
FULL_SPRING = round(F.LEVEL_MAX * PROFILE.spring)


def test_profile_keys_are_checked_and_the_level_clipped(tmp_path: Path) -> None:
    wheel = load_joystick_profile(CONFIGS / "clients" / "wheel.yaml").force_feedback
    assert wheel.enabled and wheel.max_torque_nm <= wheel.device_torque_nm
    bad = tmp_path / "bad.yaml"
    text = (CONFIGS / "clients" / "wheel.yaml").read_text()
    bad.write_text(text.replace("max_torque_nm: 2.0", "max_torque_nm: 3.0"))
    with pytest.raises(ProfileError, match=r"bad.yaml: key 'force_feedback.max_torque_nm'"):
        load_joystick_profile(bad)
    bad.write_text(text.replace("rate_hz: 250", "rate_hz: 50"))
    with pytest.raises(ProfileError, match=r"force_feedback.rate_hz"):
        load_joystick_profile(bad)
    # gain and clip: 1 N m of car torque -> 0.5 N m at the rim = 0.2 of a 2.5 N m wheel
    assert PROFILE.level(1.0) == round(0.2 * F.LEVEL_MAX)
    assert PROFILE.level(100.0) == PROFILE.level_max == int(F.LEVEL_MAX * 1.5 / 2.5)
    assert PROFILE.level(-100.0) == -PROFILE.level_max
    assert PROFILE.level(float("nan")) == 0
    inverted = F.FfbProfile(invert=True, gain=0.5, max_torque_nm=1.5, device_torque_nm=2.5)
    assert inverted.level(1.0) == -PROFILE.level(1.0)


def test_open_ff_wheel_names_what_is_missing() -> None:
    class NoFf(RecordingWheel):
        def capabilities(self) -> dict[int, list]:
            return {}

    with pytest.raises(F.FfbError, match="event3: no FF_CONSTANT"):
        F.open_ff_wheel("auto", opener=lambda p: NoFf(), lister=lambda: ["/dev/input/event3"])
    with pytest.raises(F.FfbError, match="no evdev device"):
        F.open_ff_wheel("auto", opener=lambda p: NoFf(), lister=lambda: [])
    wheel = RecordingWheel()
    assert F.open_ff_wheel("/dev/input/event7", opener=lambda p: wheel, lister=list) is wheel


def _fade_checks(wheel: RecordingWheel, since: float, until: float) -> None:
    """Between ``since`` and ``until`` the constant force only shrinks and the spring only
    grows (a fade, no jump back), ending at zero force and the profile's full spring."""
    c = wheel.series(F.FF_CONSTANT)
    s = wheel.series(F.FF_SPRING)
    c = c[(c[:, 0] >= since) & (c[:, 0] <= until)]
    s = s[(s[:, 0] >= since) & (s[:, 0] <= until)]
    assert np.all(np.diff(np.abs(c[:, 1])) <= 0)
    assert np.all(np.diff(s[:, 1]) >= 0)
    # a fade, not a step: no update moves more than two periods' share of fade_s (the
    # controller's cap when its thread runs late)
    share = 2.0 / (PROFILE.rate_hz * PROFILE.fade_s)
    assert np.all(np.diff(s[:, 1]) <= share * FULL_SPRING + 1)
    assert np.all(np.abs(np.diff(c[:, 1])) <= share * PROFILE.level_max + 1)
    assert wheel.value_at(F.FF_CONSTANT, until) == 0
    assert wheel.value_at(F.FF_SPRING, until) == round(F.LEVEL_MAX * PROFILE.spring)
    assert wheel.value_at(F.FF_DAMPER, until) == round(F.LEVEL_MAX * PROFILE.damper)


def _judgeable(arr: np.ndarray, loop_times: list[float], t0: float) -> np.ndarray:
    """The states whose 20 ms can be judged: from 0.5 s (the fade-in is over), not within
    0.25 s of the last one seen (the wheel's session may hold newer ones not seen here),
    and not in a stall of this whole process (its 2 ms loop did not run for 10 ms: the OS
    did not schedule it on this shared, loaded machine, and no thread of it could update
    anything then)."""
    if len(arr) == 0:
        return np.zeros(0, dtype=int)
    times = np.asarray(loop_times)
    gaps = np.nonzero(np.diff(times) > 0.010)[0]
    lo, hi = times[gaps], times[gaps + 1]
    keep = []
    for k in np.nonzero((arr[:, 0] > t0 + 0.5) & (arr[:, 0] < arr[-1, 0] - 0.25))[0]:
        a = arr[k, 0]
        if not np.any((lo < a + 0.020) & (hi > a - 0.005)):
            keep.append(k)
    return np.array(keep, dtype=int)


def test_the_wheel_follows_the_server_and_fades_to_the_spring_when_it_goes() -> None:
    server = ServerProcess(vehicle_id="car_ffb")
    driver = Client(server, keep_history=True)
    ffb_session = Client(server, state_capacity=0)
    wheel = RecordingWheel()
    loop = F.FfbLoop(ffb_session.ep.declare_state_inbox(capacity=16),
                     F.ForceFeedback(F.open_ff_wheel("/dev/input/event7",
                                                     opener=lambda p: wheel, lister=list),
                                     PROFILE)).start()
    try:
        driver.wait_state()
        # the effects: uploaded, playing, the wheel's own autocentre off, device gain full
        assert len(wheel.playing) == 3
        with wheel.lock:
            writes = [(code, v) for _, what, _, code, v in wheel.log if what == "write"]
        assert (F.FF_AUTOCENTER, 0) in writes and (F.FF_GAIN, F.SATURATION_MAX) in writes
        # at rest, brake on: the driver saws the wheel to and fro (the parking torque
        # builds, saturates at the bore limit and reverses: above and below the clip)
        arrivals: list[tuple[float, int, float]] = []  # (arrival, tick, torque)
        loop_times: list[float] = []
        t0 = time.monotonic()
        next_check = t0 + 4.0
        while True:
            now = time.monotonic()
            loop_times.append(now)
            steer = 0.5 * np.sin(2.0 * np.pi * 0.5 * (now - t0))
            driver.send(steer=float(steer), brake=0.5, gear=proto.Gear.D)
            for st in driver.drain_states():
                arrivals.append((time.monotonic(), int(st["tick"]),
                                 float(st["steering_wheel_torque_nm"])))
            # until enough states can be judged (below), at most 30 s
            if now > next_check:
                next_check = now + 1.0
                if len(_judgeable(np.array(arrivals), loop_times, t0)) >= 300 \
                        or now - t0 > 30.0:
                    break
            time.sleep(0.002)  # the pace of the driver's command stream (500 Hz)
        arr = np.array(arrivals)
        torques = arr[:, 2]
        assert torques.max() > 2.5 / PROFILE.gain and torques.min() < -2.5 / PROFILE.gain
        # never beyond the profile's maximum
        levels = wheel.series(F.FF_CONSTANT)[:, 1]
        assert np.abs(levels).max() == PROFILE.level_max
        assert PROFILE.level_max * PROFILE.device_torque_nm / F.LEVEL_MAX <= PROFILE.max_torque_nm
        # follows within 20 ms: 20 ms after a state arrived here, the wheel's level is the
        # one of that state or of a newer one (the two sessions receive the same states a
        # little apart: the wheel's may be ahead; the window ends 200 ms on so that a stale
        # level cannot pass as a much later state's)
        expected = np.array([PROFILE.level(T) for T in torques])
        ticks = arr[:, 1]
        judged = _judgeable(arr, loop_times, t0)
        late = []
        for k in judged:
            level = wheel.value_at(F.FF_CONSTANT, arr[k, 0] + 0.020)
            window = (ticks >= ticks[k]) & (ticks <= ticks[k] + 200)
            if level not in set(expected[window]):
                late.append((arr[k, 0] - t0, ticks[k], level))
        assert not late, f"{len(late)} states not on the wheel 20 ms later: {late[:5]}"
        assert len(judged) >= 300, len(judged)  # enough states judged to mean something
        assert len(set(expected)) > 50  # the level really moved

        # paused: the torque fades out, the centring spring in
        assert driver.ep.request("pause", timeout_s=10.0)["ok"]
        t_pause = time.monotonic()
        wait_until(lambda: wheel.value_at(F.FF_CONSTANT, time.monotonic()) == 0
                   and wheel.value_at(F.FF_SPRING, time.monotonic()) == FULL_SPRING,
                   timeout_s=5.0, what="the fade to the spring on pause")
        _fade_checks(wheel, t_pause, time.monotonic())
        assert driver.ep.request("resume", timeout_s=10.0)["ok"]
        wait_until(lambda: wheel.value_at(F.FF_SPRING, time.monotonic()) == 0, timeout_s=5.0,
                   what="following again after resume")

        # the server vanishes (SIGKILL): after timeout_s, the fade to the spring
        driver.drive(0.3, steer=0.25, brake=0.5, gear=proto.Gear.D)
        assert wheel.value_at(F.FF_CONSTANT, time.monotonic()) != 0
        server.kill()
        t_gone = time.monotonic()
        wait_until(lambda: wheel.value_at(F.FF_CONSTANT, time.monotonic()) == 0
                   and wheel.value_at(F.FF_SPRING, time.monotonic()) == FULL_SPRING,
                   timeout_s=5.0, what="the fade to the spring")
        _fade_checks(wheel, t_gone, time.monotonic())
        assert loop.error is None
    finally:
        loop.stop()
        driver.close()
        ffb_session.close()
        server.stop()
    # stopped: every effect stopped and erased
    assert not wheel.effects and not wheel.playing
