"""Cars that touch: footprint boxes and a compliant contact between them (docs/model.md
section 16).

The world's contact stage (``contact_stage``, called by ``core.world.step`` before the car
step of each car) finds the pairs of cars whose body boxes overlap and gives each car of
a pair an equal and opposite force, with its moment about the car's CG, held over the
step (the body slots ``B_CONTACT_*`` of the car's workspace, which ``core.chassis.
body_rates`` adds at every Runge-Kutta stage). Equal and opposite forces in one frame,
each integrated by the same RK4 step, exchange momentum exactly.

- **Boxes.** A car's body is a rectangle in the ground plane: from ``body_rear_overhang_m``
  behind the rear axle to ``body_front_overhang_m`` ahead of the front axle, ``body_width_m``
  wide, oriented with the car's heading. On the plane terrain the rectangles live in the
  road plane every car shares; on a height map each car's reference plane is its own, so
  the boxes are projected onto the horizontal world plane.
- **Broad phase.** A circle about each CG holding its box: a pair whose circles do not
  meet costs a subtraction and three multiplications.
- **Narrow phase.** The separating-axis test on the four edge normals of the two boxes;
  the axis of least overlap gives the contact normal and the penetration depth, the
  centroid of the overlap polygon (one box clipped by the other) the contact point.
- **Normal force.** A spring and damper along the normal, relaxed at the depth the
  boxes overlapped by on the step they met (at most one step's travel: the spring then
  stores only what the pair gives it) (Kelvin-Voigt: stiffness ``k``
  of the two bodies in series, damping ``zeta`` of critical for the pair's effective mass
  ``m_n`` along the normal at the contact point, its yaw inertias included), solved
  *exactly* over the step for the pair's relative motion along the normal; the force
  applied, held over the step, is that solution's mean, ``m_n (d'0 - d'(h)) / h``, so the
  pair's normal velocity changes as the solution's, whatever ``k h^2 / m_n``; clamped at
  zero (the contact pushes, never pulls). The step's map of the free pair then has the
  determinant ``cos(w h) + (w h) sin(w h) / 2 = 1 - (w h)^4 / 24 + ...`` (it loses a
  little), where a force evaluated at the step's start and held would gain
  ``1 + (w h)^2 / 2`` at every bounce.
- **Friction.** Coulomb at the contact point, regularised: ``mu F_n v_t / sqrt(v_t^2 +
  V_SLIP^2)`` against the tangential sliding speed ``v_t``, and never more than what
  stops the sliding within the step (``m_t |v_t| / h``), so it cannot reverse it.

Cars not touching another get ``B_CONTACT_ACTIVE = 0`` and step exactly as without
contacts. A pair is evaluated in an order of its own (the car with the smaller position
first), not the car axis': a pair of cars gives the same bits in any order of the world.
"""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np

from simserver.core.layout import (
    REF_CROSS_SLOPE_PCT,
    REF_GRADE_PCT,
    TIME_S,
    U_MPS,
    V_MPS,
    X_M,
    Y_M,
    YAW_RAD,
    YAW_RATE_RADPS,
)
from simserver.core.model import (
    B_CONTACT_ACTIVE,
    B_CONTACT_E1_N,
    B_CONTACT_E2_N,
    B_CONTACT_MZ_NM,
)
from simserver.core.params import (
    VP_BODY_FRONT_OVERHANG_M,
    VP_BODY_REAR_OVERHANG_M,
    VP_BODY_WIDTH_M,
    VP_CG_TO_FRONT_AXLE_M,
    VP_CG_TO_REAR_AXLE_M,
    VP_CONTACT_DAMPING_RATIO,
    VP_CONTACT_FRICTION,
    VP_CONTACT_STIFFNESS_N_PER_M,
    VP_MASS_KG,
    VP_YAW_INERTIA_KGM2,
)
from simserver.core.road import road_frame

V_SLIP_MPS = 0.05
"""Sliding speed at which the regularised contact friction reaches 71 % of Coulomb's
``mu F_n`` (section 16): below it the friction grows with the speed, as a stiff viscous
contact would; it cannot hold a tangential load at zero speed (nothing in a footprint
contact sticks)."""

