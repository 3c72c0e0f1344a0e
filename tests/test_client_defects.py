"""Client-side defects a new user met (issue 13), each pinned by a test that failed before.

- Safe start: launched in D with the pedals at rest, the driver released the server's
  watchdog brakes at once, and on a 10 % hill the car rolled back to -10.6 km/h within
  3 s with no key pressed. The keyboard driver (keys through a pseudo-terminal) and the
  joystick driver (SDL's virtual joystick, pedals at rest) run against a live server on
  ``configs/scenes/hill_10pct_paper_sedan.yaml``; an independent client watches the state:
  over a window of at least 3 s of simulated time with the driver's commands applied and
  no throttle, the car must not move, and the throttle must then drive it up the hill.
- The recorder's file metadata named the first scene after a ``load`` in mid-recording:
  the metadata is now per segment (a segment starts at each reset or load, seen as the
  tick going back), each with the vehicle, scene and road ``get_config`` reported then.
- The usage line of every client names the command users run (``simserver-driver``,
  ``simserver-player``, ``simserver-recorder``: the ``project.scripts`` of
  ``pyproject.toml``), not ``python -m clients.X``.
"""

from __future__ import annotations

import importlib
import importlib.util
import math
import subprocess
import tomllib
from collections.abc import Callable

import numpy as np
import pytest

from simserver.testing import (
    CONFIGS,
    REPO,
    Client,
    OutputProcess,
    ServerProcess,
    client_command,
    client_env,
    wait_until,
)
from simserver.wire import protocol as proto
from tests.test_clients import PtyProcess, hold_until

pytestmark = pytest.mark.timeout(300)

HAVE_PYGAME = importlib.util.find_spec("pygame") is not None

REST_WINDOW_S = 3.0
"""Simulated time the car must stay put with the driver connected and no key pressed (the
defect rolled it back to -2.9 m/s in that time)."""
STILL_MPS = 0.05
"""Speed bound for "does not roll" (a rolling car passes it within 0.1 s on 10 %)."""
STILL_M = 0.02
"""Displacement bound over the window."""

CLIENT_MODULES = ("driver", "player", "recorder")


def _scripts() -> dict[str, str]:
    """``project.scripts`` of pyproject.toml: command -> ``module:function``."""
    with open(REPO / "pyproject.toml", "rb") as fh:
        return tomllib.load(fh)["project"]["scripts"]


@pytest.mark.parametrize("name", CLIENT_MODULES)
def test_usage_line_names_the_installed_command(name):
    module = importlib.import_module(f"clients.{name}")
    command = {target: cmd for cmd, target in _scripts().items()}[f"clients.{name}:main"]
    assert module.PROG == command  # the name in the clients' messages
    parser = module.build_parser()
    assert parser.prog == command
    assert parser.format_usage().startswith(f"usage: {command} ")
    assert "python -m" not in parser.format_usage()


# ============================================================================ safe start


@pytest.fixture(scope="module")
def hill_server():
    server = ServerProcess(vehicle_id="hill", scene="hill_10pct_paper_sedan")
    yield server
    server.stop()


def _driven(state: np.void) -> bool:
    """The driver's commands are applied (its first seq arrived, no watchdog hold)."""
    return int(state["last_cmd_seq"]) > 0 and not int(state["flags"]) & proto.StateFlag.WATCHDOG


def _watcher(server: ServerProcess) -> Client:
    """An independent client that only listens, keeping every state it receives."""
    return Client(server, state_capacity=1 << 15, keep_history=True)


def _wait_states(watcher: Client, done: Callable[[list[np.void]], bool], timeout_s: float,
                 what: str) -> list[np.void]:
    """Poll the watcher until ``done(history)``; fail naming ``what`` after the timeout."""
    def done_yet() -> bool:
        watcher.poll()
        return done(watcher.history)

    try:  # every 20 ms: ``done`` may walk the whole history
        wait_until(done_yet, timeout_s=timeout_s, what=what, interval_s=0.02)
    except TimeoutError as exc:
        last = watcher.history[-1] if watcher.history else None
        raise AssertionError(f"{exc}; last state: {last}") from None
    return watcher.history


def _rest_window(states: list[np.void]) -> list[np.void]:
    """The states from the first driven one on, up to the first with throttle applied."""
    first = next((i for i, s in enumerate(states) if _driven(s)), None)
    if first is None:
        return []
    window = []
    for s in states[first:]:
        if float(s["throttle"]) > 0.0:
            break
        window.append(s)
    return window


def _span_s(window: list[np.void]) -> float:
    return float(window[-1]["sim_time_s"]) - float(window[0]["sim_time_s"]) if window else 0.0


