"""The built-in driver: steer, throttle, brake and gear of a car from its state (issue 30).

A driver drives a car through the very inputs a person uses (``core.layout.IN_*``): traffic
obeys the car's physics, nothing is teleported. Per step and per driven car, from the
states at the start of the step (docs/model.md section 15):

- **Where the car is on its path.** Every car of the world (driven or not: they are the
  obstacles) is projected onto every path of the world: the nearest point of the path's
  polyline to the car's CG in world x, y, its station (distance along the path, in 3-D,
  from its first point) and its signed lateral offset (+ left). The search starts at the
  segment found the step before (``proj``), so it costs a few segments a step.
- **Lateral: pure pursuit** (Coulter 1992) from the rear axle to the point of the path a
  preview distance ahead, ``L_d = max(preview_min_m, preview_time_s u)``: curvature
  ``kappa = 2 y_l / L_d^2`` (``y_l`` the point's lateral offset in the car's frame), road
  wheel angle ``delta = atan(wheelbase kappa)``, steer input ``delta`` times the steering's
  ratio over its wheel's lock.
- **Longitudinal: the Intelligent Driver Model** (Treiber, Hennecke, Helbing 2000) for the
  desired acceleration from the speed, the speed profile of the path at the car's station
  (or a commanded speed) and the bumper-to-bumper gap to the nearest car ahead on the path,
  with a stopping law that brings the car to rest at a given station (or ``s0`` behind a
  stopped car) instead of the IDM's asymptotic approach; the desired acceleration becomes
  pedals by a feedforward (gravity along the car from the step's outputs, the car's
  acceleration at full throttle and full brake) and a feedback on the acceleration's
  integral (a reference speed) with an integral term.
- **Hold and drive-off.** Below a crawl at its stop point the car holds with the brake (and
  the parking brake if asked) in gear D; it drives off when the stop point is released
  (``go``) and the IDM asks for a real acceleration: the throttle builds against the held
  brake, which is released only once the drive force (the step's outputs) carries the grade
  load, so the car does not roll back beyond what its own tire springs give.

Layouts (flat float64, named slots): per car the driver's parameters ``DP_*`` (generated
from the tables below, one source with the ``driver:`` keys and docs/configuration.md) and
its state ``DS_*`` (modes, integrators, the commands, and what it saw: station, lateral
offset, gap); the world's paths concatenated as rows ``PATH_*`` (x, y, station, speed
profile), each path a ``(first row, rows)`` pair of ``path_rows``; every car's projection on
every path ``PROJ_*``. ``drive`` is allocation-free.
"""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np

from simserver.core import layout as L
from simserver.core.param_table import Param, ParamTable, slot_count, slot_layout
from simserver.core.params import ROAD_CROSS_SLOPE_PCT, ROAD_GRADE_PCT
from simserver.core.road import road_frame
from simserver.core.terrain import TERRAIN_PLANE, terrain_road
from simserver.core.world import WorldData, WorldModel
from simserver.core.world import step as world_step

# ---------------------------------------------------------------- parameter tables
IDM = ParamTable("idm", "the Intelligent Driver Model's parameters (Treiber, Hennecke, "
                 "Helbing 2000, Phys. Rev. E 62, 1805, Table I)", (
    Param("v0_mps", "m/s", 0.0, 100.0,
          "desired speed: the speed profile where the path gives none", default=33.3, slot=0,
          const="DP_IDM_V0_MPS"),
    Param("T_s", "s", 0.1, 10.0, "safe time gap T", default=1.6, slot=1,
          const="DP_IDM_T_S"),
    Param("s0_m", "m", 0.1, 20.0,
          "jam distance s0: the bumper-to-bumper gap kept at rest behind a car", default=2.0,
          slot=2, const="DP_IDM_S0_M"),
    Param("a_mps2", "m/s^2", 0.1, 10.0, "maximum acceleration a", default=0.73, slot=3,
          const="DP_IDM_A_MPS2"),
    Param("b_mps2", "m/s^2", 0.1, 10.0, "comfortable deceleration b", default=1.67, slot=4,
          const="DP_IDM_B_MPS2"),
    Param("delta", "-", 1.0, 10.0, "acceleration exponent delta", default=4.0, slot=5,
          const="DP_IDM_DELTA"),
))
"""The IDM (``driver: {idm: {...}}``); defaults: the paper's Table I (v0 120 km/h)."""