# ---- per car (Contacts.car[c, CC_*]): what the last step's contacts did to the car; the
# first block is its output (published, recorded), the rest the stage's scratch
CC_ACTIVE = 0  # 1 when the car's box overlapped another car's over the last step
CC_FORCE_X_N = 1  # the contact force on the car: plane axes e1, e2 on the plane terrain,
CC_FORCE_Y_N = 2  # horizontal world axes x, y on a height map (N)
CC_MOMENT_NM = 3  # its moment about the car's CG, about the vertical (N m)
CC_PENETRATION_M = 4  # deepest overlap of the car's contacts (m)
CC_EVENTS = 5  # contact events the car took part in (a pair that starts to touch)
N_CAR_CONTACT_OUT = 6  # the slots above: the car's contact output
CC_POS_X_M = 6  # the step's footprint: CG position, heading, velocity, yaw rate (in the
CC_POS_Y_M = 7  # frame of CC_FORCE_*)
CC_COS = 8
CC_SIN = 9
CC_VEL_X_MPS = 10
CC_VEL_Y_MPS = 11
CC_YAW_RATE_RADPS = 12
CC_RADIUS_M = 13  # the broad phase's circle about the CG
CC_E1_X = 14  # the car's plane axes e1, e2, horizontal world components (height map)
CC_E1_Y = 15
CC_E2_X = 16
CC_E2_Y = 17
N_CAR_CONTACT = 18
CAR_CONTACT_NAMES = ("contact", "contact_force_x_n", "contact_force_y_n",
                     "contact_moment_nm", "contact_penetration_m", "contact_events")

# ---- the ring of contact events (Contacts.events[k % EVENT_RING, EV_*]): the step writes,
# Python drains (``drain_events``); Contacts.count[0] is the number of events so far
EV_SEQ = 0  # the event's number, 1, 2, ... (count[0] after it was written)
EV_TIME_S = 1  # the first car's time at the start of the step the boxes met
EV_CAR_A = 2  # the two cars' rows on the world's car axis (A < B)
EV_CAR_B = 3
EV_CLOSING_SPEED_MPS = 4  # how fast the contact point closed along the normal (m/s)
EV_X_M = 5  # the contact point (frame of CC_FORCE_*)
EV_Y_M = 6
N_EVENT = 7
EVENT_RING = 64
EV_SCRATCH = EVENT_RING  # the ring's extra row: a pair's closing speed and point, kept
# when it is a new contact
EVENT_NAMES = ("seq", "time_s", "car_a", "car_b", "closing_speed_mps", "x_m", "y_m")
K_EVENTS = 0  # Contacts.count: events written so far
N_COUNT = 1
POLY_MAX = 16  # the overlap polygon's scratch: a quadrilateral clipped by four lines has
# at most 8 corners


class Contacts(NamedTuple):
    """The world's contact data (``core.world.WorldData.contacts``)."""

    car: np.ndarray  # float64[n_cars, N_CAR_CONTACT]
    pair: np.ndarray  # float64[n_cars, n_cars]: [a, b] (a < b) 1 when touching last step,
    # [b, a] the depth at which they met
    events: np.ndarray  # float64[EVENT_RING + 1, N_EVENT]: the ring of events, a scratch row
    count: np.ndarray  # float64[N_COUNT]
    poly: np.ndarray  # float64[2, POLY_MAX, 2]: scratch of the overlap polygon


def make_contacts(n_cars: int) -> Contacts:
    """Contact data of a world of ``n_cars`` cars, nothing touching (allocates)."""
    return Contacts(car=np.zeros((n_cars, N_CAR_CONTACT)), pair=np.zeros((n_cars, n_cars)),
                    events=np.zeros((EVENT_RING + 1, N_EVENT)), count=np.zeros(N_COUNT),
                    poly=np.zeros((2, POLY_MAX, 2)))


def with_car_added(contacts: Contacts) -> Contacts:
    """The contact data with one more car (last row, touching nothing); allocates."""
    n = contacts.car.shape[0]
    pair = np.zeros((n + 1, n + 1))
    pair[:n, :n] = contacts.pair
    return contacts._replace(car=np.concatenate([contacts.car, np.zeros((1, N_CAR_CONTACT))]),
                             pair=pair)


