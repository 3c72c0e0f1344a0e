"""An OpenSCENARIO scenario served live: ``simserver serve --scenario FILE.xosc`` (issue 31
items 2-3; docs/openscenario.md, "Served live").

Every entity of the scenario is a car of the server's world (the cars the headless player
makes, ``simserver.sim.xosc_run.setup``: the reference sedan at its start, at its initial
speed, with its own path and tracking IDM), driven by the built-in driver
(``simserver.server.live_drivers``). With ``ego_from="zenoh"`` the ego
(``xosc_run.ego_name``: the entity named ``Ego``, else the first) is a client's car instead:
a person drives it with the keyboard client, and the storyboard's conditions measure it as
they measure every car.

Nothing of the storyboard runs in the tick. A worker thread (:class:`ScenarioLive`)
evaluates the storyboard every ``xosc_run.STORYBOARD_PERIOD_S`` of *simulated* time, as the
headless player does, on a copy of the world's state rows taken between two of its own
looks (a ``numpy`` copy of a few kB: the tick thread's compiled step holds the GIL, so the
copy is of one tick's rows). The storyboard's actions become driver targets in a private
copy of the driver's arrays; what changed (a target speed, a stop point, a lane change's
rewritten path rows) is *posted*, and the loop applies the posted writes between two ticks
(:meth:`ScenarioLive.apply_posted`, a loop tick hook: a few array writes, microseconds). A
write posted for driver arrays that were assembled anew since (a car added or removed) is
dropped. Actions on the person's car are not applied (a person is not commanded): the
trace says so.

Every storyboard element's state change goes out on ``{prefix}/world/storyboard``
(``protocol.ENCODING_STORYBOARD``, one JSON object, the trace line of
``run-scenario``'s ``storyboard_trace.jsonl``; non-finite condition values as null), put by
the worker, and the viewer logs them as ``TextLog`` entries on the ``sim_time`` timeline
(``simserver.adapters.viewer``). Contact events reach the ``Collision`` condition through
the loop's collision sender (:meth:`ScenarioLive.watch_collisions`: the payload is queued in
the tick, decoded by the worker). When the simulated time goes back (a world ``reset``) the
storyboard starts again from its start.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
import math
import threading
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from simserver.adapters import openscenario as X
from simserver.adapters.validate import ConfigError
from simserver.core import driver as D
from simserver.core import layout as L
from simserver.core.terrain import TERRAIN_PLANE, terrain_road
from simserver.server import cars_config, fleet
from simserver.sim import xosc_run as XR
from simserver.wire import protocol as proto

log = logging.getLogger("simserver.server")

EGO_FROM = ("driver", "zenoh")
"""Who drives the ego of a served scenario: the built-in driver under the storyboard, as
every other car, or a client over zenoh (a person with the keyboard client)."""
POLL_S = 0.002
"""The worker looks at the world's time this often (wall); it evaluates the storyboard
when a ``STORYBOARD_PERIOD_S`` boundary of simulated time has passed."""
TARGET_COLUMNS = (D.DS_TARGET_SPEED_MPS, D.DS_STOP_STATION_M, D.DS_GO_TIME_S)
"""The driver-state columns the storyboard writes (``core.driver.set_target_speed``,
``stop_at``, ``go``): the only ones posted to the tick."""


def _finite(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None (nothing non-finite leaves)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if isinstance(value, np.floating):
        return _finite(float(value))
    return value


def trace_payload(entry: dict[str, Any]) -> bytes:
    """A trace line as the ``storyboard`` message's JSON (finite numbers only)."""
    return json.dumps(_finite(entry), separators=(",", ":"), allow_nan=False).encode()


class LiveStoryboard(XR.Storyboard):
    """The headless storyboard, but the person's cars are not commanded."""

    def __init__(self, sc: X.Scenario, cars: dict[str, XR.Car], drivers: D.Drivers,
                 human: set[str]) -> None:
        super().__init__(sc, cars, drivers)
        self.human = human

    def _start_action(self, a: X.Action, now: float) -> None:
        actors = tuple(n for n in a.actors if n not in self.human)
        for name in a.actors:
            if name in self.human:
                self.trace.append({"t_s": round(now, 6), "kind": "note", "name": a.name,
                                   "note": f"{a.kind} on {name}, the person's car: not "
                                           "applied"})
        if actors:
            super()._start_action(dataclasses.replace(a, actors=actors), now)

    def _command(self, car: XR.Car, now: float) -> None:
        if car.name not in self.human:
            super()._command(car, now)