CONTROL = ParamTable("driver", "the driver's path following, pedals and hold", (
    Param("preview_min_m", "m", 0.5, 100.0,
          "pure pursuit's preview distance at low speed: L_d = max(preview_min_m, "
          "preview_time_s u)", default=4.0, slot=6),
    Param("preview_time_s", "s", 0.0, 5.0,
          "pure pursuit's preview time: the preview grows with speed", default=0.5, slot=7),
    Param("stop_decel_mps2", "m/s^2", 0.1, 10.0,
          "deceleration of the approach to a stop point or a stopped car: the speed "
          "target sqrt(2 stop_decel_mps2 d) at distance d from it", default=1.5, slot=8),
    Param("decel_max_mps2", "m/s^2", 1.0, 12.0,
          "most deceleration the driver asks for (an emergency stop)", default=8.0, slot=9),
    Param("speed_gain_per_s", "1/s", 0.0, 20.0,
          "feedback from the reference speed's error to the acceleration", default=2.0,
          slot=10),
    Param("speed_integral_per_s2", "1/s^2", 0.0, 20.0,
          "integral of the speed error (drag, rolling resistance, creep)", default=0.5,
          slot=11),
    Param("hold_brake", "-", 0.05, 1.0,
          "brake pedal held at a stop", default=0.5, slot=12),
    Param("hold_parking_brake", "-", 0.0, 1.0,
          "1: the parking brake is set too while held", default=0.0, slot=13),
    Param("lane_half_width_m", "m", 0.1, 20.0,
          "a car whose CG is this close to the path (sideways) and ahead is in the lane",
          default=1.75, slot=14),
    Param("front_overhang_m", "m", 0.0, 5.0,
          "front bumper ahead of the front axle: the gaps the driver keeps are measured to "
          "it", default="the vehicle's body_front_overhang_m (its contact box)", slot=15),
    Param("rear_overhang_m", "m", 0.0, 5.0,
          "rear bumper behind the rear axle: a follower's gap is measured from it",
          default="the vehicle's body_rear_overhang_m (its contact box)", slot=16),
    Param("throttle_accel_mps2", "m/s^2", 0.1, 30.0,
          "acceleration at full throttle, the feedforward's gain", slot=17,
          default="the vehicle's drive torque / (mass R)"),
    Param("brake_decel_mps2", "m/s^2", 0.1, 50.0,
          "deceleration at full brake, the feedforward's gain", slot=18,
          default="the vehicle's brake torque / (mass R)"),
    Param("coast_from_s_m", "m", -1e7, 1e7,
          "from this station of the CG on, both pedals are released (the car coasts; "
          "ISO 3888-2's throttle released at the entry gate, docs/manoeuvres.md section 7)",
          default=1e7, slot=29),
    Param("oncoming_stop", "-", 0.0, 1.0,
          "1: a car ahead in the lane heading against the path (more than 90 degrees off "
          "its tangent) is a stopped obstacle: the driver stops s0 before it; 0: such cars "
          "are not obstacles (a car overtaking in the oncoming lane, docs/model.md "
          "section 15)", default=1.0, slot=30),
    # derived: packed from the vehicle and the scenario, never read from a file
    Param("enabled", "-", None, None, "1: the driver drives the car; 0: an obstacle only",
          slot=19),
    Param("path", "-", None, None, "the path's index in path_rows", slot=20),
    Param("front_m", "m", None, None, "CG to front bumper along the car", slot=21),
    Param("rear_m", "m", None, None, "CG to rear bumper along the car", slot=22),
    Param("wheelbase_m", "m", None, None, "front to rear axle", slot=23),
    Param("cg_to_rear_axle_m", "m", None, None, "CG to rear axle", slot=24),
    Param("cg_height_m", "m", None, None, "static CG height (the world position)", slot=25),
    Param("steer_per_rad", "1/rad", None, None,
          "steer input per radian of road-wheel angle (ratio / wheel lock)", slot=26),
    Param("mass_kg", "kg", None, None, "the car's mass", slot=27),
    Param("wheel_radius_m", "m", None, None, "the rear tires' rolling radius", slot=28),
))
"""The driver's own keys (``driver: {...}``) and its derived slots."""

DRIVER_TABLES = (IDM, CONTROL)
DRIVER_PARAMS = slot_layout(DRIVER_TABLES)

