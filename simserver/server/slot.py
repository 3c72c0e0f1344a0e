"""One car served by the live server: the simulation it steps and what belongs to it alone.

A :class:`VehicleSlot` holds, for one vehicle id, everything the fixed-rate loop
(:mod:`simserver.server.loop`) must not share between cars: its keys, the command
arbitration (:class:`CommandArbiter`), the :class:`Watchdog`, the run state (tick,
pause, pending steps), the counters of its diagnostics, its state record and its command
log. It knows no transport and no clock: the loop hands it the payloads it drained and
the tick's time in nanoseconds, and publishes the bytes it returns. So the whole logic
runs in-process on a fake clock (``tests/test_server_logic.py``).

The simulation is called through its public API only (``x``, ``inputs``, ``out``, ``vp``,
``scene``, ``road``, ``axes``, ``pose``, ``dt_s``, ``step()``, ``reset(pose)``,
``prepare_reset(...)``, ``prepare_load(scene)``, ``commit(prepared)``, ``set_road(...)``,
``load(scene)``, ``warm_up()``, ``update_pose()``); the rules it
applies to commands and controls are those of ``docs/protocol.md`` (sections 2.1 and 3).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from simserver.adapters.opendrive import LaneStartError, lane_start
from simserver.adapters.validate import ConfigError, confined_to, display_path, short_repr
from simserver.core import layout as L
from simserver.core.contact import CC_ACTIVE, CC_FORCE_X_N, CC_FORCE_Y_N
from simserver.core.terrain import TERRAIN_KINDS, TERRAIN_PLANE
from simserver.server.load_worker import release_later
from simserver.server.logfile import RateLimitedLog
from simserver.sim.scene import Scene
from simserver.sim.scene_files import load_scene
from simserver.wire import protocol as proto
from simserver.wire.state_schema import SERVER_FIELDS, fill_record

if TYPE_CHECKING:
    from simserver.server.command_log import CommandLog
    from simserver.server.config import ServerConfig
    from simserver.server.state_frame import StateFrame
    from simserver.sim.simulation import PreparedStart

log = logging.getLogger("simserver.server")

COUNTER_NAMES: tuple[str, ...] = ("cmd_received", "cmd_rejected", "cmd_clamped",
                                  "cmd_stale", "state_published", "watchdog_trips",
                                  "nonfinite_stops", "cmd_dropped", "ctl_received", "ctl_busy",
                                  "publish_slow", "contact_events", "contact_events_lost")
"""The slot's cumulative counters, in the order of the ``stopped`` line."""

COMPUTED_STATE_FIELDS: tuple[str, ...] = (
    "flags", "tick", "sim_time_s", "last_cmd_seq", "last_cmd_sender_time_ns", "cmd_age_s",
    "brake_held", "ground_grade_pct", "ground_cross_slope_pct", "contact_force_n",
    "car_contact")
"""The VehicleState fields ``fill_state`` computes itself (``source="server"`` in
``protocol.STATE_FIELDS``); every other field is copied by ``state_schema.fill_record``."""
if set(COMPUTED_STATE_FIELDS) != set(SERVER_FIELDS):
    raise ImportError("protocol.STATE_FIELDS' server-computed fields "
                      f"{sorted(SERVER_FIELDS)} are not those VehicleSlot.fill_state "
                      f"computes {sorted(COMPUTED_STATE_FIELDS)}")


class SimulationAPI(Protocol):
    """What a slot uses of the simulation (``simserver.sim.simulation.Simulation``): nothing
    else."""

    x: np.ndarray
    inputs: np.ndarray
    out: np.ndarray
    vp: np.ndarray
    pose: np.ndarray
    axes: Any
    dt_s: float
    scene: Scene
    road: dict[str, float]

    def step(self) -> None: ...
    def reset(self, pose: dict[str, float] | None, u_mps: float | None = None) -> None: ...
    def set_road(self, grade_pct: float, cross_slope_pct: float,
                 friction_scale: float) -> None: ...
    def load(self, scene: Scene) -> None: ...
    def prepare_reset(self, pose: dict[str, float] | None,
                      u_mps: float | None = None) -> PreparedStart: ...
    def prepare_load(self, scene: Scene) -> PreparedStart: ...
    def commit(self, prepared: PreparedStart) -> Any: ...
    def warm_up(self, live: bool = False) -> None: ...
    def update_pose(self) -> np.ndarray: ...
    def contact_output(self) -> np.ndarray: ...


def ground_slopes_pct(sim: SimulationAPI, yaw_rad: float) -> tuple[float, float]:
    """The slopes of the ground under the car along and across its heading ``yaw_rad``
    (%; + = uphill ahead, + = the left side higher): the plane fitted under its wheels
    (the state's ``REF_*`` slots, docs/model.md section 11), or on the plane kind the road,
    turned to the heading as the protocol defines it (``protocol.ground_slopes_pct``)."""
    if sim.scene.terrain.kind == TERRAIN_PLANE:
        grade, cross = sim.road["grade_pct"], sim.road["cross_slope_pct"]
    else:
        grade, cross = sim.x[L.REF_GRADE_PCT], sim.x[L.REF_CROSS_SLOPE_PCT]
    return proto.ground_slopes_pct(grade, cross, yaw_rad)


