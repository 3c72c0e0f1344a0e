"""The real-time server's zenoh wiring: the car at a fixed 1 kHz of wall-clock time, driven
over zenoh (``SimServer``), and the one place the server builds its ``Simulation``
(``new_simulation``). The rest of the server is apart:

- :mod:`simserver.server.config`: the server's settings (``load_server_config``);
- :mod:`simserver.server.command_log`: the command log, read back and replayed;
- :mod:`simserver.server.loop`: the fixed-rate loop (pacer, inbox drain, publish,
  controls dispatched through a table), with the clock, inboxes and publisher injected;
- :mod:`simserver.server.slot`: one car (command arbitration, watchdog, pause and step,
  the state record, the controls' handlers).

Every applied input change and every control that changes the physics is written to an
optional command log, which ``simserver.server.command_log.replay_command_log`` re-runs
headless bit for bit.
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from simserver.ros2 import cli as ros2_cli
from simserver.ros2.supervisor import AdapterSupervisor
from simserver.server import cars_config, fleet
from simserver.server.command_log import CommandLog
from simserver.server.config import ServerConfig
from simserver.server.load_worker import ProcessPreparer
from simserver.server.logfile import renew_log_thread
from simserver.server.loop import ServerLoop, SlotPorts
from simserver.server.realtime import RealtimeScheduler, TickTrace, process_threads
from simserver.server.slot import VehicleSlot
from simserver.server.stats_text import start_text, stop_text
from simserver.server.world_desk import WorldDesk
from simserver.sim.scene import Scene
from simserver.sim.scene_files import load_scene, warm_up_in_helper
from simserver.sim.simulation import Simulation
from simserver.wire import protocol as proto

log = logging.getLogger("simserver.server")

TICK_TRACE_ENV = "SIMSERVER_TICK_TRACE"
"""A file name in this environment variable makes the server record per-tick timing there
(:class:`simserver.server.realtime.TickTrace`; ``benchmarks.bench_load`` reads it)."""


def new_simulation(scene: Scene, dt_s: float) -> Simulation:
    """The simulation a vehicle slot steps (the one place the server builds it)."""
    return Simulation(scene, dt_s)


class DuplicateVehicleError(RuntimeError):
    """Another server already serves this vehicle id on the zenoh network."""


COLD_COMPILE_S = (40, 90)
"""A cold start's compile time on the development machine, for the log line (2 vCPUs: 46 s
to ready quiet, median of 3, 2026-12-07, ``python -m benchmarks --only startup``; 80 s at
load 4.3, where the commit before the step's stages were inlined by LLVM took 122 s)."""