# --- generated slot constants
DP_IDM_V0_MPS = 0  # m/s, idm
DP_IDM_T_S = 1  # s, idm
DP_IDM_S0_M = 2  # m, idm
DP_IDM_A_MPS2 = 3  # m/s^2, idm
DP_IDM_B_MPS2 = 4  # m/s^2, idm
DP_IDM_DELTA = 5  # -, idm
DP_PREVIEW_MIN_M = 6  # m, driver
DP_PREVIEW_TIME_S = 7  # s, driver
DP_STOP_DECEL_MPS2 = 8  # m/s^2, driver
DP_DECEL_MAX_MPS2 = 9  # m/s^2, driver
DP_SPEED_GAIN_PER_S = 10  # 1/s, driver
DP_SPEED_INTEGRAL_PER_S2 = 11  # 1/s^2, driver
DP_HOLD_BRAKE = 12  # -, driver
DP_HOLD_PARKING_BRAKE = 13  # -, driver
DP_LANE_HALF_WIDTH_M = 14  # m, driver
DP_FRONT_OVERHANG_M = 15  # m, driver
DP_REAR_OVERHANG_M = 16  # m, driver
DP_THROTTLE_ACCEL_MPS2 = 17  # m/s^2, driver
DP_BRAKE_DECEL_MPS2 = 18  # m/s^2, driver
DP_ENABLED = 19  # -, driver
DP_PATH = 20  # -, driver
DP_FRONT_M = 21  # m, driver
DP_REAR_M = 22  # m, driver
DP_WHEELBASE_M = 23  # m, driver
DP_CG_TO_REAR_AXLE_M = 24  # m, driver
DP_CG_HEIGHT_M = 25  # m, driver
DP_STEER_PER_RAD = 26  # 1/rad, driver
DP_MASS_KG = 27  # kg, driver
DP_WHEEL_RADIUS_M = 28  # m, driver
DP_COAST_FROM_S_M = 29  # m, driver
DP_ONCOMING_STOP = 30  # -, driver
# --- end of generated slot constants
N_DRIVER_PARAM = slot_count(DRIVER_PARAMS)

# ---------------------------------------------------------------- driver state
DS_MODE = 0  # MODE_* below
DS_STATION_M = 1  # the CG's station on the car's path (m)
DS_LATERAL_M = 2  # the CG's offset from the path, + left (m)
DS_GAP_M = 3  # bumper-to-bumper gap to the car ahead (m; inf: none)
DS_LEADER = 4  # the car ahead's row (-1: none)
DS_ACCEL_CMD_MPS2 = 5  # the desired acceleration of the step
DS_SPEED_REF_MPS = 6  # the reference speed: the desired acceleration's integral
DS_INTEGRAL_MPS2 = 7  # the speed error's integral term
DS_TARGET_SPEED_MPS = 8  # command: the desired speed (< 0: the path's speed profile)
DS_STOP_STATION_M = 9  # command: the front bumper stops at this station (inf: none)
DS_GO_TIME_S = 10  # command: at this time the stop point is released (inf: none)
DS_STOP_DISTANCE_M = 11  # distance left to the nearest stop target (m; inf: none)
N_DRIVER_STATE = 12
DRIVER_STATE_NAMES = ("mode", "station_m", "lateral_m", "gap_m", "leader", "accel_cmd_mps2",
                      "speed_ref_mps", "integral_mps2", "target_speed_mps", "stop_station_m",
                      "go_time_s", "stop_distance_m")
assert len(DRIVER_STATE_NAMES) == N_DRIVER_STATE

MODE_DRIVE, MODE_HOLD, MODE_LAUNCH = 0.0, 1.0, 2.0
MODE_NAMES = ("drive", "hold", "launch")

# ---------------------------------------------------------------- paths and projections
PATH_X_M = 0  # world x of the point (m)
PATH_Y_M = 1  # world y (m)
PATH_S_M = 2  # station: 3-D length along the path from its first point (m)
PATH_SPEED_MPS = 3  # the speed profile at the point (m/s)
N_PATH = 4

PROJ_SEG = 0  # the segment the car is nearest (-1: not searched yet)
PROJ_S_M = 1  # the CG's station on the path
PROJ_LAT_M = 2  # its offset from the path, + left
PROJ_V_MPS = 3  # its speed along the path
N_PROJ = 4