def with_car_removed(contacts: Contacts, c: int) -> Contacts:
    """The contact data without car row ``c``; allocates."""
    pair = np.delete(np.delete(contacts.pair, c, axis=0), c, axis=1)
    return contacts._replace(car=np.delete(contacts.car, c, axis=0), pair=pair)


def drain_events(contacts: Contacts, seen: int) -> tuple[list[dict[str, float]], int, int]:
    """The events written after the first ``seen`` (oldest first), the number written so
    far (the next call's ``seen``) and how many were overwritten before they were read
    (the ring holds the last ``EVENT_RING``). Python side, between steps."""
    total = int(contacts.count[K_EVENTS])
    first = max(seen, total - EVENT_RING)
    rows = [contacts.events[k % EVENT_RING] for k in range(first, total)]
    events = [{name: float(row[j]) for j, name in enumerate(EVENT_NAMES)} for row in rows]
    for e in events:
        e["seq"] = int(e["seq"])
        e["car_a"] = int(e["car_a"])
        e["car_b"] = int(e["car_b"])
    return events, total, first - seen


@nb.njit(cache=True, inline="always")
def _box(vp: np.ndarray) -> tuple[float, float, float]:
    """The box's centre ahead of the CG, half length, half width (m)."""
    front = vp[VP_CG_TO_FRONT_AXLE_M] + vp[VP_BODY_FRONT_OVERHANG_M]
    rear = vp[VP_CG_TO_REAR_AXLE_M] + vp[VP_BODY_REAR_OVERHANG_M]
    return 0.5 * (front - rear), 0.5 * (front + rear), 0.5 * vp[VP_BODY_WIDTH_M]


def body_box(vp: np.ndarray) -> tuple[float, float, float]:
    """The body's box as lengths from the CG, ``(front_m, rear_m, half_width_m)``: the
    very box the contact stage pushes with (``_box``, from the vehicle's ``body_*``
    parameters). Python side: the checks of the cars' start poses (a headless world,
    ``simserver.sim.scene.check_starts_apart``, and the live server's, ``simserver.server.
    cars_config``) refuse a start this box overlaps another's at, one the contact would
    push apart on the first step."""
    offset, half_l, half_w = _box.py_func(vp)
    return float(offset + half_l), float(half_l - offset), float(half_w)


def _box_corners(pose: dict[str, float], box: tuple[float, float, float]) -> np.ndarray:
    front, rear, half = box
    c, s = np.cos(pose["yaw_rad"]), np.sin(pose["yaw_rad"])
    local = np.array([[front, half], [front, -half], [-rear, -half], [-rear, half]])
    return np.column_stack((pose["x_m"] + c * local[:, 0] - s * local[:, 1],
                            pose["y_m"] + s * local[:, 0] + c * local[:, 1]))


def bodies_overlap(pose_a: dict[str, float], box_a: tuple[float, float, float],
                   pose_b: dict[str, float], box_b: tuple[float, float, float]) -> bool:
    """Whether two body boxes (``body_box``) at two poses (``x_m``, ``y_m``, ``yaw_rad``)
    overlap (touching is not): the separating axis theorem on the rectangles' four edge
    normals, as the narrow phase of ``pair_contact``. Python side, off the step."""
    a, b = _box_corners(pose_a, box_a), _box_corners(pose_b, box_b)
    for yaw in (pose_a["yaw_rad"], pose_b["yaw_rad"]):
        for axis in ((np.cos(yaw), np.sin(yaw)), (-np.sin(yaw), np.cos(yaw))):
            pa, pb = a @ axis, b @ axis
            if pa.max() <= pb.min() or pb.max() <= pa.min():
                return False
    return True