# The state's flag bits as plain ints: ``int | StateFlag`` builds an enum member each time
# (about 0.5-3 us; fill_state runs for every published state, 5 cars a tick at 32 cars)
_FLAG_WATCHDOG, _FLAG_PAUSED, _FLAG_BRAKE_HOLD, _FLAG_HILL_HOLD, _FLAG_CATCHUP, _FLAG_FAULT, \
    _FLAG_SKIPPED = (int(proto.StateFlag[name]) for name in (
        "WATCHDOG", "PAUSED", "BRAKE_HOLD", "HILL_HOLD", "CATCHUP", "FAULT", "SKIPPED"))


class CommandArbiter:
    """Decode, validate and arbitrate the driver commands of one car (docs/protocol.md 2.1).

    Rules: a payload that does not decode is rejected (counted, logged at a bounded rate);
    the newest valid command of a tick wins; a command whose ``seq`` is not newer than
    the last applied one (RFC 1982 serial arithmetic, so the u32 wrap is fine) is stale.
    ``commanded`` is what the driver asked for, before the watchdog.
    """

    def __init__(self, counters: dict[str, int], initial_inputs: np.ndarray) -> None:
        self.counters = counters
        self.last_seq: int | None = None  # the newer-than rule's reference (None: any is)
        self.last_applied_seq = 0  # the state's last_cmd_seq: 0 only before the first
        self.last_seen_seq: int | None = None  # of the last valid command received
        self.last_cmd_ns: int | None = None  # loop clock when the last valid one arrived
        self.last_sender_ns = 0
        self.commanded = initial_inputs.copy()
        self.reject_log = RateLimitedLog(logger=log)

    def take(self, payloads: list[bytes], now_ns: int, buffer_full: bool = False) -> None:
        """Apply the newest valid command among ``payloads`` (oldest first), if any.

        ``buffer_full``: the receive buffer was full, so older commands were overwritten
        in it; they are counted in ``cmd_dropped`` from the ``seq`` gap between the last
        command seen before and the first one here (exact for one driver numbering its
        commands one by one, as the protocol asks).
        """
        counters = self.counters
        newest: proto.DriverCommand | None = None
        first = True
        for payload in payloads:
            counters["cmd_received"] += 1
            try:
                cmd = proto.decode_command(payload)
            except proto.ProtocolError as exc:
                counters["cmd_rejected"] += 1
                self.reject_log.warn(f"rejected command: {exc}", now_ns * 1e-9)
                continue
            if first:
                first = False
                if buffer_full and self.last_seen_seq is not None:
                    gap = (cmd.seq - self.last_seen_seq - 1) & 0xFFFFFFFF
                    if gap < 0x80000000:  # newer: the commands in between were overwritten
                        counters["cmd_dropped"] += gap
            self.last_seen_seq = cmd.seq
            if cmd.clamped:
                counters["cmd_clamped"] += 1
            if self.last_seq is not None and not proto.seq_newer(cmd.seq, self.last_seq):
                counters["cmd_stale"] += 1
                continue
            if newest is None or proto.seq_newer(cmd.seq, newest.seq):
                if newest is not None:
                    counters["cmd_stale"] += 1  # superseded within the same tick
                newest = cmd
            else:
                counters["cmd_stale"] += 1
        if newest is None:
            return
        self.last_seq = newest.seq
        self.last_applied_seq = newest.seq
        self.last_cmd_ns = now_ns
        self.last_sender_ns = newest.sender_time_ns
        c = self.commanded
        c[L.IN_STEER] = newest.steer
        c[L.IN_THROTTLE] = newest.throttle
        c[L.IN_BRAKE] = newest.brake
        c[L.IN_PARKING_BRAKE] = 1.0 if newest.parking_brake else 0.0
        c[L.IN_GEAR] = float(newest.gear)

    def cmd_age_s(self, now_ns: int) -> float:
        """Time since the last valid command arrived; -1 before the first."""
        return -1.0 if self.last_cmd_ns is None else (now_ns - self.last_cmd_ns) * 1e-9