# ---------------------------------------------------------------- fixed constants
# The stop law and the hold (docs/model.md section 15): a step's worth of reasons each.
STOP_GAIN_PER_S = 2.0  # speed error to acceleration on the approach to a stop target
LEADER_STOPPED_MPS = 0.3  # a car ahead slower than this is a stop target (s0 behind it)
HOLD_SPEED_MPS = 0.05  # below this speed ...
HOLD_DISTANCE_M = 0.01  # ... and this close to the stop target (or past it), hold
LAUNCH_ACCEL_FRACTION = 0.25  # drive off when the IDM asks for this fraction of a
LAUNCH_DISTANCE_M = 0.3  # ... and the stop target is this far ahead
LAUNCH_FORCE_MARGIN = 1.05  # the brake is released when drive force > margin x grade load
SPEED_REF_BAND_MPS = 0.5  # anti-windup: the reference speed stays this close to the speed
INTEGRAL_MAX_MPS2 = 3.0
GAP_MIN_M = 0.01  # the IDM's gap is floored here (the interaction term's division)
# A car ahead in the lane is a leader (followed at its speed along the path) only when its
# heading is within this angle of the path's tangent at its projection; any other car in
# the lane is an obstacle at rest (docs/model.md section 15): a crossing car or an oncoming
# one (heading more than 90 degrees off, ignored with oncoming_stop 0).
LEADER_HEADING_MAX_RAD = np.deg2rad(30.0)
LEADER_HEADING_MIN_COS = float(np.cos(LEADER_HEADING_MAX_RAD))
INF = np.inf


class Drivers(NamedTuple):
    """The drivers of a world's cars (row ``c`` is car ``c`` of the world's car axis)."""

    params: np.ndarray  # float64[n_cars, N_DRIVER_PARAM]
    state: np.ndarray  # float64[n_cars, N_DRIVER_STATE]
    paths: np.ndarray  # float64[n_rows, N_PATH], every path's points, one after another
    path_rows: np.ndarray  # int64[n_paths, 2]: each path's first row and number of rows
    proj: np.ndarray  # float64[n_cars, n_paths, N_PROJ]: every car on every path
    pose: np.ndarray  # float64[n_cars, 4]: world x, y of the CG, horizontal heading (scratch)
    axes: np.ndarray  # float64[n_cars, 3, 3]: each car's reference plane axes (scratch)


def initial_driver_state(n_cars: int) -> np.ndarray:
    """A fresh driver state per car: mode drive, no commands, nothing seen yet."""
    s = np.zeros((n_cars, N_DRIVER_STATE))
    s[:, DS_GAP_M] = INF
    s[:, DS_LEADER] = -1.0
    s[:, DS_TARGET_SPEED_MPS] = -1.0
    s[:, DS_STOP_STATION_M] = INF
    s[:, DS_GO_TIME_S] = INF
    s[:, DS_STOP_DISTANCE_M] = INF
    return s


# ---------------------------------------------------------------- commands (between steps)
def set_target_speed(drivers: Drivers, c: int, speed_mps: float) -> None:
    """Car ``c`` keeps ``speed_mps`` (as its IDM's desired speed) instead of its path's
    profile; a negative speed returns to the profile."""
    drivers.state[c, DS_TARGET_SPEED_MPS] = speed_mps


def stop_at(drivers: Drivers, c: int, station_m: float) -> None:
    """Car ``c`` stops with its front bumper at ``station_m`` of its path and holds."""
    drivers.state[c, DS_STOP_STATION_M] = station_m
    drivers.state[c, DS_GO_TIME_S] = INF


def go(drivers: Drivers, c: int, time_s: float = -INF) -> None:
    """Car ``c``'s stop point is released at simulated time ``time_s`` (default: now)."""
    drivers.state[c, DS_GO_TIME_S] = time_s


# ---------------------------------------------------------------- kernels
@nb.njit(cache=True, inline="always")
def _horizontal_pose(x: np.ndarray, cg_height_m: float, plane_grade_pct: float,
                     plane_cross_pct: float, use_plane: bool, axes: np.ndarray
                     ) -> tuple[float, float, float, float]:
    """World ``(x, y)`` of the CG and the unit horizontal heading ``(hx, hy)`` of the car,
    from its planar states on its reference plane (``core.pose.world_pose``'s position).
    ``use_plane``: the plane terrain, whose reference plane is the road (a fresh state has
    not been stepped onto it yet)."""
    if use_plane:
        road_frame(plane_grade_pct, plane_cross_pct, axes)
    else:
        road_frame(x[L.REF_GRADE_PCT], x[L.REF_CROSS_SLOPE_PCT], axes)
    lift = cg_height_m + x[L.HEAVE_M]
    px = x[L.X_M] * axes[0, 0] + x[L.Y_M] * axes[1, 0] + lift * axes[2, 0]
    py = x[L.X_M] * axes[0, 1] + x[L.Y_M] * axes[1, 1] + lift * axes[2, 1]
    c, s = np.cos(x[L.YAW_RAD]), np.sin(x[L.YAW_RAD])
    hx = c * axes[0, 0] + s * axes[1, 0]
    hy = c * axes[0, 1] + s * axes[1, 1]
    norm = np.sqrt(hx * hx + hy * hy)
    return px, py, hx / norm, hy / norm