@nb.njit(cache=True)
def footprint(vp: np.ndarray, x: np.ndarray, axes: np.ndarray, plane: bool,
              cc: np.ndarray) -> None:
    """The car's footprint of the step into ``cc`` (``CC_POS_X_M`` .. ``CC_E2_Y``): on the
    plane terrain in the road plane's coordinates (the planar states as they are); on a
    height map projected onto the horizontal world plane from the car's reference plane
    (its axes computed into the scratch ``axes``, float64[3, 3])."""
    c = np.cos(x[YAW_RAD])
    s = np.sin(x[YAW_RAD])
    v_1 = x[U_MPS] * c - x[V_MPS] * s
    v_2 = x[U_MPS] * s + x[V_MPS] * c
    if plane:
        cc[CC_POS_X_M] = x[X_M]
        cc[CC_POS_Y_M] = x[Y_M]
        cc[CC_COS] = c
        cc[CC_SIN] = s
        cc[CC_VEL_X_MPS] = v_1
        cc[CC_VEL_Y_MPS] = v_2
        cc[CC_E1_X] = 1.0
        cc[CC_E1_Y] = 0.0
        cc[CC_E2_X] = 0.0
        cc[CC_E2_Y] = 1.0
    else:
        road_frame(x[REF_GRADE_PCT], x[REF_CROSS_SLOPE_PCT], axes)
        e1x, e1y, e2x, e2y = axes[0, 0], axes[0, 1], axes[1, 0], axes[1, 1]
        cc[CC_POS_X_M] = x[X_M] * e1x + x[Y_M] * e2x
        cc[CC_POS_Y_M] = x[X_M] * e1y + x[Y_M] * e2y
        f_x = c * e1x + s * e2x
        f_y = c * e1y + s * e2y
        norm = np.sqrt(f_x * f_x + f_y * f_y)
        cc[CC_COS] = f_x / norm
        cc[CC_SIN] = f_y / norm
        cc[CC_VEL_X_MPS] = v_1 * e1x + v_2 * e2x
        cc[CC_VEL_Y_MPS] = v_1 * e1y + v_2 * e2y
        cc[CC_E1_X] = e1x
        cc[CC_E1_Y] = e1y
        cc[CC_E2_X] = e2x
        cc[CC_E2_Y] = e2y
    cc[CC_YAW_RATE_RADPS] = x[YAW_RATE_RADPS]
    offset, half_l, half_w = _box(vp)
    reach = abs(offset) + half_l
    cc[CC_RADIUS_M] = np.sqrt(reach * reach + half_w * half_w)


@nb.njit(cache=True, inline="always")
def _first(ca: np.ndarray, cb: np.ndarray) -> bool:
    """Whether car ``a`` comes first in a pair (its position, then its heading, smaller):
    an order of the cars' own, not of the car axis."""
    for k in (CC_POS_X_M, CC_POS_Y_M, CC_COS, CC_SIN):
        if ca[k] != cb[k]:
            return ca[k] < cb[k]
    return True


@nb.njit(cache=True)
def _overlap_centroid(poly: np.ndarray, cxa: float, cya: float, ua_x: float, ua_y: float,
                      la: float, wa: float, cxb: float, cyb: float, ub_x: float, ub_y: float,
                      lb: float, wb: float) -> tuple[float, float]:
    """Centroid of box b clipped by box a (Sutherland-Hodgman on a's four edges); the
    mean of the clipped corners if the overlap has no area, the centres' midpoint if
    nothing is left (boxes that just touch)."""
    src = poly[0]
    dst = poly[1]
    vb_x = -ub_y  # b's lateral axis
    vb_y = ub_x
    n = 4
    for q in range(4):  # b's corners, counter-clockwise: (-l, -w), (l, -w), (l, w), (-l, w)
        sl = 1.0 if q == 1 or q == 2 else -1.0
        sw = 1.0 if q >= 2 else -1.0
        src[q, 0] = cxb + sl * lb * ub_x + sw * wb * vb_x
        src[q, 1] = cyb + sl * lb * ub_y + sw * wb * vb_y
    # a's four half-planes: k . (p - c_a) <= half, for k = +-u_a (half la), +-v_a (wa)
    for e in range(4):
        if e < 2:
            k_x, k_y, half = ua_x, ua_y, la
        else:
            k_x, k_y, half = -ua_y, ua_x, wa
        if e % 2 == 1:
            k_x, k_y = -k_x, -k_y
        m = 0
        for i in range(n):
            j = (i + 1) % n
            di = k_x * (src[i, 0] - cxa) + k_y * (src[i, 1] - cya) - half
            dj = k_x * (src[j, 0] - cxa) + k_y * (src[j, 1] - cya) - half
            if di <= 0.0:
                dst[m, 0] = src[i, 0]
                dst[m, 1] = src[i, 1]
                m += 1
            if (di < 0.0 < dj) or (dj < 0.0 < di):
                t = di / (di - dj)
                dst[m, 0] = src[i, 0] + t * (src[j, 0] - src[i, 0])
                dst[m, 1] = src[i, 1] + t * (src[j, 1] - src[i, 1])
                m += 1
        src, dst = dst, src
        n = m
        if n == 0:
            return 0.5 * (cxa + cxb), 0.5 * (cya + cyb)
    area2 = 0.0
    gx = 0.0
    gy = 0.0
    mx = 0.0
    my = 0.0
    for i in range(n):
        j = (i + 1) % n
        cross = src[i, 0] * src[j, 1] - src[j, 0] * src[i, 1]
        area2 += cross
        gx += (src[i, 0] + src[j, 0]) * cross
        gy += (src[i, 1] + src[j, 1]) * cross
        mx += src[i, 0]
        my += src[i, 1]
    if abs(area2) > 1e-12:
        return gx / (3.0 * area2), gy / (3.0 * area2)
    return mx / n, my / n