def _assert_did_not_roll(window: list[np.void], who: str) -> None:
    u = np.array([float(s["u_mps"]) for s in window])
    x = np.array([float(s["x_m"]) for s in window])
    print(f"\n{who}: {_span_s(window):.2f} s at rest with the driver connected: |u| max "
          f"{np.max(np.abs(u)):.4f} m/s, x moved {x[-1] - x[0]:+.4f} m, applied brake "
          f"{float(window[-1]['brake']):.2f}, gear {int(window[-1]['gear'])}")
    assert _span_s(window) >= REST_WINDOW_S
    assert np.max(np.abs(u)) < STILL_MPS, f"{who}: the car rolled (u {u.min():.2f} m/s)"
    assert abs(x[-1] - x[0]) < STILL_M


def _at_rest_on_the_hill(watcher: Client) -> None:
    """Put the car back at the scene's start (a previous test may have driven it), with no
    driver's command applied: a driver that quits leaves its last command in force for the
    watchdog's time, across a reset, and those states (a sequence number, no watchdog flag,
    maybe throttle) would pass for the new driver's first ones."""
    # (the watchdog keeps last_cmd_seq; the reset then forgets it: docs/protocol.md 2.1)
    watcher.wait_state(lambda s: bool(int(s["flags"]) & proto.StateFlag.WATCHDOG), 5.0,
                       "the watchdog to hold the car (no driver's command left)")
    assert watcher.request("reset", timeout_s=5.0)["ok"]
    _wait_states(watcher, lambda h: bool(h) and int(h[-1]["tick"]) < 500
                 and abs(float(h[-1]["u_mps"])) < 1e-3, 10.0, "the reset")
    watcher.history.clear()


def test_keyboard_driver_holds_the_car_on_a_hill_until_the_throttle(hill_server):
    watcher = _watcher(hill_server)
    _at_rest_on_the_hill(watcher)
    drv = PtyProcess(client_command("driver", "--rate", "200", *hill_server.client_args()))
    try:
        drv.wait_for("connected to simserver/hill", 30)
        states = _wait_states(watcher, lambda h: _span_s(_rest_window(h)) >= REST_WINDOW_S,
                              30.0, f"{REST_WINDOW_S} s of driven states without a key")
        window = _rest_window(states)
        climbing = hold_until(drv, b"w", watcher,  # the driver acts: throttle until it climbs
                              lambda s: float(s["u_mps"]) >= 0.3, 20.0)
        drv.send(b"q")
        assert drv.wait(15) == 0, drv.text()
    finally:
        drv.close()
        watcher.close()
    _assert_did_not_roll(window, "keyboard")
    assert float(climbing["u_mps"]) >= 0.3  # and the hold let go when the driver acted


@pytest.mark.skipif(not HAVE_PYGAME, reason="pygame (the 'joystick' extra) is not installed")
def test_joystick_driver_with_pedals_at_rest_holds_the_car_on_a_hill(hill_server, tmp_path):
    """SDL's virtual wheel: pedals released (+1) for 7 s, then full throttle for 5 s."""
    script = tmp_path / "rest_then_throttle.yaml"
    script.write_text("""\
kind: joystick_script
end_s: 12.0
frames:
  - {t: 0.0, axes: {0: 0.0, 1: 1.0, 2: 1.0, 3: 1.0}}
  - {t: 7.0, axes: {2: -1.0}}
""")
    watcher = _watcher(hill_server)
    _at_rest_on_the_hill(watcher)
    run = subprocess.run(
        client_command("driver", "--virtual-joystick", str(script), "--profile",
                       str(REPO / "configs" / "clients" / "wheel.yaml"),
                       *hill_server.client_args()),
        cwd=REPO, env=client_env(), stdin=subprocess.DEVNULL, capture_output=True, text=True,
        timeout=120)
    watcher.poll()
    states = watcher.history
    watcher.close()
    assert run.returncode == 0, run.stdout + run.stderr
    window = _rest_window(states)
    _assert_did_not_roll(window, "joystick")
    driven = [s for s in states if _driven(s)]
    assert max(float(s["u_mps"]) for s in driven) >= 0.3  # the throttle then climbs


def test_start_hold_lets_go_only_on_the_throttle_and_rearms():
    from clients.driver import START_HOLD_RELEASE_PER_S, StartHold

    hold = StartHold()
    dt = 0.005
    for _ in range(1000):  # 5 s of brake-key taps and no throttle: still held
        assert hold.apply(0.0, 0.3, dt) == 1.0
    assert hold.engaged
    sent = [hold.apply(0.05, 0.0, dt) for _ in range(200)]  # the throttle comes in
    assert not hold.engaged
    assert sent[0] == pytest.approx(1.0 - START_HOLD_RELEASE_PER_S * dt)
    fade_s = dt * next(i for i, b in enumerate(sent) if b == 0.0)
    assert fade_s == pytest.approx(1.0 / START_HOLD_RELEASE_PER_S, abs=2 * dt)
    assert hold.apply(0.0, 0.4, dt) == 0.4  # released: the driver's own brake
    hold.arm()  # a reset
    assert hold.engaged and hold.apply(0.0, 0.0, dt) == 1.0