@nb.njit(cache=True, inline="always")
def _seg_dist2(paths: np.ndarray, k: int, px: float, py: float) -> float:
    """Squared distance from ``(px, py)`` to segment ``k`` (rows k, k+1) of ``paths``."""
    x0, y0 = paths[k, PATH_X_M], paths[k, PATH_Y_M]
    ex, ey = paths[k + 1, PATH_X_M] - x0, paths[k + 1, PATH_Y_M] - y0
    dx, dy = px - x0, py - y0
    e2 = ex * ex + ey * ey
    t = (dx * ex + dy * ey) / e2 if e2 > 0.0 else 0.0
    t = min(1.0, max(0.0, t))
    rx, ry = dx - t * ex, dy - t * ey
    return rx * rx + ry * ry


@nb.njit(cache=True)
def project(paths: np.ndarray, first: int, rows: int, px: float, py: float, hx: float,
            hy: float, u_mps: float, proj: np.ndarray) -> None:
    """The nearest point of a path (rows ``first .. first + rows``) to ``(px, py)`` into
    ``proj`` (``PROJ_*``): a local descent from ``proj[PROJ_SEG]`` (a car moves a few
    millimetres a step), a search of every segment when it is -1. Beyond either end the
    path runs on straight (the station extrapolates)."""
    n_seg = rows - 1
    k = int(proj[PROJ_SEG])
    if k < 0 or k >= n_seg:
        best = INF
        k = 0
        for j in range(n_seg):
            d = _seg_dist2(paths, first + j, px, py)
            if d < best:
                best = d
                k = j
    else:
        d = _seg_dist2(paths, first + k, px, py)
        while k + 1 < n_seg:
            d1 = _seg_dist2(paths, first + k + 1, px, py)
            if d1 >= d:
                break
            k += 1
            d = d1
        while k > 0:
            d1 = _seg_dist2(paths, first + k - 1, px, py)
            if d1 >= d:
                break
            k -= 1
            d = d1
    r = first + k
    x0, y0 = paths[r, PATH_X_M], paths[r, PATH_Y_M]
    ex, ey = paths[r + 1, PATH_X_M] - x0, paths[r + 1, PATH_Y_M] - y0
    e = np.sqrt(ex * ex + ey * ey)
    ex /= e
    ey /= e
    dx, dy = px - x0, py - y0
    along = dx * ex + dy * ey
    if k > 0 and along < 0.0:
        along = 0.0  # inside the polyline: the vertex (the next segment starts there)
    seg_len = paths[r + 1, PATH_S_M] - paths[r, PATH_S_M]
    if k < n_seg - 1 and along > e:
        along = e
    proj[PROJ_SEG] = k
    proj[PROJ_S_M] = paths[r, PATH_S_M] + along * seg_len / e  # 3-D station
    proj[PROJ_LAT_M] = ex * dy - ey * dx
    proj[PROJ_V_MPS] = u_mps * (hx * ex + hy * ey)


@nb.njit(cache=True, inline="always")
def _point_at(paths: np.ndarray, first: int, rows: int, k0: int, s: float
              ) -> tuple[float, float, float]:
    """World ``(x, y)`` of station ``s`` of a path (searched forward from segment ``k0``;
    beyond the last point the last segment runs on) and the speed profile there."""
    k = k0
    last = first + rows - 1
    r = first + k
    while r + 1 < last and paths[r + 1, PATH_S_M] < s:
        r += 1
    while r > first and paths[r, PATH_S_M] > s:
        r -= 1
    s0, s1 = paths[r, PATH_S_M], paths[r + 1, PATH_S_M]
    t = (s - s0) / (s1 - s0)
    tc = min(1.0, max(0.0, t))
    x = paths[r, PATH_X_M] + t * (paths[r + 1, PATH_X_M] - paths[r, PATH_X_M])
    y = paths[r, PATH_Y_M] + t * (paths[r + 1, PATH_Y_M] - paths[r, PATH_Y_M])
    v = paths[r, PATH_SPEED_MPS] + tc * (paths[r + 1, PATH_SPEED_MPS] - paths[r, PATH_SPEED_MPS])
    return x, y, v


