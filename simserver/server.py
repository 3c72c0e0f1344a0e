"""The real-time server: the car at a fixed 1 kHz of wall-clock time, driven over zenoh.

One thread, one loop, in this order every tick (``SimServer.run``):

1. wait for the tick's absolute deadline (``realtime.Pacer``: no drift; overrun policy:
   up to ``max_catchup_ticks`` late ticks run back to back, beyond that the passed
   deadlines are skipped and counted);
2. drain every command received since the last tick without blocking; decode and
   validate each (``protocol.decode_command``); the newest valid one wins, the rest are
   counted as rejected or stale. Nothing unvalidated reaches the physics;
3. the watchdog: with no valid command for ``watchdog_s`` the applied throttle is 0 and
   the brake at least ``watchdog_brake`` (steer and gear kept), flagged in the state;
4. step the compiled physics once (``core.integrator.step``), unless paused;
5. publish the state (every ``state_every`` ticks) and, a few times a second, the
   diagnostics;
6. answer control requests (reset, pause, resume, step, set_road, load, get_config).

Every applied input change and every control that changes the physics is written to an
optional command log, which ``replay_command_log`` re-runs headless bit for bit.
"""

from __future__ import annotations

import json
import logging
import math
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from simserver import protocol as proto
from simserver.adapters.config import ConfigError, check_keys, number, read_yaml
from simserver.core import layout as L
from simserver.core.params import VP_CG_HEIGHT_M
from simserver.core.pose import world_pose
from simserver.scenario import load_scene
from simserver.simulation import Simulation

log = logging.getLogger("simserver.server")

REPO_CONFIGS = Path(__file__).resolve().parents[1] / "configs"
DEFAULT_SERVER_CONFIG = REPO_CONFIGS / "server" / "default.yaml"

SERVER_KEYS: dict[str, tuple[float, float] | None] = {
    # key: numeric range, or None for non-numeric keys
    "scene": None,
    "prefix": None,
    "vehicle_id": None,
    "zenoh_config": None,
    "listen": None,
    "connect": None,
    "mode": None,
    "period_s": (0.0001, 0.1),
    "state_every": (1, 1000),
    "diag_hz": (0.1, 100.0),
    "watchdog_s": (0.005, 60.0),
    "watchdog_brake": (0.0, 1.0),
    "max_catchup_ticks": (0, 100000),
    "command_log": None,
    "config_dirs": None,
    "viewer": None,
}


@dataclass
class ServerConfig:
    """Validated server settings (``configs/server/default.yaml`` documents each key)."""

    path: Path
    scene: Path
    prefix: str = "simserver"
    vehicle_id: str = "car0"
    zenoh_config: Path | None = None
    listen: list[str] | None = None
    connect: list[str] | None = None
    mode: str | None = None
    period_s: float = 0.001
    state_every: int = 1
    diag_hz: float = 5.0
    watchdog_s: float = 0.2
    watchdog_brake: float = 0.6
    max_catchup_ticks: int = 100
    command_log: Path | None = None
    config_dirs: list[Path] = field(default_factory=list)
    viewer: str = "off"


def _string_list(path: Path, key: str, value: Any) -> list[str]:
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise ConfigError(f"{path}: key '{key}': expected a string or a list of strings")
    return list(value)


