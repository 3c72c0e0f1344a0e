"""The Rerun scene of a run: the car on its road, tire forces, and the engineer's plots.

Everything is logged through an explicit ``rerun.RecordingStream`` (never the global one),
on one timeline, ``sim_time`` (a duration: simulated seconds). Rerun's ``log_time``
timeline is switched off, so a recording's only clock is the simulation's.

Two entry points share the same (vectorised) per-frame math:

- ``log_result(rec, result, fps=50)`` logs a whole ``ScenarioResult`` in column batches
  (``rr.send_columns``), decimated to ``fps``: the headless ``run-scenario --rrd`` path.
- ``SceneLogger(rec, vp, tp, ...)`` with ``log_frame(time_s, state, output, input)``, for
  the live viewer process fed by the state topic: it integrates the wheel spin on every
  call, keeps at most ``fps`` frames per simulated second and sends them in small
  batches through the same column path (0.1 s of latency by default).

Entity paths (constants below; ``RESULT_ENTITY_PATHS`` lists what ``log_result`` writes)::

    world                          view coordinates: right-handed, Z up (gravity is -Z)
    world/origin                   world axes at the origin (static)
    world/road                     the plane kind: the road plane through the origin
                                   (static):
    world/road/surface               its surface, a rectangle around the run
    world/road/grid                  a 10 m grid on it, bold every 50 m
    world/road/axes                  the plane's axes e1, e2, n (core.road.road_axes)
    world/terrain/...              a height map or OpenDRIVE kind instead (static): the
                                   ground mesh, the lanes and road marks
                                   (adapters.rerun_terrain)
    world/trail                    the trajectory so far: a line strip on the road
    world/car                      transform: the car's pose on the plane its planar
                                   states live on (the road, or on a terrain the
                                   reference plane fitted under the wheels, the state's
                                   REF_* slots: core.terrain): origin on that plane below
                                   the CG (X e1 + Y e2 + its height), x forward along the
                                   heading, z along the plane's normal n
    world/car/body                 transform: the sprung mass at its CG, heave along n,
                                   pitch then roll (nose down and left side up positive)
    world/car/body/shell           the body's boxes (static)
    world/car/wheel_{w}            transform: the hub (above the contact point by the
                                   rolling radius), steered, spun by the integral of Omega;
                                   on a terrain raised along n to the ground under it, or
                                   hanging at its spring's free length when it has left
                                   the ground (``wheel_hub_offsets``)
    world/car/wheel_{w}/tire       a cylinder (static)
    world/car/wheel_{w}/spokes     spokes that make the spin visible, one red (static)
    world/car/body/driver_eye      transform: the driver's eye in the body frame
                                   (``driver_eye_offset``), the origin of the
                                   driver's-eye view (static)
    world/cars/{id}                live viewer of a multi-car world: transform, every
                                   car's world pose (``adapters.rerun_fleet``)
    world/cars/{id}/box            its body box labelled with its id (the followed car,
                                   drawn in full under world/car, gets only the label)
    world/car/forces/{w}           arrows Fx, Fy (wheel heading frame) and Fz from the
                                   contact point, FORCE_SCALE_M_PER_N, coloured by the
                                   friction use (green 0 -> yellow 0.5 -> red >= 1)
    plots/speed                    u, v: body velocities (m/s)
    plots/yaw_rate                 r (rad/s)
    plots/slip/kappa               k' per wheel: the longitudinal slip fed to the tire
    plots/slip/tan_alpha           tan a' per wheel: the lateral slip fed to the tire
    plots/friction_use             |F_shear| over the available friction, per wheel
    plots/forces/{w}               Fx, Fy, Fz of one wheel (N, wheel frame)
    plots/damping/active           the Appendix A damping flag per wheel (0/1)
    plots/damping/{fx,fy}          the auxiliary damping share of Fx, Fy per wheel (N)
    plots/inputs/driver            steer, throttle, brake, parking brake
    plots/inputs/gear              gear code (0 P, 1 R, 2 N, 3 D)
    plots/diagnostics/tick_jitter_us, plots/diagnostics/dropped_frames   live server
    scene_info                     a text note: scales and colours (static)

with ``{w}`` one of ``core.layout.WHEEL_NAMES`` (fl, fr, rl, rr). A plot entity holds one
scalar instance per signal (``PLOT_GROUPS``: wheels in the order fl, fr, rl, rr), named
and coloured by its static ``SeriesLines``: one entity per plot keeps the live logging
cheap (rerun-sdk 0.41 costs about the same per entity for 1 or 4 scalars). The road plane,
positions and rotations follow ``core.road.road_axes`` and ``core.layout`` (ISO 8855).
``scene_blueprint()`` declares the layout: a 3D view whose eye follows the car (it
tracks ``world/car/body/shell``), with the driver's-eye view a tab beside it, above
the speed and yaw-rate plots, beside tabs of time-series views grouped as slips; forces
per wheel; inputs; damping; server diagnostics; and the note.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from simserver.adapters.rerun_terrain import log_terrain
from simserver.core import layout as L
from simserver.core.chassis import static_share, wheel_position
from simserver.core.params import (
    VP_CG_HEIGHT_M,
    VP_CG_TO_FRONT_AXLE_M,
    VP_CG_TO_REAR_AXLE_M,
    VP_GRAVITY_MPS2,
    VP_SPRING_FRONT_NPM,
    VP_SPRING_REAR_NPM,
    VP_TRACK_FRONT_M,
    VP_TRACK_REAR_M,
)
from simserver.core.road import road_axes
from simserver.core.terrain import TERRAIN_PLANE, Terrain, fit_plane, plane_terrain, surface_at
from simserver.core.tire_layout import TP_RADIUS_M

if TYPE_CHECKING:  # scenario imports the compiled core at run time only where needed
    from simserver.sim.scenario import ScenarioResult

# ----------------------------------------------------------------------------- names
TIMELINE = "sim_time"
"""The one timeline: simulated time, a Rerun duration."""

WORLD = "world"
ORIGIN_AXES = "world/origin"
ROAD = "world/road"
ROAD_SURFACE = "world/road/surface"
ROAD_GRID = "world/road/grid"
ROAD_AXES = "world/road/axes"
TRAIL = "world/trail"
CAR = "world/car"
BODY = "world/car/body"
BODY_SHELL = "world/car/body/shell"
WHEELS = tuple(f"world/car/wheel_{w}" for w in L.WHEEL_NAMES)
WHEEL_TIRES = tuple(f"{p}/tire" for p in WHEELS)
WHEEL_SPOKES = tuple(f"{p}/spokes" for p in WHEELS)
FORCES = tuple(f"world/car/forces/{w}" for w in L.WHEEL_NAMES)
DRIVER_EYE = "world/car/body/driver_eye"
"""The driver's eye in the body (``driver_eye_offset``): the origin of the driver's-eye
view (``scene_blueprint``), so that view moves with the body."""
CARS = "world/cars"
"""Every car of a multi-car world, ``world/cars/{id}`` (``adapters.rerun_fleet``)."""

PLOTS = "plots"
PLOT_SPEED = "plots/speed"
PLOT_YAW_RATE = "plots/yaw_rate"
PLOT_KAPPA = "plots/slip/kappa"
PLOT_TAN_ALPHA = "plots/slip/tan_alpha"
PLOT_FRICTION_USE = "plots/friction_use"
PLOT_FORCES = "plots/forces"
PLOT_DAMPING_ACTIVE = "plots/damping/active"
PLOT_DAMPING_FX = "plots/damping/fx"
PLOT_DAMPING_FY = "plots/damping/fy"
PLOT_INPUTS = "plots/inputs"
PLOT_DRIVER = "plots/inputs/driver"
PLOT_GEAR = "plots/inputs/gear"
PLOT_DIAGNOSTICS = "plots/diagnostics"
TICK_JITTER = "plots/diagnostics/tick_jitter_us"
DROPPED_FRAMES = "plots/diagnostics/dropped_frames"
SCENE_INFO = "scene_info"

# ---------------------------------------------------------------------------- scales
FORCE_SCALE_M_PER_N = 1.0 / 5000.0
"""Force arrows: 1 m per 5 kN."""

DEFAULT_FPS = 50.0
"""3D frames (and plot samples) per simulated second."""

TRAIL_HZ = 10.0
"""Trail points per simulated second."""

TRAIL_MAX_POINTS = 3000
"""The trail keeps the newest points (5 min at ``TRAIL_HZ``)."""

ROAD_MARGIN_M = 150.0
"""The road surface extends this far beyond the run's extent (``log_result``)."""