@nb.njit(cache=True, inline="always")
def idm_accel(v: float, v0: float, gap_m: float, v_lead: float, dp: np.ndarray) -> float:
    """The IDM's acceleration (Treiber et al. 2000, eqs. 1-2):
    ``a [1 - (v/v0)^delta - (s*/s)^2]``, ``s* = s0 + max(0, v T + v dv / (2 sqrt(a b)))``
    with ``dv = v - v_lead``; no car ahead (``gap_m`` inf): the free-road term only."""
    a = dp[DP_IDM_A_MPS2]
    vp = max(v, 0.0)
    acc = a * (1.0 - (vp / max(v0, 1e-3)) ** dp[DP_IDM_DELTA])
    if gap_m < INF:
        s_star = dp[DP_IDM_S0_M] + max(0.0, vp * dp[DP_IDM_T_S] + vp * (vp - v_lead)
                                        / (2.0 * np.sqrt(a * dp[DP_IDM_B_MPS2])))
        ratio = s_star / max(gap_m, GAP_MIN_M)
        acc -= a * ratio * ratio
    return acc


@nb.njit(cache=True, inline="always")
def _drive_car(world: WorldModel, data: WorldData, drv: Drivers, c: int) -> None:
    """One car's inputs for the step (module docstring; docs/model.md section 15)."""
    dp = drv.params[c]
    ds = drv.state[c]
    x = data.x[c]
    inputs = data.inputs[c]
    out = data.out[c]
    dt = world.dt_s
    p = int(dp[DP_PATH])
    first, rows = drv.path_rows[p, 0], drv.path_rows[p, 1]
    me = drv.proj[c, p]
    s_cg = me[PROJ_S_M]
    v = x[L.U_MPS]
    t_now = x[L.TIME_S]
    # ---- commands that fall due
    if t_now >= ds[DS_GO_TIME_S]:
        ds[DS_STOP_STATION_M] = INF
        ds[DS_GO_TIME_S] = INF
    # ---- the car ahead: nearest on this path, within the lane, ahead of the front bumper
    front = s_cg + dp[DP_FRONT_M]
    gap = INF
    v_lead = 0.0
    leader = -1
    half = dp[DP_LANE_HALF_WIDTH_M]
    for j in range(data.x.shape[0]):
        if j == c:
            continue
        other = drv.proj[j, p]
        if abs(other[PROJ_LAT_M]) > half or other[PROJ_S_M] <= s_cg:
            continue
        # its heading against the path's tangent where it is (docs/model.md section 15)
        r = first + int(other[PROJ_SEG])
        ex = drv.paths[r + 1, PATH_X_M] - drv.paths[r, PATH_X_M]
        ey = drv.paths[r + 1, PATH_Y_M] - drv.paths[r, PATH_Y_M]
        cos_h = (drv.pose[j, 2] * ex + drv.pose[j, 3] * ey) / max(np.sqrt(ex * ex + ey * ey),
                                                                   1e-12)
        if cos_h < 0.0 and dp[DP_ONCOMING_STOP] < 0.5:
            continue  # oncoming, and this driver is told to pass it (overtaking)
        # the bumper it faces: its rear when it goes our way, its front when oncoming
        g = other[PROJ_S_M] - (drv.params[j, DP_REAR_M] if cos_h >= 0.0
                               else drv.params[j, DP_FRONT_M]) - front
        if g < gap:
            gap = g
            # a leader is followed at its speed; a crossing or oncoming car is at rest
            v_lead = other[PROJ_V_MPS] if cos_h >= LEADER_HEADING_MIN_COS else 0.0
            leader = j
    # ---- desired speed: the command, else the path's profile at the car
    seg = int(me[PROJ_SEG])
    v0 = ds[DS_TARGET_SPEED_MPS]
    if v0 < 0.0:
        v0 = _point_at(drv.paths, first, rows, seg, s_cg)[2]
    a_des = idm_accel(v, v0, gap, v_lead, dp)
    # ---- stop targets: the stop point (at the latest the path's end), a stopped car
    end_s = drv.paths[first + rows - 1, PATH_S_M]
    d_stop = min(ds[DS_STOP_STATION_M], end_s) - front
    if leader >= 0 and v_lead < LEADER_STOPPED_MPS:
        d_stop = min(d_stop, gap - dp[DP_IDM_S0_M])
    if d_stop < INF:
        b_stop = dp[DP_STOP_DECEL_MPS2]
        if d_stop > 0.0:
            # track the speed that stops at the target at b_stop; once behind that
            # profile (faster), at least the constant deceleration that stops there
            a_stop = STOP_GAIN_PER_S * (np.sqrt(2.0 * b_stop * d_stop) - v)
            a_kin = -v * abs(v) / (2.0 * d_stop)
            if a_kin < -b_stop:
                a_stop = min(a_stop, a_kin)
        else:  # at or past it: stop now
            a_stop = -dp[DP_DECEL_MAX_MPS2] if v > HOLD_SPEED_MPS else -STOP_GAIN_PER_S * v
        a_des = min(a_des, a_stop)
    a_des = min(max(a_des, -dp[DP_DECEL_MAX_MPS2]), dp[DP_IDM_A_MPS2])
    # ---- lateral: pure pursuit from the rear axle
    pose = drv.pose[c]
    px, py, hx, hy = pose[0], pose[1], pose[2], pose[3]
    preview = max(dp[DP_PREVIEW_MIN_M], dp[DP_PREVIEW_TIME_S] * abs(v))
    tx, ty, _ = _point_at(drv.paths, first, rows, seg, s_cg + preview)
    rx = px - dp[DP_CG_TO_REAR_AXLE_M] * hx
    ry = py - dp[DP_CG_TO_REAR_AXLE_M] * hy
    dx, dy = tx - rx, ty - ry
    y_l = -dx * hy + dy * hx
    l2 = dx * dx + dy * dy
    delta = np.arctan(dp[DP_WHEELBASE_M] * 2.0 * y_l / max(l2, 1e-6))
    inputs[L.IN_STEER] = min(1.0, max(-1.0, delta * dp[DP_STEER_PER_RAD]))
    inputs[L.IN_GEAR] = L.GEAR_D
    # ---- modes: hold at a stop, launch against the brake, drive
    mode = ds[DS_MODE]
    g_x = out[L.O_GRAVITY_X_MPS2]  # gravity along the car (+ forward: downhill)
    if mode == MODE_DRIVE and abs(v) < HOLD_SPEED_MPS and d_stop < HOLD_DISTANCE_M:
        mode = MODE_HOLD
    if mode == MODE_HOLD and (a_des > LAUNCH_ACCEL_FRACTION * dp[DP_IDM_A_MPS2]
                              and d_stop > LAUNCH_DISTANCE_M):
        mode = MODE_LAUNCH
        ds[DS_SPEED_REF_MPS] = max(v, 0.0)
        ds[DS_INTEGRAL_MPS2] = 0.0
    if mode == MODE_HOLD:
        inputs[L.IN_THROTTLE] = 0.0
        inputs[L.IN_BRAKE] = dp[DP_HOLD_BRAKE]
        inputs[L.IN_PARKING_BRAKE] = dp[DP_HOLD_PARKING_BRAKE]
        ds[DS_SPEED_REF_MPS] = 0.0
        ds[DS_INTEGRAL_MPS2] = 0.0
    else:
        # reference speed: the desired acceleration's integral, kept near the speed
        v_ref = ds[DS_SPEED_REF_MPS] + a_des * dt
        v_ref = min(max(v_ref, v - SPEED_REF_BAND_MPS), v + SPEED_REF_BAND_MPS)
        v_ref = max(v_ref, 0.0)
        err = v_ref - v
        integral = ds[DS_INTEGRAL_MPS2] + dp[DP_SPEED_INTEGRAL_PER_S2] * err * dt
        integral = min(max(integral, -INTEGRAL_MAX_MPS2), INTEGRAL_MAX_MPS2)
        ds[DS_SPEED_REF_MPS] = v_ref
        ds[DS_INTEGRAL_MPS2] = integral
        a_cmd = a_des - g_x + dp[DP_SPEED_GAIN_PER_S] * err + integral
        throttle = max(0.0, a_cmd) / dp[DP_THROTTLE_ACCEL_MPS2]
        brake = max(0.0, -a_cmd) / dp[DP_BRAKE_DECEL_MPS2]
        inputs[L.IN_THROTTLE] = min(1.0, throttle)
        inputs[L.IN_PARKING_BRAKE] = 0.0
        if mode == MODE_LAUNCH:
            # the held brake goes once the drive force carries the grade's pull back
            drive_n = 0.0
            for w in range(L.N_WHEELS):
                drive_n += out[L.O_DRIVE_TORQUE0 + w]
            drive_n /= dp[DP_WHEEL_RADIUS_M]
            if drive_n >= LAUNCH_FORCE_MARGIN * dp[DP_MASS_KG] * max(0.0, -g_x):
                mode = MODE_DRIVE
                inputs[L.IN_BRAKE] = min(1.0, brake)
            else:
                inputs[L.IN_BRAKE] = dp[DP_HOLD_BRAKE]
                ds[DS_INTEGRAL_MPS2] = 0.0
                ds[DS_SPEED_REF_MPS] = 0.0
        else:
            inputs[L.IN_BRAKE] = min(1.0, brake)
        if s_cg >= dp[DP_COAST_FROM_S_M] and mode == MODE_DRIVE:
            # coasting: the pedals released, the path still steered (docs/model.md s. 15)
            inputs[L.IN_THROTTLE] = 0.0
            inputs[L.IN_BRAKE] = 0.0
    ds[DS_MODE] = mode
    ds[DS_STATION_M] = s_cg
    ds[DS_LATERAL_M] = me[PROJ_LAT_M]
    ds[DS_GAP_M] = gap
    ds[DS_LEADER] = leader
    ds[DS_ACCEL_CMD_MPS2] = a_des
    ds[DS_STOP_DISTANCE_M] = d_stop


