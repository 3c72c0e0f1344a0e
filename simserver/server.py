"""The real-time server: the car at a fixed 1 kHz of wall-clock time, driven over zenoh.

This module holds the server's configuration (``load_server_config``), the command log
(``CommandLog``), the simulation both the server and the replay step (``Physics``), the
zenoh wiring (``SimServer``) and the replay (``replay_command_log``). The logic is apart:

- :mod:`simserver.server_loop`: the fixed-rate loop (pacer, inbox drain, publish,
  controls dispatched through a table), with the clock, inboxes and publisher injected;
- :mod:`simserver.vehicle_slot`: one car (command arbitration, watchdog, pause and step,
  the state record, the controls' handlers).

Every applied input change and every control that changes the physics is written to an
optional command log, which ``replay_command_log`` re-runs headless bit for bit.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from simserver import protocol as proto
from simserver.adapters.config import ConfigError, check_keys, number, read_yaml
from simserver.core import layout as L
from simserver.core.integrator import forget_tire_loads, make_workspace, step
from simserver.core.params import VP_CG_HEIGHT_M, road_axes, set_road
from simserver.core.pose import world_pose
from simserver.ros2 import cli as ros2_cli
from simserver.scenario import Scene, initial_state, load_scene
from simserver.server_loop import ServerLoop, SlotPorts
from simserver.vehicle_slot import VehicleSlot

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
    "ros2": None,
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
    ros2: dict[str, Any] | None = None  # the ROS 2 adapter's settings; None: off


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
    ros2_flag = overrides.pop("ros2", None)  # --ros2/--no-ros2 switch the config's section
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
        if key not in base or key in ("scene", "ros2") or base[key] is None:
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
    try:
        cfg.ros2 = ros2_cli.serve_settings(base.get("ros2"), ros2_flag, source=f"{path}: ros2")
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
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
        self._logged_inputs = np.full(L.N_INPUT, np.nan)
        self.write({"simserver_command_log": 1, **header})

    def write(self, entry: dict[str, Any]) -> None:
        """Append one line."""
        self._file.write(json.dumps(entry, separators=(",", ":")) + "\n")

    def log_inputs(self, step: int, inputs: np.ndarray) -> None:
        """The inputs applied at physics step ``step``, if they changed since the last line."""
        if not np.array_equal(inputs, self._logged_inputs):
            self._logged_inputs[:] = inputs
            self.write({"step": step, "inputs": [float(v) for v in inputs]})

    def close(self, steps: int, state: np.ndarray) -> None:
        """Write the end line with the exact final state and close."""
        self.write({"end": steps, "state": [float(v).hex() for v in state]})
        self._file.close()


class Physics:
    """The compiled vehicle plus its scene: state, parameters, and the step.

    Shared by the live server and the replay so both run the very same arithmetic.
    """

    def __init__(self, scene: Scene, dt_s: float) -> None:
        self.dt_s = dt_s
        self.load(scene)
        self.ws = make_workspace()
        self.out = np.zeros(L.N_OUT)
        self.inputs = np.zeros(L.N_INPUT)
        self.inputs[L.IN_GEAR] = L.GEAR_P
        self.pose = np.zeros(6)

    def load(self, scene: Scene) -> None:
        """Take a scene (vehicle, road, initial state); the state is reset to it."""
        self.scene = scene
        self.vp = scene.vehicle.vp.copy()
        self.tp = scene.vehicle.tp.copy()
        self.set_road(**scene.road)
        self.reset(None)

    def reset(self, pose: dict[str, float] | None) -> None:
        """Back to the scene's initial state, or at rest at ``pose`` (x_m, y_m, yaw_rad)."""
        scene = self.scene
        if pose is not None:
            at_rest = {**scene.initial, **pose, "u_mps": 0.0, "v_mps": 0.0,
                       "yaw_rate_radps": 0.0}
            scene = dataclasses.replace(scene, initial=at_rest)
        self.x = initial_state(scene)
        if hasattr(self, "ws"):
            forget_tire_loads(self.ws)

    def set_road(self, grade_pct: float, cross_slope_pct: float, friction_scale: float) -> None:
        """Change the road plane (takes effect at the next step)."""
        set_road(self.vp, grade_pct, cross_slope_pct, friction_scale)
        self.road = {"grade_pct": grade_pct, "cross_slope_pct": cross_slope_pct,
                     "friction_scale": friction_scale}
        self.axes = road_axes(grade_pct, cross_slope_pct)

    def step(self) -> None:
        """One fixed step with the current inputs."""
        step(self.x, self.vp, self.tp, self.inputs, self.dt_s, self.ws, self.out)

    def warm_up(self) -> None:
        """Compile (or load from cache) every kernel before the clock starts."""
        x, out = self.x.copy(), self.out.copy()
        step(x, self.vp, self.tp, self.inputs, self.dt_s, self.ws, out)
        world_pose(self.x, self.axes, self.vp[VP_CG_HEIGHT_M], self.pose)


def new_simulation(scene: Scene, dt_s: float) -> Physics:
    """The simulation a vehicle slot steps (the one place the server builds it)."""
    return Physics(scene, dt_s)


