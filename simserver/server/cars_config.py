"""The cars of a live server: the ``cars:`` list of a server config, validated (issue 30).

The world they make and the loop's glue are :mod:`simserver.server.fleet`.

A server config without ``cars:`` serves one car, ``vehicle_id`` (default ``car0``), on its
scene, as it always has. With ``cars:`` it serves each car listed, all in one world on the
scene's terrain and road (``simserver.sim.simulation.World``, docs/model.md section 14)::

    scene: ../scenes/crest_curve_paper_sedan.yaml   # the terrain, the road, the defaults
    max_cars: 32                  # more cars than this is an error (default 32)
    cars:
      - id: car0                  # its keys: {prefix}/car0/...
        start: {road: "0", s: 270.0, lane: -1}       # or pose: {x_m, y_m, yaw_rad}
        driven_by: client         # client (default) | keyframes | driver
      - id: lead
        vehicle: ../vehicles/paper_sedan/vehicle.yaml   # default: the scene's vehicle
        start: {road: "0", s: 290.0, lane: -1}
        driven_by: keyframes
        keyframes: ../scenarios/e3_stop_from_turn.yaml  # a scenario's inputs, in real time
      - id: traffic
        start: {road: "0", s: 250.0, lane: -1}
        driven_by: driver         # the built-in driver (docs/model.md section 15)
        driver: {path: {road: "0", lane: -1}, idm: {v0_mps: 15.0}}  # the headless block

Each car's ``vehicle`` defaults to the scene's and its start to the scene's ``initial``
(``pose`` replaces the scene's ``x_m``, ``y_m``, ``yaw_rad``; ``start`` gives them from a
road, s and lane of an OpenDRIVE terrain); every car starts at rest. The checks
(:func:`car_scenes`) run before anything is swapped, so a running world is never touched
by a bad list; each error names the file and the car (``cars[k] (id)``):

- an id given twice, an id that is not one key chunk, an id longer than
  :data:`simserver.wire.protocol.WORLD_ID_BYTES` (the world message's id field), or the reserved
  id :data:`WORLD_KEY` (the world's own keys, ``{prefix}/world/...``);
- more cars than ``max_cars``;
- a start off the road: on an OpenDRIVE terrain the car's CG must be on a lane of a road,
  on a height map inside the grid (beyond it the ground is the edge's, extended flat: no
  road) (``simserver.sim.scene.check_on_road``, a headless world's check too);
- two start poses whose body footprints overlap (``simserver.sim.scene.
  check_starts_apart``, a headless world's check too, on ``core.contact.body_box`` and
  ``bodies_overlap``): oriented rectangles in the horizontal plane (the contact stage's
  boxes, from the vehicle's ``body_*`` parameters), by the separating axis theorem.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from simserver.adapters.config import ConfigError, check_keys, load_vehicle, number
from simserver.adapters.validate import integer, referenced_file, short_repr
from simserver.core.contact import bodies_overlap, body_box
from simserver.sim.scene import (  # max_cars: a headless world's limit too (one source)
    DEFAULT_MAX_CARS,
    MAX_CARS_RANGE,
    check_car_count,
    check_on_road,
)
from simserver.wire import protocol as proto

if TYPE_CHECKING:
    from simserver.sim.scene import Scene

WORLD_KEY = "world"
"""The key chunk of the world's own keys (``{prefix}/world/state``): no car may take it."""

CAR_KEYS = ("id", "vehicle", "pose", "start", "driven_by", "keyframes", "driver")
"""The keys of one entry of ``cars:``."""

DRIVEN_BY: dict[str, str] = {
    "client": "a client over zenoh ({prefix}/{id}/cmd), as a single car's server is driven",
    "keyframes": "a scenario's input keyframes (`keyframes:` FILE), played in real time "
                 "from the car's tick 0; commands sent to it are not applied",
    "driver": "the built-in driver (`driver:` the headless scenarios' block: path or "
              "OpenDRIVE lane, speed profile, IDM, stop point, go time; docs/model.md "
              "section 15), every tick from the world's states; commands sent to it are "
              "not applied",
}
"""Who drives a car (``driven_by``), with what it means: one table for checks and docs."""

