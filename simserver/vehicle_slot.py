"""One car served by the live server: the simulation it steps and what belongs to it alone.

A :class:`VehicleSlot` holds, for one vehicle id, everything the fixed-rate loop
(:mod:`simserver.server_loop`) must not share between cars: its keys, the command
arbitration (:class:`CommandArbiter`), the :class:`Watchdog`, the run state (tick,
pause, pending steps), the counters of its diagnostics, its state record and its command
log. It knows no transport and no clock: the loop hands it the payloads it drained and
the tick's time in nanoseconds, and publishes the bytes it returns. So the whole logic
runs in-process on a fake clock (``tests/test_server_logic.py``).

The simulation is called through its public API only (``x``, ``inputs``, ``out``, ``vp``,
``scene``, ``road``, ``axes``, ``pose``, ``dt_s``, ``step()``, ``reset(pose)``,
``set_road(...)``, ``load(scene)``, ``warm_up()``); the rules it applies to commands and
controls are those of ``docs/protocol.md`` (sections 2.1 and 3).
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from simserver import protocol as proto
from simserver.core import layout as L
from simserver.core.params import VP_CG_HEIGHT_M
from simserver.core.pose import world_pose
from simserver.scenario import Scene, load_scene

if TYPE_CHECKING:
    from simserver.server import CommandLog, ServerConfig

log = logging.getLogger("simserver.server")

COUNTER_NAMES: tuple[str, ...] = ("cmd_received", "cmd_rejected", "cmd_clamped",
                                  "cmd_stale", "state_published", "watchdog_trips")
"""The slot's cumulative counters, in the order of the ``stopped`` line."""


class SimulationAPI(Protocol):
    """What a slot uses of the simulation (``Physics`` today): nothing else."""

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
    def reset(self, pose: dict[str, float] | None) -> None: ...
    def set_road(self, grade_pct: float, cross_slope_pct: float,
                 friction_scale: float) -> None: ...
    def load(self, scene: Scene) -> None: ...
    def warm_up(self) -> None: ...


class RateLimitedLog:
    """Log a recurring warning at most once per ``interval_s``, with the count in between."""

    def __init__(self, interval_s: float = 1.0) -> None:
        self.interval_s = interval_s
        self._last = -math.inf
        self._suppressed = 0

    def warn(self, message: str, now_s: float | None = None) -> None:
        """Log ``message`` unless one was logged less than ``interval_s`` before ``now_s``."""
        now = time.monotonic() if now_s is None else now_s
        if now - self._last >= self.interval_s:
            extra = f" ({self._suppressed} more since the last report)" if self._suppressed else ""
            log.warning("%s%s", message, extra)
            self._last = now
            self._suppressed = 0
        else:
            self._suppressed += 1


