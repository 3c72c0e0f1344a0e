"""The cars of a live server in one world: built, served, seen (issue 30).

The ``cars:`` list and its checks are :mod:`simserver.server.cars_config`; this module
makes the world of the listed cars (:func:`build_world`, :func:`make_cars`), the world
message (:class:`WorldMessage`), each car's log start (:func:`log_start`), and a car joining
a running world (:func:`join_world`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from simserver.server.cars_config import CarSpec, car_scenes, driver_spec, keyframe_table
from simserver.wire import protocol as proto

if TYPE_CHECKING:
    from simserver.sim.scene import Scene


# ------------------------------------------------------------------ the cars' world
def build_world(scenes: dict[str, Scene], dt_s: float) -> dict[str, Any]:
    """One ``Simulation`` per car (in ``scenes`` order), all cars of one world on the first
    car's terrain (the scenes share the world scene's terrain): each is made alone, as a
    single car's server makes it, then moved into the world (``Simulation.move_to``:
    copies of its rows, nothing recompiled), so a car starts with the bits it would have
    alone. Returns ``{id: Simulation}``."""
    from simserver.sim.simulation import Simulation

    sims: dict[str, Any] = {}
    world = None
    for car_id, scene in scenes.items():
        sim = Simulation(scene, dt_s, car_id=car_id)
        if world is None:
            world = sim.world
        else:
            sim.move_to(world)
        sims[car_id] = sim
    return sims


class WorldMessage:
    """The world message of a server's cars (``protocol.WorldBuffer``), from each car's
    newest published VehicleState: ``due(tick)`` every ``every`` ticks, ``payload(...)``
    a few vectorised copies (microseconds for 32 cars)."""

    def __init__(self, ids: list[str], driven_by: list[str], every: int,
                 capacity: int | None = None) -> None:
        self.every = max(1, int(every))
        self.buffer = proto.WorldBuffer(capacity or len(ids))
        self.states = np.zeros(self.buffer.cars.size, dtype=proto.STATE_DTYPE)
        self._raw = self.states.view(np.uint8)
        self.set_cars(ids, driven_by)

    def set_cars(self, ids: list[str], driven_by: list[str]) -> None:
        """The cars, in order (when the world changes; between ticks)."""
        self.buffer.set_cars(ids, driven_by)
        self.states[:] = 0

    def seed(self, records: np.ndarray) -> None:
        """Every car's values from ``records`` (VehicleState records in the cars' order,
        their copied fields filled from the world now: ``StateFrame.records``), until each
        car's first published state replaces them: a car just added is in the message at
        its start pose, not at zero, from the first message that lists it."""
        self.states[:len(records)] = records

    def due(self, tick: int) -> bool:
        return tick % self.every == 0

    def payload(self, states: list[bytes | None], tick: int, uptime_s: float) -> bytes:
        """The message, with car ``k``'s values from ``states[k]`` (its newest published
        VehicleState bytes; None: none yet, its record stays zero)."""
        for k, state in enumerate(states):
            if state is not None:
                self.note(k, state)
        return self.payload_noted(tick, uptime_s)

    def note(self, k: int, state: bytes) -> None:
        """Car ``k``'s newest published VehicleState, kept for :meth:`payload_noted` (the
        loop notes each as it publishes it: no pass over every car when the message is
        due, 1-2 us a car at 32 cars)."""
        size = proto.STATE_SIZE
        self._raw[k * size:(k + 1) * size] = np.frombuffer(state, dtype=np.uint8)

    def payload_noted(self, tick: int, uptime_s: float) -> bytes:
        """The message from the states noted so far (:meth:`note`)."""
        self.buffer.fill_from(self.states)
        return self.buffer.payload(tick, uptime_s)


def world_every(world_hz: float, period_s: float) -> int:
    """Ticks between two world messages at ``world_hz`` (at least 1)."""
    return max(1, int(round(1.0 / (world_hz * period_s))))


# ------------------------------------------------------------------ the server's cars
@dataclass
class ServedCar:
    """A car of the server: its spec (None: the single car of a config without ``cars:``)
    and its slot (``simserver.server.slot.VehicleSlot``)."""

    spec: CarSpec | None
    slot: Any
    driver: Any = None  # driven_by driver: its DriverSpec (simserver.server.live_drivers)


def car_log_path(log_path: Path | None, car_id: str, several: bool) -> Path | None:
    """A car's command log: the server config's ``command_log`` itself for one car; with
    several, ``NAME.<id>.SUFFIX`` beside it (``run.jsonl`` -> ``run.car0.jsonl``)."""
    if log_path is None or not several:
        return log_path
    return log_path.with_name(f"{log_path.stem}.{car_id}{log_path.suffix}")


def make_cars(cfg: Any, scene: Scene) -> list[ServedCar]:
    """The server's cars from its config: the one car ``vehicle_id`` on ``scene`` (no
    ``cars:``, as always), or every car of ``cars:`` in one world (:func:`car_scenes`,
    :func:`build_world`; keyframed cars given their tables, driven cars their validated
    ``driver:`` blocks). Each slot has the server
    config with its own ``vehicle_id`` and command log path. ``ConfigError`` naming the
    file and the car; nothing is built for a list that fails."""
    from simserver.server.slot import VehicleSlot

    if not cfg.cars:  # the single car, as simserver.server.app.new_simulation makes it
        from simserver.sim.simulation import Simulation

        return [ServedCar(None, VehicleSlot(cfg, Simulation(scene, cfg.period_s)))]
    scenes = car_scenes(cfg.cars, scene)
    tables = {car.id: keyframe_table(car, cfg.period_s) for car in cfg.cars
              if car.driven_by == "keyframes"}
    drivers = {car.id: driver_spec(car, scenes[car.id]) for car in cfg.cars
               if car.driven_by == "driver"}
    sims = build_world(scenes, cfg.period_s)
    several = len(cfg.cars) > 1
    served = []
    for car in cfg.cars:
        car_cfg = dataclasses.replace(
            cfg, vehicle_id=car.id, command_log=car_log_path(cfg.command_log, car.id, several))
        slot = VehicleSlot(car_cfg, sims[car.id])
        if car.id in tables:
            slot.drive_by_keyframes(tables[car.id])
        if car.id in drivers:
            slot.drive_by_driver()
        served.append(ServedCar(car, slot, drivers.get(car.id)))
    return served


def prepare_drivers(cars: list[ServedCar], max_cars: int = 1) -> Any:
    """The built-in driver's cars of the server (``simserver.server.live_drivers``), their
    paths sampled (off the tick), and ``core.driver.drive`` compiled (or loaded from the
    cache) by one call on copies of the world's arrays, so that the first tick does not
    compile it: when a car is driven, and also when none is but ``max_cars`` lets a driven
    car be added while the world runs (``add_car``; else the first tick after that add
    would compile it: tens of seconds cold). The call on a world of undriven cars (one
    placeholder path) has the types of every later call: one compiled signature."""
    from simserver.adapters.driver_config import build_drivers
    from simserver.core.driver import drive
    from simserver.server.live_drivers import LiveDrivers

    live = LiveDrivers()
    for car in cars:
        if car.driver is not None:
            live.prepare(car.slot.keys.vehicle, car.driver, car.slot.sim.world.model.terrain)
    if live or max_cars > 1:
        world = cars[0].slot.sim.world
        drivers = live.assemble(world) if live else build_drivers(world, {})
        data = world.data
        scratch = data._replace(x=data.x.copy(), inputs=data.inputs.copy(),
                                out=data.out.copy())
        drive(world.model, scratch, drivers)  # reads x, writes inputs and drivers only
    return live


def world_message_for(cars: list[ServedCar], cfg: Any) -> WorldMessage:
    """The world message of the server's cars at the config's ``world_hz``."""
    return WorldMessage([c.slot.keys.vehicle for c in cars], [c.slot.driven_by for c in cars],
                        every=world_every(cfg.world_hz, cfg.period_s),
                        capacity=max(len(cars), getattr(cfg, "max_cars", len(cars))))


# ------------------------------------------------------------------ cars added while running
def poses_now(slots: list[Any]) -> dict[str, tuple[dict[str, float], np.ndarray]]:
    """Each served car's position and heading now, in the frame its start is given in
    (the state's ``x_m``, ``y_m``, ``yaw_rad``), and its vehicle parameters."""
    from simserver.core import layout as L

    return {slot.keys.vehicle: ({"x_m": float(slot.sim.x[L.X_M]),
                                 "y_m": float(slot.sim.x[L.Y_M]),
                                 "yaw_rad": float(slot.sim.x[L.YAW_RAD])},
                                slot.sim.vp.copy()) for slot in slots}


def join_world(slot_cfg: Any, scene: Scene, table: np.ndarray | None, world: Any) -> Any:
    """A new car's slot, its car made alone and moved into the running ``world``
    (between ticks: tens to hundreds of microseconds, nothing recompiled). A car driven
    by the built-in driver is made a client's here; the caller hands its driver to the
    loop's ``live_drivers`` and calls ``slot.drive_by_driver()``."""
    from simserver.server.slot import VehicleSlot
    from simserver.sim.simulation import Simulation

    sim = Simulation(scene, slot_cfg.period_s, car_id=slot_cfg.vehicle_id)
    sim.move_to(world)
    slot = VehicleSlot(slot_cfg, sim)
    if table is not None:
        slot.drive_by_keyframes(table)
    return slot


def log_start(slot: Any, car: CarSpec) -> None:
    """The first lines of a car's command log (after its header, which names the world's
    scene): the ``world`` line of its joining (the world's step and its cars, in order:
    ``simserver replay`` of every car's log steps them together,
    ``simserver.server.world_replay``), a ``load`` of the scene with the car's vehicle and
    a ``reset`` to the car's start pose, so that ``simserver replay`` of this log alone
    starts the car where the live world did (every car starts at rest, so the reset gives
    the very start state); then, for a car added after a live ``set_road``, a
    ``set_road`` to the world's road (the load line gives the scene's)."""
    log = slot.command_log
    if log is None:
        return
    world = slot.sim.world  # where the car joined: the world's step and its cars' order
    log.write({"step": slot.steps_total, "world": {
        "event": "join", "step": world.steps, "car": slot.keys.vehicle,
        "cars": list(world.ids)}})
    initial = slot.sim.scene.initial
    log.write({"step": slot.steps_total, "load": {
        "scene": str(slot.scene_path),
        "vehicle": None if car.vehicle is None else str(car.vehicle)}})
    log.write({"step": slot.steps_total,
               "reset": slot.logged_start({k: float(initial[k])
                                           for k in ("x_m", "y_m", "yaw_rad")})})
    road = dict(slot.sim.road)  # the world's now: a live set_road may have changed it
    if road != {k: float(slot.sim.scene.road[k]) for k in road}:  # from the scene's
        log.write({"step": slot.steps_total, "set_road": road})