class Watchdog:
    """Hold the car when the driver goes silent (docs/protocol.md 2.1, rule 3).

    With no valid command for ``timeout_s`` the applied throttle is 0 and the brake at
    least ``brake`` (steer and gear kept). Engaged from the start: no command yet.
    """

    def __init__(self, timeout_s: float, brake: float) -> None:
        self.timeout_s = timeout_s
        self.timeout_ns = int(round(timeout_s * 1e9))
        self.brake = brake
        self.engaged = True

    def update(self, last_cmd_ns: int | None, now_ns: int) -> bool:
        """Engage or release for the tick at ``now_ns``; True when it has just engaged."""
        expired = last_cmd_ns is None or now_ns - last_cmd_ns > self.timeout_ns
        tripped = expired and not self.engaged
        if tripped:
            log.warning("watchdog: no valid command for %.0f ms, holding the car",
                        1e3 * self.timeout_s)
        elif not expired and self.engaged:
            log.info("watchdog released: commands resumed")
        self.engaged = expired
        return tripped

    def hold(self, inputs: np.ndarray) -> None:
        """Throttle off and at least the watchdog's brake, in place."""
        inputs[L.IN_THROTTLE] = 0.0
        inputs[L.IN_BRAKE] = max(inputs[L.IN_BRAKE], self.brake)


