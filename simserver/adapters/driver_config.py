"""The ``driver:`` block of a scenario's car: validated, its path sampled, packed for the
compiled driver (``simserver.core.driver``, docs/model.md section 15).

A car of a scenario is driven by the built-in driver when it has a ``driver:`` block::

    driver:
      path: {road: "1", lane: -1}          # a lane of the OpenDRIVE terrain (s_from_m,
                                           # s_to_m, step_m optional), or
      # path: {points: [[0, 0], [500, 0]]} # a polyline in world x, y (m)
      speed_profile: [{s_m: 0, v_mps: 15}, {s_m: 300, v_mps: 10}]   # optional
      idm: {v0_mps: 15, T_s: 2.0, s0_m: 2.0}                        # optional
      stop_s_m: 400.0      # optional: the front bumper stops at this station and holds
      go_t_s: 30.0         # optional: at this time the stop point is released
      preview_time_s: 0.5  # optional: any key of the driver's table

Stations are distances along the path (3-D, over the terrain's surface) from its first
point; on a lane the path runs in the lane's direction of travel. Errors name the file,
the car and the key; nothing is changed by a refused file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from simserver.adapters.config import ConfigError, check_keys, number
from simserver.adapters.opendrive import (
    LaneStartError,
    OpenDrive,
    lane_start,
    reference_points,
    road_extents,
)
from simserver.adapters.validate import integer, short_repr
from simserver.core import driver as D
from simserver.core import layout as L
from simserver.core import params as P
from simserver.core.powertrain import overall_ratio
from simserver.core.terrain import TERRAIN_PLANE, Terrain, surface_at
from simserver.core.tire_layout import TP_RADIUS_M


class Scene(Protocol):
    """What a driver's path is checked against: the scene's terrain and its OpenDRIVE
    roads, if any (``simserver.sim.scene.Scene`` has both; named structurally so this
    adapter does not import the simulation layer above it)."""

    terrain: Terrain
    roads: Any


class World(Protocol):
    """The world the drivers are built for (``simserver.sim.simulation.World``): its car
    ids in order, its static model and its mutable data."""

    ids: list[str]
    model: Any
    data: Any

PATH_POINTS_KEYS = ("points",)
PATH_LANE_KEYS = ("road", "lane", "s_from_m", "s_to_m", "step_m")
DRIVER_KEYS = ("path", "speed_profile", "idm", "stop_s_m", "go_t_s", *D.CONTROL.keys)
"""The keys of a car's ``driver:`` block (the driver table's keys and the run's)."""
MAX_PATH_POINTS = 1_000_000
LANE_STEP_M = 0.5  # default spacing of a lane's samples
OFF_ROAD_TOLERANCE_M = 0.5  # a path point this far beyond the outer lane's edge is off


@dataclass
class DriverSpec:
    """A validated ``driver:`` block: its parameters (the derived slots not yet packed),
    its path in world x, y and the speed profile along it, and its commands."""

    params: np.ndarray  # float64[N_DRIVER_PARAM]
    path_xy: np.ndarray  # float64[n, 2]
    speed_profile: list[tuple[float, float]]  # (station m, speed m/s), stations increasing
    stop_s_m: float
    go_t_s: float