@nb.njit(cache=True, _nrt=False, error_model="numpy")
def drive(world: WorldModel, data: WorldData, drv: Drivers) -> None:
    """Every driven car's inputs for the next step, from the states now: every car is
    projected onto every path (the obstacles), then each driven car (``DP_ENABLED``) writes
    its steer, throttle, brake, parking brake and gear into ``data.inputs``."""
    n_cars = data.x.shape[0]
    n_paths = drv.path_rows.shape[0]
    road = terrain_road(world.terrain)
    use_plane = world.terrain.kind == TERRAIN_PLANE  # the road is the reference plane
    for c in range(n_cars):
        dp = drv.params[c]
        x = data.x[c]
        pose = drv.pose[c]
        px, py, hx, hy = _horizontal_pose(x, dp[DP_CG_HEIGHT_M], road[ROAD_GRADE_PCT],
                                          road[ROAD_CROSS_SLOPE_PCT], use_plane,
                                          drv.axes[c])
        pose[0], pose[1], pose[2], pose[3] = px, py, hx, hy
        for p in range(n_paths):
            project(drv.paths, drv.path_rows[p, 0], drv.path_rows[p, 1], px, py, hx, hy,
                    x[L.U_MPS], drv.proj[c, p])
    for c in range(n_cars):
        if drv.params[c, DP_ENABLED] > 0.5:
            _drive_car(world, data, drv, c)