class VehicleSlot:
    """One vehicle of the server: a simulation plus its commands, watchdog, state and log.

    Parameters
    ----------
    cfg : ServerConfig
        Its settings (vehicle id and prefix, scene, watchdog, the folders ``load`` may
        read, and the timing reported by ``get_config``).
    sim : SimulationAPI
        The simulation it steps (built from ``cfg.scene``).
    command_log : CommandLog, optional
        Where applied inputs and physics-changing controls are written.

    The loop calls, every tick: :meth:`take_commands`, :meth:`apply_inputs`,
    :meth:`advance`, :meth:`check_finite`, :meth:`state_payload` (at the state rate)
    and the ``ctl_*`` handlers through its control table.
    """

    def __init__(self, cfg: ServerConfig, sim: SimulationAPI,
                 command_log: CommandLog | None = None) -> None:
        self.cfg = cfg
        self.keys = proto.vehicle_keys(cfg.prefix, cfg.vehicle_id)
        self.sim = sim
        self.scene_path = cfg.scene
        self.command_log = command_log
        # the ROS 2 adapter's supervisor's status (get_config's "ros2"), set by the server
        self.ros2_status: Callable[[], dict[str, Any]] | None = None
        # the load worker's readiness (get_config's "load_worker"), set by the server when
        # it starts the worker's warm-up; None where loads run inline (no worker)
        self.load_worker_status: Callable[[], dict[str, Any]] | None = None
        self.counters = dict.fromkeys(COUNTER_NAMES, 0)
        self.arbiter = CommandArbiter(self.counters, sim.inputs)
        self.watchdog = Watchdog(cfg.watchdog_s, cfg.watchdog_brake)
        self.paused = False
        self.steps_to_run = 0  # ticks left of a 'step' control while paused
        self.tick = 0  # ticks since start, reset or load (the protocol's tick)
        self.steps_total = 0  # physics steps since start (the command log's clock)
        self.record = proto.new_state_record()
        self.fault = False  # the state went non-finite in this episode (since start,
        # reset or load): flags bit 4, logged once
        self.state_finite = True  # x and out were finite at the last check_finite
        self._stopped = False  # stopped by check_finite and not stepped since
        self._last_finite: bytes | None = None  # the newest finite state record published
        self._braking = np.zeros(4, dtype=bool)
        self._held = np.zeros(4, dtype=bool)
        self.skipped_before = False  # deadlines were skipped since the last state
        # a car of a world of several (simserver.server.fleet; docs/protocol.md 5.1): its loads
        # change its vehicle only, on the world's terrain, from its own start (set by the
        # loop when it serves more than one car)
        self.shared_world = False
        self.stepping = False  # this tick: the car takes part in the world's step
        self.driven_by = "client"  # protocol.DRIVEN_BY_CODES
        self.keyframes: np.ndarray | None = None  # driven_by keyframes: inputs per tick
        self.final_state: np.ndarray | None = None  # its state when taken out of the world

    def drive_by_keyframes(self, table: np.ndarray) -> None:
        """Drive this car by an input table (``simserver.server.cars_config.keyframe_table``): row
        ``tick`` at each tick, the last row after the end; commands are not applied (each
        counted in ``cmd_rejected``) and the watchdog does not act."""
        self.keyframes = table
        self.driven_by = "keyframes"
        self.watchdog.engaged = False

    def drive_by_driver(self) -> None:
        """The built-in driver drives this car (``driven_by: driver``,
        ``simserver.server.live_drivers``): the loop's ``core.driver.drive`` writes its
        inputs each tick before the world's step; commands are not applied (each counted in
        ``cmd_rejected``; the world's ``get_config`` says who drives it) and the watchdog
        does not act."""
        self.driven_by = "driver"
        self.watchdog.engaged = False

    @property
    def last_published(self) -> bytes | None:
        """The newest finite VehicleState published (None before the first)."""
        return self._last_finite

    # ------------------------------------------------------------------ each tick
    def take_commands(self, payloads: list[bytes], now_ns: int,
                      buffer_full: bool = False) -> None:
        """Arbitrate the command payloads drained this tick (``buffer_full``: see
        :meth:`CommandArbiter.take`)."""
        if self.driven_by != "client":  # a keyframed or driven car takes no commands
            self.counters["cmd_received"] += len(payloads)
            self.counters["cmd_rejected"] += len(payloads)
            return
        self.arbiter.take(payloads, now_ns, buffer_full)

    def apply_inputs(self, now_ns: int) -> None:
        """Commanded inputs through the watchdog into the simulation's input vector (a
        keyframed car: its table's row of this tick; a car of the built-in driver: nothing,
        the loop's ``drive`` writes them)."""
        if self.driven_by == "driver":
            return
        if self.keyframes is not None:
            table = self.keyframes
            self.sim.inputs[:] = table[min(self.tick, len(table) - 1)]
            return
        if self.watchdog.update(self.arbiter.last_cmd_ns, now_ns):
            self.counters["watchdog_trips"] += 1
            self.arbiter.last_seq = None  # a restarted client may begin its sequence anew
        inputs = self.sim.inputs
        inputs[:] = self.arbiter.commanded
        if self.watchdog.engaged:
            self.watchdog.hold(inputs)

    def advance(self, step: bool = True) -> bool:
        """Step the simulation once unless paused with no ``step`` pending; True if stepped.

        ``step=False``: the car's part of a world step only (its inputs logged, its ticks
        counted); the loop then steps the world once for every car (``simserver.server.loop``).
        """
        if self.paused and self.steps_to_run <= 0:
            return False
        if self.command_log is not None:
            self.command_log.log_inputs(self.steps_total, self.sim.inputs)
        if step:
            self.sim.step()
        self._stopped = False
        self.tick += 1
        self.steps_total += 1
        if self.paused:
            self.steps_to_run -= 1
        return True

    def state_payload(self, now_ns: int, catching_up: bool,
                      frame: StateFrame | None = None, row: int = -1) -> bytes | None:
        """The VehicleState of this tick (docs/protocol.md 2.2), counted as published.

        Never a non-finite one: a state whose simulation (``check_finite``) or world pose
        and ground slopes are not finite is replaced by the newest finite state published,
        with this tick's flags (``FAULT`` among them), tick and command fields; None (no
        state to publish) if there was none yet (docs/reliability.md). ``frame``, ``row``:
        see :meth:`fill_state`."""
        payload = self.fill_state(now_ns, catching_up, frame, row)
        pose_ok = self._pose_finite() if frame is None else bool(frame.pose_ok[row])
        if not (self.state_finite and pose_ok):
            if self.state_finite:  # the pose went bad under a finite state: stop the car
                self._stop("non-finite world pose")
            payload = self._last_finite_state()
            if payload is None:
                return None
        else:
            self._last_finite = payload
        self.counters["state_published"] += 1
        return payload

    def _pose_finite(self) -> bool:
        """The record's fields that are not copies of the checked state (``check_finite``)
        are finite: the world pose and the ground slopes."""
        rec = self.record
        return (bool(np.isfinite(self.sim.pose).all())
                and math.isfinite(rec["ground_grade_pct"] + rec["ground_cross_slope_pct"]
                                  + rec["contact_force_n"]))

    def _last_finite_state(self) -> bytes | None:
        """The newest finite state published, with the flags, tick, time and command fields
        of the record just filled (``FAULT`` set)."""
        if self._last_finite is None:
            return None
        out = np.frombuffer(self._last_finite, dtype=proto.STATE_DTYPE).copy()
        rec = self.record
        for name in ("tick", "sim_time_s", "last_cmd_seq", "last_cmd_sender_time_ns",
                     "cmd_age_s"):
            out[name] = rec[name]
        out["flags"] = int(rec["flags"]) | proto.StateFlag.FAULT
        return out.tobytes()

    def fill_state(self, now_ns: int, catching_up: bool,
                   frame: StateFrame | None = None, row: int = -1) -> bytes:
        """Write the state record from the simulation and return its bytes.

        ``frame``: the world's records, this car's (``row``, its ``record`` a view of that
        row) filled this tick with its copied fields and the fields that follow from the
        physics (``simserver.server.state_frame.StateFrame.fill``, the whole world's in one
        go, by the rules below); only this slot's own fields are written then."""
        p = self.sim
        rec = self.record
        flags = 0
        if self.watchdog.engaged:
            flags |= _FLAG_WATCHDOG
        if self.paused:
            flags |= _FLAG_PAUSED
        if catching_up:
            flags |= _FLAG_CATCHUP
        if self.fault:
            flags |= _FLAG_FAULT
        if self.skipped_before:
            flags |= _FLAG_SKIPPED
            self.skipped_before = False
        if frame is None:
            flags |= self._fill_physics_fields(p, rec)
        else:
            p.pose[:] = frame.poses[row]
            flags |= int(frame.flag_bits[row])
        arbiter = self.arbiter
        rec["flags"] = flags
        rec["tick"] = self.tick
        rec["sim_time_s"] = self.tick * p.dt_s
        rec["last_cmd_seq"] = arbiter.last_applied_seq
        rec["last_cmd_sender_time_ns"] = arbiter.last_sender_ns
        rec["cmd_age_s"] = arbiter.cmd_age_s(now_ns)
        return rec.tobytes()

    def _fill_physics_fields(self, p: SimulationAPI, rec: np.ndarray) -> int:
        """The record's copied fields and the server's fields that follow from the physics,
        field by field (a car outside a state frame; ``state_frame.physics_fields`` is the
        same rules for a world's cars at once); returns their flag bits."""
        data = p.data  # the car's rows of the world (one lookup, not one a field)
        x, out, inputs = data.x, data.out, data.inputs
        p.update_pose()  # world axes; on a terrain from the reference plane of the step
        flags = 0
        # The core holds a wheel at zero spin whenever the torques on it balance, rolling
        # resistance included (at rest on the flat with no brake); the flag and the
        # per-wheel field say "a brake holds it": only while a brake acts (pedal, parking
        # brake on the rear wheels, or the park lock of gear P).
        braking = self._braking
        braking[:] = inputs[L.IN_BRAKE] > 0.0 or inputs[L.IN_GEAR] == L.GEAR_P
        if inputs[L.IN_PARKING_BRAKE] > 0.0:
            braking[2:] = True
        held = self._held
        np.logical_and(x[L.WHEEL_HELD] > 0.5, braking, out=held)
        if held.any():
            flags |= _FLAG_BRAKE_HOLD
        if x[L.HILL_HOLD_ACTIVE] > 0.5:
            flags |= _FLAG_HILL_HOLD
        # the fields copied from the simulation come from the state table (state_schema);
        # the rest are the server's (state_schema.SERVER_FIELDS, checked on import)
        fill_record(rec, x, out, inputs, p.pose)
        rec["brake_held"] = held
        rec["ground_grade_pct"], rec["ground_cross_slope_pct"] = ground_slopes_pct(
            p, p.pose[L.POSE_YAW_RAD])
        # the world's contact output of the car (docs/model.md section 16): an output of
        # the step, not a state, so the core's state arrays stay as they are
        cc = p.contact_output()
        rec["contact_force_n"] = math.hypot(cc[CC_FORCE_X_N], cc[CC_FORCE_Y_N])
        rec["car_contact"] = cc[CC_ACTIVE] > 0.5
        return flags

    def check_finite(self) -> bool:
        """Stop the car in a defined safe state if its state is no longer finite.

        Called before the state is published, so a non-finite value never reaches a
        client. Safe state: at rest at the scene's start pose (``reset``, logged so a
        replay does the same), forces zeroed, paused until a client resets, loads or
        resumes; ``flags`` bit 4 until the next reset or load; counted in
        ``nonfinite_stops`` once per stop (not again while the stopped car stays as it
        is); logged once per episode (``docs/reliability.md``). If even the start is not
        finite, :meth:`state_payload` publishes the newest finite state instead.
        Returns True when the state was finite.
        """
        p = self.sim
        self.state_finite = bool(np.isfinite(p.x).all() and np.isfinite(p.out).all())
        if self.state_finite:
            return True
        if not self._stopped:  # stopped already and not stepped since: nothing new
            self._stop("non-finite state")
        return False

    def _stop(self, what: str) -> None:
        """The stop of :meth:`check_finite`: counted, logged once per episode, reset to the
        scene's start at rest, paused."""
        p = self.sim
        if not self.fault:
            log.error("%s at tick %d (vehicle %s): car stopped at rest at the scene's start "
                      "and paused until reset, load or resume", what, self.tick,
                      p.scene.vehicle.name)
        self.fault = True
        self.counters["nonfinite_stops"] = min(self.counters["nonfinite_stops"] + 1, 0xFFFF)
        pose = {k: p.scene.initial[k] for k in ("x_m", "y_m", "yaw_rad")}
        p.reset(pose)
        p.out[:] = 0.0
        self.paused = True
        self.steps_to_run = 0
        self._stopped = True
        self.state_finite = bool(np.isfinite(p.x).all())
        self._log({"step": self.steps_total, "reset": self.logged_start(pose)})

    def logged_start(self, pose: dict[str, float] | None) -> dict[str, float] | None:
        """A reset's value in the command log: the pose, and in a shared world the world's
        time the car kept (one clock, ``Simulation.commit``): the replay, a car alone,
        restarts its clock there."""
        if pose is None or not self.shared_world:
            return pose
        return {**pose, "time_s": float(self.sim.x[L.TIME_S])}

    def warm_up(self) -> None:
        """Compile every kernel the tick uses (simulation and state record) before the clock
        (the live server's: not the headless loop, ``Simulation.warm_up_calls``)."""
        self.sim.warm_up(live=True)
        self.fill_state(0, False)

    # ------------------------------------------------------------------ controls
    # Each handler takes the arguments validated by protocol.validate_control and returns
    # the members of its success reply, or raises ProtocolError / ConfigError naming the
    # field (docs/protocol.md section 3). The loop's table maps control names to them.
    def ctl_reset(self, args: dict[str, Any]) -> dict[str, Any]:
        """``reset`` in one go (tools, tests): :meth:`begin_reset` settled at once, applied.

        The server's loop runs the settling of a start at speed in pieces between ticks
        instead (``simserver.server.loop``) and applies it when it is done."""
        staged = self.begin_reset(args)
        staged.prepared.finish()
        return staged.commit()

    def begin_reset(self, args: dict[str, Any]) -> StagedStart:
        """``reset``: the scene's initial state, or at rest at ``pose`` or on ``lane`` (road,
        s and lane of the scene's OpenDRIVE roads, ``lane_start``), or with ``u_mps`` driving
        straight on at that speed (wheels, slips and powertrain relaxed); tick 0. The log
        keeps the world pose, so a replay needs no roads.

        Prepared beside the running car (microseconds, with the inputs of now), then the
        settling of a start at speed (up to ``core.start.SETTLE_STEPS_MAX`` steps) is left
        to :meth:`StagedStart.advance`; :meth:`StagedStart.commit` swaps it in and gives the
        reply. Bad arguments raise here and change nothing."""
        pose = args.get("pose")
        u_mps = args.get("u_mps")
        p = self.sim
        if "lane" in args:
            if pose is not None:
                raise proto.ProtocolError("lane", "give pose or lane, not both")
            pose = self._lane_pose(args["lane"])
        if pose is None and self.shared_world:  # the car's own start, named in the log (a
            # replay's scene is the world's, whose start is another)
            pose = {k: float(p.scene.initial[k]) for k in ("x_m", "y_m", "yaw_rad")}
        prepared = p.prepare_reset(pose, u_mps)

        def commit() -> dict[str, Any]:
            p.commit(prepared)
            self.tick = 0
            self.fault = False
            self._stopped = False
            self.arbiter.last_seq = None  # docs/protocol.md 2.1: a new client may start from 0
            # the start pose as the scene's initial takes it (on the plane, the state's own
            # x, y and yaw; on a terrain the state lives on the step's reference plane); a
            # start at speed holds the body while it settles, so the pose is where it began
            start = pose if pose is not None else p.scene.initial
            start_pose = {key: float(start[key]) for key in ("x_m", "y_m", "yaw_rad")}
            logged = pose if u_mps is None else {**start_pose, "u_mps": float(u_mps)}
            self._log({"step": self.steps_total, "reset": self.logged_start(logged)})
            reply = {"tick": 0, "pose": start_pose}
            if u_mps is not None:
                reply["u_mps"] = float(p.x[L.U_MPS])
            return reply

        return StagedStart(prepared, commit)

    def _lane_pose(self, lane: dict[str, Any]) -> dict[str, float]:
        """The world pose of a reset by road, s and lane (microseconds: the roads are
        parsed already, ``Scene.roads``)."""
        roads = self.sim.scene.roads
        if roads is None:
            raise proto.ProtocolError("lane", "the scene's terrain is not an OpenDRIVE road")
        try:
            x_m, y_m, yaw_rad = lane_start(roads, lane["road"], lane["s"], lane["lane"])
        except LaneStartError as exc:
            raise proto.ProtocolError(f"lane.{exc.key}", str(exc)) from None
        return {"x_m": x_m, "y_m": y_m, "yaw_rad": yaw_rad}

    def ctl_pause(self, args: dict[str, Any]) -> dict[str, Any]:
        """``pause``: stop stepping (the state is still published)."""
        self.paused = True
        self.steps_to_run = 0
        return {"tick": self.tick, "paused": True}

    def ctl_resume(self, args: dict[str, Any]) -> dict[str, Any]:
        """``resume``: step at the wall-clock rate again."""
        self.paused = False
        self.steps_to_run = 0
        return {"tick": self.tick, "paused": False}

    def ctl_step(self, args: dict[str, Any]) -> dict[str, Any]:
        """``step``: while paused, run ``n`` more ticks at the normal rate."""
        if not self.paused:  # a state of the server, not an argument: named by the control
            raise proto.ProtocolError("step", "the server is not paused (pause first)")
        self.steps_to_run += int(args["n"])
        return {"tick": self.tick, "until_tick": self.tick + self.steps_to_run}

    def ctl_set_road(self, args: dict[str, Any]) -> dict[str, Any]:
        """``set_road``: change the given members of the road; the others are kept."""
        road = {**self.sim.road, **args}
        self.sim.set_road(**road)
        self._log({"step": self.steps_total, "set_road": road})
        return {"road": road}

    def ctl_load(self, args: dict[str, Any]) -> dict[str, Any]:
        """``load`` in one go (tests and tools): :meth:`load_job` run here, then applied.

        The server runs the job off the tick (``simserver.server.loop``: a worker process)
        and calls :meth:`apply_load` between two ticks.
        """
        fn, job_args = self.load_job(args)
        staged = self.apply_load(unwrap_prepared(fn(*job_args)))
        staged.prepared.finish()
        return staged.commit()

    def load_job(self, args: dict[str, Any]) -> tuple[Callable[..., Any], tuple[Any, ...]]:
        """The file reading of a ``load``, as a picklable ``(function, arguments)``.

        It touches nothing of the slot: run it anywhere (a worker process), then hand its
        result to :meth:`apply_load`. A car of a world of several cars loads another
        vehicle only (``ProtocolError`` naming ``scene`` otherwise): the scene is the
        world's.
        """
        if self.shared_world and args.get("scene") is not None:
            raise proto.ProtocolError("scene", "this car is one of several in a world: its "
                                      "load changes its vehicle only (the scene is the "
                                      "world's)")
        return prepare_load, (args.get("scene"), args.get("vehicle"), self.scene_path,
                              tuple(self.cfg.config_dirs), os.getcwd(), self.cfg.path.parent)

    def prepare_load(self, args: dict[str, Any]) -> tuple[Scene, Path, Path | None]:
        """The scene a ``load`` asks for, read and validated: (scene, its path, vehicle path)."""
        fn, job_args = self.load_job(args)
        return unwrap_prepared(fn(*job_args))

    def apply_load(self, prepared: tuple[Scene, Path, Path | None]) -> StagedStart:
        """A prepared scene made ready beside the running car: its model and initial state
        (tens of microseconds: the kernels are those already compiled, the model's array
        signature does not change with the vehicle; a terrain's grids are views of the
        worker's shared block, ``simserver.server.load_worker``), a relaxed start's settling left
        to :meth:`StagedStart.advance`; :meth:`StagedStart.commit` swaps it in (tick 0,
        logged) and gives the reply."""
        scene, scene_path, vehicle_path = prepared
        start = None
        if self.shared_world:  # another vehicle for this car, from its own start, on the
            # world's terrain and road (docs/protocol.md 5.1; load_job refused a scene)
            start = {k: float(self.sim.scene.initial[k]) for k in ("x_m", "y_m", "yaw_rad")}
            scene = dataclasses.replace(scene, initial=dict(self.sim.scene.initial))
        staged = self.sim.prepare_load(scene, keep_terrain=self.shared_world)

        def commit() -> dict[str, Any]:
            replaced = self.sim.commit(staged)
            if replaced is not None:  # its grids are freed off the tick (a munmap: ms)
                release_later(replaced)
                del replaced
            self.sim.warm_up(live=True)  # microseconds: a dispatch of each kernel on a copy
            self.scene_path = scene_path
            self.tick = 0
            self.fault = False
            self._stopped = False
            self._log({"step": self.steps_total, "load": {
                "scene": str(scene_path), "vehicle": None if vehicle_path is None
                else str(vehicle_path)}})
            if start is not None:  # a replay loads the scene's start, then goes to the car's
                self._log({"step": self.steps_total, "set_road": dict(self.sim.road)})
                self._log({"step": self.steps_total, "reset": self.logged_start(start)})
            return {"vehicle": self._shown(self.sim.scene.vehicle.path),
                    "scene": self._shown(scene_path)}

        return StagedStart(staged, commit)

    def ctl_get_config(self, args: dict[str, Any]) -> dict[str, Any]:
        """``get_config``: the active configuration."""
        cfg, p, keys = self.cfg, self.sim, self.keys
        return {"protocol_version": proto.PROTOCOL_VERSION, "config": {
            "server": {"path": self._shown(cfg.path), "period_s": cfg.period_s,
                       "state_every": cfg.state_every, "diag_hz": cfg.diag_hz,
                       "watchdog_s": cfg.watchdog_s, "watchdog_brake": cfg.watchdog_brake},
            "vehicle": {"name": p.scene.vehicle.name, "path": self._shown(p.scene.vehicle.path),
                        "tire_models": list(p.scene.vehicle.tire_models)},
            "scene": {"path": self._shown(self.scene_path), "initial": p.scene.initial,
                      "model": p.scene.model_options,
                      "terrain": TERRAIN_KINDS.by_id(p.scene.terrain.kind).name},
            "road": dict(p.road),
            "keys": {"cmd": keys.cmd, "state": keys.state, "diag": keys.diag,
                     "alive": keys.alive},
            "ros2": None if self.ros2_status is None else self.ros2_status(),
            "load_worker": None if self.load_worker_status is None else (
                self.load_worker_status()),
        }}

    def _shown(self, path: Path) -> str:
        """A path as a client may see it: relative to the config folder holding it."""
        return display_path(path, self.cfg.config_dirs)

    def _log(self, entry: dict[str, Any]) -> None:
        if self.command_log is not None:
            self.command_log.write(entry)


