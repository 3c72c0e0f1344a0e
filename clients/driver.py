"""``simserver-driver``: drive a simserver car from a keyboard, a gamepad or a wheel.

The driver sends a DriverCommand at a steady rate (``--rate``, default 200 Hz: the
server applies the newest one each 1 ms tick and holds the car with its watchdog if none
arrives for 200 ms), each with the next ``seq`` and ``sender_time_ns`` on this process's
monotonic clock, and shows what comes back: speed, gear, parking brake, the grade and
cross-slope of the ground under the car and which wheels touch it, the watchdog / paused /
brake-hold flags, the command-to-state latency and the server's health from the
diagnostics (tick lateness p99, overruns, rejected commands); in a server's world of
several cars, the nearest car ahead and behind with the distance and the closing speed
(the world message, :mod:`clients.world`).

Input modes
-----------
``--input keyboard`` (default)
    Any terminal, local or over SSH: arrows or W/A/S/D, with pedal ramps and
    auto-centring steering (:mod:`clients.keyboard`, tuned by
    ``configs/clients/keyboard.yaml``).
``--input joystick``
    A game controller or steering wheel through pygame (SDL2), mapped by a profile
    (``--profile configs/clients/wheel.yaml``). ``--list-joysticks`` shows the devices,
    ``--probe`` the live raw axes and buttons and what the profile makes of them.
    ``--virtual-joystick SCRIPT`` attaches SDL's virtual joystick and plays a timed
    script on it (a demo without hardware; the end-to-end test uses it).

Safe start
----------
Until the driver first presses the throttle, the commands carry the brake fully applied
(:class:`StartHold`), whatever the gear: started in D with the pedals at rest, the first
command would otherwise release the server's watchdog brakes and a car on a hill would
roll away with no key pressed. A reset re-arms the hold.

Quitting (``q``, Ctrl-C, SIGTERM, a ``quit`` button, the end of a virtual-joystick
script) stops the commands: the server's watchdog then holds the car.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import threading
import time
from collections import deque
from collections.abc import Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import Any, Protocol, TextIO

import numpy as np

from clients.common import (
    EXIT_FAILED,
    EXIT_OK,
    EXIT_USAGE,
    ClientError,
    Connection,
    RatePacer,
    ServerPresence,
    StopFlag,
    add_connection_args,
    add_rate_arg,
    check_rate,
    check_server_config,
    client_main,
    connect,
    gear_name,
    short_repr,
    state_filter,
)
from clients.ffb import FfbError, FfbLoop, ForceFeedback, open_ff_wheel
from clients.joystick import (
    ButtonEdges,
    JoystickError,
    PygameJoystick,
    VirtualJoystick,
    check_device,
    list_joysticks,
    load_joystick_profile,
    load_joystick_script,
    map_axes,
)
from clients.keyboard import (
    HELD_ACTIONS,
    KEY_BINDINGS,
    KEY_HELP,
    KEY_HELP_LINES,
    KeyboardModel,
    RawTerminal,
    load_keyboard_profile,
)
from clients.profile import ProfileError
from clients.road_view import RoadView
from clients.world import WorldWatch, traffic_text
from simserver.wire import protocol as proto

PROG = "simserver-driver"
REPO_CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "clients"
DEFAULT_KEYBOARD_PROFILE = REPO_CONFIGS / "keyboard.yaml"
DEFAULT_JOYSTICK_PROFILE = REPO_CONFIGS / "gamepad.yaml"
DEFAULT_RATE_HZ = 200.0
DISPLAY_HZ = 10.0
SERVER_SILENT_S = 2.0
"""No state for this long: the status says so (the liveliness token decides exit)."""
START_HOLD_BRAKE = 1.0
"""Brake the driver holds from launch, and after a reset, until the throttle is pressed."""
START_HOLD_RELEASE_PER_S = 3.0
"""How fast that hold lets go once the throttle is pressed (full to none in 1/3 s, the
keyboard brake key's release rate)."""


AUTO_HOLD_REST_MPS = 0.1
"""The car counts as stopped below this |u| for the auto hold: a braked stop on a hill
rocks on the tires at up to about 0.11 m/s as it settles (the wheels already held), and
the state the client sees is a few milliseconds old, so the threshold must not be so
low that the client misses the stop."""
AUTO_HOLD_MIN_BRAKE = 0.05
"""Brake pedal that, pressed at a stop, arms the auto hold (a pedal past its dead zone)."""
MESSAGE_S = 5.0
"""An event's note (gear, parking brake, a control's reply) is shown this long."""


class StartHold:
    """The brake the driver client holds for the person: a safe start and an auto hold.

    *Start hold.* The server's watchdog brakes the car until the first command arrives; a
    driver that then sends the pedals at rest in D releases those brakes, and a car on a
    hill rolls away before anyone has touched a key (on 10 %, back to -10 km/h within
    3 s). So the commands carry at least ``level`` of brake until the first throttle input
    (any non-zero throttle: a held key, a pedal past its dead zone).

    *Auto hold* (on by default, ``auto``): as in real cars, a stop made with the foot
    brake is held after the pedal is let go: once the car is stopped
    (``|u| < AUTO_HOLD_REST_MPS``) with the brake pressed (``>= AUTO_HOLD_MIN_BRAKE``) and
    no throttle, the hold engages again at ``level``. On 10 % a released keyboard brake
    otherwise rolled the manual car back at -2.19 m/s within 3 s (issue 32).

    Either hold lets go when the throttle is pressed and fades out at ``release_per_s``
    while the throttle comes in, so a hill start does not roll back first. Steering, gear
    and parking-brake inputs do not release it. Pure (no clock of its own): the driver
    feeds it each sample.

    Parameters
    ----------
    level : float
        Brake held while engaged, in [0, 1].
    release_per_s : float
        Fade-out rate once released (brake per second).
    auto : bool
        Auto hold on.
    """

    def __init__(self, level: float = START_HOLD_BRAKE,
                 release_per_s: float = START_HOLD_RELEASE_PER_S, auto: bool = True) -> None:
        self.level = level
        self.release_per_s = release_per_s
        self.auto = auto
        self.engaged = True
        self.reason = "start"  # why it is engaged: "start" (launch, reset, load) or "auto"
        self.brake = level

    def arm(self) -> None:
        """Hold again (after a reset or a load: the car is back at rest at a start)."""
        self.engaged = True
        self.reason = "start"
        self.brake = self.level

    def set_auto(self, on: bool) -> None:
        """Turn the auto hold on or off; off also lets go of an auto hold now engaged (it
        fades out as on a throttle press)."""
        self.auto = on
        if not on and self.engaged and self.reason == "auto":
            self.engaged = False

    def apply(self, throttle: float, brake: float, dt_s: float,
              speed_mps: float = math.inf) -> float:
        """The brake to send: the driver's ``brake`` or the hold, whichever is more.
        ``speed_mps`` is the car's ``u`` (``inf`` while unknown: no auto hold)."""
        if self.engaged and throttle > 0.0:
            self.engaged = False
        elif (not self.engaged and self.auto and throttle <= 0.0
              and brake >= AUTO_HOLD_MIN_BRAKE and abs(speed_mps) < AUTO_HOLD_REST_MPS):
            self.engaged = True
            self.reason = "auto"
            self.brake = self.level
        if not self.engaged:
            self.brake = max(0.0, self.brake - self.release_per_s * max(dt_s, 0.0))
        return max(brake, self.brake)

    def status(self, driver_brake: float) -> str:
        """What the screen says of the hold, from its state now (never a stale hint)."""
        if self.engaged:
            why = "auto hold" if self.reason == "auto" else "start hold"
            return f"{why}: the brake is held until you press the throttle"
        if self.brake > driver_brake:
            return "hold letting go as the throttle comes in"
        return f"auto hold {'on: a stop with the brake is held' if self.auto else 'OFF'}"


# ---------------------------------------------------------------------------- sources


class InputSource(Protocol):
    """Where the driver's inputs come from (keyboard or joystick)."""

    label: str

    def sample(self, now_s: float, dt_s: float, speed_mps: float) -> tuple[
            float, float, float, list[str]]:
        """``(steer, throttle, brake, one-shot actions)`` at ``now_s``."""

    def reset(self) -> None:
        """Return the continuous inputs to rest (after a server reset)."""


class KeyboardSource:
    """Keys from a raw terminal through :class:`KeyboardModel`.

    Parameters
    ----------
    terminal : RawTerminal
        The tty in cbreak mode.
    model : KeyboardModel
        Ramps and steering.
    """

    label = "keyboard"

    def __init__(self, terminal: RawTerminal, model: KeyboardModel) -> None:
        self.terminal = terminal
        self.model = model

    def sample(self, now_s: float, dt_s: float, speed_mps: float) -> tuple[
            float, float, float, list[str]]:
        """Read the keys typed since the last call and advance the model."""
        actions = []
        for key in self.terminal.read_keys():
            action = KEY_BINDINGS.get(key)
            if action is None:
                continue
            if action in HELD_ACTIONS:
                self.model.press(action, now_s)
            else:
                actions.append(action)
        self.model.update(now_s, dt_s, speed_mps)
        m = self.model
        return m.steer, m.throttle, m.brake, actions

    def reset(self) -> None:
        """Release every key and pedal."""
        self.model.release_all()


class JoystickSource:
    """A joystick mapped by a profile; a terminal, when there is one, adds one-shot keys.

    Parameters
    ----------
    profile : JoystickProfile
    device : InputDevice
        Opened and checked against the profile.
    terminal : RawTerminal or None
        For ``q``, space, ``x``, gear and parking-brake keys.
    virtual : VirtualJoystick or None
        With ``script``: the scripted SDL device to feed before each poll.
    script : JoystickScript or None
    """

    def __init__(self, profile: Any, device: Any, terminal: RawTerminal | None = None,
                 virtual: Any = None, script: Any = None) -> None:
        self.profile = profile
        self.device = device
        self.terminal = terminal
        self.virtual = virtual
        self.script = script
        self.edges = ButtonEdges(profile)
        self._script_t = -1.0
        self.label = f"joystick {device.name!r} ({profile.name})"

    def sample(self, now_s: float, dt_s: float, speed_mps: float) -> tuple[
            float, float, float, list[str]]:
        """Feed the script (if any), poll the device, map axes and button edges."""
        actions: list[str] = []
        if self.script is not None:
            for frame in self.script.due(self._script_t, now_s):
                for i, v in frame.axes.items():
                    self.virtual.set_axis(i, v)
                for i, down in frame.buttons.items():
                    self.virtual.set_button(i, down)
            self._script_t = now_s
            if now_s >= self.script.end_s:
                actions.append("quit")
        self.device.poll()
        if getattr(self.device, "lost", False):
            raise JoystickError(f"joystick {self.device.name!r} was disconnected")
        steer, throttle, brake = map_axes(self.profile, self.device)
        actions += self.edges.actions(self.device)
        if self.terminal is not None:
            for key in self.terminal.read_keys():
                action = KEY_BINDINGS.get(key)
                if action is not None and action not in HELD_ACTIONS:
                    actions.append(action)
        return steer, throttle, brake, actions

    def reset(self) -> None:
        """Nothing to do: a joystick's position is its own state."""


# ---------------------------------------------------------------------------- status


WHEEL_LABELS = ("fl", "fr", "rl", "rr")
"""The order of the state's per-wheel fields (docs/protocol.md: FL, FR, RL, RR)."""


def ground_text(state: np.void) -> str:
    """The ground under the car, from the state: its grade along the heading (+ = uphill
    ahead) and cross-slope (+ = the left side higher), in per cent (the plane fitted under
    the wheels on a terrain, the road on a plane: ``ground_grade_pct``,
    ``ground_cross_slope_pct``), and which wheels touch it (``wheel_contact``). The pose's
    pitch would also show the body's pitch on its suspension (about 1 degree under full
    throttle or braking), so it is shown apart."""
    contact = [bool(c) for c in state["wheel_contact"]]
    wheels = ("all 4" if all(contact) else " ".join(
        name.upper() for name, on in zip(WHEEL_LABELS, contact, strict=True) if on) or "none")
    return (f"grade {float(state['ground_grade_pct']):+5.1f} %  cross "
            f"{float(state['ground_cross_slope_pct']):+5.1f} %  wheels on ground {wheels}")


class StatusView:
    """The live status block: redrawn in place on a terminal, a line a second otherwise.

    Parameters
    ----------
    out : TextIO
        Where to write (stdout).
    header : str
        First line (connection, mode, rate).
    help_lines : sequence of str
        Key help shown under the status.
    """

    def __init__(self, out: TextIO, header: str, help_lines: Sequence[str]) -> None:
        self.out = out
        self.header = header
        self.help_lines = list(help_lines)
        self.tty = out.isatty()
        self._drawn = 0
        self._last_plain = -math.inf

    def lines(self, d: Driver) -> list[str]:
        """The status text."""
        s, g = d.state, d.diag
        c = d.controls
        drive = (f"driver  steer {c['steer']:+.2f}  throttle {c['throttle']:.2f}  "
                 f"brake {c['brake']:.2f}{' HELD' if d.hold.engaged else ''}  gear "
                 f"{gear_name(c['gear'])}  park {'ON' if c['parking_brake'] else 'off'}  "
                 f"seq {d.seq}")
        if s is None:
            car = ["car     (no state received yet)", "", ""]
            server = ["server  -", ""]
        else:
            u = float(s["u_mps"])
            flags = int(s["flags"])
            names = [n for n, bit in (("WATCHDOG", proto.StateFlag.WATCHDOG),
                                      ("PAUSED", proto.StateFlag.PAUSED),
                                      ("HOLD", proto.StateFlag.BRAKE_HOLD)) if flags & bit]
            yaw = float(s["yaw_rad"])
            heading = (math.degrees(yaw) + 180.0) % 360.0 - 180.0
            car = [f"car     speed {3.6 * u:+7.1f} km/h ({u:+7.2f} m/s)  gear "
                   f"{gear_name(int(s['gear']))}  park "
                   f"{'ON' if s['parking_brake'] else 'off'}",
                   f"        {ground_text(s)}",
                   f"        nose up {-math.degrees(float(s['pitch_rad'])):+5.1f} deg  heading "
                   f"{heading:+6.1f} deg"]
            road = d.road.line(float(s["x_m"]), float(s["y_m"]))
            if road is not None:
                car.append(road)
            age = float(s["cmd_age_s"])
            silent = time.monotonic() - d.state_wall
            server = [f"server  t {float(s['sim_time_s']):9.3f} s  [{' '.join(names) or 'ok'}]"
                      + (f"  NO STATE FOR {silent:.0f} s" if silent > SERVER_SILENT_S else ""),
                      f"        applied steer {float(s['steer']):+.2f} throttle "
                      f"{float(s['throttle']):.2f} brake {float(s['brake']):.2f}  cmd age "
                      f"{'-' if age < 0 else f'{1e3 * age:.0f} ms'}  cmd->state "
                      f"{'-' if d.latency_ms is None else f'{d.latency_ms:.2f} ms'}"]
        if g is None:
            health = ["health  (no diagnostics yet)", ""]
        else:
            health = [f"health  tick late p99 {float(g['lateness_p99_us']):.0f} us  max "
                      f"{float(g['lateness_max_us']):.0f} us  period p99 "
                      f"{float(g['period_p99_us']):.0f} us  cpu {float(g['cpu_percent']):.0f} %",
                      f"        overruns {int(g['overruns'])}  skipped "
                      f"{int(g['skipped_ticks'])}  rejected {int(g['cmd_rejected'])}  stale "
                      f"{int(g['cmd_stale'])}  watchdog trips {int(g['watchdog_trips'])}"]
        traffic = traffic_text(d.world.poll(), d.conn.ep.keys.vehicle)
        traffic_lines = [f"traffic {traffic}"] if traffic else []  # other cars, if any
        hold = f"hold    {d.hold.status(d.source_brake)}"
        if s is not None and int(s["flags"]) & proto.StateFlag.HILL_HOLD:
            hold += ("  |  HILL-START ASSIST holds the brakes for a moment after the pedal "
                     "is released, then lets go: press the throttle")
        return [self.header, *car, drive, hold, *server, *health, *traffic_lines,
                f"note    {d.message}", *self.help_lines]

    def draw(self, d: Driver, now_s: float) -> None:
        """Redraw (terminal) or print one line per second (pipe)."""
        lines = self.lines(d)
        if not self.tty:
            if self._last_plain == -math.inf:
                self.out.write(self.header + "\n")
            if now_s - self._last_plain >= 1.0:
                self._last_plain = now_s
                self.out.write(" | ".join(x.strip() for x in lines[1:10] + [
                    x for x in lines[10:11] if x.startswith("traffic")]) + "\n")
                self.out.flush()
            return
        width = max(20, shutil.get_terminal_size((120, 24)).columns - 1)
        parts = []
        if self._drawn:
            parts.append(f"\x1b[{self._drawn}A\r")  # cursor up (VT100), column 0
        for line in lines:
            parts.append("\x1b[2K" + line[:width] + "\n")
        self._drawn = len(lines)
        self.out.write("".join(parts))
        self.out.flush()


# ---------------------------------------------------------------------------- driver


class Driver:
    """The command loop: sample the inputs, send a command, read state and diagnostics.

    Parameters
    ----------
    conn : Connection
        Checked connection to the server.
    source : InputSource
        Keyboard or joystick.
    rate_hz : float
        Command rate.
    gear : int
        Initial gear code.
    out : TextIO
        Status output.
    """

    def __init__(self, conn: Connection, source: InputSource, rate_hz: float, gear: int,
                 out: TextIO) -> None:
        self.conn = conn
        self.source = source
        self.rate_hz = rate_hz
        self.controls: dict[str, Any] = {"steer": 0.0, "throttle": 0.0, "brake": 0.0,
                                         "gear": gear, "parking_brake": False}
        self.seq = 0
        self.state: np.void | None = None
        self.state_wall = time.monotonic()
        self.diag: np.void | None = None
        self._latencies: deque[float] = deque(maxlen=200)
        self._seen_seq = -1
        self.hold = StartHold()
        self._message = ""
        self._message_t = -math.inf
        self.source_brake = 0.0  # the pedal the person applies, before the hold
        self.sent = 0
        ep = conn.ep
        self.pub = ep.declare_command_publisher()
        self.states = ep.declare_state_inbox(capacity=256)
        # states another publisher sent (no ACL): dropped and counted on the status line
        self.filter = state_filter(conn, PROG, out=None)
        self._filtered_seen = (0, 0)
        self.diags = ep.declare_diag_inbox(capacity=16)
        self.world = WorldWatch(ep, ep.keys.prefix)  # the other cars (clients.world)
        self.presence = ServerPresence(ep)
        help_lines = list(KEY_HELP_LINES) if isinstance(source, KeyboardSource) else \
            ["keys    q quit, space pause/resume, x reset, 1-4 gear P R N D, h parking brake, "
             "b auto hold"]
        self.view = StatusView(out, self._header(conn.config), help_lines)
        self.road = RoadView()  # on an OpenDRIVE scene: road, lane, s, edge (clients.road_view)
        self.road.follow(conn.config)

    def _header(self, config: dict[str, Any]) -> str:
        """The status block's first line: where, which vehicle and scene, input, rate."""
        vehicle = config.get("vehicle", {}).get("name", "?")
        scene = config.get("scene", {}).get("path", "?")
        return (f"simserver driver  {self.conn.where}  vehicle {vehicle}  scene {scene}  "
                f"{self.source.label}  {self.rate_hz:g} Hz")

    def _new_run(self) -> None:
        """The server started a new run (a reset or a load, by this driver or another
        client; a restarted server): the car is at a start again, so the hold is armed
        as at launch, the keys' pedals return to rest, and the header is brought up to
        date from ``get_config``, asked off this loop (its reply may take a while)."""
        self.hold.arm()
        self.source.reset()
        self.message = "a new run on the server (reset or load): the hold is armed again"
        threading.Thread(target=self._refresh_config, name="driver-get-config",
                         daemon=True).start()

    def _refresh_config(self) -> None:
        try:
            reply = self.conn.ep.request("get_config", timeout_s=5.0)
            if not reply.get("ok"):
                raise proto.ProtocolError("get_config", short_repr(reply.get("error")))
            config = check_server_config(reply.get("config"))
        except (TimeoutError, proto.ProtocolError) as exc:
            self.message = f"get_config after the new run: {exc}"
            return
        self.conn.config = config
        self.view.header = self._header(config)
        self.road.follow(config)

    @property
    def message(self) -> str:
        """The note of the last event, for ``MESSAGE_S`` after it (then nothing: the
        screen never keeps a hint that is no longer true)."""
        return self._message if time.monotonic() - self._message_t < MESSAGE_S else ""

    @message.setter
    def message(self, text: str) -> None:
        self._message, self._message_t = text, time.monotonic()

    # ------------------------------------------------------------------ actions
    def _control(self, name: str) -> dict[str, Any] | None:
        try:
            reply = self.conn.ep.request(name, timeout_s=1.0)
        except (TimeoutError, proto.ProtocolError) as exc:
            self.message = f"{name}: {exc}"
            return None
        if not reply.get("ok"):
            self.message = f"{name}: {reply.get('error')}"
            return None
        return reply

    def act(self, action: str) -> bool:
        """Run a one-shot action; returns False for ``quit``."""
        c = self.controls
        if action == "quit":
            return False
        if action.startswith("gear_") and action[5:] in proto.Gear.__members__:
            c["gear"] = int(proto.Gear[action[5:]])
            self.message = f"gear {action[5:]}"
        elif action in ("gear_next", "gear_prev"):
            step = 1 if action == "gear_next" else -1
            c["gear"] = min(int(proto.Gear.D), max(int(proto.Gear.P), c["gear"] + step))
            self.message = f"gear {gear_name(c['gear'])}"
        elif action == "parking_brake":
            c["parking_brake"] = not c["parking_brake"]
            self.message = f"parking brake {'on' if c['parking_brake'] else 'off'}"
        elif action == "auto_hold":
            self.hold.set_auto(not self.hold.auto)
            self.message = f"auto hold {'on' if self.hold.auto else 'off'}"
        elif action == "reset":
            if self._control("reset") is not None:
                self.source.reset()
                self.hold.arm()
                self.message = "reset to the scene's start"
        elif action == "pause":
            paused = self.state is not None and bool(int(self.state["flags"])
                                                     & proto.StateFlag.PAUSED)
            name = "resume" if paused else "pause"
            if self._control(name) is not None:
                self.message = "resumed" if paused else "paused (space resumes)"
        return True

    # ------------------------------------------------------------------ loop
    def poll_states(self) -> None:
        """Take the states received so far (called every ~0.5 ms while the loop waits).

        The command-to-state latency is measured as the protocol describes it: the time
        from a command's ``sender_time_ns`` to the arrival of the first state that
        applied it (a new ``last_cmd_seq``), seen within this poll interval.
        """
        payloads = self.states.drain_newest()
        now_ns = time.monotonic_ns()
        taken = self.filter.take(payloads, now_ns / 1e9)
        counts = (self.filter.rejected, self.filter.out_of_order)
        if counts != self._filtered_seen:
            self._filtered_seen = counts
            self.message = f"warning: {self.filter.summary()}"
        if not taken:
            return
        if self.state is not None and any(kind == "restart" for _, _, kind in taken):
            self._new_run()
        state = proto.decode_state(taken[-1][0])
        self.state = state
        self.state_wall = now_ns / 1e9
        seq = int(state["last_cmd_seq"])
        sent_ns = int(state["last_cmd_sender_time_ns"])
        if seq != self._seen_seq and sent_ns:
            self._seen_seq = seq
            self._latencies.append((now_ns - sent_ns) / 1e6)

    def _read_diagnostics(self) -> None:
        diags = [d for d in self.diags.drain_newest() if len(d) == proto.DIAGNOSTICS_SIZE]
        if diags:
            raw = np.frombuffer(diags[-1], dtype=np.uint8).reshape(1, -1)
            if proto.invalid_fields(raw, "diagnostics")[0] >= 0:
                self.message = "warning: dropped a Diagnostics message no server sends"
                return
            self.diag = proto.decode_diagnostics(diags[-1])

    @property
    def latency_ms(self) -> float | None:
        """Median command-to-state latency of the last (up to) 200 commands."""
        return float(np.median(self._latencies)) if self._latencies else None

    def run(self, stop: StopFlag) -> int:
        """Loop until quit, a signal, or the server going away; returns the exit code."""
        pacer = RatePacer(self.rate_hz)
        pacer.start()
        last_t = 0.0
        next_draw = 0.0
        next_alive = 0.5
        c = self.controls
        while not stop.stopped:
            t = pacer.wait(self.poll_states)
            speed = float(self.state["u_mps"]) if self.state is not None else 0.0
            steer, throttle, brake, actions = self.source.sample(t, t - last_t, speed)
            held_speed = speed if self.state is not None else math.inf
            self.source_brake = brake
            brake = self.hold.apply(throttle, brake, t - last_t, held_speed)
            last_t = t
            c["steer"], c["throttle"], c["brake"] = steer, throttle, brake
            if not all(self.act(a) for a in actions):
                self.message = "quit"
                break
            self.seq = (self.seq + 1) & 0xFFFFFFFF
            now_ns = time.monotonic_ns()
            self.pub.put(proto.encode_command(
                steer, throttle, brake, gear=c["gear"], parking_brake=c["parking_brake"],
                seq=self.seq, sender_time_ns=now_ns))
            self.sent += 1
            self._read_diagnostics()
            if t >= next_alive:
                next_alive = t + 0.25
                was_present = self.presence.present
                gone = self.presence.gone()
                if not self.presence.present:
                    self.message = "the server's liveliness token is gone: waiting for it"
                elif not was_present:
                    self.message = "the server's liveliness token is back"
                if gone:
                    self.message = "the server went away"
                    self.view.draw(self, t)
                    print(f"{PROG}: the server's liveliness token disappeared "
                          f"({self.conn.where}): stopping", file=sys.stderr)
                    return EXIT_FAILED
            if t >= next_draw:
                next_draw = t + 1.0 / DISPLAY_HZ
                self.view.draw(self, t)
        if stop.signal_name:
            self.message = f"stopped by {stop.signal_name}"
        self.view.draw(self, math.inf)
        return EXIT_OK


# ---------------------------------------------------------------------------- main


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``simserver-driver`` (``python -m clients.driver``)."""
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Drive a simserver car from a terminal keyboard (works over SSH) or a "
        "game controller / steering wheel (pygame). Sends commands at a steady rate and "
        "shows speed, gear, slope and the server's health. The brake is held from the "
        "start (and after a reset) until the throttle is first pressed, so a car on a hill "
        "does not roll away. Keys: " + KEY_HELP,
        epilog="Exit codes: 0 normal quit, 1 the server went away, 2 bad command line or "
        "profile, 3 no server answered. docs/clients.md has the step-by-step guide.",
    )
    parser.add_argument("--input", choices=("keyboard", "joystick"), default="keyboard",
                        help="input device (default keyboard)")
    parser.add_argument("--profile", metavar="FILE", default=None,
                        help="input profile YAML (default configs/clients/keyboard.yaml, or "
                        "configs/clients/gamepad.yaml with --input joystick; "
                        "configs/clients/wheel.yaml for a wheel)")
    add_rate_arg(parser, DEFAULT_RATE_HZ)
    parser.add_argument("--gear", choices=tuple(g.name for g in proto.Gear), default="D",
                        help="gear at start (default D)")
    parser.add_argument("--list-joysticks", action="store_true",
                        help="list the joysticks SDL sees and exit")
    parser.add_argument("--probe", action="store_true",
                        help="show the joystick's raw axes and buttons and the mapped "
                        "inputs (no server needed); Ctrl-C ends")
    parser.add_argument("--virtual-joystick", metavar="SCRIPT", default=None,
                        help="attach SDL's virtual joystick and play SCRIPT on it "
                        "(implies --input joystick; the driver quits at the script's end)")
    add_connection_args(parser)
    return parser


def _joystick_setup(args: argparse.Namespace) -> JoystickSource:
    """Load the profile (and script), open the device and check it against the profile."""

    try:
        profile = load_joystick_profile(args.profile or DEFAULT_JOYSTICK_PROFILE)
        script = load_joystick_script(args.virtual_joystick) if args.virtual_joystick \
            else None
    except ProfileError as exc:
        raise ClientError(str(exc)) from None
    try:
        if script is not None:
            virtual = VirtualJoystick(max(profile.axes_needed, script.n_axes),
                                      max(profile.buttons_needed, script.n_buttons))
            device = PygameJoystick(virtual.device_index)
        else:
            virtual = None
            device = PygameJoystick.open(profile)
        check_device(profile, device)
    except JoystickError as exc:
        raise ClientError(str(exc)) from None
    return JoystickSource(profile, device, None, virtual, script)


def _probe(args: argparse.Namespace, stop: StopFlag) -> int:
    try:
        profile = load_joystick_profile(args.profile or DEFAULT_JOYSTICK_PROFILE)
        device = PygameJoystick.open(profile)
    except (ProfileError, JoystickError) as exc:
        raise ClientError(str(exc)) from None
    print(f"{device.name!r}: {device.num_axes()} axes, {device.num_buttons()} buttons; "
          f"profile {profile.path} (Ctrl-C ends)", flush=True)
    try:
        check_device(profile, device)
        usable = True
    except JoystickError as exc:
        print(f"warning: {exc}; showing raw values only", flush=True)
        usable = False
    while not stop.stopped:
        device.poll()
        axes = " ".join(f"{i}:{device.axis(i):+.2f}" for i in range(device.num_axes()))
        down = [str(i) for i in range(device.num_buttons()) if device.button(i)]
        mapped = ""
        if usable:
            steer, throttle, brake = map_axes(profile, device)
            mapped = f" | steer {steer:+.2f} throttle {throttle:.2f} brake {brake:.2f}"
        print(f"axes {axes} | buttons down [{' '.join(down)}]{mapped}", flush=True)
        time.sleep(0.1)
    return EXIT_OK


def _run(args: argparse.Namespace) -> int:
    check_rate(args.rate)
    if args.virtual_joystick:
        args.input = "joystick"
    with StopFlag() as stop:
        if args.list_joysticks:
            try:
                names = list_joysticks()
            except JoystickError as exc:
                raise ClientError(str(exc)) from None
            for i, name in enumerate(names):
                print(f"{i}: {name}")
            if not names:
                print("no joystick found")
            return EXIT_OK
        if args.probe:
            return _probe(args, stop)
        has_tty = os.isatty(sys.stdin.fileno()) if sys.stdin is not None else False
        if args.input == "keyboard":
            if not has_tty:
                raise ClientError("keyboard mode needs a terminal on stdin (run it in a "
                                  "terminal, or use --input joystick)", EXIT_USAGE)
            try:
                kb_profile = load_keyboard_profile(args.profile or DEFAULT_KEYBOARD_PROFILE)
            except ProfileError as exc:
                raise ClientError(str(exc)) from None
        with ExitStack() as stack:
            joystick = _joystick_setup(args) if args.input == "joystick" else None
            conn = connect(args, PROG)
            stack.callback(conn.close)
            scene = conn.config.get("scene", {}).get("path", "?")
            vehicle = conn.config.get("vehicle", {}).get("name", "?")
            print(f"{PROG}: connected to {conn.where}: vehicle {vehicle}, scene {scene}",
                  flush=True)
            terminal = stack.enter_context(RawTerminal()) if has_tty else None
            if joystick is None:
                assert terminal is not None
                source: InputSource = KeyboardSource(terminal, KeyboardModel(kb_profile))
            else:
                joystick.terminal = terminal
                source = joystick
            driver = Driver(conn, source, args.rate, int(proto.Gear[args.gear]), sys.stdout)
            ffb = joystick.profile.force_feedback if joystick is not None else None
            if ffb is not None and ffb.enabled and joystick.script is None:
                try:  # the wheel's force feedback, on its own thread (clients.ffb)
                    loop = FfbLoop(conn.ep.declare_state_inbox(capacity=16),
                                   ForceFeedback(open_ff_wheel(ffb.device), ffb),
                                   state_filter(conn, PROG, out=None)).start()
                    stack.callback(loop.stop)
                    print(f"{PROG}: force feedback on ({ffb.device})", flush=True)
                except (FfbError, OSError) as exc:
                    print(f"{PROG}: no force feedback: {exc}", file=sys.stderr, flush=True)
            try:
                code = driver.run(stop)
            except JoystickError as exc:  # a device lost mid-run
                raise ClientError(f"{exc}; the server's watchdog holds the car",
                                  EXIT_FAILED) from None
            if code == EXIT_OK:
                print(f"{PROG}: sent {driver.sent} commands; stopped sending, the server's "
                      "watchdog now holds the car", flush=True)
            return code


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``simserver-driver``; returns the exit code."""
    return client_main(PROG, build_parser, _run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