def parse_driver(path: Path | str, raw: Any, scene: Scene) -> DriverSpec:
    """Validate a ``driver:`` block read from ``path`` for a car of ``scene``."""
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: key 'driver': expected a mapping, got {short_repr(raw)}")
    check_keys(f"{path} (driver)", raw, DRIVER_KEYS, required=("path",))
    params = np.zeros(D.N_DRIVER_PARAM)
    for table, section, where in ((D.IDM, raw.get("idm") or {}, "driver.idm"),
                                  (D.CONTROL, raw, "driver")):
        if not isinstance(section, dict):
            raise ConfigError(f"{path}: key '{where}': expected a mapping")
        if table is D.IDM:
            check_keys(f"{path} ({where})", section, table.keys)
        for p in table:
            if p.derived:
                continue
            if p.yaml_key in section:
                params[p.slot] = number(path, f"{where}.{p.yaml_key}", section[p.yaml_key],
                                        p.lo, p.hi)
            elif isinstance(p.default, str):
                params[p.slot] = np.nan  # from the vehicle (pack_driver_params)
            else:
                params[p.slot] = p.default
    path_xy = _parse_path(path, raw["path"], scene)
    _check_on_road(path, path_xy, scene)
    profile = _parse_profile(path, raw.get("speed_profile"))
    stop = number(path, "driver.stop_s_m", raw["stop_s_m"], -1e7, 1e7) \
        if "stop_s_m" in raw else np.inf
    go_t = number(path, "driver.go_t_s", raw["go_t_s"], 0.0, 1e7) if "go_t_s" in raw else np.inf
    return DriverSpec(params=params, path_xy=path_xy, speed_profile=profile, stop_s_m=stop,
                      go_t_s=go_t)


def _parse_path(path: Path | str, raw: Any, scene: Scene) -> np.ndarray:
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: key 'driver.path': expected a mapping {{points}} or "
                          f"{{road, lane}}, got {short_repr(raw)}")
    if "points" in raw:
        check_keys(f"{path} (driver.path)", raw, PATH_POINTS_KEYS)
        pts = raw["points"]
        if not isinstance(pts, list) or not 2 <= len(pts) <= MAX_PATH_POINTS:
            raise ConfigError(f"{path}: key 'driver.path.points': expected a list of 2 to "
                              f"{MAX_PATH_POINTS} points [x, y]")
        xy = np.empty((len(pts), 2))
        for k, pt in enumerate(pts):
            if not isinstance(pt, list) or len(pt) != 2:
                raise ConfigError(f"{path}: key 'driver.path.points[{k}]': expected [x, y], "
                                  f"got {short_repr(pt)}")
            for j in range(2):
                xy[k, j] = number(path, f"driver.path.points[{k}][{j}]", pt[j], -1e7, 1e7)
    else:
        check_keys(f"{path} (driver.path)", raw, PATH_LANE_KEYS, required=("road", "lane"))
        xy = _lane_points(path, raw, scene.roads)
    seg = np.hypot(*np.diff(xy, axis=0).T)
    if (seg < 1e-3).any():
        k = int(np.argmax(seg < 1e-3))
        raise ConfigError(f"{path}: key 'driver.path': points {k} and {k + 1} are closer than "
                          "1 mm (a path needs a direction everywhere)")
    return xy


def _lane_points(path: Path | str, raw: dict[str, Any], roads: OpenDrive | None) -> np.ndarray:
    """The centre of a lane, every ``step_m``, in its direction of travel."""
    if roads is None:
        raise ConfigError(f"{path}: key 'driver.path.road': a path along a lane needs an "
                          "OpenDRIVE terrain (terrain: {kind: opendrive, ...})")
    road_id = raw["road"]
    if isinstance(road_id, bool) or not isinstance(road_id, (str, int)):
        raise ConfigError(f"{path}: key 'driver.path.road': expected a road id, got "
                          f"{short_repr(road_id)}")
    road = {r.id: r for r in roads.roads}.get(str(road_id))
    if road is None:
        raise ConfigError(f"{path}: key 'driver.path.road': no road {road_id!r} in "
                          f"{roads.path.name} (roads: {', '.join(r.id for r in roads.roads)})")
    lane = integer(path, "driver.path.lane", raw["lane"], -1000, 1000)
    s_from = number(path, "driver.path.s_from_m", raw.get("s_from_m", 0.0), 0.0, road.length)
    s_to = number(path, "driver.path.s_to_m", raw.get("s_to_m", road.length), 0.0, road.length)
    step = number(path, "driver.path.step_m", raw.get("step_m", LANE_STEP_M), 0.05, 100.0)
    if s_to - s_from < step:
        raise ConfigError(f"{path}: key 'driver.path.s_to_m': the lane's piece "
                          f"{s_from:g} .. {s_to:g} m is shorter than step_m {step:g} m")
    n = int(np.ceil((s_to - s_from) / step)) + 1
    if n > MAX_PATH_POINTS:
        raise ConfigError(f"{path}: key 'driver.path.step_m': {n} samples, more than "
                          f"{MAX_PATH_POINTS}")
    xy = np.empty((n, 2))
    yaw0 = None
    for k, s in enumerate(np.linspace(s_from, s_to, n)):
        try:
            x, y, yaw = lane_start(roads, road.id, float(s), lane)
        except LaneStartError as exc:
            raise ConfigError(f"{path}: key 'driver.path.{exc.key}': {exc}") from None
        xy[k] = x, y
        yaw0 = yaw if yaw0 is None else yaw0
    # the lane's direction of travel: the samples run along s; reversed if it runs against
    ds_dir = xy[1] - xy[0]
    if ds_dir[0] * np.cos(yaw0) + ds_dir[1] * np.sin(yaw0) < 0.0:
        xy = xy[::-1].copy()
    return xy