def test_auto_hold_engages_at_a_braked_stop_and_can_be_turned_off():
    """Auto hold (issue 32): the brake pressed with the car stopped engages the hold; the
    pedal let go keeps it; the throttle releases it; a coasting stop (no brake), a stop
    with the throttle on and an unknown speed do not engage it; ``set_auto(False)`` lets
    go and keeps it off."""
    from clients.driver import AUTO_HOLD_MIN_BRAKE, AUTO_HOLD_REST_MPS, StartHold

    hold = StartHold()
    dt = 0.005
    hold.apply(0.5, 0.0, dt, 3.0)
    for _ in range(100):  # the start hold faded out: driving
        hold.apply(0.5, 0.0, dt, 3.0)
    assert not hold.engaged and hold.apply(0.0, 0.0, dt, 3.0) == 0.0
    assert hold.apply(0.0, 0.6, dt, 1.0) == 0.6  # braking at speed: the driver's brake
    assert not hold.engaged
    assert hold.apply(0.0, 0.0, dt, 0.0) == 0.0  # a stop without the brake: no hold
    assert hold.apply(0.2, 0.6, dt, 0.0) == 0.6  # nor with the throttle on
    assert hold.apply(0.0, 0.6, dt, math.inf) == 0.6  # nor with no state yet
    assert not hold.engaged
    assert hold.apply(0.0, AUTO_HOLD_MIN_BRAKE, dt, 0.9 * AUTO_HOLD_REST_MPS) == 1.0
    assert hold.engaged and hold.reason == "auto"
    assert "auto hold: the brake is held" in hold.status(0.0)
    assert all(hold.apply(0.0, 0.0, dt, 0.0) == 1.0 for _ in range(2000))  # pedal let go
    assert hold.apply(0.1, 0.0, dt, 0.0) < 1.0 and not hold.engaged  # throttle: fades
    assert "letting go" in hold.status(0.0)
    hold.apply(0.0, 0.5, dt, 0.0)
    assert hold.engaged
    hold.set_auto(False)
    assert not hold.engaged
    for _ in range(100):
        hold.apply(0.0, 0.5, dt, 0.0)
    assert not hold.engaged and hold.apply(0.0, 0.0, dt, 0.0) == 0.0
    assert hold.status(0.0) == "auto hold OFF"


# ============================================================================ recorder


def test_recorder_metadata_per_segment_after_a_load_and_a_reset(tmp_path):
    """flat scene -> ``load`` the 10 % hill -> ``reset``: three segments, each described."""
    from clients.recorder import HISTORY_FILE, read_segments
    from simserver.adapters.history import read_history

    hill = CONFIGS / "scenes" / "hill_10pct_paper_sedan.yaml"
    server = ServerProcess(vehicle_id="rec", scene="flat_paper_sedan")
    watcher = _watcher(server)
    out = tmp_path / "rec"
    rec = OutputProcess(client_command("recorder", "--out", str(out), "--quiet",
                                       *server.client_args()),
                        ready="recording", env=client_env())
    try:
        assert rec.wait_ready(30.0), rec.text()

        def ran_300_ticks(h: list[np.void]) -> bool:
            """300 ticks since the segment's first state in ``h``: a load or a reset
            restarts the tick, and the last states of the segment before may open ``h``."""
            if len(h) < 2:
                return False
            ticks = np.array([int(s["tick"]) for s in h])
            restarts = np.flatnonzero(np.diff(ticks) < 0)
            first = ticks[restarts[-1] + 1 if restarts.size else 0]
            return ticks[-1] - first >= 300

        def run_a_while(what: str) -> None:  # 0.3 s of simulated time in this segment
            watcher.history.clear()
            _wait_states(watcher, ran_300_ticks, 30.0, what)

        run_a_while("the flat segment")
        assert watcher.request("load", {"scene": str(hill)}, timeout_s=30.0)["ok"]
        run_a_while("the hill segment")
        assert watcher.request("reset", timeout_s=5.0)["ok"]
        run_a_while("the segment after the reset")
        assert rec.stop(timeout_s=60.0) == 0, rec.text()
    finally:
        rec.kill()
        watcher.close()
        server.stop()
    history = read_history(out)
    segments = read_segments(out / HISTORY_FILE)
    print(f"\nsegments: {segments}")
    assert [s["segment"] for s in segments] == [0, 1, 2] == \
        sorted(set(history["segment"].tolist()))
    assert [s["scene"].rsplit("/", 1)[-1] for s in segments] == [
        "flat_paper_sedan.yaml", "hill_10pct_paper_sedan.yaml", "hill_10pct_paper_sedan.yaml"]
    assert [s["road"]["grade_pct"] for s in segments] == [0.0, 10.0, 10.0]
    assert all(s["vehicle"] == "paper_sedan" for s in segments)
    for s in segments:  # each entry starts where its rows do
        rows = history["segment"] == s["segment"]
        assert s["first_tick"] == int(history["tick"][rows][0])
        assert s["rows"] == int(np.sum(rows))
    assert segments[1]["first_tick"] < 300  # a new segment restarts the tick