# ---------------------------------------------------------------------- load, off the tick
class StagedStart:
    """A ``reset`` or ``load`` made ready beside the running car: the start state
    (``Simulation.prepare_reset`` / ``prepare_load``) whose settling runs in pieces
    (:meth:`advance`), and the ``commit`` that swaps it in and returns the reply."""

    def __init__(self, prepared: PreparedStart, commit: Callable[[], dict[str, Any]]) -> None:
        self.prepared = prepared
        self.commit = commit

    def advance(self, max_steps: int) -> bool:
        """Up to ``max_steps`` settling steps; True when ready to commit."""
        return self.prepared.advance(max_steps)


def resolve_config_path(field: str, value: str, config_dirs: tuple[Path, ...],
                        cwd: str | Path, config_folder: Path | None = None) -> Path:
    """The file a ``load`` names: absolute, or relative to the server's working directory
    first, then to each config directory in turn, then to the server config's own folder
    (``config_folder``; relative paths in that file are relative to it) (``docs/protocol.md``,
    ``ctl/load``).

    Raises
    ------
    ProtocolError
        Naming ``field`` and every place it looked, when no candidate is a file; or when
        the file is outside the config directories.
    """
    given = Path(value)
    bases = list(dict.fromkeys([Path(cwd), *map(Path, config_dirs),
                                *([config_folder] if config_folder is not None else [])]))
    candidates = [given] if given.is_absolute() else [b / given for b in bases]
    for candidate in candidates:
        path = candidate.resolve()
        if path.is_file() or given.is_absolute():
            if not any(path.is_relative_to(d) for d in config_dirs):
                raise proto.ProtocolError(  # not the absolute paths: docs/security.md
                    field, f"{short_repr(value)} is outside the server's config directories")
            if path.is_file():
                return path
        if path.exists() and not path.is_file():  # never opened: a FIFO would block
            raise proto.ProtocolError(field, f"{path}: not a regular file (a FIFO, a "
                                             "device or a directory)")
    looked = dict.fromkeys(str(c.resolve()) for c in candidates)
    raise proto.ProtocolError(field, f"{value}: no such file; looked in {', '.join(looked)}")