class CommandArbiter:
    """Decode, validate and arbitrate the driver commands of one car (docs/protocol.md 2.1).

    Rules: a payload that does not decode is rejected (counted, logged at a bounded rate);
    the newest valid command of a tick wins; a command whose ``seq`` is not newer than
    the last applied one (RFC 1982 serial arithmetic, so the u32 wrap is fine) is stale.
    ``commanded`` is what the driver asked for, before the watchdog.
    """

    def __init__(self, counters: dict[str, int], initial_inputs: np.ndarray) -> None:
        self.counters = counters
        self.last_seq: int | None = None
        self.last_cmd_ns: int | None = None  # loop clock when the last valid one arrived
        self.last_sender_ns = 0
        self.commanded = initial_inputs.copy()
        self.reject_log = RateLimitedLog()

    def take(self, payloads: list[bytes], now_ns: int) -> None:
        """Apply the newest valid command among ``payloads`` (oldest first), if any."""
        counters = self.counters
        newest: proto.DriverCommand | None = None
        for payload in payloads:
            counters["cmd_received"] += 1
            try:
                cmd = proto.decode_command(payload)
            except proto.ProtocolError as exc:
                counters["cmd_rejected"] += 1
                self.reject_log.warn(f"rejected command: {exc}", now_ns * 1e-9)
                continue
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
    :meth:`advance`, :meth:`state_payload` (at the state rate), the ``ctl_*`` handlers
    through its control table, and :meth:`check_finite`.
    """

    def __init__(self, cfg: ServerConfig, sim: SimulationAPI,
                 command_log: CommandLog | None = None) -> None:
        self.cfg = cfg
        self.keys = proto.vehicle_keys(cfg.prefix, cfg.vehicle_id)
        self.sim = sim
        self.scene_path = cfg.scene
        self.command_log = command_log
        self.counters = dict.fromkeys(COUNTER_NAMES, 0)
        self.arbiter = CommandArbiter(self.counters, sim.inputs)
        self.watchdog = Watchdog(cfg.watchdog_s, cfg.watchdog_brake)
        self.paused = False
        self.steps_to_run = 0  # ticks left of a 'step' control while paused
        self.tick = 0  # ticks since start, reset or load (the protocol's tick)
        self.steps_total = 0  # physics steps since start (the command log's clock)
        self.record = proto.new_state_record()

    # ------------------------------------------------------------------ each tick
    def take_commands(self, payloads: list[bytes], now_ns: int) -> None:
        """Arbitrate the command payloads drained this tick."""
        self.arbiter.take(payloads, now_ns)

    def apply_inputs(self, now_ns: int) -> None:
        """Commanded inputs through the watchdog into the simulation's input vector."""
        if self.watchdog.update(self.arbiter.last_cmd_ns, now_ns):
            self.counters["watchdog_trips"] += 1
            self.arbiter.last_seq = None  # a restarted client may begin its sequence anew
        inputs = self.sim.inputs
        inputs[:] = self.arbiter.commanded
        if self.watchdog.engaged:
            self.watchdog.hold(inputs)

    def advance(self) -> bool:
        """Step the simulation once unless paused with no ``step`` pending; True if stepped."""
        if self.paused and self.steps_to_run <= 0:
            return False
        if self.command_log is not None:
            self.command_log.log_inputs(self.steps_total, self.sim.inputs)
        self.sim.step()
        self.tick += 1
        self.steps_total += 1
        if self.paused:
            self.steps_to_run -= 1
        return True

    def state_payload(self, now_ns: int, catching_up: bool) -> bytes:
        """The VehicleState of this tick (docs/protocol.md 2.2), counted as published."""
        self.counters["state_published"] += 1
        return self.fill_state(now_ns, catching_up)

    def fill_state(self, now_ns: int, catching_up: bool) -> bytes:
        """Write the state record from the simulation and return its bytes."""
        p = self.sim
        x, out, rec = p.x, p.out, self.record
        world_pose(x, p.axes, p.vp[VP_CG_HEIGHT_M], p.pose)
        flags = 0
        if self.watchdog.engaged:
            flags |= proto.StateFlag.WATCHDOG
        if self.paused:
            flags |= proto.StateFlag.PAUSED
        held = x[L.WHEEL_HELD0:L.WHEEL_HELD0 + 4]
        if held.any():
            flags |= proto.StateFlag.BRAKE_HOLD
        if catching_up:
            flags |= proto.StateFlag.CATCHUP
        arbiter = self.arbiter
        rec["flags"] = flags
        rec["tick"] = self.tick
        rec["sim_time_s"] = self.tick * p.dt_s
        rec["last_cmd_seq"] = arbiter.last_seq or 0
        rec["last_cmd_sender_time_ns"] = arbiter.last_sender_ns
        rec["cmd_age_s"] = arbiter.cmd_age_s(now_ns)
        rec["x_m"], rec["y_m"], rec["z_m"] = p.pose[0], p.pose[1], p.pose[2]
        rec["yaw_rad"], rec["pitch_rad"], rec["roll_rad"] = p.pose[3], p.pose[4], p.pose[5]
        rec["u_mps"] = x[L.U_MPS]
        rec["v_mps"] = x[L.V_MPS]
        rec["w_mps"] = x[L.HEAVE_RATE_MPS]
        rec["roll_rate_radps"] = x[L.ROLL_RATE_RADPS]
        rec["pitch_rate_radps"] = x[L.PITCH_RATE_RADPS]
        rec["yaw_rate_radps"] = x[L.YAW_RATE_RADPS]
        rec["ax_mps2"] = out[L.O_AX_MPS2]
        rec["ay_mps2"] = out[L.O_AY_MPS2]
        rec["omega_radps"] = x[L.OMEGA0:L.OMEGA0 + 4]
        rec["kappa_lag"] = x[L.KAPPA0:L.KAPPA0 + 4]
        rec["tan_alpha_lag"] = x[L.TAN_ALPHA0:L.TAN_ALPHA0 + 4]
        rec["fx_n"] = out[L.O_FX0:L.O_FX0 + 4]
        rec["fy_n"] = out[L.O_FY0:L.O_FY0 + 4]
        rec["fz_n"] = out[L.O_FZ0:L.O_FZ0 + 4]
        rec["steer_rad"] = out[L.O_STEER0:L.O_STEER0 + 4]
        rec["damping_active"] = x[L.DAMPING_ACTIVE0:L.DAMPING_ACTIVE0 + 4]
        rec["brake_held"] = held
        rec["wheel_contact"] = x[L.IN_CONTACT0:L.IN_CONTACT0 + 4]
        inputs = p.inputs
        rec["steer"] = inputs[L.IN_STEER]
        rec["throttle"] = inputs[L.IN_THROTTLE]
        rec["brake"] = inputs[L.IN_BRAKE]
        rec["parking_brake"] = inputs[L.IN_PARKING_BRAKE]
        rec["gear"] = inputs[L.IN_GEAR]
        return rec.tobytes()

    def check_finite(self) -> None:
        """Never expected: a non-finite state is logged loudly and the car reset."""
        if not np.isfinite(self.sim.x).all():
            log.error("non-finite state at tick %d: resetting", self.tick)
            self.sim.reset(None)

    def warm_up(self) -> None:
        """Compile every kernel the tick uses (simulation and state record) before the clock."""
        self.sim.warm_up()
        self.fill_state(0, False)

    # ------------------------------------------------------------------ controls
    # Each handler takes the arguments validated by protocol.validate_control and returns
    # the members of its success reply, or raises ProtocolError / ConfigError naming the
    # field (docs/protocol.md section 3). The loop's table maps control names to them.
    def ctl_reset(self, args: dict[str, Any]) -> dict[str, Any]:
        """``reset``: the scene's initial state, or at rest at ``pose``; tick 0."""
        pose = args.get("pose")
        p = self.sim
        p.reset(pose)
        self.tick = 0
        self._log({"step": self.steps_total, "reset": pose})
        return {"tick": 0, "pose": {"x_m": p.x[L.X_M], "y_m": p.x[L.Y_M],
                                    "yaw_rad": p.x[L.YAW_RAD]}}

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
        if not self.paused:
            raise proto.ProtocolError("n", "the server is not paused (pause first)")
        self.steps_to_run += int(args["n"])
        return {"tick": self.tick, "until_tick": self.tick + self.steps_to_run}

    def ctl_set_road(self, args: dict[str, Any]) -> dict[str, Any]:
        """``set_road``: change the given members of the road; the others are kept."""
        road = {**self.sim.road, **args}
        self.sim.set_road(**road)
        self._log({"step": self.steps_total, "set_road": road})
        return {"road": road}

    def ctl_load(self, args: dict[str, Any]) -> dict[str, Any]:
        """``load``: validate everything first, then swap; nothing changes on error.

        Two halves: :meth:`prepare_load` reads and validates the files (touches nothing
        of the slot), :meth:`apply_load` swaps the result in and compiles (from the
        cache: same array types), so the loop rebases its pacer afterwards.
        """
        return self.apply_load(*self.prepare_load(args))

    def prepare_load(self, args: dict[str, Any]) -> tuple[Scene, Path, Path | None]:
        """The scene a ``load`` asks for, read and validated: (scene, its path, vehicle path)."""
        base = self.cfg.path.parent
        scene_path = self._resolve_config_path(args["scene"], base) if "scene" in args \
            else self.scene_path
        vehicle_path = self._resolve_config_path(args["vehicle"], base) \
            if "vehicle" in args else None
        return load_scene(scene_path, vehicle_path=vehicle_path), scene_path, vehicle_path

    def apply_load(self, scene: Scene, scene_path: Path,
                   vehicle_path: Path | None) -> dict[str, Any]:
        """Swap a prepared scene in: the simulation reset to it, tick 0, logged."""
        self.sim.load(scene)
        self.sim.warm_up()
        self.scene_path = scene_path
        self.tick = 0
        self._log({"step": self.steps_total, "load": {
            "scene": str(scene_path), "vehicle": None if vehicle_path is None
            else str(vehicle_path)}})
        return {"vehicle": str(self.sim.scene.vehicle.path), "scene": str(scene_path)}

    def ctl_get_config(self, args: dict[str, Any]) -> dict[str, Any]:
        """``get_config``: the active configuration."""
        cfg, p, keys = self.cfg, self.sim, self.keys
        return {"protocol_version": proto.PROTOCOL_VERSION, "config": {
            "server": {"path": str(cfg.path), "period_s": cfg.period_s,
                       "state_every": cfg.state_every, "diag_hz": cfg.diag_hz,
                       "watchdog_s": cfg.watchdog_s, "watchdog_brake": cfg.watchdog_brake},
            "vehicle": {"name": p.scene.vehicle.name, "path": str(p.scene.vehicle.path),
                        "tire_models": list(p.scene.vehicle.tire_models)},
            "scene": {"path": str(self.scene_path), "initial": p.scene.initial,
                      "model": p.scene.model_options},
            "road": dict(p.road),
            "keys": {"cmd": keys.cmd, "state": keys.state, "diag": keys.diag,
                     "alive": keys.alive},
        }}

    def _resolve_config_path(self, value: str, base: Path) -> Path:
        path = (base / value).resolve() if not Path(value).is_absolute() else Path(value)
        path = path.resolve()
        dirs = self.cfg.config_dirs
        if not any(path.is_relative_to(d) for d in dirs):
            raise proto.ProtocolError(
                "path", f"{path} is outside the server's config directories "
                        f"({', '.join(str(d) for d in dirs)})")
        if not path.is_file():
            raise proto.ProtocolError("path", f"{path}: no such file")
        return path

    def _log(self, entry: dict[str, Any]) -> None:
        if self.command_log is not None:
            self.command_log.write(entry)