@nb.njit(cache=True)
def pair_contact(vp_a: np.ndarray, vp_b: np.ndarray, ca: np.ndarray, cb: np.ndarray,
                 poly: np.ndarray, dt_s: float, event: np.ndarray, rest_depth: float) -> float:
    """The contact of cars a and b (their footprints ``ca``, ``cb``): 0 if their boxes do
    not overlap; else their depth, and adds the force on each, its moment and the depth to
    ``ca``, ``cb`` (``CC_FORCE_*``, ``CC_MOMENT_NM``, ``CC_PENETRATION_M``, ``CC_ACTIVE``,
    the force's start and rate slots) and leaves the closing speed and the contact point
    in ``event`` (``EV_*``). ``rest_depth``: the depth at which the spring is relaxed, the
    depth of the step the pair met (negative: they meet now)."""
    off_a, la, wa = _box(vp_a)
    off_b, lb, wb = _box(vp_b)
    ua_x, ua_y = ca[CC_COS], ca[CC_SIN]
    ub_x, ub_y = cb[CC_COS], cb[CC_SIN]
    cxa = ca[CC_POS_X_M] + off_a * ua_x
    cya = ca[CC_POS_Y_M] + off_a * ua_y
    cxb = cb[CC_POS_X_M] + off_b * ub_x
    cyb = cb[CC_POS_Y_M] + off_b * ub_y
    d_x = cxb - cxa
    d_y = cyb - cya
    # separating axes: a's and b's edge normals; the least overlap gives the normal (a to b)
    depth = np.inf
    n_x = 1.0
    n_y = 0.0
    for k in range(4):
        if k == 0:
            k_x, k_y = ua_x, ua_y
        elif k == 1:
            k_x, k_y = -ua_y, ua_x
        elif k == 2:
            k_x, k_y = ub_x, ub_y
        else:
            k_x, k_y = -ub_y, ub_x
        r_a = la * abs(ua_x * k_x + ua_y * k_y) + wa * abs(-ua_y * k_x + ua_x * k_y)
        r_b = lb * abs(ub_x * k_x + ub_y * k_y) + wb * abs(-ub_y * k_x + ub_x * k_y)
        s = d_x * k_x + d_y * k_y
        overlap = r_a + r_b - abs(s)
        if not overlap > 0.0:
            return 0.0
        if overlap < depth:
            depth = overlap
            sign = -1.0 if s < 0.0 else 1.0
            n_x = sign * k_x
            n_y = sign * k_y
    p_x, p_y = _overlap_centroid(poly, cxa, cya, ua_x, ua_y, la, wa, cxb, cyb, ub_x, ub_y,
                                 lb, wb)
    # arms from the CGs, the velocities of the contact point on each body
    ra_x = p_x - ca[CC_POS_X_M]
    ra_y = p_y - ca[CC_POS_Y_M]
    rb_x = p_x - cb[CC_POS_X_M]
    rb_y = p_y - cb[CC_POS_Y_M]
    va_x = ca[CC_VEL_X_MPS] - ca[CC_YAW_RATE_RADPS] * ra_y
    va_y = ca[CC_VEL_Y_MPS] + ca[CC_YAW_RATE_RADPS] * ra_x
    vb_x = cb[CC_VEL_X_MPS] - cb[CC_YAW_RATE_RADPS] * rb_y
    vb_y = cb[CC_VEL_Y_MPS] + cb[CC_YAW_RATE_RADPS] * rb_x
    rel_x = vb_x - va_x
    rel_y = vb_y - va_y
    closing = -(rel_x * n_x + rel_y * n_y)  # > 0: the boxes move into each other
    t_x = -n_y
    t_y = n_x
    v_t = rel_x * t_x + rel_y * t_y
    m_a, m_b = vp_a[VP_MASS_KG], vp_b[VP_MASS_KG]
    i_a, i_b = vp_a[VP_YAW_INERTIA_KGM2], vp_b[VP_YAW_INERTIA_KGM2]
    arm_an = ra_x * n_y - ra_y * n_x
    arm_bn = rb_x * n_y - rb_y * n_x
    arm_at = ra_x * t_y - ra_y * t_x
    arm_bt = rb_x * t_y - rb_y * t_x
    mass_n = 1.0 / (1.0 / m_a + 1.0 / m_b + arm_an * arm_an / i_a + arm_bn * arm_bn / i_b)
    mass_t = 1.0 / (1.0 / m_a + 1.0 / m_b + arm_at * arm_at / i_a + arm_bt * arm_bt / i_b)
    k_a = vp_a[VP_CONTACT_STIFFNESS_N_PER_M]
    k_b = vp_b[VP_CONTACT_STIFFNESS_N_PER_M]
    stiffness = k_a * k_b / (k_a + k_b)
    zeta = 0.5 * (vp_a[VP_CONTACT_DAMPING_RATIO] + vp_b[VP_CONTACT_DAMPING_RATIO])
    mu = 0.5 * (vp_a[VP_CONTACT_FRICTION] + vp_b[VP_CONTACT_FRICTION])
    # the spring is relaxed at the depth of the step the boxes met (at most a step's
    # travel, closing speed x h): from there on the pair moves as the spring says, so the
    # overlap a step found at its start stores no energy the pair did not give it
    compression = depth - (depth if rest_depth < 0.0 else rest_depth)
    # the pair's normal motion over the step, m_n d'' = -k d - c d', solved exactly
    # (zeta < 1: underdamped), from the depth and the closing speed at the step start
    w = np.sqrt(stiffness / mass_n)
    w_d = w * np.sqrt(1.0 - zeta * zeta)
    sigma = zeta * w
    h = dt_s
    b_coef = (closing + sigma * compression) / w_d
    decay = np.exp(-sigma * h)
    cos_h = np.cos(w_d * h)
    sin_h = np.sin(w_d * h)
    closing_end = decay * ((b_coef * w_d - sigma * compression) * cos_h
                           - (compression * w_d + sigma * b_coef) * sin_h)
    # the exact solution's mean force over the step, held over it (the pair's velocity
    # change is the solution's): it pushes, never pulls
    f_n = max(mass_n * (closing - closing_end) / h, 0.0)
    # Coulomb, regularised, at most what stops the sliding within the step
    f_t = mu * f_n * abs(v_t) / np.sqrt(v_t * v_t + V_SLIP_MPS * V_SLIP_MPS)
    f_t = min(f_t, mass_t * abs(v_t) / h)
    if v_t < 0.0:
        f_t = -f_t
    # the force on b (a gets its opposite): the normal push, friction against b's sliding
    f_x = f_n * n_x - f_t * t_x
    f_y = f_n * n_y - f_t * t_y
    ca[CC_FORCE_X_N] -= f_x
    ca[CC_FORCE_Y_N] -= f_y
    ca[CC_MOMENT_NM] -= ra_x * f_y - ra_y * f_x
    cb[CC_FORCE_X_N] += f_x
    cb[CC_FORCE_Y_N] += f_y
    cb[CC_MOMENT_NM] += rb_x * f_y - rb_y * f_x
    ca[CC_ACTIVE] = 1.0
    cb[CC_ACTIVE] = 1.0
    ca[CC_PENETRATION_M] = max(ca[CC_PENETRATION_M], depth)
    cb[CC_PENETRATION_M] = max(cb[CC_PENETRATION_M], depth)
    event[EV_CLOSING_SPEED_MPS] = closing
    event[EV_X_M] = p_x
    event[EV_Y_M] = p_y
    return depth