class ScenarioLive:
    """A scenario served live (module docstring): the cars, then the worker.

    ``ScenarioLive(path, ego_from)`` reads the file (``XoscError``/``ConfigError`` naming
    file, line and element: nothing is served); :meth:`make_cars` makes the server's cars;
    :meth:`attach` hooks the loop; :meth:`start` starts the worker, :meth:`stop` ends it.
    """

    def __init__(self, path: str | Path, ego_from: str = "driver") -> None:
        if ego_from not in EGO_FROM:
            raise ConfigError(f"--ego-from: expected one of {', '.join(EGO_FROM)}, got "
                              f"{ego_from!r}")
        self.path = Path(path)
        self.sc, cars, self.ws = XR.setup(self.path)
        for line in self.sc.ignored:
            log.warning("%s", line)
        if len(cars) < 2:  # the live loop drives the cars of a world of several only
            raise ConfigError(f"{self.path}: <Entities>: serve --scenario needs at least two "
                              f"entities, this file has {len(cars)} (run-scenario plays "
                              "it headless)")
        self.ego = XR.ego_name(self.sc)
        self.human = {self.ego} if ego_from == "zenoh" else set()
        self._start_cars = {n: dataclasses.replace(c) for n, c in cars.items()}
        for name in cars:
            cars_config.check_car_id(f"{self.path}: entity {name!r}", name)
        self.loop: Any = None
        self.trace: list[dict[str, Any]] = []  # every line published (tests, the log)
        self._posted: collections.deque = collections.deque()
        self._contacts: collections.deque = collections.deque()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._publish: Callable[[bytes], None] | None = None
        self.evaluations = 0
        self.failed: str | None = None

    # ------------------------------------------------------------------ the cars
    def make_cars(self, cfg: Any) -> list[fleet.ServedCar]:
        """The server's cars: every entity in ``<Entities>`` order, one world; the person's
        ego a client's car, every other car the built-in driver's."""
        from simserver.server.slot import VehicleSlot

        if len(self.ws.cars) > cfg.max_cars:
            raise ConfigError(f"{self.path}: {len(self.ws.cars)} entities, more than "
                              f"max_cars ({cfg.max_cars})")
        scenes = {cid: s.scene for cid, s in self.ws.cars.items()}
        sims = fleet.build_world(scenes, cfg.period_s)
        served = []
        several = len(scenes) > 1
        for cid, s in self.ws.cars.items():
            car_cfg = dataclasses.replace(cfg, vehicle_id=cid, command_log=fleet.car_log_path(
                cfg.command_log, cid, several))
            slot = VehicleSlot(car_cfg, sims[cid])
            u_mps = float(s.scene.initial.get("u_mps", 0.0))
            if u_mps > 0.0:  # a world reset restarts the scenario: each car at its speed
                slot.world_reset_args = {"u_mps": u_mps}
            driven = cid not in self.human
            if driven:
                slot.drive_by_driver()
            spec = cars_config.CarSpec(id=cid, where=f"{self.path} ({cid})",
                                       vehicle=XR.REFERENCE_CAR,
                                       driven_by="driver" if driven else "client")
            served.append(fleet.ServedCar(spec, slot, s.driver if driven else None))
        return served

    def attach(self, loop: Any) -> None:
        """Hook ``loop`` (before its cars are added): each driven car a path of its own,
        the posted driver targets applied once a tick."""
        self.loop = loop
        if loop.live_drivers is not None:
            loop.live_drivers.own_paths = True
        loop.tick_hooks.append(self.apply_posted)

    def watch_collisions(self, send: Callable[[bytes], None] | None
                         ) -> Callable[[bytes], None]:
        """The loop's collision sender, with each payload queued for the ``Collision``
        condition too (an append in the tick; decoded by the worker)."""

        def both(payload: bytes) -> None:
            self._contacts.append(payload)
            if send is not None:
                send(payload)

        return both

    # ------------------------------------------------------------------ the tick's part
    _tick_t = -math.inf
    _restart: Any = None

    def apply_posted(self) -> None:
        """The worker's posted driver targets, written between two ticks (a few writes);
        and, when the world's time went back (a ``reset`` committed in this tick), a copy
        of its start rows for the worker: the restarted storyboard's first look is at the
        start, time 0, whenever the worker gets to it."""
        world = self.loop.world
        if world is not None:
            t = world.data.x[0, L.TIME_S]
            if t < self._tick_t:
                self._restart = world.data.x.copy()
            self._tick_t = t
        posted = self._posted
        if not posted:
            return
        drivers = self.loop.drivers
        while posted:
            key, states, paths = posted.popleft()
            if drivers is None or id(drivers) != key:
                continue  # assembled anew since: the targets were for other rows
            for c, j, value in states:
                drivers.state[c, j] = value
            for first, rows in paths:
                drivers.paths[first:first + len(rows)] = rows

    # ------------------------------------------------------------------ the worker
    def start(self, publish: Callable[[bytes], None] | None = None) -> None:
        """Start the worker; each trace line goes to ``publish`` (a zenoh put). The first
        evaluation runs here, before the loop's first tick, at simulated time 0 (as the
        headless player's: a ``rising`` edge of ``SimulationTime > 0`` needs the look at 0)."""
        self._publish = publish
        self._thread = threading.Thread(target=self._work, name="storyboard", daemon=True)
        self._work(first=True)
        if self.failed is None:
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread.is_alive():
            self._thread.join(timeout=5.0)

    def _fresh_board(self, drivers: D.Drivers) -> tuple[LiveStoryboard, dict[str, XR.Car]]:
        cars = {n: dataclasses.replace(c) for n, c in self._start_cars.items()}
        return LiveStoryboard(self.sc, cars, drivers, self.human), cars

    def _work(self, first: bool = False) -> None:
        try:
            if first:
                self._look()
                return
            while not self._stop.wait(POLL_S):
                self._look()
        except Exception as exc:  # a bug must not stop the server: said once, loudly
            self.failed = f"{type(exc).__name__}: {exc}"
            log.error("the storyboard of %s stopped: %s", self.path, self.failed,
                      exc_info=exc)
            self._emit({"t_s": None, "kind": "storyboard", "name": "error",
                        "note": f"the storyboard stopped: {self.failed}"})

    _board: Any = None
    _cars: Any = None
    _groups: Any = None
    _next_t = 0.0
    _last_t = -math.inf
    _ended = False

    def _look(self) -> None:
        """One look at the world: the storyboard evaluated if a ``STORYBOARD_PERIOD_S``
        boundary of simulated time has passed since the last evaluation (or afresh, when
        the time went back: a reset)."""
        period = XR.STORYBOARD_PERIOD_S
        loop = self.loop
        world, drivers = loop.world, loop.drivers
        if world is None or drivers is None:
            return
        x, self._restart = self._restart, None
        restart = x is not None
        if x is None:
            x = world.data.x.copy()  # one tick's rows (module docstring)
        now = float(x[0, L.TIME_S])
        if self._board is None or restart or now < self._last_t - 1e-9:  # start, reset
            self._board, self._cars = self._fresh_board(drivers)
            self._groups = XR.frame_groups(self._cars)
            self._prev_xy: dict[str, tuple[float, float]] = {}
            self._axes = np.zeros((3, 3))
            self._next_t = now
            self._last_t = -math.inf
            self._ended = False
            self._contacts.clear()
        if now + 1e-9 < self._next_t:
            return
        self._next_t = (math.floor(now / period + 1e-6) + 1) * period
        board, cars = self._board, self._cars
        ids = list(world.ids)
        here = {n: c for n, c in cars.items() if n in ids}
        for name, car in here.items():
            car.index = ids.index(name)
        view = SimpleNamespace(data=SimpleNamespace(x=x))
        XR.measure(here, [(f, [c for c in m if c.name in here], near)
                          for f, m, near in self._groups],
                   view, drivers, self._axes, terrain_road(world.model.terrain),
                   world.model.terrain.kind == TERRAIN_PLANE, now,
                   0.0 if self._last_t == -math.inf else now - self._last_t, self._prev_xy)
        self._last_t = now
        board.contacts = self._drain_contacts()
        state = drivers.state.copy()
        paths = drivers.paths.copy()
        board.drivers = drivers._replace(state=state.copy(), paths=paths.copy())
        n_trace = len(board.trace)
        if not self._ended and board.tick(now) is not None:
            self._ended = True  # the storyboard ended; the cars drive on
        self.evaluations += 1
        self._post(drivers, state, paths, board.drivers)
        for entry in board.trace[n_trace:]:
            self._emit(entry)

    def _drain_contacts(self) -> list[dict[str, Any]]:
        events = []
        while self._contacts:
            try:
                e = proto.decode_collision(self._contacts.popleft())
            except proto.ProtocolError:
                continue
            events.append({"car_a": e["car_a"], "car_b": e["car_b"],
                           "closing_speed_mps": float(e["closing_speed_mps"])})
        return events

    def _post(self, drivers: D.Drivers, state: np.ndarray, paths: np.ndarray,
              mine: D.Drivers) -> None:
        """What the evaluation changed in its copy of the driver's arrays, posted."""
        cols = list(TARGET_COLUMNS)
        diff = np.argwhere(mine.state[:, cols] != state[:, cols])
        states = [(int(c), cols[k], float(mine.state[c, cols[k]])) for c, k in diff]
        changed = np.flatnonzero((mine.paths != paths).any(axis=1))
        rows = []
        if changed.size:
            first, last = int(changed[0]), int(changed[-1]) + 1
            rows.append((first, mine.paths[first:last].copy()))
        if states or rows:
            self._posted.append((id(drivers), states, rows))

    def _emit(self, entry: dict[str, Any]) -> None:
        self.trace.append(entry)
        if self._publish is not None:
            try:
                self._publish(trace_payload(entry))
            except Exception as exc:  # noqa: BLE001 - the transport: logged, go on
                log.warning("storyboard line not published: %s", exc)