def load_server_config(path: str | Path, **overrides: Any) -> ServerConfig:
    """Load a server YAML; ``overrides`` (command-line flags) replace keys that are not None.

    Paths in the file are relative to it; paths in ``overrides`` to the working directory.
    """
    path = Path(path).resolve()
    data = read_yaml(path)
    check_keys(path, data, tuple(SERVER_KEYS), required=("scene",))
    base = {k: (path.parent / v).resolve() if k in ("scene", "zenoh_config", "command_log")
            and isinstance(v, str) else v for k, v in data.items()}
    if overrides.get("zenoh_config") is not None:
        # a zenoh file given on the command line decides its own endpoints and mode,
        # unless they are given on the command line too
        for key in ("listen", "connect", "mode"):
            base.pop(key, None)
    for k, v in overrides.items():
        if v is not None:
            if k not in SERVER_KEYS:
                raise ConfigError(f"command line: unknown server setting '{k}'")
            base[k] = Path(v).resolve() if k in ("scene", "zenoh_config", "command_log") else v
    cfg = ServerConfig(path=path, scene=Path(base["scene"]))
    for key, rng in SERVER_KEYS.items():
        if key not in base or key == "scene" or base[key] is None:
            continue
        value = base[key]
        if rng is not None:
            val = number(path, key, value, *rng)
            setattr(cfg, key, int(val) if key in ("state_every", "max_catchup_ticks") else val)
        elif key in ("listen", "connect"):
            setattr(cfg, key, _string_list(path, key, value))
        elif key == "config_dirs":
            cfg.config_dirs = [(path.parent / d).resolve() for d in _string_list(path, key, value)]
        elif key in ("prefix", "vehicle_id", "mode", "viewer"):
            if not isinstance(value, str):
                raise ConfigError(f"{path}: key '{key}': expected a string")
            setattr(cfg, key, value)
        else:
            setattr(cfg, key, Path(value))
    if cfg.mode not in (None, "peer", "router", "client"):
        raise ConfigError(f"{path}: key 'mode': expected peer, router or client")
    try:
        proto.vehicle_keys(cfg.prefix, cfg.vehicle_id)
    except proto.ProtocolError as exc:
        raise ConfigError(f"{path}: {exc}") from exc
    if cfg.viewer != "off":
        from simserver.adapters.rerun_sink import RerunSinkError, parse_sink

        try:
            parse_sink(cfg.viewer)
        except RerunSinkError as exc:
            raise ConfigError(f"{path}: key 'viewer': {exc}") from exc
    if not cfg.config_dirs:
        cfg.config_dirs = [REPO_CONFIGS, path.parent]
    return cfg


class CommandLog:
    """Applied inputs and physics-changing controls, one JSON object a line.

    Lines: a header (scene, vehicle, step); ``{"step": n, "inputs": [steer, throttle,
    brake, parking_brake, gear]}`` whenever the applied inputs change (before physics step
    ``n``); ``{"step": n, "reset": pose|null}``, ``{"step": n, "set_road": {...}}``,
    ``{"step": n, "load": {"scene": ..., "vehicle": ...}}``; and at a clean shutdown
    ``{"end": n, "state": [hex floats]}``, the full final state, for checking a replay.
    """

    def __init__(self, path: Path, header: dict[str, Any]) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self._file = path.open("w", encoding="utf-8", buffering=1 << 16)
        self.write({"simserver_command_log": 1, **header})

    def write(self, entry: dict[str, Any]) -> None:
        """Append one line."""
        self._file.write(json.dumps(entry, separators=(",", ":")) + "\n")

    def close(self, steps: int, state: np.ndarray) -> None:
        """Write the end line with the exact final state and close."""
        self.write({"end": steps, "state": [float(v).hex() for v in state]})
        self._file.close()


class RateLimitedLog:
    """Log a recurring warning at most once per ``interval_s``, with the count in between."""

    def __init__(self, interval_s: float = 1.0) -> None:
        self.interval_s = interval_s
        self._last = -math.inf
        self._suppressed = 0

    def warn(self, message: str) -> None:
        now = time.monotonic()
        if now - self._last >= self.interval_s:
            extra = f" ({self._suppressed} more since the last report)" if self._suppressed else ""
            log.warning("%s%s", message, extra)
            self._last = now
            self._suppressed = 0
        else:
            self._suppressed += 1