POSE_KEYS = ("x_m", "y_m", "yaw_rad")


@dataclass(frozen=True)
class CarSpec:
    """One car of ``cars:``, as written (checked for form; files not read yet)."""

    id: str
    where: str  # "FILE: cars[k] (id)": the prefix of every error about this car
    vehicle: Path | None = None  # None: the scene's vehicle
    pose: dict[str, float] | None = None  # x_m, y_m, yaw_rad; None: the scene's (or start)
    start: dict[str, Any] | None = None  # road, s, lane on the scene's OpenDRIVE roads
    driven_by: str = "client"
    keyframes: Path | None = None
    driver: dict[str, Any] | None = None  # the ``driver:`` block as written (driven_by driver)


def parse_cars(path: Path, raw: Any, max_cars: int = DEFAULT_MAX_CARS) -> list[CarSpec]:
    """The ``cars:`` list of the server config ``path``, checked for form: ids (unique,
    one key chunk, not ``world``, at most ``proto.WORLD_ID_BYTES`` bytes), the count, each
    entry's keys and values. Files are resolved (relative to ``path``) but not read."""
    if not isinstance(raw, list) or not raw:
        raise ConfigError(f"{path}: key 'cars': expected a non-empty list of cars")
    check_car_count(path, len(raw), max_cars)
    cars: list[CarSpec] = []
    seen: dict[str, int] = {}
    for k, entry in enumerate(raw):
        if not isinstance(entry, dict):
            raise ConfigError(f"{path}: key 'cars[{k}]': expected a mapping, got "
                              f"{short_repr(entry)}")
        car_id = entry.get("id")
        where = f"{path}: cars[{k}]" + (f" ({car_id})" if isinstance(car_id, str) else "")
        check_keys(where, entry, CAR_KEYS, required=("id",))
        car_id = check_car_id(where, car_id)
        if car_id in seen:
            raise ConfigError(f"{where}: key 'id': {car_id!r} is the id of cars[{seen[car_id]}] "
                              "too; each car needs its own")
        seen[car_id] = k
        cars.append(_parse_car(path, where, car_id, entry))
    return cars


def check_car_id(where: str, car_id: Any) -> str:
    """A car id: one key chunk (``proto.validate_vehicle_id``), not :data:`WORLD_KEY`, at
    most ``proto.WORLD_ID_BYTES`` bytes; ``ConfigError`` naming ``where`` and the id."""
    if not isinstance(car_id, str):
        raise ConfigError(f"{where}: key 'id': expected a string, got {short_repr(car_id)}")
    try:
        proto.validate_vehicle_id(car_id)
    except proto.ProtocolError as exc:
        raise ConfigError(f"{where}: key 'id': {exc}") from None
    if car_id == WORLD_KEY:
        raise ConfigError(f"{where}: key 'id': {WORLD_KEY!r} is reserved for the world's own "
                          f"keys ({{prefix}}/{WORLD_KEY}/...)")
    if len(car_id.encode()) > proto.WORLD_ID_BYTES:
        raise ConfigError(f"{where}: key 'id': {car_id!r} is longer than "
                          f"{proto.WORLD_ID_BYTES} characters (the world message's id field)")
    return car_id