class SimServer:
    """The live server over zenoh: one vehicle slot, the loop, the viewer, the signals.

    ``run()`` blocks until SIGINT/SIGTERM or ``stop()``. The logic lives in
    :class:`simserver.vehicle_slot.VehicleSlot` and :class:`simserver.server_loop.ServerLoop`;
    this class only wires them to zenoh (:mod:`simserver.adapters.zenoh_io`).
    """

    def __init__(self, cfg: ServerConfig) -> None:
        self.cfg = cfg
        self.slots = [VehicleSlot(cfg, new_simulation(load_scene(cfg.scene), cfg.period_s))]
        self.loop = ServerLoop(cfg)

    @property
    def physics(self) -> Physics:
        """The first (default: only) vehicle's simulation."""
        return self.slots[0].sim

    def stop(self, *_: Any) -> None:
        """Ask the loop to finish (signal handler)."""
        self.loop.stop()

    def run(self) -> dict[str, Any]:
        """Serve until stopped; returns the final statistics."""
        from simserver.adapters.zenoh_io import ZenohEndpoint, make_zenoh_config

        cfg = self.cfg
        t_compile = time.perf_counter()
        for slot in self.slots:
            slot.warm_up()
        compile_s = time.perf_counter() - t_compile
        zcfg = make_zenoh_config(listen=cfg.listen, connect=cfg.connect,
                                 config_file=cfg.zenoh_config, mode=cfg.mode)
        for slot in self.slots:
            if slot.cfg.command_log is not None:
                slot.command_log = CommandLog(slot.cfg.command_log, {
                    "scene": str(slot.scene_path), "dt_s": cfg.period_s, "step": 0})
        loop = self.loop
        loop.running = True  # before the handlers: a signal from now on ends the loop
        previous = {s: signal.signal(s, self.stop) for s in (signal.SIGINT, signal.SIGTERM)}
        viewer = ros2 = None
        try:
            with ZenohEndpoint(zcfg, prefix=cfg.prefix, vehicle=cfg.vehicle_id) as ep:
                for slot in self.slots:
                    keys = slot.keys
                    commands = ep.declare_command_inbox(capacity=proto.COMMAND_RING_SLOTS, keys=keys)
                    publisher = ep.declare_vehicle_publisher(keys=keys)
                    controls = ep.declare_control_inbox(keys=keys, validate=False)
                    ep.declare_alive_token(keys=keys)
                    loop.add(slot, SlotPorts(commands, controls, publisher))
                first = self.slots[0]
                log.info("serving %s (vehicle %s) every %.3f ms; compiled in %.2f s",
                         first.keys.base, first.sim.scene.vehicle.name,
                         1e3 * cfg.period_s, compile_s)
                print(f"simserver: ready on {first.keys.base} "
                      f"(listen {cfg.listen or 'tcp/127.0.0.1:7447'})", flush=True)
                viewer = self._start_viewer()
                ros2 = self._start_ros2()
                loop.run()
        finally:
            for s, h in previous.items():
                signal.signal(s, h)
            self._stop_viewer(viewer)
            self._stop_viewer(ros2)
            for slot in self.slots:
                if slot.command_log is not None:
                    slot.command_log.close(slot.steps_total, slot.sim.x)
        final = loop.final_stats()
        print("simserver: stopped " + json.dumps(final), flush=True)
        return final

    def _start_viewer(self) -> subprocess.Popen | None:
        """Start ``simserver view`` in its own process (the physics never waits on it)."""
        cfg = self.cfg
        if cfg.viewer == "off":
            return None
        args = [sys.executable, "-m", "simserver", "view", "--sink", cfg.viewer,
                "--connect", self._own_endpoint(), "--prefix", cfg.prefix,
                "--vehicle-id", cfg.vehicle_id]
        log.info("live view: %s", " ".join(args[2:]))
        return subprocess.Popen(args)

    def _own_endpoint(self) -> str:
        """The loopback form of the server's first listen endpoint, for its side processes."""
        endpoint = (self.cfg.listen or ["tcp/127.0.0.1:7447"])[0]
        return endpoint.replace("0.0.0.0", "127.0.0.1").replace("[::]", "[::1]")

    def _start_ros2(self) -> subprocess.Popen | None:
        """Start ``simserver ros2`` in its own process when configured, like the viewer; a
        thread logs its death while the server runs."""
        cfg = self.cfg
        if cfg.ros2 is None:
            return None
        args = ros2_cli.adapter_command(self._own_endpoint(), cfg.prefix, cfg.vehicle_id,
                                        cfg.ros2)
        log.info("ROS 2 adapter: %s", " ".join(args[2:]))
        adapter = subprocess.Popen(args)

        def watch() -> None:
            code = adapter.wait()
            if self.loop.running:
                log.error("the ROS 2 adapter (pid %d) ended with exit code %d; the server "
                          "goes on without it", adapter.pid, code)

        threading.Thread(target=watch, name="ros2-watch", daemon=True).start()
        return adapter

    @staticmethod
    def _stop_viewer(viewer: subprocess.Popen | None) -> None:
        if viewer is None:
            return
        viewer.terminate()
        try:
            viewer.wait(timeout=10)
        except subprocess.TimeoutExpired:
            viewer.kill()


# ---------------------------------------------------------------------- replay
@dataclass
class Replay:
    """A command log re-run headless: the state after every step, and the final state."""

    states: np.ndarray  # (steps, N_STATE): state after step k
    outputs: np.ndarray  # (steps, N_OUT): forces at the start of step k
    final_state: np.ndarray
    logged_final_state: np.ndarray | None
    steps: int


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
    physics = Physics(load_scene(header["scene"]), float(header["dt_s"]))
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