class SimServer:
    """The live server. ``run()`` blocks until SIGINT/SIGTERM or ``stop()``."""

    def __init__(self, cfg: ServerConfig) -> None:
        self.cfg = cfg
        self.keys = proto.vehicle_keys(cfg.prefix, cfg.vehicle_id)
        self.scene_path = cfg.scene
        self.physics = Simulation(load_scene(cfg.scene), cfg.period_s)
        self.running = False
        self.paused = False
        self.steps_to_run = 0  # ticks left of a 'step' control while paused
        self.tick = 0  # ticks since start or reset (the protocol's tick)
        self.steps_total = 0  # physics steps since start (the command log's clock)
        self.counters = {k: 0 for k in ("cmd_received", "cmd_rejected", "cmd_clamped",
                                        "cmd_stale", "state_published", "watchdog_trips")}
        self.last_seq: int | None = None
        self.last_cmd_wall: float | None = None
        self.last_cmd_sender_ns = 0
        self.commanded = self.physics.inputs.copy()  # what the driver asked for
        self.watchdog = True  # no command yet: hold the car
        self.reject_log = RateLimitedLog()
        self.record = proto.new_state_record()
        self.command_log: CommandLog | None = None
        self._logged_inputs = np.full(L.N_INPUT, np.nan)
        self.catching_up = False

    # ------------------------------------------------------------------ commands
    def _take_commands(self, payloads: list[bytes], now: float) -> None:
        newest: proto.DriverCommand | None = None
        for payload in payloads:
            self.counters["cmd_received"] += 1
            try:
                cmd = proto.decode_command(payload)
            except proto.ProtocolError as exc:
                self.counters["cmd_rejected"] += 1
                self.reject_log.warn(f"rejected command: {exc}")
                continue
            if cmd.clamped:
                self.counters["cmd_clamped"] += 1
            if self.last_seq is not None and not proto.seq_newer(cmd.seq, self.last_seq):
                self.counters["cmd_stale"] += 1
                continue
            if newest is None or proto.seq_newer(cmd.seq, newest.seq):
                if newest is not None:
                    self.counters["cmd_stale"] += 1  # superseded within the same tick
                newest = cmd
            else:
                self.counters["cmd_stale"] += 1
        if newest is None:
            return
        self.last_seq = newest.seq
        self.last_cmd_wall = now
        self.last_cmd_sender_ns = newest.sender_time_ns
        c = self.commanded
        c[L.IN_STEER] = newest.steer
        c[L.IN_THROTTLE] = newest.throttle
        c[L.IN_BRAKE] = newest.brake
        c[L.IN_PARKING_BRAKE] = 1.0 if newest.parking_brake else 0.0
        c[L.IN_GEAR] = float(newest.gear)

    def _apply_inputs(self, now: float) -> None:
        """Commanded inputs through the watchdog into the physics' input vector."""
        expired = self.last_cmd_wall is None or now - self.last_cmd_wall > self.cfg.watchdog_s
        if expired and not self.watchdog:
            self.counters["watchdog_trips"] += 1
            self.last_seq = None  # a restarted client may begin its sequence anew
            log.warning("watchdog: no valid command for %.0f ms, holding the car",
                        1e3 * self.cfg.watchdog_s)
        elif not expired and self.watchdog:
            log.info("watchdog released: commands resumed")
        self.watchdog = expired
        inputs = self.physics.inputs
        inputs[:] = self.commanded
        if expired:
            inputs[L.IN_THROTTLE] = 0.0
            inputs[L.IN_BRAKE] = max(inputs[L.IN_BRAKE], self.cfg.watchdog_brake)

    # ------------------------------------------------------------------ state out
    def _fill_state(self, now: float) -> bytes:
        p = self.physics
        x, out, rec = p.x, p.out, self.record
        world_pose(x, p.axes, p.vp[VP_CG_HEIGHT_M], p.pose)
        flags = 0
        if self.watchdog:
            flags |= proto.StateFlag.WATCHDOG
        if self.paused:
            flags |= proto.StateFlag.PAUSED
        held = x[L.WHEEL_HELD0:L.WHEEL_HELD0 + 4]
        if held.any():
            flags |= proto.StateFlag.BRAKE_HOLD
        if self.catching_up:
            flags |= proto.StateFlag.CATCHUP
        rec["flags"] = flags
        rec["tick"] = self.tick
        rec["sim_time_s"] = self.tick * p.dt_s
        rec["last_cmd_seq"] = self.last_seq or 0
        rec["last_cmd_sender_time_ns"] = self.last_cmd_sender_ns
        rec["cmd_age_s"] = -1.0 if self.last_cmd_wall is None else now - self.last_cmd_wall
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
        inputs = p.inputs
        rec["steer"] = inputs[L.IN_STEER]
        rec["throttle"] = inputs[L.IN_THROTTLE]
        rec["brake"] = inputs[L.IN_BRAKE]
        rec["parking_brake"] = inputs[L.IN_PARKING_BRAKE]
        rec["gear"] = inputs[L.IN_GEAR]
        return rec.tobytes()

    def _diagnostics(self) -> bytes:
        st = self.pacer.stats()
        return proto.encode_diagnostics(
            window_ticks=st.window_ticks, tick=self.tick, uptime_s=time.monotonic() - self.t0,
            lateness_p50_us=st.lateness_p50_us, lateness_p99_us=st.lateness_p99_us,
            lateness_max_us=st.lateness_max_us, period_p50_us=st.period_p50_us,
            period_p99_us=st.period_p99_us, period_max_us=st.period_max_us,
            period_min_us=st.period_min_us, cpu_percent=self.cpu.percent(),
            overruns=st.overruns, skipped_ticks=st.skipped_ticks, late_ticks=st.late_ticks,
            **self.counters,
        )

    # ------------------------------------------------------------------ controls
    def _road_dict(self) -> dict[str, float]:
        return dict(self.physics.road)

    def _resolve_config_path(self, value: str, base: Path) -> Path:
        path = (base / value).resolve() if not Path(value).is_absolute() else Path(value)
        path = path.resolve()
        if not any(path.is_relative_to(d) for d in self.cfg.config_dirs):
            raise proto.ProtocolError(
                "path", f"{path} is outside the server's config directories "
                        f"({', '.join(str(d) for d in self.cfg.config_dirs)})")
        if not path.is_file():
            raise proto.ProtocolError("path", f"{path}: no such file")
        return path

    def _handle_control(self, req: Any) -> None:
        name, args = req.name, req.args
        p = self.physics
        try:
            if name == "reset":
                pose = args.get("pose")
                p.reset(pose)
                self.tick = 0
                self._log({"step": self.steps_total, "reset": pose})
                req.reply_ok(tick=0, pose={"x_m": p.x[L.X_M], "y_m": p.x[L.Y_M],
                                           "yaw_rad": p.x[L.YAW_RAD]})
            elif name == "pause":
                self.paused = True
                self.steps_to_run = 0
                req.reply_ok(tick=self.tick, paused=True)
            elif name == "resume":
                self.paused = False
                self.steps_to_run = 0
                req.reply_ok(tick=self.tick, paused=False)
            elif name == "step":
                if not self.paused:
                    req.reply_error("n: the server is not paused (pause first)", field="n")
                    return
                self.steps_to_run += int(args["n"])
                req.reply_ok(tick=self.tick, until_tick=self.tick + self.steps_to_run)
            elif name == "set_road":
                road = {**self._road_dict(), **args}
                p.set_road(**road)
                self._log({"step": self.steps_total, "set_road": road})
                req.reply_ok(road=road)
            elif name == "load":
                self._load(args)
                req.reply_ok(vehicle=str(p.scene.vehicle.path), scene=str(self.scene_path))
            elif name == "get_config":
                req.reply_ok(protocol_version=proto.PROTOCOL_VERSION, config=self._config_dict())
            else:  # validate_control knows every name; this is a programming error
                req.reply_error(f"control: {name!r} is not implemented", field="control")
        except proto.ProtocolError as exc:
            req.reply_error(exc)
        except ConfigError as exc:
            req.reply_error(f"{name}: {exc}", field=name)
        except Exception as exc:  # a bug must not stop the 1 kHz loop: answer, log, go on
            log.exception("control %s failed", name)
            req.reply_error(f"{name}: internal error ({type(exc).__name__})", field=name)

    def _load(self, args: dict[str, Any]) -> None:
        """The ``load`` control: validate everything first, then swap; nothing changes on error."""
        base = self.cfg.path.parent
        scene_path = self._resolve_config_path(args["scene"], base) if "scene" in args \
            else self.scene_path
        vehicle_path = self._resolve_config_path(args["vehicle"], base) \
            if "vehicle" in args else None
        scene = load_scene(scene_path, vehicle_path=vehicle_path)
        was_paused = self.paused
        self.paused = True
        self.physics.load(scene)
        self.physics.warm_up()  # same array types: served from the compiled cache
        self.scene_path = scene_path
        self.tick = 0
        self._log({"step": self.steps_total, "load": {
            "scene": str(scene_path), "vehicle": None if vehicle_path is None
            else str(vehicle_path)}})
        self.paused = was_paused
        self.pacer.rebase()

    def _config_dict(self) -> dict[str, Any]:
        p = self.physics
        return {
            "server": {"path": str(self.cfg.path), "period_s": self.cfg.period_s,
                       "state_every": self.cfg.state_every, "diag_hz": self.cfg.diag_hz,
                       "watchdog_s": self.cfg.watchdog_s,
                       "watchdog_brake": self.cfg.watchdog_brake},
            "vehicle": {"name": p.scene.vehicle.name, "path": str(p.scene.vehicle.path),
                        "tire_models": list(p.scene.vehicle.tire_models)},
            "scene": {"path": str(self.scene_path), "initial": p.scene.initial,
                      "model": p.scene.model_options},
            "road": self._road_dict(),
            "keys": {"cmd": self.keys.cmd, "state": self.keys.state, "diag": self.keys.diag,
                     "alive": self.keys.alive},
        }

    def _log(self, entry: dict[str, Any]) -> None:
        if self.command_log is not None:
            self.command_log.write(entry)

    # ------------------------------------------------------------------ the loop
    def stop(self, *_: Any) -> None:
        """Ask the loop to finish (signal handler)."""
        self.running = False

    def run(self) -> dict[str, Any]:
        """Serve until stopped; returns the final statistics."""
        from simserver.adapters.zenoh_io import ZenohEndpoint, make_zenoh_config
        from simserver.realtime import CpuMeter, Pacer

        cfg = self.cfg
        t_compile = time.perf_counter()
        self.physics.warm_up()
        self._fill_state(0.0)
        compile_s = time.perf_counter() - t_compile
        zcfg = make_zenoh_config(listen=cfg.listen, connect=cfg.connect,
                                 config_file=cfg.zenoh_config, mode=cfg.mode)
        if cfg.command_log is not None:
            self.command_log = CommandLog(cfg.command_log, {
                "scene": str(self.scene_path), "dt_s": cfg.period_s, "step": 0})
        period_ns = int(round(cfg.period_s * 1e9))
        self.pacer = Pacer(period_ns=period_ns, max_catchup_ticks=cfg.max_catchup_ticks)
        self.cpu = CpuMeter()
        self.catching_up = False
        diag_every = max(1, int(round(1.0 / (cfg.diag_hz * cfg.period_s))))
        self.running = True  # before the handlers: a signal from now on ends the loop
        previous = {s: signal.signal(s, self.stop) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            with ZenohEndpoint(zcfg, prefix=cfg.prefix, vehicle=cfg.vehicle_id) as ep:
                inbox = ep.declare_command_inbox(capacity=256)
                state_pub = ep.declare_state_publisher()
                diag_pub = ep.declare_diag_publisher()
                controls = ep.declare_control_inbox()
                ep.declare_alive_token()
                log.info("serving %s (vehicle %s) every %.3f ms; compiled in %.2f s",
                         self.keys.base, self.physics.scene.vehicle.name,
                         1e3 * cfg.period_s, compile_s)
                print(f"simserver: ready on {self.keys.base} "
                      f"(listen {cfg.listen or 'tcp/127.0.0.1:7447'})", flush=True)
                viewer = self._start_viewer()
                self.t0 = time.monotonic()
                self.pacer.start()
                loop_count = 0
                while self.running:
                    self.pacer.wait()
                    self.catching_up = self.pacer.catching_up
                    now = time.monotonic()
                    self._take_commands(inbox.drain_newest(), now)
                    self._apply_inputs(now)
                    if not self.paused or self.steps_to_run > 0:
                        self._log_inputs()
                        self.physics.step()
                        self.tick += 1
                        self.steps_total += 1
                        if self.paused:
                            self.steps_to_run -= 1
                    if loop_count % cfg.state_every == 0:
                        state_pub.put(self._fill_state(now))
                        self.counters["state_published"] += 1
                    if loop_count % diag_every == 0:
                        diag_pub.put(self._diagnostics())
                    for req in controls.poll():
                        self._handle_control(req)
                    loop_count += 1
                    if not np.isfinite(self.physics.x).all():  # never expected; be loud
                        log.error("non-finite state at tick %d: resetting", self.tick)
                        self.physics.reset(None)
        finally:
            for s, h in previous.items():
                signal.signal(s, h)
            self._stop_viewer(locals().get("viewer"))
            if self.command_log is not None:
                self.command_log.close(self.steps_total, self.physics.x)
        stats = self.pacer.stats()
        final = {"ticks": self.tick, "steps_total": self.steps_total,
                 "uptime_s": round(time.monotonic() - self.t0, 3),
                 "lateness_p50_us": stats.lateness_p50_us,
                 "lateness_p99_us": stats.lateness_p99_us,
                 "lateness_max_us": stats.max_lateness_us, "overruns": stats.overruns,
                 "skipped_ticks": stats.skipped_ticks, "late_ticks": stats.late_ticks,
                 **self.counters}
        print("simserver: stopped " + json.dumps(final), flush=True)
        return final

    def _start_viewer(self) -> subprocess.Popen | None:
        """Start ``simserver view`` in its own process (the physics never waits on it)."""
        cfg = self.cfg
        if cfg.viewer == "off":
            return None
        endpoint = (cfg.listen or ["tcp/127.0.0.1:7447"])[0]
        endpoint = endpoint.replace("0.0.0.0", "127.0.0.1").replace("[::]", "[::1]")
        args = [sys.executable, "-m", "simserver", "view", "--sink", cfg.viewer,
                "--connect", endpoint, "--prefix", cfg.prefix, "--vehicle-id", cfg.vehicle_id]
        log.info("live view: %s", " ".join(args[2:]))
        return subprocess.Popen(args)

    @staticmethod
    def _stop_viewer(viewer: subprocess.Popen | None) -> None:
        if viewer is None:
            return
        viewer.terminate()
        try:
            viewer.wait(timeout=10)
        except subprocess.TimeoutExpired:
            viewer.kill()

    def _log_inputs(self) -> None:
        if self.command_log is None:
            return
        inputs = self.physics.inputs
        if not np.array_equal(inputs, self._logged_inputs):
            self._logged_inputs[:] = inputs
            self.command_log.write({"step": self.steps_total,
                                    "inputs": [float(v) for v in inputs]})


# ---------------------------------------------------------------------- replay
@dataclass
class Replay:
    """A command log re-run headless: the state after every step, and the final state.

    ``logged_final_state`` is the log's ``end`` state as written, which may be shorter
    than ``N_STATE``: a log written before state slots were appended (``core.layout``)
    holds the older layout, a prefix of this one. ``final_state_matches`` compares them
    on the slots both have.
    """

    states: np.ndarray  # (steps, N_STATE): state after step k
    outputs: np.ndarray  # (steps, N_OUT): forces at the start of step k
    final_state: np.ndarray
    logged_final_state: np.ndarray | None
    steps: int

    @property
    def final_state_matches(self) -> bool | None:
        """The replayed final state equals the logged one bit for bit on the common slots
        (None if the log has no end state)."""
        if self.logged_final_state is None:
            return None
        n = self.logged_final_state.size
        return n <= self.final_state.size and bool(
            np.array_equal(self.final_state[:n], self.logged_final_state))


def read_command_log(path: str | Path) -> list[dict[str, Any]]:
    """Parse a command log, with errors naming the file and line."""
    path = Path(path)
    entries = []
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    for n, line in enumerate(lines, 1):
        try:
            entries.append(json.loads(line))
        except json.JSONDecodeError as exc:
            raise ConfigError(f"{path}:{n}: not a JSON line: {exc.msg}") from exc
    if not entries or entries[0].get("simserver_command_log") != 1:
        raise ConfigError(f"{path}: not a simserver command log (no header line)")
    return entries


def replay_command_log(path: str | Path, progress: Any = None) -> Replay:
    """Re-run a command log headless with the same compiled step as the server."""
    entries = read_command_log(path)
    header = entries[0]
    physics = Simulation(load_scene(header["scene"]), float(header["dt_s"]))
    events = entries[1:]
    end = next((e for e in events if "end" in e), None)
    total = int(end["end"]) if end else max((int(e.get("step", 0)) for e in events), default=0)
    states = np.zeros((total, L.N_STATE))
    outputs = np.zeros((total, L.N_OUT))
    k = 0
    for n in range(total + 1):
        while k < len(events) and events[k].get("step") == n:
            e = events[k]
            if "inputs" in e:
                physics.inputs[:] = e["inputs"]
            elif "reset" in e:
                physics.reset(e["reset"])
            elif "set_road" in e:
                physics.set_road(**e["set_road"])
            elif "load" in e:
                spec = e["load"]
                physics.load(load_scene(spec["scene"], vehicle_path=spec["vehicle"]))
            k += 1
        if n == total:
            break
        physics.step()
        states[n] = physics.x
        outputs[n] = physics.out
        if progress is not None and n % 10000 == 0:
            progress(n, total)
    logged = None if end is None else np.array([float.fromhex(v) for v in end["state"]])
    return Replay(states=states, outputs=outputs, final_state=physics.x.copy(),
                  logged_final_state=logged, steps=total)