class CompileProgress:
    """Say so when the kernels compile (a cold numba cache), with the seconds so far.

    Silent when the kernels come from the cache, however long that takes on a busy
    machine (a cache load fires no ``numba:compile`` event; a start once said "compiling"
    and "compiled in 1.7 s" loading from the cache); otherwise, once a compile has begun
    and ``quiet_s`` passed, one line ``simserver: compiling ... (first start only, about
    40-90 s)``, one line every ``every_s`` with the time so far, and one when done. A
    daemon thread prints them: the compiling thread is busy.
    """

    def __init__(self, quiet_s: float = 1.0, every_s: float = 5.0,
                 out: Any = None) -> None:
        self.quiet_s = quiet_s
        self.every_s = every_s
        self.out = out
        self.announced = False
        self._done = threading.Event()
        self._compiling = threading.Event()  # a numba:compile event began
        self._t0 = 0.0

    def _print(self, text: str) -> None:
        print(text, file=self.out or sys.stdout, flush=True)

    def _watch(self) -> None:
        if self._done.wait(self.quiet_s):
            return
        while not self._compiling.wait(0.05):
            if self._done.is_set():
                return
        self.announced = True
        lo, hi = COLD_COMPILE_S
        self._print(f"simserver: compiling the vehicle kernels (first start only, about "
                    f"{lo}-{hi} s; later starts load them from the cache) ...")
        while not self._done.wait(self.every_s):
            self._print(f"simserver: compiling ... {time.perf_counter() - self._t0:.0f} s")

    def __enter__(self) -> CompileProgress:
        from numba.core import event

        compiling = self._compiling

        class _Seen(event.Listener):
            def on_start(self, ev: event.Event) -> None:
                compiling.set()

            def on_end(self, ev: event.Event) -> None:
                pass

        self._listener = _Seen()
        event.register("numba:compile", self._listener)
        self._t0 = time.perf_counter()
        self._thread = threading.Thread(target=self._watch, name="compile-progress",
                                        daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        from numba.core import event

        event.unregister("numba:compile", self._listener)
        self._done.set()
        self._thread.join()
        if self.announced:
            self._print(f"simserver: compiled in {time.perf_counter() - self._t0:.1f} s")


def _shown_path(path: Any) -> str:
    """A scene file as a person finds it: relative to the working directory when under it."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd()))
    except (TypeError, ValueError, OSError):
        return str(path)


def loopback_of(endpoint: str) -> str:
    """An endpoint a local client can connect to (``0.0.0.0``/``[::]`` -> loopback)."""
    return endpoint.replace("0.0.0.0", "127.0.0.1").replace("[::]", "[::1]")


def _collision_sender(loop: ServerLoop, publisher: Any) -> Callable[[bytes], None]:
    """Where the loop's collision events go: put by the sender thread (``state-tx``) of
    the world's first car (the cars change while the world runs; each has one), never
    in the tick (docs/protocol.md 5.1)."""

    def send(payload: bytes) -> None:
        if loop.slots:
            loop.slots[0][1].publisher.publish_on(publisher, payload)

    return send


class SimServer:
    """The live server over zenoh: one vehicle slot, the loop, the viewer, the signals.

    ``run()`` blocks until SIGINT/SIGTERM or ``stop()``. The logic lives in
    :class:`simserver.server.slot.VehicleSlot` and :class:`simserver.server.loop.ServerLoop`;
    this class only wires them to zenoh (:mod:`simserver.adapters.zenoh_io`), applies the
    real-time scheduling (:class:`simserver.server.realtime.RealtimeScheduler`) and watches the
    viewer and the vehicle's liveliness once a second.
    """

    def __init__(self, cfg: ServerConfig, scenario: Any = None) -> None:
        self.cfg = cfg
        # an OpenSCENARIO scenario served live (simserver.server.scenario_live), or None
        self.scenario = scenario
        self.preparer = ProcessPreparer()
        if scenario is None:
            # the load worker starts now and compiles the warm-up's kernels that call no
            # step into the cache, beside this process's compile of the step (a cold
            # cache: two cores at work; a warm one: a few loads from the cache); this
            # process's warm-up then finds them there (sim.scene_files.warm_up_in_helper)
            self.preparer.warm(warm_up_in_helper, str(cfg.scene), cfg.period_s)
        try:
            with CompileProgress():
                # one car, or the cars of cfg.cars in one world (checked: ConfigError
                # naming the file and the car before anything runs), or the scenario's
                # entities
                self.cars = (scenario.make_cars(cfg) if scenario is not None
                             else fleet.make_cars(cfg, load_scene(cfg.scene)))
                self.slots: list[VehicleSlot] = [car.slot for car in self.cars]
                for slot in self.slots:
                    slot.warm_up()
                # and drive() compiled (also for a driven car add_car may bring)
                live_drivers = fleet.prepare_drivers(self.cars, cfg.max_cars)
        except BaseException:  # a bad config: no worker outlives the refusal
            self.preparer.close()
            raise
        trace = os.environ.get(TICK_TRACE_ENV)
        self.loop = ServerLoop(cfg, preparer=self.preparer,
                               trace=TickTrace(trace) if trace else None)
        self.loop.live_drivers = live_drivers
        if scenario is not None:
            scenario.attach(self.loop)
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

    def run(self, stats_json: bool = False) -> dict[str, Any]:
        """Serve until stopped; returns the final statistics, printed as a few lines
        (``server.stats_text``) and, with ``stats_json``, as the JSON line
        ``simserver: stopped {...}`` too.

        Raises
        ------
        DuplicateVehicleError
            When the vehicle's liveliness token already exists on the network.
        """
        from simserver.adapters.zenoh_io import (
            ZenohEndpoint,
            effective_endpoints,
            make_zenoh_config,
        )

        cfg = self.cfg
        t_compile = time.perf_counter()
        for slot in self.slots:
            slot.warm_up()  # from the cache: the kernels compiled in __init__
        compile_s = time.perf_counter() - t_compile
        zcfg = make_zenoh_config(listen=cfg.listen, connect=cfg.connect,
                                 config_file=cfg.zenoh_config, mode=cfg.mode)
        listen = effective_endpoints(zcfg)
        fn, job_args = self.slots[0].load_job({})  # the load worker: imports, one scene
        warming = self.preparer.warm(fn, *job_args)
        progress = self.preparer.progress
        for slot in self.slots:  # a client can wait for it (tests: a first load's reply)
            slot.load_worker_status = lambda: {"ready": warming.done(),
                                               "progress": progress.message()}
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
                loop.publish_collision = _collision_sender(
                    loop, ep.declare_collision_publisher(cfg.prefix))
                if self.scenario is not None:  # its Collision conditions see the events
                    loop.publish_collision = self.scenario.watch_collisions(
                        loop.publish_collision)
                loop.world_desk = WorldDesk(
                    loop, cfg, ep.declare_control_inbox(keys=proto.world_keys(cfg.prefix),
                                                        validate=False),
                    lambda car_cfg: self._added_ports(ep, car_cfg), self._removed,
                    on_added=self._added)
                first = self.slots[0]
                # the kernels compiled (if at all) in __init__, which said so
                # (CompileProgress); here they load from the cache
                log.info("serving %s (vehicle %s) every %.3f ms; kernels ready in %.2f s",
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
                print(start_text(
                    f"simserver: ready on {first.keys.base} ({where}){cars}",
                    [(s.keys.base, s.sim.scene.vehicle.name, _shown_path(s.scene_path))
                     for s in self.slots], cfg.period_s,
                    loopback_of(listen[0]) if listen else None), flush=True)
                self.viewer = self._start_viewer(listen)
                ros2 = self._start_ros2(listen)
                if self.scenario is not None:  # its storyboard, in its own thread
                    self.scenario.start(ep.declare_storyboard_publisher(cfg.prefix).put)
                loop.run()
        finally:
            if self.scenario is not None:
                self.scenario.stop()
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
        print(stop_text(final), flush=True)
        if stats_json:
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
        fleet.log_start(slot, cars_config.CarSpec(id=slot.keys.vehicle, where="",
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
                "--vehicle-id", cfg.vehicle_id, "--fps", f"{cfg.viewer_fps:g}"]
        self.viewer_command = "simserver " + " ".join(args[3:])
        log.info("live viewer: %s", self.viewer_command)
        # beside the physics on this machine: only CPU time nothing else wants (a view
        # started by hand runs at viewer.VIEW_NICE)
        return subprocess.Popen([*args, "--idle-priority"])

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
                                        cfg.ros2, several_cars=len(cfg.cars or ()) > 1)
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

