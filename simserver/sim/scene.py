"""A scene: a vehicle on a road or terrain at an initial state, what every run starts from
(the live server, a headless scenario, the soak, a sweep's worker).

``load_scene`` reads a scene file, ``parse_scene`` the scene keys of any mapping (a
scenario file is a scene too: its timing and inputs are the runner's,
:mod:`simserver.sim.scenario`, whose docstring shows the keys). The order of reading is
the file's: the vehicle (``simserver.adapters.config.load_vehicle``, which reads its tire
files through their models' loaders, :mod:`simserver.tires`), the road, the initial state,
the terrain (``simserver.adapters.terrain_files``) and a start by road, s and lane on an
OpenDRIVE terrain (``simserver.adapters.opendrive``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from simserver.adapters.config import VehicleConfig, load_vehicle
from simserver.adapters.opendrive import (
    START_KEYS,
    GeometryArray,
    LaneStartError,
    OpenDrive,
    Road,
    lane_start,
    load_opendrive,
    road_extents,
)
from simserver.adapters.terrain_files import terrain_from_spec, terrain_spec
from simserver.adapters.validate import (
    ConfigError,
    check_keys,
    integer,
    number,
    read_yaml,
    referenced_file,
    short_repr,
)
from simserver.core.contact import bodies_overlap, body_box
from simserver.core.terrain import (
    GRID_DX_M,
    GRID_DY_M,
    GRID_X0_M,
    GRID_Y0_M,
    TERRAIN_HEIGHTMAP,
    TERRAIN_OPENDRIVE,
    Terrain,
    plane_terrain,
)

ROAD_RANGES = {"grade_pct": (-100.0, 100.0), "cross_slope_pct": (-100.0, 100.0),
               "friction_scale": (0.0, 3.0)}
INITIAL_RANGES = {"x_m": (-1e7, 1e7), "y_m": (-1e7, 1e7), "yaw_rad": (-1e3, 1e3),
                  "u_mps": (-100.0, 100.0), "v_mps": (-100.0, 100.0),
                  "yaw_rate_radps": (-10.0, 10.0), "relaxed": (0.0, 1.0)}
"""``initial.relaxed``: 0 (the default, the paper's starts) the wheels spin at ``u / R``
with the slip states at zero; 1 the wheels, slip states and powertrain start relaxed to
their steady values at the initial velocity (``Simulation.reset``, ``core.start``)."""


@dataclass
class Scene:
    """A vehicle on a road at an initial state: what the live server starts from."""

    path: Path
    vehicle: VehicleConfig
    road: dict[str, float]
    initial: dict[str, float]
    model_options: dict[str, Any] = field(default_factory=dict)
    terrain: Terrain = field(default_factory=plane_terrain)  # core.terrain
    roads: OpenDrive | None = None  # an OpenDRIVE terrain's roads: starts by road, s, lane
    terrain_spec: dict[str, Any] | None = None  # adapters.terrain_files.terrain_spec


SCENE_KEYS = ("vehicle", "road", "initial", "model", "terrain", "start")
START_POSE_KEYS = ("x_m", "y_m", "yaw_rad")
"""The ``initial`` keys a ``start:`` gives (so they may not be given with it)."""


def parse_scene(path: Path, data: dict[str, Any], vehicle_path: Path | None = None) -> Scene:
    """Validate the scene keys of a scene or scenario mapping read from ``path``.

    ``vehicle_path`` overrides the file's ``vehicle`` key (the server's ``load`` control).
    """
    model_options = data.get("model") or {}
    if vehicle_path is None and isinstance(data.get("vehicle"), dict):  # resolve_scenario
        vehicle = load_vehicle(f"{path}#vehicle", model_options, options_source=str(path),
                               resolved=data["vehicle"])
    else:
        if vehicle_path is None:
            vehicle_path = referenced_file(path, "vehicle", data.get("vehicle"))
        vehicle = load_vehicle(vehicle_path, model_options, options_source=str(path))
    road_raw = data.get("road") or {}
    if not isinstance(road_raw, dict):
        raise ConfigError(f"{path}: key 'road': expected a mapping")
    check_keys(f"{path} (road)", road_raw, tuple(ROAD_RANGES))
    road = {"grade_pct": 0.0, "cross_slope_pct": 0.0, "friction_scale": 1.0}
    for key, (lo, hi) in ROAD_RANGES.items():
        if key in road_raw:
            road[key] = number(path, f"road.{key}", road_raw[key], lo, hi)
    init_raw = data.get("initial") or {}
    if not isinstance(init_raw, dict):
        raise ConfigError(f"{path}: key 'initial': expected a mapping")
    check_keys(f"{path} (initial)", init_raw, tuple(INITIAL_RANGES))
    initial = {key: number(path, f"initial.{key}", init_raw.get(key, 0.0), lo, hi)
               for key, (lo, hi) in INITIAL_RANGES.items()}
    if initial["relaxed"] not in (0.0, 1.0):
        raise ConfigError(f"{path}: key 'initial.relaxed': expected 0 or 1")
    spec = terrain_spec(path, data.get("terrain"))
    terrain = terrain_from_spec(spec)
    roads = None
    if terrain.kind == TERRAIN_OPENDRIVE:  # read again for its roads (milliseconds)
        roads = load_opendrive(Path(spec["file"]))
    if data.get("start") is not None:
        clash = [key for key in START_POSE_KEYS if key in init_raw]
        if clash:
            raise ConfigError(f"{path}: key 'initial.{clash[0]}': the start pose is given by "
                              "'start'; give one or the other")
        initial.update(start_by_lane(path, "start", data["start"], roads))
    return Scene(path=path, vehicle=vehicle, road=road, initial=initial,
                 model_options=dict(model_options), terrain=terrain, roads=roads,
                 terrain_spec=spec)


def start_by_lane(path: Path | str, key: str, raw: Any, roads: OpenDrive | None
                  ) -> dict[str, float]:
    """``x_m``, ``y_m``, ``yaw_rad`` of a start by road, s and lane (``START_KEYS``,
    ``simserver.adapters.opendrive.lane_start``); ``ConfigError`` naming ``path`` and the
    key (``start.road``, ``start.s``, ``start.lane``) at fault."""
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: key '{key}': expected a mapping {{road, s, lane}}, got "
                          f"{short_repr(raw)}")
    check_keys(f"{path} ({key})", raw, tuple(START_KEYS), required=tuple(START_KEYS))
    if roads is None:
        raise ConfigError(f"{path}: key '{key}': a start by road, s and lane needs an "
                          "OpenDRIVE terrain (terrain: {kind: opendrive, ...})")
    road_id = raw["road"]
    if isinstance(road_id, bool) or not isinstance(road_id, (str, int)):
        raise ConfigError(f"{path}: key '{key}.road': expected a road id, got "
                          f"{short_repr(road_id)}")
    s_m = number(path, f"{key}.s", raw["s"], -1e7, 1e7)
    lane = integer(path, f"{key}.lane", raw["lane"], -1000, 1000)
    try:
        x_m, y_m, yaw_rad = lane_start(roads, str(road_id), s_m, lane)
    except LaneStartError as exc:
        raise ConfigError(f"{path}: key '{key}.{exc.key}': {exc}") from None
    return {"x_m": x_m, "y_m": y_m, "yaw_rad": yaw_rad}


SCENARIO_ONLY_KEYS = ("duration_s", "dt_s", "record_every", "inputs", "driver", "analysis",
                      "speed_hold")


# ------------------------------------------------------------- several cars on one scene
DEFAULT_MAX_CARS = 32
MAX_CARS_RANGE = (1, 256)
"""``max_cars`` of a world of several cars (the live server's config, a headless scenario
with ``cars:``): the default and the range it may be set in. More cars than it is an
error naming the file."""


def check_car_count(path: Path | str, n_cars: int, max_cars: int) -> None:
    """At most ``max_cars`` cars; else ``ConfigError`` naming the file and ``cars``."""
    if n_cars > max_cars:
        raise ConfigError(f"{path}: key 'cars': {n_cars} cars, more than max_cars "
                          f"({max_cars})")


def check_starts_apart(cars: list[tuple[str, str, dict[str, float], Any]]) -> None:
    """No two cars' start poses put their bodies in each other: ``cars`` lists, in the
    file's order, each car's ``where`` (the prefix of its errors, ``FILE: cars[k] (id)``),
    id, start pose (``x_m``, ``y_m``, ``yaw_rad``) and vehicle parameters; the boxes are
    the contact stage's (``core.contact.body_box``, ``bodies_overlap``). ``ConfigError``
    naming the later car and the earlier one it overlaps. The live server's ``cars:``
    (``simserver.server.cars_config``) and a headless world (``simserver.sim.scenario.
    load_world_scenario``) are checked by this one function."""
    boxes = [body_box(vp) for _, _, _, vp in cars]
    for i, (where, _, pa, _) in enumerate(cars):
        for j in range(i):
            other, pb = cars[j][1], cars[j][2]
            if bodies_overlap(pa, boxes[i], pb, boxes[j]):
                raise ConfigError(
                    f"{where}: its start ({pa['x_m']:.2f}, {pa['y_m']:.2f}) m overlaps the "
                    f"start of car {other!r} ({pb['x_m']:.2f}, {pb['y_m']:.2f}) m (bodies "
                    f"{sum(boxes[i][:2]):.2f} x {2 * boxes[i][2]:.2f} m): move one")


LANE_SAMPLE_M = 0.5
"""Spacing of the reference-line samples :func:`on_lane` projects a point onto."""


def check_on_road(where: str, scene: Scene) -> None:
    """The scene's start is on its road, else ``ConfigError`` naming ``where`` (a car of a
    world: ``FILE: cars[k] (id)``): on an OpenDRIVE terrain the CG on a lane of a road
    (:func:`on_lane`), on a height map inside the grid (beyond it the ground is the
    edge's, extended flat: no road). The live server's ``cars:`` and ``add_car``
    (``simserver.server.cars_config``) and a headless world (``simserver.sim.scenario.
    load_world_scenario``) are checked by this one function."""
    x, y = scene.initial["x_m"], scene.initial["y_m"]
    terrain = scene.terrain
    if terrain.kind == TERRAIN_OPENDRIVE and scene.roads is not None:
        if not on_lane(scene.roads, x, y):
            raise ConfigError(f"{where}: the start ({x:.2f}, {y:.2f}) m is off the road: not "
                              f"on a lane of {scene.roads.path.name}")
    elif terrain.kind == TERRAIN_HEIGHTMAP:
        g = terrain.grid
        ny, nx = terrain.heights.shape
        x0, y0 = g[GRID_X0_M], g[GRID_Y0_M]
        x1, y1 = x0 + (nx - 1) * g[GRID_DX_M], y0 + (ny - 1) * g[GRID_DY_M]
        if not (x0 <= x <= x1 and y0 <= y <= y1):
            raise ConfigError(f"{where}: the start ({x:.2f}, {y:.2f}) m is off the height "
                              f"map ({x0:g} .. {x1:g}, {y0:g} .. {y1:g}) m")


def _reference_samples(road: Road, step_m: float) -> tuple[np.ndarray, ...]:
    """``(s, x, y, heading)`` of the reference line every ``step_m`` (and at its end)."""
    s = np.append(np.arange(0.0, road.length, step_m), road.length)
    geos = road.geometries
    starts = geos.starts if isinstance(geos, GeometryArray) else np.array(
        [g.s for g in geos])
    which = np.clip(np.searchsorted(starts, s + 1e-9, side="right") - 1, 0, len(geos) - 1)
    x, y, h = (np.empty_like(s) for _ in range(3))
    for k in np.unique(which):
        sel = which == k
        geo = geos[int(k)]
        x[sel], y[sel], h[sel] = geo.points(np.clip(s[sel] - geo.s, 0.0, geo.length))
    return s, x, y, h


def on_lane(od: OpenDrive, x_m: float, y_m: float, step_m: float = LANE_SAMPLE_M) -> bool:
    """Whether the point ``(x_m, y_m)`` is on a lane of a road of ``od``: its projection on
    some road's reference line (the nearest of samples every ``step_m``, refined along the
    local heading) falls within the road's length, and its lateral offset within the
    road's lanes there (``road_extents``; superelevation ignored: a lateral error of
    ``t (1 - cos roll)``, 2 mm for 4 m at 4 %)."""
    for road in od.roads:
        if road.length <= 0.0:
            continue
        s, x, y, h = _reference_samples(road, step_m)
        dx, dy = x_m - x, y_m - y
        n = int(np.argmin(dx * dx + dy * dy))
        c, sn = math.cos(h[n]), math.sin(h[n])
        along = dx[n] * c + dy[n] * sn
        s_here = s[n] + along
        if not -1e-6 <= s_here <= road.length + 1e-6 or abs(along) > step_m:
            continue
        t = -dx[n] * sn + dy[n] * c
        right, left = road_extents(road, np.array([min(max(s_here, 0.0), road.length)]))
        if right[0] - 1e-6 <= t <= left[0] + 1e-6:
            return True
    return False


def load_scene(path: str | Path, vehicle_path: str | Path | None = None) -> Scene:
    """Load a scene file: ``vehicle``, ``road``, ``initial`` and ``model`` as in a scenario.

    A scenario file is also a scene (its start): its timing and inputs are ignored here,
    so the live server can start from any headless scenario. This reads YAML; any scene
    file, an OpenSCENARIO ``.xosc`` included, is read by ``simserver.sim.scene_files``.
    """
    path = Path(path)
    data = read_yaml(path)
    check_keys(path, data, ("name", "description", *SCENE_KEYS, *SCENARIO_ONLY_KEYS),
               required=("vehicle",))
    return parse_scene(path, data, None if vehicle_path is None else Path(vehicle_path))
