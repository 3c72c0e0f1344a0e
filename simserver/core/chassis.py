"""Chassis right-hand side: sprung body on four suspended corners, four spinning wheels.

Degrees of freedom (``core.layout``): planar motion on the road plane (X, Y, yaw; body
velocities u, v, r), heave, roll and pitch of the sprung mass on a spring and damper per
corner with anti-roll bars, four wheel spins, and the eight lagged slip states.

Modelling choices (the paper's vehicle, its ref. 9, has the same degrees of freedom):

- Roll centres at ground level: all load transfer goes through the springs, so the
  normal loads respond dynamically (with the suspension's own frequency and damping) to
  the tire shear forces. The overturning moments are taken about the ground point below
  the CG, where the tire shear forces have no arm: ``M_roll = h * sum(Fy)``,
  ``M_pitch = -h * sum(Fx)``; gravity adds its destabilising ``m_s g_n h phi``.
- Normal load of a corner = its static share (from the CG position and the component of
  gravity normal to the road) + the suspension's dynamic force; a wheel whose load would
  go negative lifts off (``Fz = 0``) and then carries nothing to the body either.
- Tire forces act in the wheel's heading frame and are rotated by the road-wheel angle.
  The hub velocity ignores the small contributions of roll and pitch rates.
- Gravity is resolved from the road plane into body axes with the heading (``core.road.
  set_road``), so grade and cross-slope work at any heading.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from simserver.core.damping import (
    DAMPING_OFF,
    DAMPING_PAPER,
    DAMPING_PATCH,
    damping_coefficients,
    low_speed_fade,
)
from simserver.core.layout import (
    DAMPING_ACTIVE0,
    HEAVE_M,
    HEAVE_RATE_MPS,
    IN_CONTACT0,
    KAPPA0,
    N_AXLES,
    N_FRONT_WHEELS,
    N_WHEELS,
    O_AX_MPS2,
    O_AY_MPS2,
    O_CAMBER0,
    O_DAMPING_FX0,
    O_DAMPING_FY0,
    O_DRIVE_TORQUE0,
    O_FRICTION_USE0,
    O_FX0,
    O_FX_BODY_SUM_N,
    O_FY0,
    O_FY_BODY_SUM_N,
    O_FZ0,
    O_GRAVITY_X_MPS2,
    O_GRAVITY_Y_MPS2,
    O_HUB_U0,
    O_HUB_V0,
    O_KAPPA0,
    O_MZ0,
    O_STEER0,
    O_TAN_ALPHA0,
    O_YAW_ACC_RADPS2,
    OMEGA0,
    PITCH_RAD,
    PITCH_RATE_RADPS,
    REF_CROSS_SLOPE_PCT,
    REF_GRADE_PCT,
    REF_HEIGHT_M,
    ROLL_RAD,
    ROLL_RATE_RADPS,
    STEP_JIT_OPTIONS,
    TAN_ALPHA0,
    U_MPS,
    V_MPS,
    WHEELS_PER_AXLE,
    X_M,
    Y_M,
    YAW_RAD,
    YAW_RATE_RADPS,
)
from simserver.core.model import (
    B_AX_MPS2,
    B_AY_MPS2,
    B_CONTACT_ACTIVE,
    B_CONTACT_E1_N,
    B_CONTACT_E2_N,
    B_CONTACT_MZ_NM,
    B_FX_SUM_N,
    B_FY_SUM_N,
    B_GRAVITY_X_MPS2,
    B_GRAVITY_Y_MPS2,
    B_YAW_ACC_RADPS2,
    D_DRAG_NS2PM2,
    D_SPIN_DAMPING_CAP0,
    D_WHEEL_X0,
    D_WHEEL_Y0,
    G_AXES,
    G_AXES_CROSS_SLOPE_PCT,
    G_AXES_GRADE_PCT,
    G_COS_YAW0,
    G_GRAVITY_E1_MPS2,
    G_GRAVITY_E2_MPS2,
    G_GRAVITY_N_MPS2,
    G_MU0,
    G_SIN_YAW0,
    G_STATIC_FRONT_N,
    G_STATIC_REAR_N,
    G_X0_M,
    G_Y0_M,
    G_YAW0_RAD,
    W_CONTACT_S1_M,
    W_CONTACT_S2_M,
    W_DAMPING_FX,
    W_DAMPING_FY,
    W_FX,
    W_FX_PEAK,
    W_FX_PLANE,
    W_FY,
    W_FY_PEAK,
    W_FY_PLANE,
    W_FZ,
    W_FZ_DYN,
    W_GAP0_M,
    W_GAP_D1,
    W_GAP_D2,
    W_GAP_M,
    W_GAP_RATE_MPS,
    W_HUB_U,
    W_HUB_V,
    W_KAPPA,
    W_KAPPA_SLIDE,
    W_MY,
    W_MZ,
    W_N0,
    W_N1,
    W_TAN_ALPHA,
    W_TAN_ALPHA_SLIDE,
    W_TILT,
    W_TX0,
    W_TX1,
    W_TY0,
    W_TY1,
    WI_BRAKE_NM,
    WI_CAMBER_RAD,
    WI_COS_STEER,
    WI_DRIVE_NM,
    WI_HELD,
    WI_SIN_STEER,
    WI_STEER_RAD,
    Model,
    Workspace,
)
from simserver.core.params import (
    ROAD_CROSS_SLOPE_PCT,
    ROAD_FRICTION_SCALE,
    ROAD_GRADE_PCT,
    ROAD_GRAVITY_E1_MPS2,
    ROAD_GRAVITY_E2_MPS2,
    ROAD_GRAVITY_N_MPS2,
    VP_ANTIROLL_FRONT_NPM,
    VP_ANTIROLL_REAR_NPM,
    VP_BUMPER_HEIGHT_M,
    VP_CAMBER_HEAVE_GAIN_FRONT_RADPM,
    VP_CAMBER_HEAVE_GAIN_REAR_RADPM,
    VP_CAMBER_ROLL_GAIN_FRONT,
    VP_CAMBER_ROLL_GAIN_REAR,
    VP_CAMBER_STATIC_FRONT_RAD,
    VP_CAMBER_STATIC_REAR_RAD,
    VP_CG_HEIGHT_M,
    VP_CG_TO_FRONT_AXLE_M,
    VP_CG_TO_REAR_AXLE_M,
    VP_DAMPER_FRONT_NSPM,
    VP_DAMPER_REAR_NSPM,
    VP_DAMPING_FADE_SPEED_MPS,
    VP_DAMPING_MODEL,
    VP_DAMPING_RATIO,
    VP_GRAVITY_MPS2,
    VP_KINEMATIC_U_MIN_MPS,
    VP_MASS_KG,
    VP_PITCH_INERTIA_KGM2,
    VP_ROLL_INERTIA_KGM2,
    VP_SLIP_MODEL,
    VP_SPRING_FRONT_NPM,
    VP_SPRING_REAR_NPM,
    VP_SPRUNG_MASS_KG,
    VP_TRACK_FRONT_M,
    VP_TRACK_REAR_M,
    VP_WHEEL_INERTIA_FRONT_KGM2,
    VP_WHEEL_INERTIA_REAR_KGM2,
    VP_YAW_INERTIA_KGM2,
)
from simserver.core.road import road_axes, road_frame
from simserver.core.slip import (
    SLIP_KINEMATIC,
    SLIP_LAGGED_PAPER,
    SLIP_LAGGED_PASSIVE,
    kinematic_slip,
    lagged_slip_rates,
)
from simserver.core.terrain import (
    TERRAIN_PLANE,
    fit_plane,
    rebase_reference_plane,
    surface_at,
    surface_under_wheel,
    terrain_road,
)
from simserver.core.tire import (
    every_tire_is,
    tire_evaluate,
    tire_evaluate_mf61_wheels,
    tire_evaluate_simple_wheels,
)
from simserver.core.tire_layout import (
    OUT_C_ALPHA,
    OUT_C_KAPPA,
    OUT_FX,
    OUT_FX_PEAK,
    OUT_FY,
    OUT_FY_PEAK,
    OUT_KAPPA_SLIDE,
    OUT_MY,
    OUT_MZ,
    OUT_TAN_ALPHA_SLIDE,
    TIRE_MODEL_MF61,
    TIRE_MODEL_SIMPLE,
    TP_RADIUS_M,
    TP_RELAX_LAT_M,
    TP_RELAX_LONG_M,
)

LEFT, RIGHT = 0, 1  # side of a wheel on its axle


@nb.njit(cache=True)
def is_front(i: int) -> bool:
    """Wheel ``i`` is on the front axle."""
    return i < N_FRONT_WHEELS


@nb.njit(cache=True)
def wheel_position(vp: np.ndarray, i: int) -> tuple[float, float]:
    """Contact-point position (x, y) of wheel ``i`` relative to the CG in body axes (m)."""
    if is_front(i):
        return vp[VP_CG_TO_FRONT_AXLE_M], (0.5 if i == 0 else -0.5) * vp[VP_TRACK_FRONT_M]
    return -vp[VP_CG_TO_REAR_AXLE_M], (0.5 if i == 2 else -0.5) * vp[VP_TRACK_REAR_M]


@nb.njit(cache=True, inline="always")
def wheel_camber(vp: np.ndarray, x: np.ndarray, i: int) -> float:
    """Inclination angle of wheel ``i`` to the road (rad), as the tire model takes it.

    ISO 8855 (``docs/model.md`` section 2): positive when the top of the wheel leans
    toward -y (the car's right). From the suspension (the ``camber_*`` keys, per axle):
    the static camber plus the heave gain times the corner's compression (the same
    compression as in ``corner_loads``), both in the vehicle's sense (negative: the top
    leans inboard, i.e. toward -y on the left and +y on the right), and the roll gain
    times the body roll (positive roll lifts the left side: the body, and a wheel with
    gain 1, leans toward -y).
    """
    px, py = wheel_position(vp, i)
    if is_front(i):
        static = vp[VP_CAMBER_STATIC_FRONT_RAD]
        roll_gain = vp[VP_CAMBER_ROLL_GAIN_FRONT]
        heave_gain = vp[VP_CAMBER_HEAVE_GAIN_FRONT_RADPM]
    else:
        static = vp[VP_CAMBER_STATIC_REAR_RAD]
        roll_gain = vp[VP_CAMBER_ROLL_GAIN_REAR]
        heave_gain = vp[VP_CAMBER_HEAVE_GAIN_REAR_RADPM]
    compression = -(x[HEAVE_M] + py * x[ROLL_RAD] - px * x[PITCH_RAD])
    camber = static + heave_gain * compression  # vehicle sense
    # at camber c < 0 the top leans by -c toward inboard (-y on the left, +y on the right),
    # which is an inclination of inboard * c in the ISO sense
    inboard = -1.0 if py > 0.0 else 1.0
    return roll_gain * x[ROLL_RAD] + inboard * camber


@nb.njit(cache=True)
def wheel_inertia(vp: np.ndarray, i: int) -> float:
    """Spin inertia of wheel ``i`` (kg m^2)."""
    return vp[VP_WHEEL_INERTIA_FRONT_KGM2] if is_front(i) else vp[VP_WHEEL_INERTIA_REAR_KGM2]


@nb.njit(cache=True)
def static_wheel_load(vp: np.ndarray, road: np.ndarray, i: int) -> float:
    """Static normal load of wheel ``i`` on the road plane ``road`` (a terrain's road,
    ``core.params.ROAD_*``) (N)."""
    return static_share(vp, i, road[ROAD_GRAVITY_N_MPS2])


@nb.njit(cache=True, inline="always")
def static_share(vp: np.ndarray, i: int, gravity_n_mps2: float) -> float:
    """Static normal load of wheel ``i`` on a plane where gravity presses with
    ``gravity_n_mps2`` (N)."""
    a = vp[VP_CG_TO_FRONT_AXLE_M]
    b = vp[VP_CG_TO_REAR_AXLE_M]
    weight_n = vp[VP_MASS_KG] * gravity_n_mps2
    if is_front(i):
        return 0.5 * weight_n * b / (a + b)
    return 0.5 * weight_n * a / (a + b)


WALL_SLOPE = 1.0
"""The steepest face (rise per run, relative to the reference plane) the contact takes as
the ground under a wheel: a steeper one (a step, a wall, a cliff's edge on a height map)
is ridden as a face of this slope (docs/model.md section 11). A tire meets a face steeper
than 45 degrees with its tread's front, not its contact patch; the massless wheel has no
such contact, and taking the face as it is sent the load to sqrt(1 + slope^2) times the
suspension's force and the damper's rate to slope x speed (issue 34: 0.7 to 9 MN on a
10 m step)."""


@nb.njit(cache=True)
def hub_velocity(
    x: np.ndarray, derived: np.ndarray, i: int, cos_steer: float, sin_steer: float
) -> tuple[float, float]:
    """Hub velocity of wheel ``i`` in its own heading frame (u along the wheel, v left),
    given the cosine and sine of its road-wheel angle; ``derived``: the model's derived
    constants (``core.model.D_*``: the wheel's position)."""
    px, py = derived[D_WHEEL_X0 + i], derived[D_WHEEL_Y0 + i]
    r = x[YAW_RATE_RADPS]
    u_c = x[U_MPS] - r * py
    v_c = x[V_MPS] + r * px
    return cos_steer * u_c + sin_steer * v_c, -sin_steer * u_c + cos_steer * v_c


@nb.njit(**STEP_JIT_OPTIONS)
def follow_terrain(model: Model, ws: Workspace, x: np.ndarray) -> None:
    """Stage 1b: the reference plane of the step (docs/model.md section 11) into
    ``ws.ground``: its axes, gravity resolved into them, the friction under each wheel.

    On the plane kind it is the road (the terrain's ``road``, ``core.road.set_road``'s
    slots, copied: the step does what it did before terrains). On a height map a plane is
    fitted through the four contact points and the states are re-expressed on it
    (``core.terrain``)."""
    vp, terrain = model.vp, model.terrain
    road = terrain_road(terrain)
    ground, wheel = ws.ground, ws.wheel
    if terrain.kind == TERRAIN_PLANE:
        ground[G_GRAVITY_E1_MPS2] = road[ROAD_GRAVITY_E1_MPS2]
        ground[G_GRAVITY_E2_MPS2] = road[ROAD_GRAVITY_E2_MPS2]
        ground[G_GRAVITY_N_MPS2] = road[ROAD_GRAVITY_N_MPS2]
        x[REF_GRADE_PCT] = road[ROAD_GRADE_PCT]
        x[REF_CROSS_SLOPE_PCT] = road[ROAD_CROSS_SLOPE_PCT]
        x[REF_HEIGHT_M] = 0.0
        for i in range(N_WHEELS):
            ground[G_MU0 + i] = road[ROAD_FRICTION_SCALE]
        static_loads(vp, ground)
        return
    axes_old = ws.axes[0]
    axes_new = ws.axes[1]
    contact = ws.contact
    if (ground[G_AXES_GRADE_PCT] == x[REF_GRADE_PCT]
            and ground[G_AXES_CROSS_SLOPE_PCT] == x[REF_CROSS_SLOPE_PCT]):
        for r in range(3):  # the last step's new plane is this step's old one
            for k in range(3):
                axes_old[r, k] = ground[G_AXES + 3 * r + k]
    else:
        road_frame(x[REF_GRADE_PCT], x[REF_CROSS_SLOPE_PCT], axes_old)
    psi = x[YAW_RAD]
    c = np.cos(psi)
    s = np.sin(psi)
    for i in range(N_WHEELS):
        px, py = wheel_position(vp, i)
        s1 = x[X_M] + px * c - py * s
        s2 = x[Y_M] + px * s + py * c
        wx = s1 * axes_old[0, 0] + s2 * axes_old[1, 0]
        wy = s1 * axes_old[0, 1] + s2 * axes_old[1, 1]
        height, grad_x, grad_y, mu = surface_under_wheel(terrain, ws.cells[i], wx, wy)
        # ground farther below the corner than its reach (the body's height) is a drop:
        # the wheel hangs above it, and the fitted plane does not swing down onto the
        # cliff's foot (section 11; the plane's small-angle re-expression holds)
        corner_z = (s1 * axes_old[0, 2] + s2 * axes_old[1, 2] + x[REF_HEIGHT_M]
                    + (x[HEAVE_M] + py * x[ROLL_RAD] - px * x[PITCH_RAD]) * axes_old[2, 2])
        if height < corner_z - vp[VP_CG_HEIGHT_M]:
            height = corner_z - vp[VP_CG_HEIGHT_M]
        contact[0, i] = wx
        contact[1, i] = wy
        contact[2, i] = height
        ground[G_MU0 + i] = road[ROAD_FRICTION_SCALE] * mu
        wheel[i, W_GAP_D1] = grad_x  # the gradient, until contact_frames below
        wheel[i, W_GAP_D2] = grad_y
    slope_x, slope_y, height0 = fit_plane(contact[0], contact[1], contact[2])
    c, s = rebase_reference_plane(x, 100.0 * slope_x, 100.0 * slope_y, height0,
                                  vp[VP_CG_HEIGHT_M], axes_old, axes_new, c, s)
    g = vp[VP_GRAVITY_MPS2]
    ground[G_GRAVITY_E1_MPS2] = -g * axes_new[0, 2]
    ground[G_GRAVITY_E2_MPS2] = -g * axes_new[1, 2]
    ground[G_GRAVITY_N_MPS2] = g * axes_new[2, 2]
    for r in range(3):
        for k in range(3):
            ground[G_AXES + 3 * r + k] = axes_new[r, k]
    ground[G_AXES_GRADE_PCT] = x[REF_GRADE_PCT]
    ground[G_AXES_CROSS_SLOPE_PCT] = x[REF_CROSS_SLOPE_PCT]
    static_loads(vp, ground)
    contact_frames(model, ws, x, c, s)


@nb.njit(cache=True, inline="always")
def static_loads(vp: np.ndarray, ground: np.ndarray) -> None:
    """Each axle's static wheel load on the step's reference plane (``G_STATIC_FRONT_N``,
    ``G_STATIC_REAR_N``: ``static_share`` at ``G_GRAVITY_N_MPS2``), once per step instead
    of in each ``corner_loads`` of the step (the same arithmetic: the same bits)."""
    g_n = ground[G_GRAVITY_N_MPS2]
    ground[G_STATIC_FRONT_N] = static_share(vp, 0, g_n)
    ground[G_STATIC_REAR_N] = static_share(vp, N_FRONT_WHEELS, g_n)


@nb.njit(cache=True, inline="always")
def contact_frames(model: Model, ws: Workspace, x: np.ndarray, c: float, s: float) -> None:
    """Once per step, per wheel on a terrain: the surface under the wheel as its tangent
    plane at the step start, in the reference plane's terms (the gap ``W_GAP0_M`` at the
    contact point ``W_CONTACT_S1_M``, ``W_CONTACT_S2_M`` and its gradient ``W_GAP_D1``,
    ``W_GAP_D2``), and the wheel's contact frame on it: the normal, the wheel heading
    projected onto the tangent plane, and their cross product (docs/model.md section 11).
    Frozen over the step, as the tires' coefficients are. Reads the world gradient that
    ``follow_terrain`` left in ``W_GAP_D1``, ``W_GAP_D2`` and the queried points and
    heights in ``ws.contact``; ``c``, ``s``: the cosine and sine of the yaw."""
    vp = model.vp
    ground, wheel, wheel_in, contact = ws.ground, ws.wheel, ws.wheel_in, ws.contact
    slope_x = x[REF_GRADE_PCT] / 100.0
    slope_y = x[REF_CROSS_SLOPE_PCT] / 100.0
    e1x, e1y, e1z = ground[G_AXES], ground[G_AXES + 1], ground[G_AXES + 2]
    e2x, e2y, e2z = ground[G_AXES + 3], ground[G_AXES + 4], ground[G_AXES + 5]
    n_z = ground[G_AXES + 8]
    psi = x[YAW_RAD]
    ground[G_X0_M] = x[X_M]
    ground[G_Y0_M] = x[Y_M]
    ground[G_YAW0_RAD] = psi
    ground[G_COS_YAW0] = c
    ground[G_SIN_YAW0] = s
    for i in range(N_WHEELS):
        px, py = wheel_position(vp, i)
        s1 = x[X_M] + px * c - py * s
        s2 = x[Y_M] + px * s + py * c
        wx = s1 * e1x + s2 * e2x
        wy = s1 * e1y + s2 * e2y
        wz = s1 * e1z + s2 * e2z + x[REF_HEIGHT_M]
        grad_x = wheel[i, W_GAP_D1]
        grad_y = wheel[i, W_GAP_D2]
        # the surface's tangent plane at the queried point, evaluated where the wheel's
        # contact point is on the new reference plane (micrometres away)
        height = contact[2, i] + grad_x * (wx - contact[0, i]) + grad_y * (wy - contact[1, i])
        rel_x = grad_x - slope_x
        rel_y = grad_y - slope_y
        # d(gap)/ds along e1 and e2 (an in-plane step ds moves (e_x, e_y) ds horizontally)
        d_gap_1 = n_z * (rel_x * e1x + rel_y * e1y)
        d_gap_2 = n_z * (rel_x * e2x + rel_y * e2y)
        steep = d_gap_1 * d_gap_1 + d_gap_2 * d_gap_2
        if steep > WALL_SLOPE * WALL_SLOPE:  # a wall under the wheel (section 11): ridden
            scale = WALL_SLOPE / np.sqrt(steep)  # as a face of WALL_SLOPE, so the gap
            d_gap_1 *= scale  # rate (slope x speed) and the normal's tilt stay bounded
            d_gap_2 *= scale
        wheel[i, W_CONTACT_S1_M] = s1
        wheel[i, W_CONTACT_S2_M] = s2
        wheel[i, W_GAP0_M] = (height - wz) * n_z
        wheel[i, W_GAP_D1] = d_gap_1
        wheel[i, W_GAP_D2] = d_gap_2
        # slopes along and across the wheel heading, then the contact frame
        c_h = c * wheel_in[WI_COS_STEER, i] - s * wheel_in[WI_SIN_STEER, i]
        s_h = s * wheel_in[WI_COS_STEER, i] + c * wheel_in[WI_SIN_STEER, i]
        slope_long = c_h * d_gap_1 + s_h * d_gap_2
        slope_lat = -s_h * d_gap_1 + c_h * d_gap_2
        tilt = np.sqrt(1.0 + slope_long * slope_long + slope_lat * slope_lat)
        n_2 = 1.0 / tilt
        n_0 = -slope_long * n_2
        n_1 = -slope_lat * n_2
        # t_x: the wheel heading (1, 0, 0) projected onto the tangent plane, whose length
        # is sqrt(1 - n_0^2) (|n| = 1); t_y = n x t_x
        t_x0 = 1.0 - n_0 * n_0
        inv_t_norm = 1.0 / np.sqrt(t_x0)
        t_x1 = -n_0 * n_1 * inv_t_norm
        t_x2 = -n_0 * n_2 * inv_t_norm
        t_x0 *= inv_t_norm
        wheel[i, W_TILT] = tilt
        wheel[i, W_N0] = n_0
        wheel[i, W_N1] = n_1
        wheel[i, W_TX0] = t_x0
        wheel[i, W_TX1] = t_x1
        wheel[i, W_TY0] = n_1 * t_x2 - n_2 * t_x1
        wheel[i, W_TY1] = n_2 * t_x0 - n_0 * t_x2


@nb.njit(cache=True, inline="always")
def terrain_gaps(model: Model, ws: Workspace, x: np.ndarray) -> None:
    """Per wheel and evaluation, what the reference plane misses of the surface under it:
    the gap (``W_GAP_M``, along the plane's normal) and its rate as the wheel moves
    (``W_GAP_RATE_MPS``), on the tangent planes of the step start (``contact_frames``).

    The wheel's displacement from its start point is the body's, with the turn of the
    heading linearised (the heading moves by a milliradian a step: the neglected term is
    a micrometre), so no trigonometry is repeated per stage."""
    derived = model.derived
    wheel, ground = ws.wheel, ws.ground
    c = ground[G_COS_YAW0]
    s = ground[G_SIN_YAW0]
    d_x = x[X_M] - ground[G_X0_M]
    d_y = x[Y_M] - ground[G_Y0_M]
    d_psi = x[YAW_RAD] - ground[G_YAW0_RAD]
    r = x[YAW_RATE_RADPS]
    for i in range(N_WHEELS):
        px, py = derived[D_WHEEL_X0 + i], derived[D_WHEEL_Y0 + i]
        # in-plane offsets of the wheel from the CG at the start: (px c - py s, px s + py c);
        # turning by d_psi moves the wheel by d_psi times the offset turned a quarter
        d_s1 = d_x - d_psi * (px * s + py * c)
        d_s2 = d_y + d_psi * (px * c - py * s)
        d_gap_1 = wheel[i, W_GAP_D1]
        d_gap_2 = wheel[i, W_GAP_D2]
        u_c = x[U_MPS] - r * py
        v_c = x[V_MPS] + r * px
        wheel[i, W_GAP_M] = wheel[i, W_GAP0_M] + d_gap_1 * d_s1 + d_gap_2 * d_s2
        wheel[i, W_GAP_RATE_MPS] = d_gap_1 * (u_c * c - v_c * s) + d_gap_2 * (u_c * s + v_c * c)


@nb.njit(**STEP_JIT_OPTIONS)
def corner_loads(model: Model, ws: Workspace, x: np.ndarray) -> None:
    """Stage 1: the normal load of each corner (N) into ``ws.wheel[i, W_FZ]`` (and what it
    adds to the static share into ``W_FZ_DYN``).

    Static share (from the CG position and the component of gravity normal to the
    reference plane, ``static_loads`` of the step) plus the suspension's force (spring,
    damper, anti-roll bar) from the body's heave, roll and pitch and, on a terrain, the
    surface's gap under the wheel; a corner whose load would go negative lifts off
    (``Fz = 0``). On a terrain, ``W_FZ`` is the load along the wheel's own contact normal
    (docs/model.md section 11).
    """
    vp = model.vp
    wheel = ws.wheel
    on_plane = model.terrain.kind == TERRAIN_PLANE
    if not on_plane:
        terrain_gaps(model, ws, x)
    ground = ws.ground
    heave = x[HEAVE_M]
    heave_rate = x[HEAVE_RATE_MPS]
    roll = x[ROLL_RAD]
    roll_rate = x[ROLL_RATE_RADPS]
    pitch = x[PITCH_RAD]
    pitch_rate = x[PITCH_RATE_RADPS]
    for axle in range(N_AXLES):
        left = WHEELS_PER_AXLE * axle
        px, py_left = model.derived[D_WHEEL_X0 + left], model.derived[D_WHEEL_Y0 + left]
        if axle == 0:
            k_s = vp[VP_SPRING_FRONT_NPM]
            c_s = vp[VP_DAMPER_FRONT_NSPM]
            k_arb = vp[VP_ANTIROLL_FRONT_NPM]
        else:
            k_s = vp[VP_SPRING_REAR_NPM]
            c_s = vp[VP_DAMPER_REAR_NSPM]
            k_arb = vp[VP_ANTIROLL_REAR_NPM]
        # suspension compression (positive = compressed) from the body's heave/roll/pitch
        comp_l = -(heave + py_left * roll - px * pitch)
        comp_r = -(heave - py_left * roll - px * pitch)
        rate_l = -(heave_rate + py_left * roll_rate - px * pitch_rate)
        rate_r = -(heave_rate - py_left * roll_rate - px * pitch_rate)
        if not on_plane:
            # the corner compresses at most to its bump stop, the body's height: ground
            # higher than that is a wall the wheel meets, not a load (section 11)
            travel = vp[VP_CG_HEIGHT_M]
            comp_l = min(comp_l + wheel[left + LEFT, W_GAP_M], travel)
            comp_r = min(comp_r + wheel[left + RIGHT, W_GAP_M], travel)
            rate_l += wheel[left + LEFT, W_GAP_RATE_MPS]
            rate_r += wheel[left + RIGHT, W_GAP_RATE_MPS]
        arb = k_arb * (comp_l - comp_r)
        static = ground[G_STATIC_FRONT_N] if axle == 0 else ground[G_STATIC_REAR_N]
        fz_l = max(0.0, static + (k_s * comp_l + c_s * rate_l + arb))
        fz_r = max(0.0, static + (k_s * comp_r + c_s * rate_r - arb))
        wheel[left + LEFT, W_FZ_DYN] = fz_l - static
        wheel[left + RIGHT, W_FZ_DYN] = fz_r - static
        if not on_plane:  # the plane-normal force is the contact normal's n component
            fz_l *= wheel[left + LEFT, W_TILT]
            fz_r *= wheel[left + RIGHT, W_TILT]
        wheel[left + LEFT, W_FZ] = fz_l
        wheel[left + RIGHT, W_FZ] = fz_r


@nb.njit(cache=True, inline="always")
def auxiliary_damping(
    vp: np.ndarray,
    i: int,
    tp_wheel: np.ndarray,
    tire_out: np.ndarray,
    fz: float,
    u_w: float,
    v_w: float,
    damping_active: float,
    d_tan_alpha: float,
    d_kappa: float,
    spin_damping_cap: float,
) -> tuple[float, float]:
    """The low-speed damping shares ``(dFx, dFy)`` of one wheel (paper Appendix A,
    ``core.damping``), added to the tire forces ``tire_out[OUT_FX]``, ``[OUT_FY]``.
    ``spin_damping_cap``: the wheel's ``D_SPIN_DAMPING_CAP`` (``core.model``)."""
    damping_model = int(vp[VP_DAMPING_MODEL])
    slip_model = int(vp[VP_SLIP_MODEL])
    if damping_model == DAMPING_PAPER:
        if damping_active > 0.5:
            c_x, c_y = damping_coefficients(
                fz, tire_out[OUT_C_KAPPA], tire_out[OUT_C_ALPHA], tp_wheel[TP_RELAX_LONG_M],
                tp_wheel[TP_RELAX_LAT_M], vp[VP_DAMPING_RATIO], vp[VP_GRAVITY_MPS2],
            )
            return -c_x * u_w, -c_y * v_w
        return 0.0, 0.0
    if damping_model == DAMPING_PATCH:
        if slip_model == SLIP_KINEMATIC:  # no patch deflection to damp
            return 0.0, 0.0
        fade = low_speed_fade(np.sqrt(u_w * u_w + v_w * v_w), vp[VP_DAMPING_FADE_SPEED_MPS])
        if not fade > 0.0:
            return 0.0, 0.0
        relax_long = tp_wheel[TP_RELAX_LONG_M]
        relax_lat = tp_wheel[TP_RELAX_LAT_M]
        c_x, c_y = damping_coefficients(
            fz, tire_out[OUT_C_KAPPA], tire_out[OUT_C_ALPHA], relax_long, relax_lat,
            vp[VP_DAMPING_RATIO], vp[VP_GRAVITY_MPS2],
        )
        # The damper also loads the wheel's spin: c R^2 / I is its rate there.
        # Beyond 2/dt it is faster than the step can resolve (and than any
        # physical carcass damping); cap it so the explicit stages stay stable
        # (spin_damping_cap = 2 I / (R^2 dt), once per model: derive_constants).
        c_x = min(c_x, spin_damping_cap)
        damp_x = fade * c_x * relax_long * d_kappa
        damp_y = -fade * c_y * relax_lat * d_tan_alpha
        # a damper in series with sliding cannot push beyond the friction limit
        fx = tire_out[OUT_FX]
        fy = tire_out[OUT_FY]
        lim_x = max(tire_out[OUT_FX_PEAK], abs(fx))
        lim_y = max(tire_out[OUT_FY_PEAK], abs(fy))
        damp_x = min(max(fx + damp_x, -lim_x), lim_x) - fx
        damp_y = min(max(fy + damp_y, -lim_y), lim_y) - fy
        return damp_x, damp_y
    if damping_model == DAMPING_OFF:
        return 0.0, 0.0
    raise ValueError("unknown damping model id (core.damping.DAMPING_MODELS)")


@nb.njit(**STEP_JIT_OPTIONS)
def wheel_forces(model: Model, ws: Workspace, x: np.ndarray, dx: np.ndarray) -> None:
    """Stage 2: per wheel, the slip, the tire forces with the auxiliary damping and the
    spin; writes ``dx``'s spin and slip slots and ``ws.wheel`` (``W_*``).

    Reads the loads of stage 1 (``ws.wheel[i, W_FZ]``) and the inputs held over the step
    (``ws.wheel_in``). Three loops: the slips of every wheel (kept in ``ws.wheel`` and
    ``dx``), the tires, the forces and spins. With an MF 6.1 tire on every wheel the four
    tires are one call (``core.tire.tire_evaluate_mf61_wheels``: their curves vectorised
    together); with a brush tire on every wheel, also one call
    (``core.tire.tire_evaluate_simple_wheels``);
    any other set of tires is evaluated wheel by wheel.

    The per-wheel parts are written here once, not as inlined helpers and not once per
    branch: this function is inlined four times into the step (then by numba; now one
    loop of ``rates_and_rk4`` calls it, inlined by LLVM), and each extra inlined
    copy or helper grew the cold compile (measured, ``run-scenario`` from an empty cache:
    the MF-only copy of every part +47 % CPU, helpers +22 %, this form +4 %).
    """
    vp, tp, tires, derived = model.vp, model.tp, model.tires, model.derived
    wheel_in, wheel, tire_out, tire_coef = ws.wheel_in, ws.wheel, ws.tire_out, ws.tire_coef
    slip_model = int(vp[VP_SLIP_MODEL])
    on_plane = model.terrain.kind == TERRAIN_PLANE
    for i in range(N_WHEELS):
        tp_wheel = tp[i]
        u_w, v_w = hub_velocity(x, derived, i, wheel_in[WI_COS_STEER, i],
                                wheel_in[WI_SIN_STEER, i])
        if not on_plane:  # into the wheel's contact frame (docs/model.md section 11)
            u_w, v_w = (u_w * wheel[i, W_TX0] + v_w * wheel[i, W_TX1],
                        u_w * wheel[i, W_TY0] + v_w * wheel[i, W_TY1])
        radius = tp_wheel[TP_RADIUS_M]
        omega = x[OMEGA0 + i]
        if slip_model == SLIP_KINEMATIC:
            tan_alpha, kappa = kinematic_slip(
                u_w, v_w, omega, radius, vp[VP_KINEMATIC_U_MIN_MPS]
            )
            d_tan_alpha = 0.0
            d_kappa = 0.0
        elif slip_model == SLIP_LAGGED_PASSIVE or slip_model == SLIP_LAGGED_PAPER:
            tan_alpha = x[TAN_ALPHA0 + i]
            kappa = x[KAPPA0 + i]
            d_tan_alpha, d_kappa = lagged_slip_rates(
                tan_alpha, kappa, u_w, v_w, omega, radius, tp_wheel[TP_RELAX_LAT_M],
                tp_wheel[TP_RELAX_LONG_M],
            )
        else:
            raise ValueError("unknown slip model id (core.slip.SLIP_MODELS)")
        wheel[i, W_HUB_U] = u_w
        wheel[i, W_HUB_V] = v_w
        wheel[i, W_KAPPA] = kappa
        wheel[i, W_TAN_ALPHA] = tan_alpha
        dx[TAN_ALPHA0 + i] = d_tan_alpha
        dx[KAPPA0 + i] = d_kappa
    # one call for the four tires when they share a built-in model (the MF 6.1 curves then
    # one vectorised loop), else wheel by wheel through the dispatcher
    mf61 = every_tire_is(tp, TIRE_MODEL_MF61)
    if mf61 or every_tire_is(tp, TIRE_MODEL_SIMPLE):
        kappa4 = (wheel[0, W_KAPPA], wheel[1, W_KAPPA], wheel[2, W_KAPPA], wheel[3, W_KAPPA])
        tan_alpha4 = (wheel[0, W_TAN_ALPHA], wheel[1, W_TAN_ALPHA], wheel[2, W_TAN_ALPHA],
                      wheel[3, W_TAN_ALPHA])
        fz4 = (wheel[0, W_FZ], wheel[1, W_FZ], wheel[2, W_FZ], wheel[3, W_FZ])
        hub_u4 = (wheel[0, W_HUB_U], wheel[1, W_HUB_U], wheel[2, W_HUB_U], wheel[3, W_HUB_U])
        if mf61:
            tire_evaluate_mf61_wheels(tp, tire_coef, kappa4, tan_alpha4, fz4, hub_u4, tire_out)
        else:
            tire_evaluate_simple_wheels(tp, tire_coef, kappa4, tan_alpha4, fz4, hub_u4,
                                        tire_out)
    else:
        for i in range(N_WHEELS):
            tire_evaluate(tires, tp[i], tire_coef[i], wheel[i, W_KAPPA], wheel[i, W_TAN_ALPHA],
                          wheel[i, W_FZ], wheel[i, W_HUB_U], tire_out[i])
    for i in range(N_WHEELS):
        tp_wheel = tp[i]
        out_i = tire_out[i]
        fz = wheel[i, W_FZ]
        u_w = wheel[i, W_HUB_U]
        v_w = wheel[i, W_HUB_V]
        radius = tp_wheel[TP_RADIUS_M]
        damp_x, damp_y = auxiliary_damping(
            vp, i, tp_wheel, out_i, fz, u_w, v_w, x[DAMPING_ACTIVE0 + i], dx[TAN_ALPHA0 + i],
            dx[KAPPA0 + i], derived[D_SPIN_DAMPING_CAP0 + i],
        )
        fx = out_i[OUT_FX] + damp_x
        fy = out_i[OUT_FY] + damp_y
        if on_plane:
            wheel[i, W_FX_PLANE] = fx
            wheel[i, W_FY_PLANE] = fy
        else:
            if not fz > 0.0:  # off the ground: no shear either
                fx = fy = damp_x = damp_y = 0.0
                out_i[OUT_MZ] = out_i[OUT_MY] = 0.0
            # the contact force in the reference plane, along and across the wheel heading
            wheel[i, W_FX_PLANE] = (fx * wheel[i, W_TX0] + fy * wheel[i, W_TY0]
                                    + fz * wheel[i, W_N0])
            wheel[i, W_FY_PLANE] = (fx * wheel[i, W_TX1] + fy * wheel[i, W_TY1]
                                    + fz * wheel[i, W_N1])
        if wheel_in[WI_HELD, i] > 0.5:
            d_omega = 0.0
        else:
            d_omega = (wheel_in[WI_DRIVE_NM, i] - radius * fx + wheel_in[WI_BRAKE_NM, i]) / (
                wheel_inertia(vp, i))
        dx[OMEGA0 + i] = d_omega
        wheel[i, W_FX] = fx
        wheel[i, W_FY] = fy
        wheel[i, W_MZ] = out_i[OUT_MZ]
        wheel[i, W_MY] = out_i[OUT_MY]
        wheel[i, W_KAPPA_SLIDE] = out_i[OUT_KAPPA_SLIDE]
        wheel[i, W_TAN_ALPHA_SLIDE] = out_i[OUT_TAN_ALPHA_SLIDE]
        wheel[i, W_FX_PEAK] = out_i[OUT_FX_PEAK]
        wheel[i, W_FY_PEAK] = out_i[OUT_FY_PEAK]
        wheel[i, W_DAMPING_FX] = damp_x
        wheel[i, W_DAMPING_FY] = damp_y


@nb.njit(**STEP_JIT_OPTIONS)
def body_rates(model: Model, ws: Workspace, x: np.ndarray, dx: np.ndarray) -> None:
    """Stage 3: the sprung body on the corner loads and the tire forces; writes ``dx``'s
    body slots and ``ws.body`` (``B_*``).

    Roll centres at ground level: the overturning moments are taken about the ground
    point below the CG, where the tire shear forces have no arm: ``M_roll = h sum(Fy)``,
    ``M_pitch = -h sum(Fx)``; gravity adds its destabilising ``m_s g_n h phi``.
    """
    vp, derived = model.vp, model.derived
    wheel_in, wheel, body = ws.wheel_in, ws.wheel, ws.body
    mass = vp[VP_MASS_KG]
    sprung = vp[VP_SPRUNG_MASS_KG]
    h_cg = vp[VP_CG_HEIGHT_M]
    ground = ws.ground
    g_n = ground[G_GRAVITY_N_MPS2]

    yaw = x[YAW_RAD]
    cos_yaw = np.cos(yaw)
    sin_yaw = np.sin(yaw)
    g_x = ground[G_GRAVITY_E1_MPS2] * cos_yaw + ground[G_GRAVITY_E2_MPS2] * sin_yaw
    g_y = -ground[G_GRAVITY_E1_MPS2] * sin_yaw + ground[G_GRAVITY_E2_MPS2] * cos_yaw
    u = x[U_MPS]
    v = x[V_MPS]
    r = x[YAW_RATE_RADPS]

    fx_sum = 0.0
    fy_sum = 0.0
    mz_sum = 0.0
    heave_force = 0.0
    roll_moment = 0.0
    pitch_moment = 0.0
    for i in range(N_WHEELS):
        px, py = derived[D_WHEEL_X0 + i], derived[D_WHEEL_Y0 + i]
        dyn = wheel[i, W_FZ_DYN]
        heave_force += dyn
        roll_moment += py * dyn
        pitch_moment -= px * dyn
        # tire forces into body axes
        c_d = wheel_in[WI_COS_STEER, i]
        s_d = wheel_in[WI_SIN_STEER, i]
        fx_body = c_d * wheel[i, W_FX_PLANE] - s_d * wheel[i, W_FY_PLANE]
        fy_body = s_d * wheel[i, W_FX_PLANE] + c_d * wheel[i, W_FY_PLANE]
        fx_sum += fx_body
        fy_sum += fy_body
        mz_sum += px * fy_body - py * fx_body + wheel[i, W_MZ]

    drag = derived[D_DRAG_NS2PM2] * u * abs(u)
    force_x = fx_sum + mass * g_x - drag
    force_y = fy_sum + mass * g_y
    if body[B_CONTACT_ACTIVE] > 0.5:
        # another car's push (core.contact, docs/model.md section 16): held over the step
        # in the plane's axes, turned into body axes at each stage's heading, acting at the
        # bumper's height (its overturning arm to the CG). Only while a contact acts: a
        # car that touches nothing does exactly the arithmetic it did without contacts.
        f_e1 = body[B_CONTACT_E1_N]
        f_e2 = body[B_CONTACT_E2_N]
        f_cx = f_e1 * cos_yaw + f_e2 * sin_yaw
        f_cy = -f_e1 * sin_yaw + f_e2 * cos_yaw
        force_x += f_cx
        force_y += f_cy
        mz_sum += body[B_CONTACT_MZ_NM]
        arm = h_cg - vp[VP_BUMPER_HEIGHT_M]
        roll_moment += arm * f_cy
        pitch_moment -= arm * f_cx
    ax = force_x / mass
    ay = force_y / mass
    yaw_acc = mz_sum / vp[VP_YAW_INERTIA_KGM2]

    dx[X_M] = u * cos_yaw - v * sin_yaw
    dx[Y_M] = u * sin_yaw + v * cos_yaw
    dx[YAW_RAD] = r
    dx[U_MPS] = ax + v * r
    dx[V_MPS] = ay - u * r
    dx[YAW_RATE_RADPS] = yaw_acc
    dx[HEAVE_M] = x[HEAVE_RATE_MPS]
    dx[HEAVE_RATE_MPS] = heave_force / sprung
    dx[ROLL_RAD] = x[ROLL_RATE_RADPS]
    dx[ROLL_RATE_RADPS] = (
        roll_moment + h_cg * fy_sum + sprung * g_n * h_cg * x[ROLL_RAD]
    ) / vp[VP_ROLL_INERTIA_KGM2]
    dx[PITCH_RAD] = x[PITCH_RATE_RADPS]
    dx[PITCH_RATE_RADPS] = (
        pitch_moment - h_cg * fx_sum + sprung * g_n * h_cg * x[PITCH_RAD]
    ) / vp[VP_PITCH_INERTIA_KGM2]

    body[B_AX_MPS2] = ax
    body[B_AY_MPS2] = ay
    body[B_YAW_ACC_RADPS2] = yaw_acc
    body[B_GRAVITY_X_MPS2] = g_x
    body[B_GRAVITY_Y_MPS2] = g_y
    body[B_FX_SUM_N] = fx_sum
    body[B_FY_SUM_N] = fy_sum


@nb.njit(cache=True, inline="always")
def vehicle_rates(model: Model, ws: Workspace, x: np.ndarray, dx: np.ndarray) -> None:
    """Time derivatives ``dx`` (float64[N_INTEGRATED]) of the integrated states at ``x``.

    The discrete slots of ``x`` are read, not differentiated. Leaves the per-wheel and
    body quantities of ``x`` in the workspace (``ws.wheel``, ``ws.body``).
    """
    corner_loads(model, ws, x)
    forces_and_rates(model, ws, x, dx)


@nb.njit(cache=True, inline="always")
def forces_and_rates(model: Model, ws: Workspace, x: np.ndarray, dx: np.ndarray) -> None:
    """:func:`vehicle_rates` after its ``corner_loads``: for a state whose loads are
    already in ``ws.wheel`` (the step's start state, loaded by ``prepare_tires``)."""
    wheel_forces(model, ws, x, dx)
    body_rates(model, ws, x, dx)


@nb.njit(cache=True, inline="always")
def record_contacts(ws: Workspace, x: np.ndarray) -> None:
    """Which wheels carried load at the start of the step (state ``IN_CONTACT``)."""
    for i in range(N_WHEELS):
        x[IN_CONTACT0 + i] = 1.0 if ws.wheel[i, W_FZ] > 0.0 else 0.0


@nb.njit(cache=True, inline="always")
def record_outputs(ws: Workspace, out: np.ndarray) -> None:
    """Copy the forces of the state just evaluated into the outputs (``O_*`` slots);
    the brake torques are written by the integrator once the brakes are resolved."""
    wheel_in, wheel, body = ws.wheel_in, ws.wheel, ws.body
    for i in range(N_WHEELS):
        fx = wheel[i, W_FX]
        fy = wheel[i, W_FY]
        out[O_FX0 + i] = fx
        out[O_FY0 + i] = fy
        out[O_FZ0 + i] = wheel[i, W_FZ]
        out[O_MZ0 + i] = wheel[i, W_MZ]
        out[O_HUB_U0 + i] = wheel[i, W_HUB_U]
        out[O_HUB_V0 + i] = wheel[i, W_HUB_V]
        out[O_STEER0 + i] = wheel_in[WI_STEER_RAD, i]
        out[O_DRIVE_TORQUE0 + i] = wheel_in[WI_DRIVE_NM, i]
        fx_avail = max(wheel[i, W_FX_PEAK], 1e-9)
        fy_avail = max(wheel[i, W_FY_PEAK], 1e-9)
        out[O_FRICTION_USE0 + i] = np.sqrt((fx / fx_avail) ** 2 + (fy / fy_avail) ** 2)
        out[O_DAMPING_FX0 + i] = wheel[i, W_DAMPING_FX]
        out[O_DAMPING_FY0 + i] = wheel[i, W_DAMPING_FY]
        out[O_KAPPA0 + i] = wheel[i, W_KAPPA]
        out[O_TAN_ALPHA0 + i] = wheel[i, W_TAN_ALPHA]
        out[O_CAMBER0 + i] = wheel_in[WI_CAMBER_RAD, i]
    out[O_AX_MPS2] = body[B_AX_MPS2]
    out[O_AY_MPS2] = body[B_AY_MPS2]
    out[O_YAW_ACC_RADPS2] = body[B_YAW_ACC_RADPS2]
    out[O_GRAVITY_X_MPS2] = body[B_GRAVITY_X_MPS2]
    out[O_GRAVITY_Y_MPS2] = body[B_GRAVITY_Y_MPS2]
    out[O_FX_BODY_SUM_N] = body[B_FX_SUM_N]
    out[O_FY_BODY_SUM_N] = body[B_FY_SUM_N]


def place_on_terrain(model: Model, ws: Workspace, x: np.ndarray) -> None:
    """Put the car of state ``x`` onto a terrain: ``X_M``, ``Y_M`` and ``YAW_RAD`` are read
    as the world position and heading of the CG; the reference plane is fitted under the
    wheels there, the springs left static, and the planar velocities kept (docs/model.md
    section 11)."""
    u, v, r = x[U_MPS], x[V_MPS], x[YAW_RATE_RADPS]
    world_x, world_y, world_yaw = x[X_M], x[Y_M], x[YAW_RAD]
    x[REF_GRADE_PCT] = 0.0
    x[REF_CROSS_SLOPE_PCT] = 0.0
    x[REF_HEIGHT_M] = surface_at(model.terrain, world_x, world_y)[0]
    for _ in range(4):  # the fit moves the wheels' points a little: repeat to a fixed point
        x[U_MPS] = x[V_MPS] = x[YAW_RATE_RADPS] = 0.0
        follow_terrain(model, ws, x)
        for k in (HEAVE_M, HEAVE_RATE_MPS, ROLL_RAD, ROLL_RATE_RADPS, PITCH_RAD,
                  PITCH_RATE_RADPS):
            x[k] = 0.0
        # the CG's foot on the plane straight below (world_x, world_y)
        axes = road_axes(x[REF_GRADE_PCT], x[REF_CROSS_SLOPE_PCT])
        rise = (x[REF_GRADE_PCT] * world_x + x[REF_CROSS_SLOPE_PCT] * world_y) / 100.0
        x[X_M] = world_x * axes[0, 0] + world_y * axes[0, 1] + rise * axes[0, 2]
        x[Y_M] = world_x * axes[1, 0] + world_y * axes[1, 1] + rise * axes[1, 2]
    # the heading from world x is that of the forward axis seen from above: the horizontal
    # direction lifted onto the plane. (The re-expression above projects along the plane's
    # normal instead, which turns the heading seen from above by about grade x cross slope:
    # 6e-4 rad on a 3 %, 2 % plane.)
    c, s = np.cos(world_yaw), np.sin(world_yaw)
    lifted = np.array((c, s, (x[REF_GRADE_PCT] * c + x[REF_CROSS_SLOPE_PCT] * s) / 100.0))
    x[YAW_RAD] = np.arctan2(lifted @ axes[1], lifted @ axes[0])
    x[U_MPS], x[V_MPS], x[YAW_RATE_RADPS] = u, v, r