@nb.njit(cache=True, _nrt=False, error_model="numpy")
def simulate_driven(world: WorldModel, data: WorldData, drv: Drivers,
                    inputs_per_step: np.ndarray, states: np.ndarray, outputs: np.ndarray,
                    applied: np.ndarray, driver_states: np.ndarray, record_every: int) -> None:
    """``core.world.simulate`` closed loop: each step the cars' inputs are the row of
    ``inputs_per_step`` (the keyframed cars'), then ``drive`` writes the driven cars' over
    them, then the world steps (``core.world.step``). Row ``k`` of ``states``, ``outputs``
    as ``core.world.simulate``'s; ``applied`` (float64[rows, n_cars, N_INPUT]) the inputs
    the step applied and ``driver_states`` (float64[rows, n_cars, N_DRIVER_STATE]) the
    drivers' states after ``drive``, at every ``record_every``-th step."""
    x, out, inputs = data.x, data.out, data.inputs
    n_cars = x.shape[0]
    row = 0
    for k in range(inputs_per_step.shape[0]):
        for c in range(n_cars):
            for j in range(L.N_INPUT):
                inputs[c, j] = inputs_per_step[k, c, j]
        drive(world, data, drv)
        record = k % record_every == 0
        if record:
            for c in range(n_cars):
                for j in range(L.N_STATE):
                    states[row, c, j] = x[c, j]
                for j in range(L.N_INPUT):
                    applied[row, c, j] = inputs[c, j]
                for j in range(N_DRIVER_STATE):
                    driver_states[row, c, j] = drv.state[c, j]
        world_step(world, data)
        if record:
            for c in range(n_cars):
                for j in range(L.N_OUT):
                    outputs[row, c, j] = out[c, j]
            row += 1
