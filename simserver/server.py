"""The real-time server: the car at a fixed 1 kHz of wall-clock time, driven over zenoh.

This module holds the server's configuration (``load_server_config``), the command log
(``CommandLog``), the one place the server builds its ``Simulation`` (``new_simulation``), the
zenoh wiring (``SimServer``) and the replay (``replay_command_log``). The logic is apart:

- :mod:`simserver.server_loop`: the fixed-rate loop (pacer, inbox drain, publish,
  controls dispatched through a table), with the clock, inboxes and publisher injected;
- :mod:`simserver.vehicle_slot`: one car (command arbitration, watchdog, pause and step,
  the state record, the controls' handlers).

Every applied input change and every control that changes the physics is written to an
optional command log, which ``replay_command_log`` re-runs headless bit for bit.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import socket
import stat
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from simserver import fleet
from simserver import protocol as proto
from simserver.adapters.config import ConfigError, check_keys, number, read_yaml
from simserver.adapters.validate import integer, is_path_text, short_repr
from simserver.core import layout as L
from simserver.load_worker import ProcessPreparer
from simserver.logfile import LogWriter, check_log_path, open_log_file, renew_log_thread
from simserver.realtime import (
    DEFAULT_RT_PRIORITY,
    REALTIME_MODES,
    RealtimeScheduler,
    RealtimeSettings,
    TickTrace,
    parse_cpus,
    process_threads,
)
from simserver.ros2 import cli as ros2_cli
from simserver.ros2.supervisor import AdapterSupervisor
from simserver.scenario import INITIAL_RANGES, Scene, load_scene
from simserver.server_loop import ServerLoop, SlotPorts
from simserver.simulation import Simulation
from simserver.vehicle_slot import VehicleSlot
from simserver.world_desk import WorldDesk

log = logging.getLogger("simserver.server")

TICK_TRACE_ENV = "SIMSERVER_TICK_TRACE"
"""A file name in this environment variable makes the server record per-tick timing there
(:class:`simserver.realtime.TickTrace`; ``benchmarks.bench_load`` reads it)."""

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
    "load_stall_s": (1.0, 600.0),
    "load_timeout_s": (1.0, 3600.0),
    "command_log": None,
    "config_dirs": None,
    "viewer": None,
    "realtime": None,
    "rt_priority": (2, 99),
    "rt_cpus": None,
    "rt_lock_memory": None,
    "ros2": None,
    "tls_front": None,
    "cars": None,
    "max_cars": fleet.MAX_CARS_RANGE,
    "world_hz": (1.0, 1000.0),
}


TLS_FRONT_MODES = ("auto", "off")
"""``tls_front``: auto puts :mod:`simserver.adapters.tls_front` before every ``tls/`` listen
endpoint (docs/security.md section 5); off lets zenoh listen on them itself."""


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
    load_stall_s: float = 10.0  # server_loop.JOB_TIMEOUT_S
    load_timeout_s: float = 300.0  # server_loop.LOAD_TIMEOUT_S
    command_log: Path | None = None
    config_dirs: list[Path] = field(default_factory=list)
    viewer: str = "off"
    realtime: str = "auto"
    rt_priority: int = DEFAULT_RT_PRIORITY
    rt_cpus: tuple[int, ...] = ()
    rt_lock_memory: bool = False
    ros2: dict[str, Any] | None = None  # the ROS 2 adapter's settings; None: off
    tls_front: str = "auto"  # auto: an accept-filtering front per tls/ listen endpoint
    cars: list[fleet.CarSpec] | None = None  # None: the one car vehicle_id (simserver.fleet)
    max_cars: int = fleet.DEFAULT_MAX_CARS
    world_hz: float = proto.WORLD_HZ_DEFAULT  # the world message's rate

    def realtime_settings(self) -> RealtimeSettings:
        """The real-time scheduling asked for (``simserver.realtime``)."""
        return RealtimeSettings(mode=self.realtime, priority=self.rt_priority,
                                cpus=self.rt_cpus, lock_memory=self.rt_lock_memory)


def _string_list(path: Path, key: str, value: Any) -> list[str]:
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise ConfigError(f"{path}: key '{key}': expected a string or a list of strings")
    return list(value)


ZENOH_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe",
                   "serial", "vsock")
"""The link protocols a zenoh endpoint may name (``proto/address``)."""
_IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")


def _check_endpoint(where: str, endpoint: str) -> None:
    """A zenoh endpoint ``proto/address[?params][#config]`` with a known protocol and, for
    IP protocols, ``host:port`` with a port in 0-65535; errors name ``where``."""
    proto_name, sep, rest = endpoint.partition("/")
    if not sep or proto_name not in ZENOH_PROTOCOLS:
        raise ConfigError(f"{where}: {short_repr(endpoint)}: expected PROTOCOL/ADDRESS with "
                          f"PROTOCOL one of {', '.join(ZENOH_PROTOCOLS)}")
    if proto_name in _IP_PROTOCOLS:
        address = rest.split("?", 1)[0].split("#", 1)[0]
        host, colon, port = address.rpartition(":")
        if not colon or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
            raise ConfigError(f"{where}: {short_repr(endpoint)}: expected "
                              f"{proto_name}/HOST:PORT with a port in 0-65535")


def _check_command_log(where: str, log_path: Path) -> None:
    """The command log's file can be created: not a folder, in an existing folder, not a
    symbolic link nor anything but a regular file (checked again when it is opened)."""
    if log_path.is_dir():
        raise ConfigError(f"{where}: {log_path} is a folder, not a file")
    if not log_path.parent.is_dir():
        raise ConfigError(f"{where}: the folder {log_path.parent} does not exist")
    why = check_log_path(log_path)
    if why is not None:
        raise ConfigError(f"{where}: {log_path} {why}")


def _log_path(path: str | Path) -> Path:
    """An absolute log path whose last part is kept as it is: a symbolic link there is
    refused, never followed (``simserver.logfile``)."""
    path = Path(os.path.abspath(path))
    return path.parent.resolve() / path.name


def load_server_config(path: str | Path, **overrides: Any) -> ServerConfig:
    """Load a server YAML; ``overrides`` (command-line flags) replace keys that are not None.

    Paths in the file are relative to it; paths in ``overrides`` to the working directory.
    Errors name the file and the key, or the command-line option that set it.
    """
    path = Path(path).resolve()
    ros2_flag = overrides.pop("ros2", None)  # --ros2/--no-ros2 switch the config's section
    data = read_yaml(path)
    check_keys(path, data, tuple(SERVER_KEYS), required=("scene",))
    for key in ("scene", "zenoh_config", "command_log"):
        if (key == "scene" or data.get(key) is not None) and not is_path_text(data.get(key)):
            raise ConfigError(f"{path}: key '{key}': expected a file path")
    base = {k: (path.parent / v).resolve() if k in ("scene", "zenoh_config")
            and isinstance(v, str) else v for k, v in data.items()}
    if isinstance(base.get("command_log"), str):
        base["command_log"] = _log_path(path.parent / base["command_log"])
    if overrides.get("zenoh_config") is not None:
        # a zenoh file given on the command line decides its own endpoints and mode,
        # unless they are given on the command line too
        for key in ("listen", "connect", "mode"):
            base.pop(key, None)
    from_cli: set[str] = set()
    for k, v in overrides.items():
        if v is not None:
            if k not in SERVER_KEYS:
                raise ConfigError(f"command line: unknown server setting '{k}'")
            base[k] = Path(v).resolve() if k in ("scene", "zenoh_config") else \
                _log_path(v) if k == "command_log" else v
            from_cli.add(k)

    def where(key: str) -> str:
        if key in from_cli:
            return f"command line: option '--{key.replace('_', '-')}'"
        return f"{path}: key '{key}'"

    cfg = ServerConfig(path=path, scene=Path(base["scene"]))
    for key, rng in SERVER_KEYS.items():
        if key not in base or key in ("scene", "ros2", "cars") or base[key] is None:
            continue
        value = base[key]
        if key in ("state_every", "max_catchup_ticks", "rt_priority", "max_cars"):
            lo, hi = rng
            setattr(cfg, key, integer(path, key, value, int(lo), int(hi)))
        elif rng is not None:
            setattr(cfg, key, number(path, key, value, *rng))
        elif key in ("listen", "connect"):
            endpoints = _string_list(path, key, value)
            for endpoint in endpoints:
                _check_endpoint(where(key), endpoint)
            setattr(cfg, key, endpoints)
        elif key == "config_dirs":
            folders = _string_list(path, key, value)
            if not all(is_path_text(d) for d in folders):
                raise ConfigError(f"{path}: key '{key}': expected folder paths")
            cfg.config_dirs = [(path.parent / d).resolve() for d in folders]
        elif key == "rt_cpus":
            try:
                cfg.rt_cpus = parse_cpus(str(value))
            except ValueError as exc:
                raise ConfigError(f"{path}: key 'rt_cpus': {exc}") from None
        elif key == "rt_lock_memory":
            if not isinstance(value, bool):
                raise ConfigError(f"{path}: key 'rt_lock_memory': expected true or false")
            cfg.rt_lock_memory = value
        elif key in ("prefix", "vehicle_id", "mode", "viewer", "realtime", "tls_front"):
            if not isinstance(value, str):
                raise ConfigError(f"{path}: key '{key}': expected a string")
            setattr(cfg, key, value)
        else:
            setattr(cfg, key, Path(value))
    if cfg.realtime not in REALTIME_MODES:
        raise ConfigError(f"{path}: key 'realtime': expected one of "
                          f"{', '.join(REALTIME_MODES)}, got {cfg.realtime!r}")
    if cfg.tls_front not in TLS_FRONT_MODES:
        raise ConfigError(f"{where('tls_front')}: expected one of "
                          f"{', '.join(TLS_FRONT_MODES)}, got {cfg.tls_front!r}")
    if cfg.mode not in (None, "peer", "router", "client"):
        raise ConfigError(f"{path}: key 'mode': expected peer, router or client")
    for key in ("scene", "zenoh_config"):
        file = getattr(cfg, key)
        if file is not None and not file.is_file():
            raise ConfigError(f"{where(key)}: {file}: no such file")
    if base.get("cars") is not None:  # several cars in one world (simserver.fleet)
        cfg.cars = fleet.parse_cars(path, base["cars"], cfg.max_cars)
    if cfg.command_log is not None:
        _check_command_log(where("command_log"), cfg.command_log)
    try:
        proto.vehicle_keys(cfg.prefix, cfg.vehicle_id)
    except proto.ProtocolError as exc:
        raise ConfigError(f"{path}: {exc}") from exc
    if cfg.viewer != "off":
        from simserver.adapters.rerun_sink import RerunSinkError, _split_host_port, parse_sink

        try:
            mode, target = parse_sink(cfg.viewer)
            if mode == "serve" and target is not None:
                _split_host_port(mode, target, "127.0.0.1", 0)  # the port is in 1-65535
        except RerunSinkError as exc:
            raise ConfigError(f"{where('viewer')}: {exc}") from exc
        why = check_log_path(Path(target)) if mode == "save" and target else None
        if why is not None:  # a recording is written like a log (simserver.logfile)
            raise ConfigError(f"{where('viewer')}: {target} {why}")
    try:
        cfg.ros2 = ros2_cli.serve_settings(base.get("ros2"), ros2_flag, source=f"{path}: ros2")
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    if not cfg.config_dirs:
        cfg.config_dirs = [REPO_CONFIGS, path.parent]
    return cfg


COMMAND_LOG_FLUSH_S = 0.1
"""Longest time an applied input stays in the command log's buffer before it is written."""


class CommandLog:
    """Applied inputs and physics-changing controls, one JSON object a line.

    Lines: a header (scene, vehicle, step); ``{"step": n, "inputs": [steer, throttle,
    brake, parking_brake, gear]}`` whenever the applied inputs change (before physics step
    ``n``); ``{"step": n, "reset": pose|null}``, ``{"step": n, "set_road": {...}}``,
    ``{"step": n, "load": {"scene": ..., "vehicle": ...}}``; and at a clean shutdown
    ``{"end": n, "state": [hex floats]}``, the full final state, for checking a replay.
    A log that could not be written to its end (a full disk, an I/O error) ends instead
    with ``{"end": n, "cut": reason}``: every line before it is whole and the replay of its
    ``n`` steps is the live run's.

    Written off the tick (``docs/reliability.md``, "Logs that fail safe"): the tick thread
    only formats a line and hands it to a :class:`simserver.logfile.LogWriter`, whose own
    thread writes control lines at once and input lines at least every
    ``COMMAND_LOG_FLUSH_S / 2``, so a ``kill -9`` of the server loses at most the last
    :data:`COMMAND_LOG_FLUSH_S` of inputs; a line torn by the kill is ignored by
    :func:`read_command_log`. No ``fsync`` but at a clean shutdown: what the server wrote
    survives the server's crash, not a crash of the machine. A write that fails closes the
    log with one warning and the live loop goes on. The file is opened by
    :func:`simserver.logfile.open_log_file` (no symbolic link, regular files only, never
    blocking).
    """

    def __init__(self, path: Path, header: dict[str, Any]) -> None:
        fd = open_log_file(path, "command log")
        self._writer = LogWriter(fd, path, self._cut_line, COMMAND_LOG_FLUSH_S / 2,
                                 what="command log")
        self._logged_inputs = np.full(L.N_INPUT, np.nan)
        self._writer.put(0, json.dumps({"simserver_command_log": 1, **header},
                                       separators=(",", ":")) + "\n", urgent=True)

    @staticmethod
    def _cut_line(step: int, reason: str) -> str:
        return json.dumps({"end": step, "cut": reason}, separators=(",", ":")) + "\n"

    @property
    def cut(self) -> str | None:
        """Why the log was cut (closed before the end), or None."""
        return self._writer.cut

    def write(self, entry: dict[str, Any]) -> None:
        """Append one control line (``{"step": n, ...}``), written at once."""
        if not self._writer.stopped:
            self._writer.put(entry["step"], json.dumps(entry, separators=(",", ":")) + "\n",
                             urgent=True)

    def log_inputs(self, step: int, inputs: np.ndarray) -> None:
        """The inputs applied at physics step ``step``, if they changed since the last line
        (called at every step)."""
        if not self._writer.stopped and not np.array_equal(inputs, self._logged_inputs):
            self._logged_inputs[:] = inputs
            self._writer.put(step, json.dumps({"step": step,
                                               "inputs": [float(v) for v in inputs]},
                                              separators=(",", ":")) + "\n")

    def close(self, steps: int, state: np.ndarray) -> None:
        """Write the end line with the exact final state, fsync and close (a log already
        cut stays as it is)."""
        self._writer.close((steps, json.dumps({"end": steps, "state": [float(v).hex()
                                                                       for v in state]},
                                              separators=(",", ":")) + "\n"))


def new_simulation(scene: Scene, dt_s: float) -> Simulation:
    """The simulation a vehicle slot steps (the one place the server builds it)."""
    return Simulation(scene, dt_s)


class DuplicateVehicleError(RuntimeError):
    """Another server already serves this vehicle id on the zenoh network."""


COLD_COMPILE_S = (45, 90)
"""A cold start's compile time on the development machine (2 vCPUs; 61 s quiet, more when busy:
``python -m benchmarks.bench_compile``), for the log line."""


class CompileProgress:
    """Say so when compiling takes long (a cold numba cache), with the seconds so far.

    Silent when the kernels come from the cache (under ``quiet_s``); otherwise one line
    ``simserver: compiling ... (first start only, about 45-90 s)``, one line every
    ``every_s`` with the time so far, and one when done. A daemon thread prints them: the
    compiling thread is busy.
    """

    def __init__(self, quiet_s: float = 1.0, every_s: float = 5.0,
                 out: Any = None) -> None:
        self.quiet_s = quiet_s
        self.every_s = every_s
        self.out = out
        self.announced = False
        self._done = threading.Event()
        self._t0 = 0.0

    def _print(self, text: str) -> None:
        print(text, file=self.out or sys.stdout, flush=True)

    def _watch(self) -> None:
        if self._done.wait(self.quiet_s):
            return
        self.announced = True
        lo, hi = COLD_COMPILE_S
        self._print(f"simserver: compiling the vehicle kernels (first start only, about "
                    f"{lo}-{hi} s; later starts load them from the cache) ...")
        while not self._done.wait(self.every_s):
            self._print(f"simserver: compiling ... {time.perf_counter() - self._t0:.0f} s")

    def __enter__(self) -> CompileProgress:
        self._t0 = time.perf_counter()
        self._thread = threading.Thread(target=self._watch, name="compile-progress",
                                        daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._done.set()
        self._thread.join()
        if self.announced:
            self._print(f"simserver: compiled in {time.perf_counter() - self._t0:.1f} s")


def effective_endpoints(zcfg: Any, key: str = "listen/endpoints") -> list[str]:
    """The endpoints a zenoh config really has (a list, or per mode for routers/peers)."""
    value = json.loads(zcfg.get_json(key))
    if isinstance(value, dict):
        mode = json.loads(zcfg.get_json("mode")) or "peer"
        value = value.get(mode, [])
    return [str(v) for v in value or []]


def loopback_of(endpoint: str) -> str:
    """An endpoint a local client can connect to (``0.0.0.0``/``[::]`` -> loopback)."""
    return endpoint.replace("0.0.0.0", "127.0.0.1").replace("[::]", "[::1]")


class SimServer:
    """The live server over zenoh: one vehicle slot, the loop, the viewer, the signals.

    ``run()`` blocks until SIGINT/SIGTERM or ``stop()``. The logic lives in
    :class:`simserver.vehicle_slot.VehicleSlot` and :class:`simserver.server_loop.ServerLoop`;
    this class only wires them to zenoh (:mod:`simserver.adapters.zenoh_io`), applies the
    real-time scheduling (:class:`simserver.realtime.RealtimeScheduler`) and watches the
    viewer and the vehicle's liveliness once a second.
    """

    def __init__(self, cfg: ServerConfig) -> None:
        self.cfg = cfg
        with CompileProgress():
            # one car, or the cars of cfg.cars in one world (checked: ConfigError naming
            # the file and the car before anything runs)
            self.cars = fleet.make_cars(cfg, load_scene(cfg.scene))
            self.slots: list[VehicleSlot] = [car.slot for car in self.cars]
            for slot in self.slots:
                slot.warm_up()
        self.preparer = ProcessPreparer()
        trace = os.environ.get(TICK_TRACE_ENV)
        self.loop = ServerLoop(cfg, preparer=self.preparer,
                               trace=TickTrace(trace) if trace else None)
        self.scheduler = RealtimeScheduler(cfg.realtime_settings(), log=log.log)
        self.viewer: subprocess.Popen | None = None
        self.viewer_command: str | None = None
        self._viewer_reported = False
        self._alive_watches: list[Any] = []
        self._tokens: dict[str, Any] = {}  # each car's liveliness token, by id
        self._new_logs: dict[str, CommandLog] = {}  # of cars being added, by id
        self._removed_slots: list[VehicleSlot] = []
        self._zid = ""
        self.fronts: Any = None  # the TLS fronts (simserver.adapters.tls_front), if any

    @property
    def physics(self) -> Simulation:
        """The first (default: only) vehicle's simulation."""
        return self.slots[0].sim

    def stop(self, *_: Any) -> None:
        """Ask the loop to finish (signal handler)."""
        self.loop.stop()

    def run(self) -> dict[str, Any]:
        """Serve until stopped; returns the final statistics.

        Raises
        ------
        DuplicateVehicleError
            When the vehicle's liveliness token already exists on the network.
        """
        from simserver.adapters.zenoh_io import ZenohEndpoint, make_zenoh_config

        cfg = self.cfg
        t_compile = time.perf_counter()
        for slot in self.slots:
            slot.warm_up()  # from the cache: the kernels compiled in __init__
        compile_s = time.perf_counter() - t_compile
        zcfg = make_zenoh_config(listen=cfg.listen, connect=cfg.connect,
                                 config_file=cfg.zenoh_config, mode=cfg.mode)
        listen = effective_endpoints(zcfg)
        fn, job_args = self.slots[0].load_job({})  # the load worker: imports, one scene
        self.preparer.warm(fn, *job_args)
        loop = self.loop
        loop.running = True  # before the handlers: a signal from now on ends the loop
        previous = {s: signal.signal(s, self.stop) for s in (signal.SIGINT, signal.SIGTERM)}
        ros2 = fronts = None
        try:
            if cfg.tls_front == "auto" and any(ep.startswith("tls/") for ep in listen):
                # docs/security.md section 5: the public TLS port is an accept-filtering
                # front (its own process); zenoh listens on loopback behind it
                from simserver.adapters.tls_front import FrontSupervisor

                fronts = self.fronts = FrontSupervisor(listen)
                zcfg = make_zenoh_config(listen=fronts.zenoh_listen, connect=cfg.connect,
                                         config_file=cfg.zenoh_config, mode=cfg.mode)
                listen = fronts.public_listen
            with ZenohEndpoint(zcfg, prefix=cfg.prefix, vehicle=cfg.vehicle_id) as ep:
                if fronts is not None:  # zenoh listens now: lock it to the fronts (issue
                    fronts.start()      # 34), then start them
                self._zid = str(ep.session.zid())
                for slot in self.slots:
                    self._claim_vehicle(ep, slot)
                for car in self.cars:
                    slot = car.slot
                    if slot.cfg.command_log is not None:
                        slot.command_log = CommandLog(slot.cfg.command_log, {
                            "scene": str(slot.scene_path), "dt_s": cfg.period_s, "step": 0})
                        if car.spec is not None:  # its vehicle and start (a replay's)
                            fleet.log_start(slot, car.spec)
                for slot in self.slots:
                    loop.add(slot, self._ports(ep, slot.keys))
                # every car's id, pose and speed at world_hz (docs/protocol.md 5.1), and
                # the world's controls: cars added and removed while it runs
                loop.world_message = fleet.world_message_for(self.cars, cfg)
                loop.publish_world = ep.declare_world_publisher(cfg.prefix).put
                loop.world_desk = WorldDesk(
                    loop, cfg, ep.declare_control_inbox(keys=proto.world_keys(cfg.prefix),
                                                        validate=False),
                    lambda car_cfg: self._added_ports(ep, car_cfg), self._removed,
                    on_added=self._added)
                first = self.slots[0]
                log.info("serving %s (vehicle %s) every %.3f ms; compiled in %.2f s",
                         first.keys.base, first.sim.scene.vehicle.name,
                         1e3 * cfg.period_s, compile_s)
                summary = self.scheduler.apply()
                renew_log_thread()  # its writer thread under the tick's policy, one lower
                if fronts is not None and self.scheduler.policy == "SCHED_FIFO":
                    fronts.set_priority(max(1, self.scheduler._rt_priority - 1))
                log.log(logging.WARNING if self.scheduler.warnings else logging.INFO, "%s",
                        summary)
                loop.every_second.append(self._housekeeping)
                where = f"listen {', '.join(listen)}" if listen else \
                    f"connect {', '.join(effective_endpoints(zcfg, 'connect/endpoints'))}"
                cars = "" if len(self.slots) == 1 else \
                    f", {len(self.slots)} cars: {', '.join(s.keys.vehicle for s in self.slots)}"
                print(f"simserver: ready on {first.keys.base} ({where}){cars}", flush=True)
                self.viewer = self._start_viewer(listen)
                ros2 = self._start_ros2(listen)
                loop.run()
        finally:
            for s, h in previous.items():
                signal.signal(s, h)
            if fronts is not None:
                fronts.stop()
            self._stop_viewer(self.viewer)
            if ros2 is not None:
                ros2.stop(self._stop_viewer)
            self.preparer.close()
            if loop.world_desk is not None:
                loop.world_desk.close()
            self.scheduler.release()
            served = [s for s, _ in loop.slots] or self.slots  # cars added and removed
            for slot in served:
                if slot.command_log is not None:
                    slot.command_log.close(slot.steps_total, slot.sim.x)
        final = loop.final_stats()
        cuts = [s.command_log.cut for s in (*served, *self._removed_slots)
                if s.command_log is not None and s.command_log.cut is not None]
        if cuts:  # the live run went on without its log (docs/reliability.md)
            final["command_log_cut"] = cuts[0]
        print("simserver: stopped " + json.dumps(final), flush=True)
        return final

    def _ports(self, ep: Any, keys: proto.VehicleKeys) -> SlotPorts:
        """A car's transport: its command inbox, publisher and control queryable."""
        cfg = self.cfg
        commands = ep.declare_command_inbox(capacity=proto.COMMAND_RING_SLOTS, keys=keys)
        # puts in the tick while they are cheap, else off the tick thread
        publisher = ep.declare_vehicle_publisher(
            keys=keys, states_per_s=1.0 / (cfg.period_s * cfg.state_every),
            sender_thread=True, inline_while_cheap=True)
        controls = ep.declare_control_inbox(keys=keys, validate=False)
        return SlotPorts(commands, controls, publisher)

    def _added_ports(self, ep: Any, car_cfg: ServerConfig) -> SlotPorts:
        """A car added while running (``world_desk``, in its thread): its id claimed on the
        network, its transport, its command log; its liveliness token last (clients find
        it once it is served)."""
        keys = proto.vehicle_keys(car_cfg.prefix, car_cfg.vehicle_id)
        if ep.alive_tokens(keys.alive, timeout_s=ALIVE_QUERY_S):
            raise DuplicateVehicleError(f"vehicle '{car_cfg.vehicle_id}' is already served "
                                        "on this zenoh network")
        ports = self._ports(ep, keys)
        if car_cfg.command_log is not None:  # opened here: a file and a thread, not the tick
            self._new_logs[car_cfg.vehicle_id] = CommandLog(car_cfg.command_log, {
                "scene": str(car_cfg.scene), "dt_s": car_cfg.period_s, "step": 0})
        self._tokens[car_cfg.vehicle_id] = ep.declare_alive_token(keys=keys)
        return ports

    def _added(self, slot: VehicleSlot) -> None:
        """A car joined the world (in the tick): its command log, opened beforehand."""
        slot.command_log = self._new_logs.pop(slot.keys.vehicle, None)
        fleet.log_start(slot, fleet.CarSpec(id=slot.keys.vehicle, where="",
                                            vehicle=slot.sim.scene.vehicle.path))

    def _removed(self, slot: VehicleSlot, ports: SlotPorts) -> None:
        """A removed car's transport closed (``world_desk``, in its thread); its log ends
        with the state it had when it left (``slot.final_state``)."""
        token = self._tokens.pop(slot.keys.vehicle, None)
        if token is not None:
            token.undeclare()
        for port in (ports.commands, ports.controls, ports.publisher):
            port.close()
        self._removed_slots.append(slot)
        if slot.command_log is not None:
            slot.command_log.close(slot.steps_total, slot.final_state)

    # ------------------------------------------------------------------ one vehicle id
    def _claim_vehicle(self, ep: Any, slot: VehicleSlot) -> None:
        """Refuse a vehicle id another server serves; declare ours and watch for others.

        Zenoh merges liveliness tokens of the same key (a second one is not announced,
        and the first one's end looks like the key's end), so besides the protocol's
        ``alive`` token each server declares ``alive/<its session id>`` and watches
        ``alive/*`` for the others'.
        """
        keys = slot.keys
        present = ep.alive_tokens(keys.alive, timeout_s=ALIVE_QUERY_S)
        if present:
            raise DuplicateVehicleError(
                f"vehicle '{cfg_vehicle(slot)}' is already served on this zenoh network "
                f"(liveliness token {keys.alive} exists): stop that server or give this one "
                "another --vehicle-id")
        self._tokens[slot.keys.vehicle] = ep.declare_alive_token(keys=keys)
        ep._keep(ep.session.liveliness().declare_token(f"{keys.alive}/{self._zid}"))
        self._alive_watches.append((slot, ep.declare_alive_watch(f"{keys.alive}/*")))

    def _check_alive(self) -> None:
        mine = self._zid
        for slot, watch in self._alive_watches:
            for key, appeared in watch.poll():
                if appeared and not key.endswith("/" + mine):
                    log.warning("another server (session %s) now serves vehicle '%s' on "
                                "this zenoh network: clients get both state streams; stop "
                                "one of them", key.rsplit("/", 1)[-1], cfg_vehicle(slot))

    # ------------------------------------------------------------------ once a second
    def _housekeeping(self) -> None:
        """Off the hot path, once a second: new zenoh threads, liveliness, the viewer."""
        self.scheduler.promote_new_threads()
        self._check_alive()
        viewer = self.viewer
        if viewer is not None and not self._viewer_reported:
            code = viewer.poll()
            if code is not None:
                self._viewer_reported = True
                log.warning("the live viewer exited (code %s); the server runs on. Start one "
                            "again with: %s", code, self.viewer_command)

    # ------------------------------------------------------------------ the viewer
    def _start_viewer(self, listen: list[str]) -> subprocess.Popen | None:
        """Start ``simserver view`` in its own process (the physics never waits on it).

        ``serve`` on a port in use moves to a free port and says so; the command to open
        the viewer is logged (the same as the README's).
        """
        cfg = self.cfg
        if cfg.viewer == "off":
            return None
        if not listen:
            log.warning("live viewer not started: the server listens on no endpoint "
                        "(run 'simserver view --connect ENDPOINT' yourself)")
            return None
        from simserver.adapters.rerun_sink import DEFAULT_GRPC_PORT, parse_sink

        sink = cfg.viewer
        mode, target = parse_sink(sink)
        if mode == "serve":
            port = int(target.rpartition(":")[2]) if target else DEFAULT_GRPC_PORT
            if not _port_free(port):
                taken, port = port, _free_port()
                sink = f"serve:{port}"
                log.warning("viewer port %d is in use: the live viewer serves on %d instead "
                            "(choose one with --viewer serve:PORT, or --viewer off)", taken,
                            port)
            # the same command as the README's and the viewer's own line
            log.info("open the live viewer with: rerun rerun+http://127.0.0.1:%d/proxy", port)
        args = [sys.executable, "-m", "simserver", "view", "--sink", sink,
                "--connect", loopback_of(listen[0]), "--prefix", cfg.prefix,
                "--vehicle-id", cfg.vehicle_id]
        self.viewer_command = "simserver " + " ".join(args[3:])
        log.info("live viewer: %s", self.viewer_command)
        return subprocess.Popen(args)

    def _start_ros2(self, listen: list[str]) -> AdapterSupervisor | None:
        """Start ``simserver ros2`` in its own process when configured, like the viewer;
        restarted with backoff if it dies (:mod:`simserver.ros2.supervisor`), its state in
        ``get_config``'s reply."""
        cfg = self.cfg
        if cfg.ros2 is None:
            return None
        if not listen:
            log.warning("ROS 2 adapter not started: the server listens on no endpoint "
                        "(run 'simserver ros2 --connect ENDPOINT' yourself)")
            return None
        args = ros2_cli.adapter_command(loopback_of(listen[0]), cfg.prefix, cfg.vehicle_id,
                                        cfg.ros2)
        log.info("ROS 2 adapter: %s", " ".join(args[2:]))
        adapter = AdapterSupervisor(args)
        adapter.start()
        for slot in self.slots:
            slot.ros2_status = adapter.status
        return adapter

    @staticmethod
    def _stop_viewer(viewer: subprocess.Popen | None) -> None:
        """Stop a child (the viewer, the ROS 2 adapter): at idle CPU priority it may get no
        CPU on a busy machine to run its SIGTERM handler (the README's server took 30 s to
        stop beside other work), so its threads go back to normal priority first."""
        if viewer is None:
            return
        with contextlib.suppress(OSError):  # exited already
            for tid in process_threads(viewer.pid):
                with contextlib.suppress(OSError):  # gone meanwhile, or not ours to change
                    os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
        viewer.terminate()
        try:
            viewer.wait(timeout=10)
        except subprocess.TimeoutExpired:
            viewer.kill()


ALIVE_QUERY_S = 1.0
"""How long the start-up asks the network whether the vehicle id is served already."""


def cfg_vehicle(slot: VehicleSlot) -> str:
    """The vehicle id of a slot."""
    return slot.cfg.vehicle_id


def _port_free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


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
    cut: str | None = None  # why the log was cut at ``steps`` (it holds no final state)

    @property
    def final_state_matches(self) -> bool | None:
        """The replayed final state equals the logged one bit for bit on the common slots
        (None if the log has no end state)."""
        if self.logged_final_state is None:
            return None
        n = self.logged_final_state.size
        return n <= self.final_state.size and bool(
            np.array_equal(self.final_state[:n], self.logged_final_state))


MAX_REPLAY_STEPS = 2_500_000
"""Longest log replayed (about 42 min at 1 kHz): the replay keeps every state and output in
memory, 800 bytes a step (2 GB at this limit)."""
_LOG_INPUT_RANGES = ((-1.0, 1.0), (0.0, 1.0), (0.0, 1.0), (0.0, 1.0), (0.0, 3.0))
"""Ranges of the logged inputs, in the order of ``core.layout.INPUT_NAMES``."""


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number a command log holds")


def _log_numbers(where: str, key: str, value: Any, spec: dict[str, tuple[float, float]],
                 ) -> dict[str, float]:
    if not isinstance(value, dict) or set(value) != set(spec):
        raise ConfigError(f"{where}: key '{key}': expected an object with "
                          f"{', '.join(spec)}")
    return {k: number(where, f"{key}.{k}", value[k], *spec[k]) for k in spec}


def _control_ranges(control: str, member: str | None = None) -> dict[str, tuple[float, float]]:
    """The ranges of a control's numeric arguments, from the protocol's table."""
    args = proto.CONTROL_SPECS[control].args
    if member is not None:
        args = next(a for a in args if a.name == member).children
    return {a.name: (a.lo, a.hi) for a in args}


def _check_log_entry(where: str, entry: Any, last_step: int) -> int:
    """Validate one event line of a command log; its step."""
    if not isinstance(entry, dict):
        raise ConfigError(f"{where}: expected a JSON object, got {type(entry).__name__}")
    if "end" in entry:
        check_keys(where, entry, ("end", "state", "cut"), required=("end",))
        end = entry["end"]
        if isinstance(end, bool) or not isinstance(end, int) or \
                not last_step <= end <= MAX_REPLAY_STEPS:
            raise ConfigError(f"{where}: key 'end': expected an integer step in "
                              f"[{last_step}, {MAX_REPLAY_STEPS}], got {short_repr(end)}")
        if ("state" in entry) == ("cut" in entry):
            raise ConfigError(f"{where}: an end line holds either 'state' (a clean "
                              "shutdown) or 'cut' (a log that could not be written on)")
        if "cut" in entry:  # the log was cut there (CommandLog): no final state
            if not isinstance(entry["cut"], str) or len(entry["cut"]) > 500:
                raise ConfigError(f"{where}: key 'cut': expected the reason, a short text")
            return end
        state = entry["state"]
        # a log of an earlier release holds its shorter layout, a prefix of this one
        if not isinstance(state, list) or not L.N_STATE_V1 <= len(state) <= L.N_STATE:
            raise ConfigError(f"{where}: key 'state': expected {L.N_STATE} (or, from an "
                              f"earlier release, {L.N_STATE_V1} or more) hex floats")
        for k, v in enumerate(state):
            try:
                if not isinstance(v, str):
                    raise ValueError
                float.fromhex(v)
            except (ValueError, OverflowError):
                raise ConfigError(f"{where}: key 'state[{k}]': not a hex float: "
                                  f"{short_repr(v)}") from None
        return end
    kinds = [k for k in ("inputs", "reset", "set_road", "load") if k in entry]
    if len(kinds) != 1:
        raise ConfigError(f"{where}: expected one of inputs, reset, set_road, load, end")
    kind = kinds[0]
    check_keys(where, entry, ("step", kind), required=("step", kind))
    step = entry["step"]
    if isinstance(step, bool) or not isinstance(step, int) or \
            not last_step <= step <= MAX_REPLAY_STEPS:
        raise ConfigError(f"{where}: key 'step': expected an integer step in "
                          f"[{last_step}, {MAX_REPLAY_STEPS}] (steps never go back), got "
                          f"{short_repr(step)}")
    value = entry[kind]
    if kind == "inputs":
        if not isinstance(value, list) or len(value) != L.N_INPUT:
            raise ConfigError(f"{where}: key 'inputs': expected {L.N_INPUT} numbers")
        for name, v, (lo, hi) in zip(L.INPUT_NAMES, value, _LOG_INPUT_RANGES, strict=True):
            val = number(where, f"inputs.{name}", v, lo, hi)
            if name in ("parking_brake", "gear") and not val.is_integer():
                raise ConfigError(f"{where}: key 'inputs.{name}': {val:g} is not a whole "
                                  "number")
    elif kind == "reset":
        if value is not None:  # a reset control's pose, or a scene's start (a fault stop)
            spec = {k: INITIAL_RANGES[k] for k in ("x_m", "y_m", "yaw_rad")}
            if isinstance(value, dict) and "u_mps" in value:  # a reset at speed (issue 17)
                spec["u_mps"] = _control_ranges("reset")["u_mps"]
            _log_numbers(where, "reset", value, spec)
    elif kind == "set_road":
        _log_numbers(where, "set_road", value, _control_ranges("set_road"))
    else:
        if not isinstance(value, dict) or set(value) != {"scene", "vehicle"} or \
                not isinstance(value["scene"], str) or \
                not isinstance(value["vehicle"], str | None):
            raise ConfigError(f"{where}: key 'load': expected {{\"scene\": path, "
                              "\"vehicle\": path or null}")
    return step


def read_command_log(path: str | Path) -> list[dict[str, Any]]:
    """Parse and validate a command log, with errors naming the file, line and key.

    A last line without its newline that is not valid JSON is the line the server was
    writing when it was killed (``kill -9``, a crash): it is dropped with a warning. Any
    other malformed line is an error (``ConfigError``), as are values a live server never
    logs (NaN, inputs out of range, steps going back, more than
    :data:`MAX_REPLAY_STEPS`).
    """
    path = Path(path)
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            raise ConfigError(f"{path}: cannot read: not a regular file")
        with path.open("rb") as f:
            text = f.read().decode("utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a simserver command log (not UTF-8 text at byte "
                          f"{exc.start})") from None
    lines = text.split("\n")
    torn = lines.pop()  # "" when the file ends with a newline, as every complete log does
    entries = []
    for n, line in enumerate(lines, 1):
        try:
            entries.append(json.loads(line, parse_constant=_reject_constant))
        except (ValueError, RecursionError) as exc:
            msg = exc.msg if isinstance(exc, json.JSONDecodeError) else str(exc) or "too deep"
            raise ConfigError(f"{path}:{n}: not a JSON line: {msg}") from None
    if torn:
        try:
            entries.append(json.loads(torn, parse_constant=_reject_constant))
        except (ValueError, RecursionError):
            log.warning("%s:%d: the last line is torn (the server was killed while writing "
                        "it): ignored", path, len(lines) + 1)
    header = entries[0] if entries else None
    if not isinstance(header, dict) or header.get("simserver_command_log") != 1:
        raise ConfigError(f"{path}: not a simserver command log (no header line)")
    where = f"{path}:1"
    if not isinstance(header.get("scene"), str):
        raise ConfigError(f"{where}: key 'scene': expected a scene path")
    number(where, "dt_s", header.get("dt_s"), *SERVER_KEYS["period_s"])
    last_step = 0
    for n, entry in enumerate(entries[1:], 2):
        if last_step is None:
            raise ConfigError(f"{path}:{n}: a line after the end line")
        step = _check_log_entry(f"{path}:{n}", entry, last_step)
        last_step = None if "end" in entry else step
    return entries


def replay_command_log(path: str | Path, progress: Any = None) -> Replay:
    """Re-run a command log headless with the same compiled step as the server."""
    entries = read_command_log(path)
    header = entries[0]

    def scene_of(line: int, key: str, scene: str, vehicle: str | None = None) -> Scene:
        try:
            return load_scene(scene, vehicle_path=vehicle)
        except ConfigError as exc:  # a file the log refers to: name the line and the key
            raise ConfigError(f"{path}:{line}: key '{key}': {exc}") from None

    physics = Simulation(scene_of(1, "scene", header["scene"]), float(header["dt_s"]))
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
                pose = None if e["reset"] is None else dict(e["reset"])
                physics.reset(pose, None if pose is None else pose.pop("u_mps", None))
            elif "set_road" in e:
                physics.set_road(**e["set_road"])
            elif "load" in e:
                spec = e["load"]
                physics.load(scene_of(k + 2, "load", spec["scene"], spec["vehicle"]))
            k += 1
        if n == total:
            break
        physics.step()
        states[n] = physics.x
        outputs[n] = physics.out
        if progress is not None and n % 10000 == 0:
            progress(n, total)
    logged = None if end is None or "state" not in end else \
        np.array([float.fromhex(v) for v in end["state"]])
    return Replay(states=states, outputs=outputs, final_state=physics.x.copy(),
                  logged_final_state=logged, steps=total,
                  cut=None if end is None else end.get("cut"))