def _parse_car(path: Path, where: str, car_id: str, entry: dict[str, Any]) -> CarSpec:
    vehicle = None
    if entry.get("vehicle") is not None:
        vehicle = _file(path, where, "vehicle", entry["vehicle"])
    pose = None
    if entry.get("pose") is not None:
        raw = entry["pose"]
        if not isinstance(raw, dict):
            raise ConfigError(f"{where}: key 'pose': expected a mapping {{x_m, y_m, yaw_rad}}")
        check_keys(f"{where} (pose)", raw, POSE_KEYS, required=("x_m", "y_m"))
        from simserver.sim.scene import INITIAL_RANGES

        pose = {key: number(where, f"pose.{key}", raw.get(key, 0.0), *INITIAL_RANGES[key])
                for key in POSE_KEYS}
    start = entry.get("start")
    if start is not None and pose is not None:
        raise ConfigError(f"{where}: key 'start': give pose or start, not both")
    if start is not None and not isinstance(start, dict):
        raise ConfigError(f"{where}: key 'start': expected a mapping {{road, s, lane}}, got "
                          f"{short_repr(start)}")
    driven_by = entry.get("driven_by", "client")
    if driven_by not in DRIVEN_BY:
        raise ConfigError(f"{where}: key 'driven_by': expected one of "
                          f"{', '.join(DRIVEN_BY)}, got {short_repr(driven_by)}")
    keyframes = None
    if driven_by == "keyframes":
        if entry.get("keyframes") is None:
            raise ConfigError(f"{where}: key 'keyframes': a car driven by keyframes needs a "
                              "scenario file whose inputs it plays")
        keyframes = _file(path, where, "keyframes", entry["keyframes"])
    elif entry.get("keyframes") is not None:
        raise ConfigError(f"{where}: key 'keyframes': only a car driven_by keyframes plays "
                          "them")
    driver = entry.get("driver")
    if driven_by == "driver":
        if not isinstance(driver, dict):
            raise ConfigError(f"{where}: key 'driver': a car driven by the driver needs a "
                              "driver: block (path or lane, speed profile, idm, stop_s_m, "
                              f"go_t_s), got {short_repr(driver)}")
    elif driver is not None:
        raise ConfigError(f"{where}: key 'driver': only a car driven_by driver takes a "
                          "driver: block")
    return CarSpec(id=car_id, where=where, vehicle=vehicle, pose=pose,
                   start=None if start is None else dict(start), driven_by=driven_by,
                   keyframes=keyframes, driver=None if driver is None else dict(driver))


def _file(path: Path, where: str, key: str, value: Any) -> Path:
    try:
        return referenced_file(path, key, value)
    except ConfigError as exc:  # name the car too
        raise ConfigError(f"{where}: {str(exc).removeprefix(f'{path}: ')}") from None


def parse_max_cars(path: Path, value: Any) -> int:
    """``max_cars`` of the server config."""
    return integer(path, "max_cars", value, *MAX_CARS_RANGE)


# ------------------------------------------------------------------ scenes of the cars
def car_scenes(cars: list[CarSpec], scene: Scene) -> dict[str, Scene]:
    """Each car's scene (in ``cars`` order): the world's ``scene`` with the car's vehicle and
    start pose. Reads the vehicle files (once per file) and checks every start: on the road
    and apart from every other car's (module docstring). ``ConfigError`` naming the file
    and the car; nothing is built for a list that fails."""
    from simserver.sim.scene import start_by_lane

    vehicles: dict[Path, Any] = {}
    scenes: dict[str, Scene] = {}
    for car in cars:
        vehicle = scene.vehicle
        if car.vehicle is not None:
            if car.vehicle not in vehicles:
                try:
                    vehicles[car.vehicle] = load_vehicle(car.vehicle, scene.model_options,
                                                         options_source=str(scene.path))
                except ConfigError as exc:
                    raise ConfigError(f"{car.where}: key 'vehicle': {exc}") from None
            vehicle = vehicles[car.vehicle]
        # every car starts at rest (a reset to its pose gives the same state: its command
        # log names that pose, and the replay starts there)
        initial = {**scene.initial, "u_mps": 0.0, "v_mps": 0.0, "yaw_rate_radps": 0.0}
        if car.start is not None:
            initial.update(start_by_lane(car.where, "start", car.start, scene.roads))
        elif car.pose is not None:
            initial.update(car.pose)
        one = dataclasses.replace(scene, vehicle=vehicle, initial=initial)
        check_on_road(car.where, one)
        scenes[car.id] = one
    check_apart(cars, scenes)
    return scenes