LIVE_ROAD_HALF_SIZE_M = 300.0
"""Live: half size of the road square; it is re-centred when the car nears an edge."""

GRID_SPACING_M = 10.0
GRID_MAJOR_EVERY = 5

TIRE_WIDTH_M = 0.22
ARROW_RADIUS_M = 0.035
SURFACE_OFFSET_M = -0.02  # the surface sits just below the contact plane, the grid on it
GRID_OFFSET_M = -0.01
TRAIL_OFFSET_M = 0.03

WHEEL_COLORS = {"fl": (230, 80, 60), "fr": (60, 150, 230), "rl": (240, 170, 40),
                "rr": (110, 190, 80)}
"""One colour per wheel in every plot."""

_GREEN = np.array([40.0, 200.0, 60.0])
_YELLOW = np.array([250.0, 210.0, 40.0])
_RED = np.array([230.0, 30.0, 30.0])


# ---------------------------------------------------------------------- plotted series
@dataclass(frozen=True)
class PlotGroup:
    """Signals plotted together: one entity, one scalar instance per signal.

    Attributes
    ----------
    path : str
        Entity path (under ``plots/``).
    source : str
        ``"state"``, ``"output"`` or ``"input"``: which ``core.layout`` array.
    indices : tuple of int
        Columns in that array (``core.layout`` constants), one per instance.
    labels : tuple of str
        Legend names, with units.
    colors : tuple of tuple of int
        RGB per instance.
    """

    path: str
    source: Literal["state", "output", "input"]
    indices: tuple[int, ...]
    labels: tuple[str, ...]
    colors: tuple[tuple[int, int, int], ...]

    def values(self, states: np.ndarray, outputs: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """The ``(n, len(indices))`` values of the group's signals for ``n`` rows."""
        source = {"state": states, "output": outputs, "input": inputs}[self.source]
        return source[:, list(self.indices)]


def _per_wheel(path: str, source: Literal["state", "output", "input"], first: int,
               label: str) -> PlotGroup:
    return PlotGroup(path, source, tuple(first + i for i in range(L.N_WHEELS)),
                     tuple(f"{label} {w}" for w in L.WHEEL_NAMES),
                     tuple(WHEEL_COLORS[w] for w in L.WHEEL_NAMES))


PLOT_GROUPS: tuple[PlotGroup, ...] = (
    PlotGroup(PLOT_SPEED, "state", (L.U_MPS, L.V_MPS), ("u (m/s)", "v (m/s)"),
              ((40, 110, 220), (230, 120, 30))),
    PlotGroup(PLOT_YAW_RATE, "state", (L.YAW_RATE_RADPS,), ("r (rad/s)",), ((150, 60, 190),)),
    _per_wheel(PLOT_KAPPA, "output", L.O_KAPPA0, "k'"),
    _per_wheel(PLOT_TAN_ALPHA, "output", L.O_TAN_ALPHA0, "tan a'"),
    _per_wheel(PLOT_FRICTION_USE, "output", L.O_FRICTION_USE0, "friction use"),
    *(PlotGroup(f"{PLOT_FORCES}/{w}", "output", (L.O_FX0 + i, L.O_FY0 + i, L.O_FZ0 + i),
                (f"Fx {w} (N)", f"Fy {w} (N)", f"Fz {w} (N)"),
                ((220, 60, 50), (50, 150, 60), (60, 90, 220)))
      for i, w in enumerate(L.WHEEL_NAMES)),
    _per_wheel(PLOT_DAMPING_ACTIVE, "state", L.DAMPING_ACTIVE0, "damping on"),
    _per_wheel(PLOT_DAMPING_FX, "output", L.O_DAMPING_FX0, "damping Fx (N)"),
    _per_wheel(PLOT_DAMPING_FY, "output", L.O_DAMPING_FY0, "damping Fy (N)"),
    PlotGroup(PLOT_DRIVER, "input", (L.IN_STEER, L.IN_THROTTLE, L.IN_BRAKE, L.IN_PARKING_BRAKE),
              ("steer [-1, 1]", "throttle [0, 1]", "brake [0, 1]", "parking brake (0/1)"),
              ((150, 60, 190), (50, 160, 60), (220, 50, 40), (120, 120, 120))),
    PlotGroup(PLOT_GEAR, "input", (L.IN_GEAR,), ("gear (0 P, 1 R, 2 N, 3 D)",),
              ((200, 200, 200),)),
)
"""Every plotted signal of a frame, by entity (the diagnostics are logged apart)."""

DIAGNOSTIC_SERIES = {TICK_JITTER: ("tick jitter (us)", (200, 60, 60)),
                     DROPPED_FRAMES: ("viewer frames dropped", (90, 90, 90))}

RESULT_ENTITY_PATHS: tuple[str, ...] = (
    WORLD, ORIGIN_AXES, ROAD_SURFACE, ROAD_GRID, ROAD_AXES, TRAIL, CAR, BODY, BODY_SHELL,
    DRIVER_EYE,
    *WHEELS, *WHEEL_TIRES, *WHEEL_SPOKES, *FORCES, SCENE_INFO,
    *(g.path for g in PLOT_GROUPS),
)
"""Every entity ``log_result`` writes (``SceneLogger`` adds ``DIAGNOSTIC_SERIES``)."""


# -------------------------------------------------------------------------- geometry
@dataclass(frozen=True)
class CarGeometry:
    """What the scene needs of a vehicle, read from its packed parameters.

    Attributes
    ----------
    wheel_xy_m : ndarray
        ``(4, 2)`` contact points relative to the CG in body axes (``wheel_position``).
    wheel_radius_m : ndarray
        ``(4,)`` rolling radii.
    cg_height_m : float
        CG height above the road.
    """

    wheel_xy_m: np.ndarray
    wheel_radius_m: np.ndarray
    cg_height_m: float

    @classmethod
    def from_params(cls, vp: np.ndarray, tp: np.ndarray) -> CarGeometry:
        """Geometry of the vehicle ``vp`` (``core.params``) on tires ``tp`` (4 rows)."""
        xy = np.array([wheel_position(vp, i) for i in range(L.N_WHEELS)], dtype=np.float64)
        radius = np.asarray(tp, dtype=np.float64)[:, TP_RADIUS_M].copy()
        return cls(wheel_xy_m=xy, wheel_radius_m=radius, cg_height_m=float(vp[VP_CG_HEIGHT_M]))

    def body_boxes(self, vp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centres and half sizes of the body's boxes (lower body, cabin) in the body frame.

        Styling only: overhangs of 0.85 m, width the track plus 0.2 m, clearance of
        0.6 rolling radii, beltline 0.95 m and roof 1.42 m above the road.
        """
        front = float(vp[VP_CG_TO_FRONT_AXLE_M]) + 0.85
        rear = float(vp[VP_CG_TO_REAR_AXLE_M]) + 0.85
        half_w = 0.5 * max(float(vp[VP_TRACK_FRONT_M]), float(vp[VP_TRACK_REAR_M])) + 0.1
        h = self.cg_height_m
        bottom = 0.6 * float(self.wheel_radius_m.mean())
        belt, roof = 0.95, 1.42
        lower_c = [0.5 * (front - rear), 0.0, 0.5 * (bottom + belt) - h]
        lower_h = [0.5 * (front + rear), half_w, 0.5 * (belt - bottom)]
        cab_len = 0.5 * (front + rear)
        cabin_c = [lower_c[0] - 0.12 * (front + rear), 0.0, 0.5 * (belt + roof) - h]
        cabin_h = [0.5 * cab_len, half_w - 0.08, 0.5 * (roof - belt)]
        return np.array([lower_c, cabin_c]), np.array([lower_h, cabin_h])


DRIVER_EYE_HEIGHT_M = 1.2
"""The driver's eye above the road: between the styled body's beltline (0.95 m) and roof
(1.42 m, ``CarGeometry.body_boxes``), about a sedan driver's seated eye height."""
DRIVER_EYE_LEFT_M = 0.37
"""The eye's offset to the left of the centre line (ISO 8855 y is left): a left-hand-drive
seat, half a seat width plus the console's half width."""


def driver_eye_offset(geometry: CarGeometry, vp: np.ndarray) -> np.ndarray:
    """The driver's eye in the body frame (origin at the CG, x forward, z up): above the
    middle of the styled cabin (``CarGeometry.body_boxes``), ``DRIVER_EYE_LEFT_M`` left of
    the centre line, ``DRIVER_EYE_HEIGHT_M`` above the road. Styling, as the boxes are."""
    centers, _ = geometry.body_boxes(vp)
    return np.array([float(centers[1][0]), DRIVER_EYE_LEFT_M,
                     DRIVER_EYE_HEIGHT_M - geometry.cg_height_m])


# ----------------------------------------------------------------------- quaternions
def quat_axis(axis: int, angle_rad: np.ndarray) -> np.ndarray:
    """Quaternions ``(..., 4)`` (x, y, z, w) of rotations by ``angle_rad`` about axis 0/1/2."""
    half = 0.5 * np.asarray(angle_rad, dtype=np.float64)
    q = np.zeros((*half.shape, 4))
    q[..., axis] = np.sin(half)
    q[..., 3] = np.cos(half)
    return q


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a b`` of (x, y, z, w) quaternions: rotate by ``b``, then ``a``."""
    ax, ay, az, aw = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bx, by, bz, bw = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ], axis=-1)


def quat_from_matrix(m: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a 3x3 rotation matrix (Shepperd's method)."""
    m = np.asarray(m, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0.0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i] = 0.25 * s
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
    q_arr = np.array(q)
    return q_arr / np.linalg.norm(q_arr)


# --------------------------------------------------------------- per-frame quantities
def car_pose(states: np.ndarray, axes: np.ndarray, heights_m: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
    """Pose of ``world/car`` in the world: the plane point below the CG, heading frame.

    Parameters
    ----------
    states : ndarray
        ``(n, N_STATE)``.
    axes : ndarray
        ``road_axes(grade, cross)``: rows e1, e2, n; or ``(n, 3, 3)``, one plane per row
        (``reference_planes``).
    heights_m : ndarray, optional
        ``(n,)``: each row's plane height at the world origin (default 0).

    Returns
    -------
    translation : ndarray
        ``(n, 3)``: ``X e1 + Y e2`` (plus the height along world z).
    quaternion : ndarray
        ``(n, 4)``: the plane's rotation (columns e1, e2, n), then the yaw about n.
    """
    axes = np.asarray(axes, dtype=np.float64)
    if axes.ndim == 2:
        translation = states[:, L.X_M, None] * axes[0] + states[:, L.Y_M, None] * axes[1]
        q_road = quat_from_matrix(axes.T)
    else:
        translation = (states[:, L.X_M, None] * axes[:, 0]
                       + states[:, L.Y_M, None] * axes[:, 1])
        q_road = np.array([quat_from_matrix(a.T) for a in axes]).reshape(-1, 4)
    if heights_m is not None:
        translation = translation + np.asarray(heights_m)[:, None] * [0.0, 0.0, 1.0]
    return translation, quat_mul(q_road, quat_axis(2, states[:, L.YAW_RAD]))


def reference_planes(states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plane each row's planar states live on (on a terrain, the one fitted under the
    wheels: ``REF_GRADE_PCT``, ``REF_CROSS_SLOPE_PCT``, ``REF_HEIGHT_M``, core.terrain):
    ``(n, 3, 3)`` axes (``road_axes``) and ``(n,)`` heights at the world origin."""
    grades = states[:, L.REF_GRADE_PCT]
    crosses = states[:, L.REF_CROSS_SLOPE_PCT]
    pairs, inverse = np.unique(np.stack([grades, crosses], axis=1), axis=0,
                               return_inverse=True)
    axes = np.array([road_axes(g, c) for g, c in pairs]).reshape(-1, 3, 3)
    return axes[np.ravel(inverse)], states[:, L.REF_HEIGHT_M].copy()


def terrain_plane_under(terrain: Terrain, geometry: CarGeometry, x_m: float, y_m: float,
                        yaw_rad: float) -> tuple[float, float, float]:
    """A reference plane under a car whose CG is above the world point ``(x_m, y_m)``
    heading ``yaw_rad``: the least-squares plane through the surface under its four wheels
    (``core.terrain.fit_plane``, as the step fits its own), as ``(grade_pct,
    cross_slope_pct, height_m)``. For the live viewer, which receives world poses only."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    px, py = geometry.wheel_xy_m[:, 0], geometry.wheel_xy_m[:, 1]
    wx = x_m + px * c - py * s
    wy = y_m + px * s + py * c
    wz = np.array([surface_at(terrain, a, b)[0] for a, b in zip(wx, wy, strict=True)])
    slope_x, slope_y, height = fit_plane(wx, wy, wz)
    return 100.0 * slope_x, 100.0 * slope_y, height


def wheel_hub_offsets(
    states: np.ndarray, outputs: np.ndarray, axes: np.ndarray, heights_m: np.ndarray,
    terrain: Terrain, vp: np.ndarray, geometry: CarGeometry, motion_scale: float = 1.0,
) -> np.ndarray:
    """How far each hub sits above its place on the row's plane, along its normal.

    A wheel that carries load (``O_FZ`` > 0) stands on the surface under its contact
    point: the gap from the plane to the surface ``(h_surface - h_plane) n_z`` (as
    ``core.chassis`` measures it). A wheel without load hangs with its spring at free
    length, the body corner's lift ``heave + y roll - x pitch`` less the spring's static
    deflection (static load / stiffness), unless the ground is higher there (a wheel the
    damper lifts off a bump stays drawn on it: the wheels are massless in the model).
    ``(n, 4)``; zeros on the plane kind.
    """
    n = states.shape[0]
    offsets = np.zeros((n, L.N_WHEELS))
    if terrain.kind == TERRAIN_PLANE:
        return offsets
    g = float(vp[VP_GRAVITY_MPS2])
    psi = states[:, L.YAW_RAD]
    c, s = np.cos(psi), np.sin(psi)
    heave = motion_scale * states[:, L.HEAVE_M]
    roll = motion_scale * states[:, L.ROLL_RAD]
    pitch = motion_scale * states[:, L.PITCH_RAD]
    for i in range(L.N_WHEELS):
        px, py = geometry.wheel_xy_m[i]
        s1 = states[:, L.X_M] + px * c - py * s
        s2 = states[:, L.Y_M] + px * s + py * c
        world = s1[:, None] * axes[:, 0] + s2[:, None] * axes[:, 1]
        plane_z = world[:, 2] + heights_m
        surface = np.array([surface_at(terrain, wx, wy)[0] for wx, wy in world[:, :2]])
        gap = (surface - plane_z) * axes[:, 2, 2]
        k_spring = float(vp[VP_SPRING_FRONT_NPM if i < L.N_FRONT_WHEELS
                            else VP_SPRING_REAR_NPM])
        droop = static_share(vp, i, g) / k_spring
        hanging = np.maximum(gap, heave + py * roll - px * pitch - droop)
        offsets[:, i] = np.where(outputs[:, L.O_FZ0 + i] > 0.0, gap, hanging)
    return offsets


def body_pose(
    states: np.ndarray, cg_height_m: float, motion_scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Pose of ``world/car/body`` in the car frame: the CG, pitched then rolled.

    ``motion_scale`` exaggerates heave, roll and pitch (1 = true to the simulation).
    Positive pitch (nose down) and roll (left side up) are positive rotations about the
    body's y and x axes (``core.chassis``: corner lift ``heave + y roll - x pitch``).
    """
    n = states.shape[0]
    translation = np.zeros((n, 3))
    translation[:, 2] = cg_height_m + motion_scale * states[:, L.HEAVE_M]
    q = quat_mul(quat_axis(1, motion_scale * states[:, L.PITCH_RAD]),
                 quat_axis(0, motion_scale * states[:, L.ROLL_RAD]))
    return translation, q


def integrate_spin(
    time_s: np.ndarray,
    omega_radps: np.ndarray,
    t_prev: float | None = None,
    omega_prev: np.ndarray | None = None,
    angle_prev: np.ndarray | None = None,
) -> np.ndarray:
    """Wheel spin angles: the trapezoidal integral of Omega over time, wrapped to 2 pi.

    Parameters
    ----------
    time_s : ndarray
        ``(n,)`` sample times.
    omega_radps : ndarray
        ``(n, 4)`` spin rates.
    t_prev, omega_prev, angle_prev : optional
        The last sample already integrated (time, ``(4,)`` rates and angles); without
        them the first sample has angle zero.

    Returns
    -------
    ndarray
        ``(n, 4)`` angles (rad) in ``[0, 2 pi)``.
    """
    t = np.asarray(time_s, dtype=np.float64)
    om = np.asarray(omega_radps, dtype=np.float64)
    if t_prev is None or omega_prev is None or angle_prev is None:
        t_all, om_all, start = t, om, np.zeros(om.shape[1])
    else:
        t_all = np.concatenate([[t_prev], t])
        om_all = np.vstack([omega_prev, om])
        start = np.asarray(angle_prev, dtype=np.float64)
    increments = 0.5 * (om_all[1:] + om_all[:-1]) * np.diff(t_all)[:, None]
    angles = start + np.vstack([np.zeros((1, om.shape[1])), np.cumsum(increments, axis=0)])
    if t_prev is not None and omega_prev is not None and angle_prev is not None:
        angles = angles[1:]
    return np.mod(angles, 2.0 * np.pi)


def wheel_poses(
    outputs: np.ndarray, spin_rad: np.ndarray, geometry: CarGeometry,
    hub_offsets_m: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Hub poses in the car frame: ``(n, 4, 3)`` translations and ``(n, 4, 4)`` quaternions.

    The hub sits a rolling radius above its contact point (raised by ``hub_offsets_m``,
    ``(n, 4)``, on a terrain: ``wheel_hub_offsets``); the rotation is the steer
    (road-wheel angle, about z) then the spin about the axle (y; positive rolls forward).
    """
    n = outputs.shape[0]
    hub = np.column_stack([geometry.wheel_xy_m, geometry.wheel_radius_m])
    translation = np.broadcast_to(hub, (n, L.N_WHEELS, 3)).copy()
    if hub_offsets_m is not None:
        translation[:, :, 2] += hub_offsets_m
    steer = outputs[:, L.O_STEER0:L.O_STEER0 + L.N_WHEELS]
    return translation, quat_mul(quat_axis(2, steer), quat_axis(1, spin_rad))


def friction_colors(use: np.ndarray) -> np.ndarray:
    """RGBA ``uint8`` colours for friction use: green at 0, yellow at 0.5, red at 1 and above."""
    u = np.clip(np.nan_to_num(np.asarray(use, dtype=np.float64)), 0.0, 1.0)[..., None]
    rgb = np.where(u < 0.5, _GREEN + (_YELLOW - _GREEN) * (2.0 * u),
                   _YELLOW + (_RED - _YELLOW) * (2.0 * u - 1.0))
    alpha = np.full((*rgb.shape[:-1], 1), 255.0)
    return np.round(np.concatenate([rgb, alpha], axis=-1)).astype(np.uint8)


def force_arrows(
    outputs: np.ndarray, geometry: CarGeometry, scale_m_per_n: float = FORCE_SCALE_M_PER_N
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Force arrows at the contact points, in the car frame.

    Returns
    -------
    origins, vectors : ndarray
        ``(n, 4, 3, 3)``: per wheel the arrows Fx (along the steered wheel), Fy (to its
        left) and Fz (along the road normal), scaled by ``scale_m_per_n``.
    colors : ndarray
        ``(n, 4, 3, 4)`` ``uint8``, from the wheel's friction use (``friction_colors``).
    """
    n = outputs.shape[0]
    steer = outputs[:, L.O_STEER0:L.O_STEER0 + L.N_WHEELS]
    fx = outputs[:, L.O_FX0:L.O_FX0 + L.N_WHEELS] * scale_m_per_n
    fy = outputs[:, L.O_FY0:L.O_FY0 + L.N_WHEELS] * scale_m_per_n
    fz = outputs[:, L.O_FZ0:L.O_FZ0 + L.N_WHEELS] * scale_m_per_n
    c, s = np.cos(steer), np.sin(steer)
    vectors = np.zeros((n, L.N_WHEELS, 3, 3))
    vectors[:, :, 0, 0] = c * fx
    vectors[:, :, 0, 1] = s * fx
    vectors[:, :, 1, 0] = -s * fy
    vectors[:, :, 1, 1] = c * fy
    vectors[:, :, 2, 2] = fz
    origins = np.zeros((n, L.N_WHEELS, 3, 3))
    origins[:, :, :, :2] = geometry.wheel_xy_m[None, :, None, :]
    use = outputs[:, L.O_FRICTION_USE0:L.O_FRICTION_USE0 + L.N_WHEELS]
    colors = np.repeat(friction_colors(use)[:, :, None, :], 3, axis=2)
    return origins, vectors, colors


def decimate(time_s: np.ndarray, fps: float | None) -> np.ndarray:
    """Row indices of at most ``fps`` rows per simulated second.

    The first row at or after each grid time ``t0 + k / fps`` (as ``RateGate`` passes
    them one by one), and always the last row; every row if ``fps`` is None.
    """
    t = np.asarray(time_s, dtype=np.float64)
    n = t.size
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    if fps is None:
        return np.arange(n)
    if not fps > 0.0:
        raise ValueError(f"fps must be positive, got {fps}")
    grid = t[0] + np.arange(int(np.floor((t[-1] - t[0]) * fps + 1e-9)) + 1) / fps
    idx = np.searchsorted(t, grid - 1e-9, side="left")
    idx = np.unique(np.append(idx[idx < n], n - 1))
    return idx


def time_ns(time_s: np.ndarray | float) -> np.ndarray:
    """Seconds to ``timedelta64[ns]``, rounded (``rr.TimeColumn`` would truncate floats)."""
    return np.round(np.asarray(time_s, dtype=np.float64) * 1e9).astype("int64").astype(
        "timedelta64[ns]")


# ------------------------------------------------------------------------ emitting
@dataclass
class _Batch:
    """One entity's data for ``n`` rows: an archetype and its field arrays.

    ``instances`` = 0: one instance per row (arrays ``(n, ...)``); k > 0: k instances per
    row (arrays ``(n, k, ...)``); -1: ragged, ``fields`` hold lists of per-row arrays.
    """

    path: str
    archetype: Any
    fields: dict[str, Any]
    instances: int = 0


def _send(rec: rr.RecordingStream, batch: _Batch, times: np.ndarray) -> None:
    n = times.size
    if n == 0:
        return
    if batch.instances > 0:
        k = batch.instances
        flat = {name: np.asarray(v).reshape(n * k, *np.asarray(v).shape[2:])
                for name, v in batch.fields.items()}
        columns = batch.archetype.columns(**flat).partition([k] * n)
    else:
        columns = batch.archetype.columns(**batch.fields)
    rr.send_columns(batch.path, indexes=[rr.TimeColumn(TIMELINE, duration=times)],
                    columns=columns, recording=rec)


@dataclass(frozen=True)
class Ground:
    """What the car is drawn on: the road plane (``axes``) or a terrain.

    Attributes
    ----------
    axes : ndarray
        ``road_axes`` of the road (the plane kind).
    terrain : Terrain
        The scene's terrain; on any kind but the plane the car is drawn on each row's
        reference plane and the wheels on the ground (``reference_planes``,
        ``wheel_hub_offsets``).
    vp : ndarray
        Vehicle parameters (the springs, for a wheel off the ground).
    """

    axes: np.ndarray
    terrain: Terrain
    vp: np.ndarray

    @property
    def on_terrain(self) -> bool:
        return self.terrain.kind != TERRAIN_PLANE

    def planes(self, states: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The axes (one, or one per row) and heights the rows' planar states live on."""
        if self.on_terrain:
            return reference_planes(states)
        return self.axes, None

    def points(self, states: np.ndarray, lift_m: float) -> np.ndarray:
        """The plane points below the CG of ``states``, lifted ``lift_m`` along n."""
        axes, heights = self.planes(states)
        translation, _ = car_pose(states, axes, heights)
        normal = axes[2] if axes.ndim == 2 else axes[:, 2]
        return translation + lift_m * normal


def _frame_batches(
    states: np.ndarray,
    outputs: np.ndarray,
    spin_rad: np.ndarray,
    geometry: CarGeometry,
    ground: Ground,
    force_scale_m_per_n: float,
    motion_scale: float,
) -> list[_Batch]:
    """The 3D frame (car, body, wheels, force arrows) for ``n`` rows."""
    axes, heights = ground.planes(states)
    car_t, car_q = car_pose(states, axes, heights)
    body_t, body_q = body_pose(states, geometry.cg_height_m, motion_scale)
    offsets = None
    if ground.on_terrain:
        offsets = wheel_hub_offsets(states, outputs, axes, heights, ground.terrain,
                                    ground.vp, geometry, motion_scale)
    wheel_t, wheel_q = wheel_poses(outputs, spin_rad, geometry, offsets)
    origins, vectors, colors = force_arrows(outputs, geometry, force_scale_m_per_n)
    batches = [
        _Batch(CAR, rr.Transform3D, {"translation": car_t, "quaternion": car_q}),
        _Batch(BODY, rr.Transform3D, {"translation": body_t, "quaternion": body_q}),
    ]
    for i in range(L.N_WHEELS):
        batches.append(_Batch(WHEELS[i], rr.Transform3D,
                              {"translation": wheel_t[:, i], "quaternion": wheel_q[:, i]}))
        batches.append(_Batch(FORCES[i], rr.Arrows3D,
                              {"origins": origins[:, i], "vectors": vectors[:, i],
                               "colors": colors[:, i]}, instances=3))
    return batches


def _plot_batches(states: np.ndarray, outputs: np.ndarray, inputs: np.ndarray) -> list[_Batch]:
    """The plotted signals for ``n`` rows, one batch per ``PLOT_GROUPS`` entity."""
    return [_Batch(g.path, rr.Scalars, {"scalars": g.values(states, outputs, inputs)},
                   instances=len(g.indices)) for g in PLOT_GROUPS]


# --------------------------------------------------------------------- static scene
def road_grid(
    axes: np.ndarray, x_range: tuple[float, float], y_range: tuple[float, float],
    spacing_m: float = GRID_SPACING_M,
) -> tuple[list[np.ndarray], np.ndarray]:
    """Grid lines on the road plane: world-frame strips and a major-line flag per strip."""
    x0, x1 = x_range
    y0, y1 = y_range
    strips: list[np.ndarray] = []
    major: list[bool] = []
    lift = GRID_OFFSET_M * axes[2]
    for a in np.arange(np.ceil(x0 / spacing_m), np.floor(x1 / spacing_m) + 1) * spacing_m:
        strips.append(np.array([a * axes[0] + y0 * axes[1], a * axes[0] + y1 * axes[1]]) + lift)
        major.append(round(a / spacing_m) % GRID_MAJOR_EVERY == 0)
    for b in np.arange(np.ceil(y0 / spacing_m), np.floor(y1 / spacing_m) + 1) * spacing_m:
        strips.append(np.array([x0 * axes[0] + b * axes[1], x1 * axes[0] + b * axes[1]]) + lift)
        major.append(round(b / spacing_m) % GRID_MAJOR_EVERY == 0)
    return strips, np.array(major, dtype=bool)


def log_road(
    rec: rr.RecordingStream, axes: np.ndarray, x_range: tuple[float, float],
    y_range: tuple[float, float],
) -> None:
    """Log (static) the road surface and grid over ``x_range`` x ``y_range`` (along e1, e2)."""
    x0, x1 = x_range
    y0, y1 = y_range
    lift = SURFACE_OFFSET_M * axes[2]
    corners = np.array([x0 * axes[0] + y0 * axes[1], x1 * axes[0] + y0 * axes[1],
                        x1 * axes[0] + y1 * axes[1], x0 * axes[0] + y1 * axes[1]]) + lift
    rec.log(ROAD_SURFACE, rr.Mesh3D(vertex_positions=corners,
                                    triangle_indices=[[0, 1, 2], [0, 2, 3]],
                                    vertex_normals=np.repeat(axes[2][None], 4, axis=0),
                                    albedo_factor=[118, 122, 128, 255]), static=True)
    strips, major = road_grid(axes, x_range, y_range)
    colors = np.where(major[:, None], [[235, 235, 235, 255]], [[175, 178, 182, 255]])
    radii = np.where(major, -0.9, -0.45)  # negative: UI points, as thin far as near
    rec.log(ROAD_GRID, rr.LineStrips3D(strips, colors=colors.astype(np.uint8), radii=radii),
            static=True)


def log_static_scene(
    rec: rr.RecordingStream,
    vp: np.ndarray,
    geometry: CarGeometry,
    axes: np.ndarray,
    x_range: tuple[float, float],
    y_range: tuple[float, float],
    force_scale_m_per_n: float = FORCE_SCALE_M_PER_N,
    road_text: str = "",
    terrain: Terrain | None = None,
    terrain_spec: dict[str, Any] | None = None,
) -> None:
    """Log what never changes: frames, road or terrain, the car's body and wheel geometry,
    a note.

    Parameters
    ----------
    rec : rerun.RecordingStream
        Where to log.
    vp : ndarray
        Vehicle parameters (body proportions).
    geometry : CarGeometry
        Wheel positions and radii.
    axes : ndarray
        ``road_axes(grade, cross)``.
    x_range, y_range : tuple of float
        The road rectangle along e1 and e2 (m).
    force_scale_m_per_n : float
        Stated in the note.
    road_text : str
        The road's description for the note.
    terrain, terrain_spec : optional
        ``Scene.terrain`` and ``Scene.terrain_spec``: on any kind but the plane, the
        terrain is drawn (``rerun_terrain.log_terrain``) instead of the road plane.
    """
    rec.log(WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log(ORIGIN_AXES, rr.TransformAxes3D(5.0), static=True)
    if terrain is not None and terrain.kind != TERRAIN_PLANE:
        road_text = log_terrain(rec, terrain, terrain_spec)
    else:
        rec.log(ROAD_AXES, rr.Transform3D(mat3x3=axes.T), rr.TransformAxes3D(3.0),
                static=True)
        log_road(rec, axes, x_range, y_range)
    rec.log(TRAIL, rr.LineStrips3D.from_fields(colors=[[20, 60, 160, 255]], radii=[0.07]),
            static=True)
    centers, half_sizes = geometry.body_boxes(vp)
    rec.log(BODY_SHELL, rr.Boxes3D(centers=centers, half_sizes=half_sizes,
                                   colors=[[200, 205, 215, 255], [150, 170, 200, 255]],
                                   fill_mode="majorwireframe", radii=0.02), static=True)
    rec.log(DRIVER_EYE, rr.Transform3D(translation=driver_eye_offset(geometry, vp)),
            static=True)
    for i in range(L.N_WHEELS):
        radius = float(geometry.wheel_radius_m[i])
        rec.log(WHEEL_TIRES[i], rr.Cylinders3D(
            lengths=[TIRE_WIDTH_M], radii=[radius],
            rotation_axis_angles=[rr.RotationAxisAngle(axis=[1.0, 0.0, 0.0], degrees=90.0)],
            colors=[[35, 35, 38, 255]], fill_mode="solid"), static=True)
        side = 0.5 * TIRE_WIDTH_M + 0.01
        strips = []
        for k in range(3):
            ang = k * np.pi / 3.0
            d = 0.95 * radius * np.array([np.sin(ang), 0.0, np.cos(ang)])
            for y in (side, -side):
                strips.append(np.array([-d + [0.0, y, 0.0], d + [0.0, y, 0.0]]))
        colors = [[230, 40, 40, 255]] * 2 + [[220, 220, 220, 255]] * 4
        rec.log(WHEEL_SPOKES[i], rr.LineStrips3D(strips, colors=colors, radii=0.015),
                static=True)
        rec.log(FORCES[i], rr.Arrows3D.from_fields(radii=[ARROW_RADIUS_M]), static=True)
    if terrain is not None and terrain.kind != TERRAIN_PLANE:
        ground_line = (f"- Terrain: {road_text}; the car on the plane fitted under its "
                       "wheels, each wheel on the ground under it.\n")
    else:
        ground_line = (f"- Road: {road_text or 'plane through the origin'}; grid "
                       f"{GRID_SPACING_M:g} m, bold every {GRID_SPACING_M * GRID_MAJOR_EVERY:g}"
                       " m; axes: world (5 m) and road e1, e2, n (3 m).\n")
    note = (
        "### simserver scene\n\n"
        + ground_line +
        f"- Force arrows at each contact point: Fx along the wheel, Fy to its left, Fz "
        f"along the road normal; 1 m per {1.0 / force_scale_m_per_n / 1000.0:g} kN.\n"
        "- Arrow colour: friction use |F_shear| / available, green 0 -> yellow 0.5 -> "
        "red 1 and above.\n"
        "- Wheels: steered by the road-wheel angle, spun by the integral of Omega (red "
        "spoke).\n"
        "- Timeline `sim_time`: simulated time.\n"
    )
    rec.log(SCENE_INFO, rr.TextDocument(note, media_type=rr.MediaType.MARKDOWN), static=True)
    for g in PLOT_GROUPS:
        rec.log(g.path, rr.SeriesLines(names=g.labels, colors=g.colors,
                                       widths=[1.5] * len(g.indices)), static=True)


def log_diagnostics_styles(rec: rr.RecordingStream) -> None:
    """Log (static) the names and colours of the diagnostics series."""
    for path, (label, color) in DIAGNOSTIC_SERIES.items():
        rec.log(path, rr.SeriesLines(names=label, colors=[color], widths=1.5), static=True)


def log_diagnostics(
    rec: rr.RecordingStream,
    time_s: float,
    tick_jitter_us: float,
    dropped_frames: int | None = None,
) -> None:
    """Log one diagnostics sample of the live server at ``time_s``.

    Parameters
    ----------
    rec : rerun.RecordingStream
        Where to log.
    time_s : float
        Simulated time of the sample.
    tick_jitter_us : float
        The tick's lateness (or period error) in microseconds.
    dropped_frames : int, optional
        Viewer frames dropped so far by the bounded queue.
    """
    rec.set_time(TIMELINE, duration=time_ns(time_s)[()])
    rec.log(TICK_JITTER, rr.Scalars(float(tick_jitter_us)))
    if dropped_frames is not None:
        rec.log(DROPPED_FRAMES, rr.Scalars(float(dropped_frames)))


# ------------------------------------------------------------------------- blueprint
def scene_blueprint(
    plot_window_s: float | None = None,
    eye_position: Sequence[float] | None = None,
    look_target: Sequence[float] | None = None,
    play_state: str | None = None,
) -> rrb.Blueprint:
    """The layout: the 3D view tracking the car, beside tabs of grouped plots.

    Parameters
    ----------
    plot_window_s : float, optional
        Plots show the last ``plot_window_s`` seconds before the time cursor (live use);
        None shows the whole run (recordings).
    eye_position, look_target : sequence of float, optional
        Initial camera position and target in world coordinates; the camera then follows
        the car (``EyeControls3D.tracking_entity`` = ``BODY_SHELL``).
    play_state : str, optional
        ``"following"`` keeps the time cursor on the newest data (live use and
        screenshots); ``"paused"``/``"playing"``; None leaves the viewer's default.
    """
    time_ranges = None
    if plot_window_s is not None:
        time_ranges = rrb.VisibleTimeRange(
            TIMELINE,
            start=rrb.TimeRangeBoundary.cursor_relative(seconds=-float(plot_window_s)),
            end=rrb.TimeRangeBoundary.cursor_relative(),
        )

    def plot(name: str, origin: str) -> rrb.View:
        return rrb.TimeSeriesView(name=name, origin=origin, time_ranges=time_ranges)

    # The viewer tracks an entity by its visual bounds: ``world/car`` holds only a
    # transform, so track the body's boxes (rerun 0.41 ignores an entity with nothing
    # drawn).
    eye = rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, tracking_entity=BODY_SHELL,
                            position=eye_position, look_target=look_target)
    scene = rrb.Spatial3DView(name="car on the road", origin=WORLD, contents=f"{WORLD}/**",
                              eye_controls=eye, line_grid=rrb.LineGrid3D(visible=False),
                              background=[205, 215, 228])
    # The driver's eye: a first-person eye at the origin of ``DRIVER_EYE`` looking along
    # its x (forward), z up; the view's frame is that entity's, so the eye rides with the
    # body (heave, pitch, roll) and everything else (road, other cars) is placed relative
    # to it. The own body's boxes are left out: they would fill the view from inside.
    driver = rrb.Spatial3DView(
        name="driver's eye", origin=DRIVER_EYE,
        contents=[f"+ {WORLD}/**", f"- {BODY_SHELL}", f"- {TRAIL}", f"- {CAR}/forces/**"],
        eye_controls=rrb.EyeControls3D(kind=rrb.Eye3DKind.FirstPerson, position=[0.0, 0.0, 0.0],
                                       look_target=[10.0, 0.0, 0.0], eye_up=[0.0, 0.0, 1.0]),
        line_grid=rrb.LineGrid3D(visible=False), background=[170, 200, 235])
    speed_yaw = rrb.Vertical(plot("speed u, v", PLOT_SPEED),
                             plot("yaw rate", PLOT_YAW_RATE), name="speed & yaw")
    slips = rrb.Vertical(plot("k' (longitudinal slip)", PLOT_KAPPA),
                         plot("tan a' (lateral slip)", PLOT_TAN_ALPHA),
                         plot("friction use", PLOT_FRICTION_USE), name="slips")
    forces = rrb.Grid(*(plot(f"forces {w}", f"{PLOT_FORCES}/{w}") for w in L.WHEEL_NAMES),
                      grid_columns=2, name="forces per wheel")
    inputs = rrb.Vertical(plot("driver inputs", PLOT_DRIVER), plot("gear", PLOT_GEAR),
                          row_shares=[3, 1], name="inputs")
    damping = rrb.Vertical(plot("damping flag (Appendix A)", PLOT_DAMPING_ACTIVE),
                           plot("damping share of Fx", PLOT_DAMPING_FX),
                           plot("damping share of Fy", PLOT_DAMPING_FY), name="damping")
    server = rrb.Vertical(plot("tick jitter", TICK_JITTER),
                          plot("viewer frames dropped", DROPPED_FRAMES), name="server")
    about = rrb.TextDocumentView(origin=SCENE_INFO, name="about")
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(rrb.Tabs(scene, driver, active_tab=0), speed_yaw,
                         row_shares=[3, 2]),
            rrb.Tabs(slips, forces, inputs, damping, server, about, active_tab=0),
            column_shares=[3, 2],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="expanded", timeline=TIMELINE, play_state=play_state),
    )


# ------------------------------------------------------------------------ entry points
def _road_text(grade_pct: float, cross_slope_pct: float) -> str:
    return f"grade {grade_pct:+g} %, cross-slope {cross_slope_pct:+g} %"


def _road_range(positions_m: np.ndarray) -> tuple[float, float]:
    """The run's extent along one road axis plus ``ROAD_MARGIN_M``, on the grid."""
    finite = positions_m[np.isfinite(positions_m)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 0.0)
    return (GRID_SPACING_M * np.floor((lo - ROAD_MARGIN_M) / GRID_SPACING_M),
            GRID_SPACING_M * np.ceil((hi + ROAD_MARGIN_M) / GRID_SPACING_M))


def _eye_for(translation: np.ndarray, axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A chase position behind, to the left of and above a car at ``translation``."""
    eye = translation - 10.0 * axes[0] + 6.5 * axes[1] + 4.5 * axes[2]
    return eye, translation + 0.5 * axes[2]


def log_result(
    rec: rr.RecordingStream,
    result: ScenarioResult,
    fps: float = DEFAULT_FPS,
    plot_fps: float | None = None,
    trail_hz: float = TRAIL_HZ,
    force_scale_m_per_n: float = FORCE_SCALE_M_PER_N,
    motion_scale: float = 1.0,
    send_blueprint: bool = True,
) -> None:
    """Log a whole run: static scene, frames decimated to ``fps``, plots, blueprint.

    Parameters
    ----------
    rec : rerun.RecordingStream
        Where to log (``adapters.rerun_sink.open_recording``).
    result : ScenarioResult
        The run (``simserver.sim.scenario.run_scenario``).
    fps : float
        3D frames per simulated second.
    plot_fps : float, optional
        Plot samples per simulated second; default ``fps``.
    trail_hz : float
        Trail points per simulated second (fewer for runs longer than
        ``TRAIL_MAX_POINTS / trail_hz``).
    force_scale_m_per_n : float
        Arrow length per newton.
    motion_scale : float
        Exaggeration of heave, roll and pitch (1 = true).
    send_blueprint : bool
        Send ``scene_blueprint()`` with the recording (made active).
    """
    rec.set_log_time_enabled(False)
    sc = result.scenario
    vp, tp = sc.scene.vehicle.vp, sc.scene.vehicle.tp
    grade, cross = sc.scene.road["grade_pct"], sc.scene.road["cross_slope_pct"]
    axes = road_axes(grade, cross)
    ground = Ground(axes, sc.scene.terrain, vp)
    geometry = CarGeometry.from_params(vp, tp)
    states, outputs, inputs, t = result.states, result.outputs, result.inputs, result.time_s
    if t.size == 0:
        return

    x_range, y_range = (_road_range(states[:, col]) for col in (L.X_M, L.Y_M))
    log_static_scene(rec, vp, geometry, axes, x_range, y_range, force_scale_m_per_n,
                     _road_text(grade, cross), sc.scene.terrain, sc.scene.terrain_spec)
    if send_blueprint:
        start_axes, _ = ground.planes(states[:1])
        start_axes = start_axes if start_axes.ndim == 2 else start_axes[0]
        eye, target = _eye_for(ground.points(states[:1], 0.0)[0], start_axes)
        rec.send_blueprint(scene_blueprint(eye_position=eye, look_target=target))

    spin = integrate_spin(t, states[:, L.OMEGA0:L.OMEGA0 + L.N_WHEELS])
    frames = decimate(t, fps)
    for batch in _frame_batches(states[frames], outputs[frames], spin[frames], geometry,
                                ground, force_scale_m_per_n, motion_scale):
        _send(rec, batch, time_ns(t[frames]))
    rows = decimate(t, plot_fps if plot_fps is not None else fps)
    for batch in _plot_batches(states[rows], outputs[rows], inputs[rows]):
        _send(rec, batch, time_ns(t[rows]))

    # A long run gets a coarser trail, so that its strips stay within TRAIL_MAX_POINTS rows
    # of at most TRAIL_MAX_POINTS points.
    trail_rows = decimate(t, min(trail_hz, TRAIL_MAX_POINTS / max(t[-1] - t[0], 1e-9)))
    points = ground.points(states[trail_rows], TRAIL_OFFSET_M)
    strips = [points[max(0, k + 1 - TRAIL_MAX_POINTS):k + 1].astype(np.float32)
              for k in range(trail_rows.size)]
    _send(rec, _Batch(TRAIL, rr.LineStrips3D, {"strips": strips}, instances=-1),
          time_ns(t[trail_rows]))


class RateGate:
    """Lets through at most ``rate_hz`` samples per simulated second, one by one.

    The grid is ``t0 + k / rate_hz`` (``t0``: the first sample); a sample passes if it is
    the first at or after a grid point, as ``decimate`` picks rows of a whole run. A rate
    of None passes everything.
    """

    def __init__(self, rate_hz: float | None) -> None:
        if rate_hz is not None and not rate_hz > 0.0:
            raise ValueError(f"rate must be positive or None, got {rate_hz}")
        self.rate_hz = rate_hz
        self.reset()

    def reset(self) -> None:
        """Start a new grid at the next sample."""
        self._t0: float | None = None
        self._next_s = -np.inf

    def due(self, time_s: float) -> bool:
        """True if ``time_s`` passes (and then advance to the next grid point)."""
        if self.rate_hz is None:
            return True
        if self._t0 is None:
            self._t0 = time_s
        if time_s < self._next_s - 1e-9:
            return False
        k = np.floor((time_s - self._t0) * self.rate_hz + 1e-9) + 1.0
        self._next_s = self._t0 + k / self.rate_hz
        return True


@dataclass
class _SpinState:
    time_s: float | None = None
    omega: np.ndarray | None = None
    angle: np.ndarray = field(default_factory=lambda: np.zeros(L.N_WHEELS))


class SceneLogger:
    """Logs the scene as it happens, for the live viewer process.

    ``log_frame`` is called with every state row received (any rate); it integrates the
    wheel spin on every call, keeps at most ``fps`` frames per simulated second and
    sends them in batches of ``flush_every`` frames through the same column path as
    ``log_result`` (``rr.send_columns``): one batch of 26 entities costs about as much as
    one frame logged entity by entity, so the view lags by at most ``flush_every / fps``
    seconds (0.1 s by default) for a fraction of the CPU.

    Parameters
    ----------
    rec : rerun.RecordingStream
        Where to log; ``log_time`` is switched off on it.
    vp : ndarray
        Vehicle parameters (``core.params``).
    tp : ndarray
        ``(4, N_TIRE_PARAM)`` tire parameters.
    grade_pct, cross_slope_pct : float
        The road plane.
    terrain : Terrain, optional
        The scene's terrain (default the plane): on any other kind it is drawn once
        (``rerun_terrain``) and the rows' planar states are on their own reference
        planes (their ``REF_*`` slots, as ``viewer.rows_from_state`` fills them).
    terrain_spec : dict, optional
        ``Scene.terrain_spec`` (an OpenDRIVE road's lanes are read from its file).
    fps : float, optional
        At most this many frames per simulated second; None keeps every call.
    flush_every : int
        Frames per batch (1: send each frame at once).
    trail_hz : float
        Trail points per simulated second (the newest ``TRAIL_MAX_POINTS`` are kept).
    force_scale_m_per_n, motion_scale : float
        As for ``log_result``.
    plot_window_s : float, optional
        Sent blueprint: plots show this many seconds before the cursor.
    send_blueprint : bool
        Send ``scene_blueprint`` (following the newest data) with the first batch.
    """

    def __init__(
        self,
        rec: rr.RecordingStream,
        vp: np.ndarray,
        tp: np.ndarray,
        grade_pct: float = 0.0,
        cross_slope_pct: float = 0.0,
        terrain: Terrain | None = None,
        terrain_spec: dict[str, Any] | None = None,
        fps: float | None = DEFAULT_FPS,
        flush_every: int = 5,
        trail_hz: float = TRAIL_HZ,
        force_scale_m_per_n: float = FORCE_SCALE_M_PER_N,
        motion_scale: float = 1.0,
        plot_window_s: float | None = 30.0,
        send_blueprint: bool = True,
    ) -> None:
        if flush_every < 1:
            raise ValueError(f"flush_every must be at least 1, got {flush_every}")
        self.rec = rec
        self.vp = np.asarray(vp, dtype=np.float64)
        self.geometry = CarGeometry.from_params(self.vp, tp)
        self.grade_pct = float(grade_pct)
        self.cross_slope_pct = float(cross_slope_pct)
        self.axes = road_axes(self.grade_pct, self.cross_slope_pct)
        self.terrain = plane_terrain() if terrain is None else terrain
        self.terrain_spec = terrain_spec
        self.ground = Ground(self.axes, self.terrain, self.vp)
        self.flush_every = int(flush_every)
        self.force_scale_m_per_n = force_scale_m_per_n
        self.motion_scale = motion_scale
        self.plot_window_s = plot_window_s
        self.send_blueprint = send_blueprint
        self.frames_logged = 0
        self._spin = _SpinState()
        self._frame_gate = RateGate(fps)
        self._trail_gate = RateGate(trail_hz)
        self._trail: deque[np.ndarray] = deque(maxlen=TRAIL_MAX_POINTS)
        self._road_center: np.ndarray | None = None
        self._rows: list[tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self._trail_rows: list[tuple[float, np.ndarray]] = []
        rec.set_log_time_enabled(False)
        log_diagnostics_styles(rec)

    def reset(self) -> None:
        """Send what is pending, then forget the trail, the spin and the frame clock (a new
        run; called by ``log_frame`` when time jumps backwards)."""
        self.flush()
        self._spin = _SpinState()
        self._frame_gate.reset()
        self._trail_gate.reset()
        self._trail.clear()

    def _ensure_road(self, state: np.ndarray) -> None:
        """Log the static scene once, and re-centre the road when the car nears its edge."""
        half = LIVE_ROAD_HALF_SIZE_M
        x_m, y_m = float(state[L.X_M]), float(state[L.Y_M])
        pos = np.array([x_m, y_m])
        if not np.all(np.isfinite(pos)):
            return
        if self._road_center is not None and (
                self.ground.on_terrain  # a terrain is drawn whole, once
                or np.all(np.abs(pos - self._road_center) < half - ROAD_MARGIN_M / 3.0)):
            return
        center = GRID_SPACING_M * np.round(pos / GRID_SPACING_M)
        x_range = (center[0] - half, center[0] + half)
        y_range = (center[1] - half, center[1] + half)
        if self._road_center is None:
            log_static_scene(self.rec, self.vp, self.geometry, self.axes, x_range, y_range,
                             self.force_scale_m_per_n,
                             _road_text(self.grade_pct, self.cross_slope_pct), self.terrain,
                             self.terrain_spec)
            if self.send_blueprint:
                if self.ground.on_terrain:
                    start = state[None]
                    eye, target = _eye_for(self.ground.points(start, 0.0)[0],
                                           self.ground.planes(start)[0][0])
                else:
                    eye, target = _eye_for(x_m * self.axes[0] + y_m * self.axes[1],
                                           self.axes)
                self.rec.send_blueprint(scene_blueprint(self.plot_window_s, eye, target,
                                                        play_state="following"))
        else:
            log_road(self.rec, self.axes, x_range, y_range)
        self._road_center = center

    def log_frame(
        self,
        time_s: float,
        state_row: np.ndarray,
        output_row: np.ndarray,
        input_row: np.ndarray,
    ) -> bool:
        """Integrate the wheel spin to ``time_s`` and keep a frame if one is due.

        Parameters
        ----------
        time_s : float
            Simulated time of the row.
        state_row, output_row, input_row : ndarray
            ``(N_STATE,)``, ``(N_OUT,)``, ``(N_INPUT,)`` (``core.layout``); copied.

        Returns
        -------
        bool
            True if the row became a frame (sent with the next batch).
        """
        t = float(time_s)
        sp = self._spin
        if sp.time_s is not None and t < sp.time_s:
            self.reset()
            sp = self._spin
        state = np.array(state_row, dtype=np.float64)
        omega = state[None, L.OMEGA0:L.OMEGA0 + L.N_WHEELS]
        spin = integrate_spin(np.array([t]), omega, sp.time_s, sp.omega, sp.angle)[0]
        sp.time_s, sp.omega, sp.angle = t, omega[0], spin
        if not self._frame_gate.due(t):
            return False
        self._rows.append((t, state, np.array(output_row, dtype=np.float64),
                           np.array(input_row, dtype=np.float64), spin))
        if self._trail_gate.due(t):
            self._trail.append(self.ground.points(state[None], TRAIL_OFFSET_M)[0])
            self._trail_rows.append((t, np.array(self._trail, dtype=np.float32)))
        if len(self._rows) >= self.flush_every:
            self.flush()
        return True

    def flush(self) -> None:
        """Send the pending frames (``log_frame`` calls it every ``flush_every`` frames)."""
        if not self._rows:
            return
        times = np.array([r[0] for r in self._rows])
        states = np.stack([r[1] for r in self._rows])
        outputs = np.stack([r[2] for r in self._rows])
        inputs = np.stack([r[3] for r in self._rows])
        spin = np.stack([r[4] for r in self._rows])
        self._rows.clear()
        self._ensure_road(states[-1])
        stamps = time_ns(times)
        for batch in _frame_batches(states, outputs, spin, self.geometry, self.ground,
                                    self.force_scale_m_per_n, self.motion_scale):
            _send(self.rec, batch, stamps)
        for batch in _plot_batches(states, outputs, inputs):
            _send(self.rec, batch, stamps)
        if self._trail_rows:
            _send(self.rec, _Batch(TRAIL, rr.LineStrips3D,
                                   {"strips": [r[1] for r in self._trail_rows]}, instances=-1),
                  time_ns(np.array([r[0] for r in self._trail_rows])))
            self._trail_rows.clear()
        self.frames_logged += times.size

    def log_diagnostics(
        self, time_s: float, tick_jitter_us: float, dropped_frames: int | None = None
    ) -> None:
        """Log one diagnostics sample at once (``log_diagnostics``)."""
        log_diagnostics(self.rec, time_s, tick_jitter_us, dropped_frames)