def _check_on_road(path: Path | str, xy: np.ndarray, scene: Scene) -> None:
    """A path must stay on the terrain's roads (OpenDRIVE: within the lanes' outer edges
    plus ``OFF_ROAD_TOLERANCE_M``) or on its height map's grid."""
    terrain = scene.terrain
    if terrain.kind == TERRAIN_PLANE:
        return
    if scene.roads is None:  # a height map: the grid's extent
        g = terrain.grid
        from simserver.core.terrain import GRID_DX_M, GRID_DY_M, GRID_X0_M, GRID_Y0_M
        ny, nx = terrain.heights.shape
        x0, y0 = g[GRID_X0_M], g[GRID_Y0_M]
        x1, y1 = x0 + (nx - 1) * g[GRID_DX_M], y0 + (ny - 1) * g[GRID_DY_M]
        off = (xy[:, 0] < x0) | (xy[:, 0] > x1) | (xy[:, 1] < y0) | (xy[:, 1] > y1)
        if off.any():
            k = int(np.argmax(off))
            raise ConfigError(f"{path}: key 'driver.path': point {k} "
                              f"({xy[k, 0]:g}, {xy[k, 1]:g}) leaves the height map "
                              f"({x0:g} .. {x1:g}, {y0:g} .. {y1:g} m)")
        return
    on = np.zeros(len(xy), dtype=bool)
    for road in scene.roads.roads:
        s = np.arange(0.0, road.length + 0.5, 0.5)
        s[-1] = min(s[-1], road.length)
        rx, ry, hdg = reference_points(road, s)
        right, left = road_extents(road, s)
        for lo in range(0, len(xy), 2048):  # point chunks: memory bounded
            p = xy[lo:lo + 2048]
            dx = p[:, 0, None] - rx[None, :]
            dy = p[:, 1, None] - ry[None, :]
            near = np.argmin(dx * dx + dy * dy, axis=1)
            rows = np.arange(len(p))
            c, sn = np.cos(hdg[near]), np.sin(hdg[near])
            along = dx[rows, near] * c + dy[rows, near] * sn
            t = -dx[rows, near] * sn + dy[rows, near] * c
            on[lo:lo + 2048] |= ((np.abs(along) <= 0.5)
                                 & (t >= right[near] - OFF_ROAD_TOLERANCE_M)
                                 & (t <= left[near] + OFF_ROAD_TOLERANCE_M))
    if not on.all():
        k = int(np.argmin(on))
        raise ConfigError(f"{path}: key 'driver.path': point {k} ({xy[k, 0]:.6g}, "
                          f"{xy[k, 1]:.6g}) leaves the road (no lane of "
                          f"{scene.roads.path.name} there)")