def check_apart(cars: list[CarSpec], scenes: dict[str, Scene]) -> None:
    """No two cars' start footprints overlap; else ``ConfigError`` naming both
    (``simserver.sim.scene.check_starts_apart``, a headless world's check too)."""
    from simserver.sim.scene import check_starts_apart

    check_starts_apart([(car.where, car.id, scenes[car.id].initial,
                         scenes[car.id].vehicle.vp) for car in cars])


MAX_KEYFRAME_STEPS = 3_600_000
"""Longest keyframe table a car plays (an hour at 1 kHz, 144 MB): longer is an error."""


def keyframe_table(car: CarSpec, dt_s: float) -> np.ndarray:
    """The inputs a car ``driven_by: keyframes`` applies at each of its ticks: its file's
    keyframes sampled every ``dt_s`` over the file's ``duration_s`` (``simserver.sim.keyframes``,
    the headless runner's and the player's sampling); past the end the last row holds.
    Read off the tick (the server's start, the load worker). ``ConfigError`` naming the
    car."""
    from simserver.adapters.config import read_yaml
    from simserver.sim.keyframes import input_table, read_keyframe_file

    assert car.keyframes is not None
    try:
        run = read_keyframe_file(car.keyframes, read_yaml(car.keyframes))
    except ConfigError as exc:
        raise ConfigError(f"{car.where}: key 'keyframes': {exc}") from None
    steps = int(round(run.duration_s / dt_s)) + 1
    if steps > MAX_KEYFRAME_STEPS:
        raise ConfigError(f"{car.where}: key 'keyframes': {car.keyframes} lasts "
                          f"{run.duration_s:g} s, more than {MAX_KEYFRAME_STEPS * dt_s:g} s")
    return np.ascontiguousarray(input_table(run.keyframes, np.arange(steps) * dt_s))


def check_clear(car: CarSpec, scene: Scene, others: dict[str, tuple[dict[str, float],
                                                                     np.ndarray]]) -> None:
    """A car to add at ``scene``'s start does not overlap any car of a running world
    (``others``: id -> (its pose now: x_m, y_m, yaw_rad, and its vehicle parameters));
    ``ConfigError`` naming the car and the one in the way."""
    if car.id in others:
        raise ConfigError(f"{car.where}: key 'id': the world has a car {car.id!r} already")
    box = body_box(scene.vehicle.vp)
    for other_id, (pose, vp) in others.items():
        if bodies_overlap(scene.initial, box, pose, body_box(vp)):
            raise ConfigError(f"{car.where}: its start ({scene.initial['x_m']:.2f}, "
                              f"{scene.initial['y_m']:.2f}) m overlaps car {other_id!r} where "
                              f"it is now ({pose['x_m']:.2f}, {pose['y_m']:.2f}) m")


def new_car(car: CarSpec, scene: Scene, dt_s: float,
            others: dict[str, tuple[dict[str, float], np.ndarray]]
            ) -> tuple[Scene, np.ndarray | None]:
    """What adding ``car`` to a running world on ``scene`` needs, read and checked (off the
    tick: the vehicle file, the keyframes): the car's scene and its keyframe table (None
    for a client's car). ``ConfigError`` naming the car; nothing changes."""
    scenes = car_scenes([car], scene)
    check_clear(car, scenes[car.id], others)
    table = keyframe_table(car, dt_s) if car.driven_by == "keyframes" else None
    return scenes[car.id], table


def driver_spec(car: CarSpec, scene: Scene) -> Any:
    """A car ``driven_by: driver``'s ``driver:`` block validated against its scene (the
    headless scenarios' parser, ``simserver.adapters.driver_config.parse_driver``: a path
    off the road is an error); None for any other car. Read off the tick. ``ConfigError``
    naming the file and the car."""
    if car.driver is None:
        return None
    from simserver.adapters.driver_config import parse_driver

    return parse_driver(car.where, car.driver, scene)