@nb.njit(cache=True, inline="always")
def contact_stage(vp: np.ndarray, x: np.ndarray, ws_body: np.ndarray, ws_axes: np.ndarray,
                  plane: bool, dt_s: float, contacts: Contacts) -> None:
    """The world's contact stage, before the cars' steps: every car's contact wrench of the
    step into its body slots (``B_CONTACT_*``), the outputs ``CC_*``, the events.

    ``vp``, ``x``, ``ws_body``, ``ws_axes``: the world's stacks (car axis
    first). A world of fewer than two cars only clears the body slots."""
    n = x.shape[0]
    car = contacts.car
    for c in range(n):
        ws_body[c, B_CONTACT_ACTIVE] = 0.0
    if n < 2:
        return
    for c in range(n):
        for k in range(CC_ACTIVE, CC_PENETRATION_M + 1):
            car[c, k] = 0.0
        footprint(vp[c], x[c], ws_axes[c, 0], plane, car[c])
    pair = contacts.pair
    events = contacts.events
    for i in range(n):
        for j in range(i + 1, n):
            d_x = car[j, CC_POS_X_M] - car[i, CC_POS_X_M]
            d_y = car[j, CC_POS_Y_M] - car[i, CC_POS_Y_M]
            reach = car[i, CC_RADIUS_M] + car[j, CC_RADIUS_M]
            touching = False
            if d_x * d_x + d_y * d_y < reach * reach:  # broad phase: the circles meet
                scratch = events[EV_SCRATCH]
                # the lower triangle keeps the depth the pair met at (-1: not touching)
                rest = pair[j, i] if pair[i, j] > 0.5 else -1.0
                if _first(car[i], car[j]):
                    depth = pair_contact(vp[i], vp[j], car[i], car[j], contacts.poly, dt_s,
                                         scratch, rest)
                else:
                    depth = pair_contact(vp[j], vp[i], car[j], car[i], contacts.poly, dt_s,
                                         scratch, rest)
                touching = depth > 0.0
                if touching and not pair[i, j] > 0.5:  # a new contact: an event
                    slot = int(contacts.count[K_EVENTS]) % EVENT_RING
                    contacts.count[K_EVENTS] += 1.0
                    events[slot, EV_SEQ] = contacts.count[K_EVENTS]
                    events[slot, EV_TIME_S] = x[i, TIME_S]
                    events[slot, EV_CAR_A] = i
                    events[slot, EV_CAR_B] = j
                    for k in (EV_CLOSING_SPEED_MPS, EV_X_M, EV_Y_M):
                        events[slot, k] = scratch[k]
                    car[i, CC_EVENTS] += 1.0
                    car[j, CC_EVENTS] += 1.0
                    pair[j, i] = depth
            pair[i, j] = 1.0 if touching else 0.0
    for c in range(n):
        if car[c, CC_ACTIVE] > 0.5:
            cc = car[c]
            body = ws_body[c]
            body[B_CONTACT_ACTIVE] = 1.0
            # into the car's plane axes (the plane terrain: e1, e2 are x, y, the same force)
            body[B_CONTACT_E1_N] = cc[CC_FORCE_X_N] * cc[CC_E1_X] + cc[CC_FORCE_Y_N] * cc[CC_E1_Y]
            body[B_CONTACT_E2_N] = cc[CC_FORCE_X_N] * cc[CC_E2_X] + cc[CC_FORCE_Y_N] * cc[CC_E2_Y]
            body[B_CONTACT_MZ_NM] = cc[CC_MOMENT_NM]