def _parse_profile(path: Path | str, raw: Any) -> list[tuple[float, float]]:
    if raw is None:
        return []
    if not isinstance(raw, list) or not raw:
        raise ConfigError(f"{path}: key 'driver.speed_profile': expected a list of "
                          "{s_m, v_mps}")
    out: list[tuple[float, float]] = []
    for k, row in enumerate(raw):
        where = f"driver.speed_profile[{k}]"
        if not isinstance(row, dict):
            raise ConfigError(f"{path}: key '{where}': expected a mapping {{s_m, v_mps}}")
        check_keys(f"{path} ({where})", row, ("s_m", "v_mps"), required=("s_m", "v_mps"))
        s = number(path, f"{where}.s_m", row["s_m"], -1e7, 1e7)
        v = number(path, f"{where}.v_mps", row["v_mps"], 0.0, 100.0)
        if out and s <= out[-1][0]:
            raise ConfigError(f"{path}: key '{where}.s_m': stations must increase")
        out.append((s, v))
    return out


def vehicle_gains(vp: np.ndarray, tp: np.ndarray) -> tuple[float, float]:
    """The car's acceleration at full throttle from rest in first gear and its deceleration
    at full brake (m/s^2), on the flat: the feedforward's gains (``throttle_accel_mps2``,
    ``brake_decel_mps2``' defaults). The feedback absorbs what they miss (the power
    limit, the gears above first, the converter)."""
    mass_radius = vp[P.VP_MASS_KG] * tp[2, TP_RADIUS_M]
    if int(vp[P.VP_POWERTRAIN_KIND]) == P.POWERTRAIN_AUTOMATIC:
        n = P.ENGINE_CURVE_POINTS
        torque = float(np.max(vp[P.VP_ENGINE_FULL_LOAD_TORQUE_NM:P.VP_ENGINE_FULL_LOAD_TORQUE_NM
                                 + n])) * overall_ratio(vp, 1)
    else:
        torque = vp[P.VP_DRIVE_TORQUE_MAX_NM]
    return float(torque / mass_radius), float(vp[P.VP_BRAKE_TORQUE_MAX_NM] / mass_radius)


def pack_params(spec: DriverSpec | None, vp: np.ndarray, tp: np.ndarray, path_index: int
                ) -> np.ndarray:
    """A car's ``DP_*`` vector: the spec's keys (or the defaults, for a car the driver
    does not drive: its lengths make it an obstacle) and the slots derived from the car."""
    if spec is None:
        dp = np.zeros(D.N_DRIVER_PARAM)
        for p in D.DRIVER_PARAMS:
            if not p.derived:
                dp[p.slot] = np.nan if isinstance(p.default, str) else p.default
    else:
        dp = spec.params.copy()
    throttle, brake = vehicle_gains(vp, tp)
    if np.isnan(dp[D.DP_THROTTLE_ACCEL_MPS2]):
        dp[D.DP_THROTTLE_ACCEL_MPS2] = throttle
    if np.isnan(dp[D.DP_BRAKE_DECEL_MPS2]):
        dp[D.DP_BRAKE_DECEL_MPS2] = brake
    # the bumpers the gaps are measured to: the car's contact box unless given (a gap of
    # s0 is then s0 between the boxes the contact stage pushes with, section 16)
    if np.isnan(dp[D.DP_FRONT_OVERHANG_M]):
        dp[D.DP_FRONT_OVERHANG_M] = vp[P.VP_BODY_FRONT_OVERHANG_M]
    if np.isnan(dp[D.DP_REAR_OVERHANG_M]):
        dp[D.DP_REAR_OVERHANG_M] = vp[P.VP_BODY_REAR_OVERHANG_M]
    a, b = vp[P.VP_CG_TO_FRONT_AXLE_M], vp[P.VP_CG_TO_REAR_AXLE_M]
    dp[D.DP_ENABLED] = 0.0 if spec is None else 1.0
    dp[D.DP_PATH] = path_index
    dp[D.DP_FRONT_M] = a + dp[D.DP_FRONT_OVERHANG_M]
    dp[D.DP_REAR_M] = b + dp[D.DP_REAR_OVERHANG_M]
    dp[D.DP_WHEELBASE_M] = a + b
    dp[D.DP_CG_TO_REAR_AXLE_M] = b
    dp[D.DP_CG_HEIGHT_M] = vp[P.VP_CG_HEIGHT_M]
    dp[D.DP_STEER_PER_RAD] = vp[P.VP_STEERING_RATIO] / vp[P.VP_STEERING_WHEEL_MAX_RAD]
    dp[D.DP_MASS_KG] = vp[P.VP_MASS_KG]
    dp[D.DP_WHEEL_RADIUS_M] = tp[2, TP_RADIUS_M]
    return dp