def prepare_load(scene: str | None, vehicle: str | None, current_scene: Path,
                 config_dirs: tuple[Path, ...], cwd: str,
                 config_folder: Path | None = None) -> tuple[str, Any]:
    """Read and validate the files of a ``load`` (run in the load worker).

    Returns ``("ok", (scene, scene path, vehicle path))`` or ``("error", field, message)``
    (errors as data: they cross a process boundary).
    """
    try:
        scene_path = resolve_config_path("scene", scene, config_dirs, cwd, config_folder) \
            if scene is not None else current_scene
        vehicle_path = resolve_config_path("vehicle", vehicle, config_dirs, cwd,
                                           config_folder) if vehicle is not None else None
    except proto.ProtocolError as exc:
        return "error", exc.field, redacted(str(exc), config_dirs, cwd)
    # every file the scene refers to, nested or not, must be in the config folders too;
    # errors show paths relative to them only (docs/security.md)
    with confined_to(config_dirs):
        try:
            loaded = load_scene(scene_path, vehicle_path=vehicle_path)
        except ConfigError as exc:  # named by the argument whose files are at fault
            message = str(exc)
            field = "scene" if vehicle is None or (
                scene is not None and message.startswith(f"{scene_path}:")) else "vehicle"
            return "error", field, f"{field}: {redacted(message, config_dirs, cwd)}"
        except Exception as exc:  # noqa: BLE001 - a loader's bug: still name the files
            log.error("load of %s failed", scene_path, exc_info=exc)
            files = display_path(scene_path, config_dirs) + (
                "" if vehicle_path is None else f" with {display_path(vehicle_path, config_dirs)}")
            field = "scene" if scene is not None or vehicle is None else "vehicle"
            return "error", field, (f"{field}: {files}: not loaded: {type(exc).__name__} "
                                    "while reading it or a file it names (a loader's bug: "
                                    "the server's log has the details); nothing changed")
    return "ok", (loaded, scene_path, vehicle_path)


def redacted(message: str, config_dirs: tuple[Path, ...], cwd: str | Path) -> str:
    """``message`` with the config folders' and the working directory's absolute paths made
    relative: a reply never discloses where the server is installed."""
    for root in sorted((*map(str, config_dirs), str(cwd)), key=lambda d: -len(d)):
        message = message.replace(f"{root}{os.sep}", "")
    return message


def unwrap_prepared(result: tuple[str, Any] | tuple[str, str, str]) -> Any:
    """The value of a :func:`prepare_load` result, or its error raised as ProtocolError."""
    if result[0] == "ok":
        return result[1]
    _, field, message = result
    err = proto.ProtocolError(field, "x")
    err.args = (message,)
    raise err