def path_rows(xy: np.ndarray, terrain: Terrain, profile: list[tuple[float, float]],
              v0_mps: float) -> np.ndarray:
    """A path's ``PATH_*`` rows: its points, their 3-D stations over the terrain's
    surface (the plane's road, or the height grid) and the speed profile at them."""
    n = len(xy)
    if terrain.kind == TERRAIN_PLANE:
        road = terrain.road
        z = (road[P.ROAD_GRADE_PCT] * xy[:, 0] + road[P.ROAD_CROSS_SLOPE_PCT] * xy[:, 1]) / 100.0
    else:
        z = np.array([surface_at(terrain, float(x), float(y))[0] for x, y in xy])
    rows = np.zeros((n, D.N_PATH))
    rows[:, D.PATH_X_M] = xy[:, 0]
    rows[:, D.PATH_Y_M] = xy[:, 1]
    rows[1:, D.PATH_S_M] = np.cumsum(np.sqrt(np.sum(np.diff(xy, axis=0) ** 2, axis=1)
                                             + np.diff(z) ** 2))
    if profile:
        s, v = np.array(profile).T
        rows[:, D.PATH_SPEED_MPS] = np.interp(rows[:, D.PATH_S_M], s, v)
    else:
        rows[:, D.PATH_SPEED_MPS] = v0_mps
    return rows


def build_drivers(world: World, specs: dict[str, DriverSpec | None]) -> D.Drivers:
    """The drivers of a world's cars (``specs`` by car id; None or absent: not driven),
    their paths packed (identical paths once) and every car's projection unsearched."""
    paths: list[np.ndarray] = []
    keys: list[bytes] = []
    params = np.zeros((len(world.ids), D.N_DRIVER_PARAM))
    state = D.initial_driver_state(len(world.ids))
    for c, cid in enumerate(world.ids):
        spec = specs.get(cid)
        index = 0
        if spec is not None:
            rows = path_rows(spec.path_xy, world.model.terrain, spec.speed_profile,
                             spec.params[D.DP_IDM_V0_MPS])
            key = rows.tobytes()
            if key in keys:
                index = keys.index(key)
            else:
                index = len(paths)
                keys.append(key)
                paths.append(rows)
            state[c, D.DS_STOP_STATION_M] = spec.stop_s_m
            state[c, D.DS_GO_TIME_S] = spec.go_t_s
            # a car that starts at a crawl starts held: its drive-off is a launch
            if abs(world.data.x[c, L.U_MPS]) < D.HOLD_SPEED_MPS:
                state[c, D.DS_MODE] = D.MODE_HOLD
        params[c] = pack_params(spec, world.model.vp[c], world.model.tp[c], index)
    if not paths:  # no driven car: one dummy path keeps the shapes (nothing reads it)
        paths.append(np.array([[0.0, 0.0, 0.0, 0.0], [1.0, 0.0, 1.0, 0.0]]))
    counts = np.array([len(p) for p in paths], dtype=np.int64)
    path_index = np.stack([np.concatenate([[0], np.cumsum(counts)[:-1]]), counts], axis=1)
    proj = np.zeros((len(world.ids), len(paths), D.N_PROJ))
    proj[:, :, D.PROJ_SEG] = -1.0
    return D.Drivers(params=params, state=state, paths=np.ascontiguousarray(np.concatenate(paths)),
                     path_rows=np.ascontiguousarray(path_index), proj=proj,
                     pose=np.zeros((len(world.ids), 4)),
                     axes=np.zeros((len(world.ids), 3, 3)))
