"""The steering system: from the front tires' forces to the torque at the steering wheel.

An output of the vehicle, not a part of its motion: the road-wheel angles still come
straight from the driver's steering-wheel position (``integrator.road_wheel_angles``), and
this stage only reads the forces of the step and writes its own state slots, so the car
moves bit for bit as without it (docs/model.md section 12 gives the equations, signs and
sources).

Per front wheel i (side s_i = +1 left, -1 right), the moment about its kingpin, positive
turning the wheel to the left (ISO 8855, z up):

    M_kp,i = Mz_i - t_c Fy_i - s_i r_s Fx_i - d_c sin(sigma) Fz_i sin(delta_i) - k_t phi_i

- ``Mz_i``: the tire's aligning moment (the brush tire's ``-t_p Fy``, MF 6.1's Mz);
- ``-t_c Fy_i``: the lateral force at the contact patch, ``t_c`` (caster trail) behind the
  kingpin axis' ground point;
- ``-s_i r_s Fx_i``: the longitudinal force at the patch, ``r_s`` (scrub radius) outboard
  of that point;
- the kingpin inclination ``sigma`` lifts the car as a wheel steers (Gillespie 1992,
  ch. 8: ``-Fz d sin(sigma) sin(delta)``), ``d_c = r_s + R tan(sigma)`` the spindle's
  offset from the axis at the wheel centre;
- ``-k_t phi_i``: the contact patch's torsion. ``phi_i`` is how far the rim has turned
  against its patch; steering moves it one for one, and rolling relaxes it over the
  tire's lateral relaxation length b, as the lagged slip of paper eq. (16):
  ``dphi/dt = ddelta/dt - |u_i| / b phi``; it is capped by the patch's bore friction
  ``k_t |phi| <= c_bore mu Fz``. At standstill nothing relaxes it: a wheel turned at rest
  keeps its torque until the car rolls.

Through a linkage of the steering ratio N (ideal, by virtual work) the load at the column
is ``T_L = sum M_kp,i / N``. The power assist adds ``A = clip(g(u) T_d, +-A_max)`` to the
driver's torsion-bar torque ``T_d`` with a boost falling with speed,
``g(u) = g_hw + (g_park - g_hw) / (1 + (u / u_f)^2)``; solving ``T_d + A = T_L`` for T_d
gives what comes through to the hands. The column adds viscous damping on the (low-pass
filtered) steering-wheel rate and Coulomb friction as Dahl's model (a friction torque that
follows the angle: ``dT_f/dtheta = sigma_f (1 - sign(dtheta) T_f / T_c)``), integrated
exactly per step. The steering-wheel torque, what the system applies to the driver's hands
and what a force-feedback wheel should produce, positive to the left:

    T_sw = T_d - c_col omega_sw - T_f
"""

from __future__ import annotations

import numba as nb
import numpy as np

from simserver.core.layout import (
    IN_STEER,
    N_FRONT_WHEELS,
    O_FX0,
    O_FY0,
    O_FZ0,
    O_HUB_U0,
    O_MZ0,
    PATCH_TWIST0,
    STEERING_FRICTION_NM,
    STEERING_PRIMED,
    STEERING_WHEEL_ANGLE_RAD,
    STEERING_WHEEL_RATE_RADPS,
    STEERING_WHEEL_TORQUE_NM,
    STEP_JIT_OPTIONS,
    WHEELS_PER_AXLE,
)
from simserver.core.model import (
    D_COLUMN_RATE_BLEND,
    D_KINGPIN_LIFT_ARM0,
    G_MU0,
    WI_SIN_STEER,
    Data,
    Model,
)
from simserver.core.params import (
    VP_ASSIST_BOOST_HIGHWAY,
    VP_ASSIST_BOOST_PARKING,
    VP_ASSIST_FADE_SPEED_MPS,
    VP_ASSIST_TORQUE_MAX_NM,
    VP_CASTER_TRAIL_M,
    VP_COLUMN_DAMPING_NMS_PER_RAD,
    VP_COLUMN_FRICTION_NM,
    VP_COLUMN_FRICTION_STIFFNESS_NM_PER_RAD,
    VP_COLUMN_RATE_FILTER_S,
    VP_KINGPIN_INCLINATION_RAD,
    VP_PATCH_BORE_ARM_M,
    VP_PATCH_TORSION_STIFFNESS_NM_PER_RAD,
    VP_SCRUB_RADIUS_M,
    VP_STEERING_RATIO,
    VP_STEERING_WHEEL_MAX_RAD,
)
from simserver.core.tire_layout import TP_RELAX_LAT_M


@nb.njit(cache=True)
def kingpin_lift_arm_m(vp: np.ndarray, radius: float) -> float:
    """The kingpin inclination's lift arm ``d_c sin(sigma)`` (m) of a front wheel of rolling
    radius ``radius`` (m): ``d_c = r_s + R tan(sigma)`` the spindle's offset from the axis at
    the wheel centre. Module docstring, docs/model.md section 12."""
    sigma = vp[VP_KINGPIN_INCLINATION_RAD]
    spindle_offset = vp[VP_SCRUB_RADIUS_M] + radius * np.tan(sigma)
    return spindle_offset * np.sin(sigma)


@nb.njit(cache=True)
def column_rate_blend(vp: np.ndarray, dt_s: float) -> float:
    """The column rate filter's blend over one step of ``dt_s``: the low-pass filter's
    exact weight ``1 - exp(-dt / tau)`` of the new rate (1: no filter)."""
    tau = vp[VP_COLUMN_RATE_FILTER_S]
    return 1.0 if tau <= 0.0 else -np.expm1(-dt_s / tau)


@nb.njit(cache=True)
def kingpin_moment(vp: np.ndarray, side: float, fx: float, fy: float, fz: float, mz: float,
                   sin_delta: float, lift_arm_m: float, twist: float) -> float:
    """The moment about one front wheel's kingpin (N m, + turns the wheel left).

    ``side`` +1 for a left wheel, -1 for a right one; forces in the wheel frame (N),
    ``sin_delta`` the sine of the road-wheel angle (the step's, ``WI_SIN_STEER``),
    ``lift_arm_m`` the wheel's :func:`kingpin_lift_arm_m`, ``twist`` the patch torsion phi
    (rad). Module docstring, docs/model.md section 12.
    """
    return (mz - vp[VP_CASTER_TRAIL_M] * fy - side * vp[VP_SCRUB_RADIUS_M] * fx
            - lift_arm_m * fz * sin_delta
            - vp[VP_PATCH_TORSION_STIFFNESS_NM_PER_RAD] * twist)


@nb.njit(cache=True)
def assist_boost(vp: np.ndarray, speed_mps: float) -> float:
    """The assist's boost g(u): assist torque per unit driver torque, falling with speed."""
    park = vp[VP_ASSIST_BOOST_PARKING]
    highway = vp[VP_ASSIST_BOOST_HIGHWAY]
    ratio = speed_mps / vp[VP_ASSIST_FADE_SPEED_MPS]
    return highway + (park - highway) / (1.0 + ratio * ratio)


@nb.njit(cache=True)
def driver_torque(load_nm: float, boost: float, assist_max_nm: float) -> float:
    """The torsion-bar torque T_d with ``T_d + clip(boost T_d, +-A_max) = load``.

    Below the assist's limit ``T_d = load / (1 + boost)``; beyond it the assist stays at
    its maximum and the driver carries the rest (continuous at the limit).
    """
    if boost <= 0.0 or assist_max_nm <= 0.0:
        return load_nm
    if abs(load_nm) * boost <= (1.0 + boost) * assist_max_nm:
        return load_nm / (1.0 + boost)
    return load_nm - assist_max_nm if load_nm > 0.0 else load_nm + assist_max_nm


@nb.njit(cache=True)
def dahl_friction(friction_nm: float, d_angle_rad: float, limit_nm: float,
                  stiffness_nm_per_rad: float) -> float:
    """Dahl's friction after the angle moved by ``d_angle_rad``: the exact solution of
    ``dT/dtheta = k (1 - sign(dtheta) T / T_c)`` over the move (stays put at rest)."""
    if limit_nm <= 0.0:
        return 0.0
    if d_angle_rad == 0.0:
        return friction_nm
    target = limit_nm if d_angle_rad > 0.0 else -limit_nm
    return target + (friction_nm - target) * np.exp(
        -stiffness_nm_per_rad * abs(d_angle_rad) / limit_nm)


@nb.njit(**STEP_JIT_OPTIONS)
def steering_system(model: Model, data: Data) -> None:
    """Stage 8: the steering-wheel torque from the forces of the step (``data.out``, the
    state at the step's start) and the driver's steering-wheel position; writes the
    steering slots of the state (the steering-wheel angle, rate and torque, the
    column friction, the patch torsions). Reads nothing the vehicle's motion
    depends on and writes nothing it reads."""
    x, out = data.x, data.out
    vp, tp, h = model.vp, model.tp, model.dt_s
    derived = model.derived
    mu = data.ws.ground
    sin_steer = data.ws.wheel_in[WI_SIN_STEER]
    ratio = vp[VP_STEERING_RATIO]
    angle = data.inputs[IN_STEER] * vp[VP_STEERING_WHEEL_MAX_RAD]
    # a fresh state has no previous angle: the first step does not turn the wheel
    d_angle = angle - x[STEERING_WHEEL_ANGLE_RAD] if x[STEERING_PRIMED] > 0.5 else 0.0
    d_delta = d_angle / ratio
    load = 0.0
    speed = 0.0
    stiffness = vp[VP_PATCH_TORSION_STIFFNESS_NM_PER_RAD]
    for i in range(N_FRONT_WHEELS):
        # the patch's torsion, exact for a steer rate constant over the step
        hub_u = abs(out[O_HUB_U0 + i])
        decay = hub_u * h / tp[i, TP_RELAX_LAT_M]
        gain = 1.0 if decay < 1e-12 else -np.expm1(-decay) / decay
        twist = np.exp(-decay) * x[PATCH_TWIST0 + i] + gain * d_delta
        bore_max = vp[VP_PATCH_BORE_ARM_M] * mu[G_MU0 + i] * max(out[O_FZ0 + i], 0.0)
        if stiffness * abs(twist) > bore_max:  # the patch slips: torsion at the limit
            twist = bore_max / stiffness if twist > 0.0 else -bore_max / stiffness
        x[PATCH_TWIST0 + i] = twist
        speed += hub_u / N_FRONT_WHEELS
        side = 1.0 if i % WHEELS_PER_AXLE == 0 else -1.0
        # the arm is the model's (derive_constants), the sine that of the road-wheel angle
        # of stage 1: no trigonometry repeated here
        load += kingpin_moment(vp, side, out[O_FX0 + i], out[O_FY0 + i], out[O_FZ0 + i],
                               out[O_MZ0 + i], sin_steer[i], derived[D_KINGPIN_LIFT_ARM0 + i],
                               twist)
    load /= ratio
    t_d = driver_torque(load, assist_boost(vp, speed), vp[VP_ASSIST_TORQUE_MAX_NM])
    blend = derived[D_COLUMN_RATE_BLEND]  # column_rate_blend, once per model
    rate = x[STEERING_WHEEL_RATE_RADPS] + blend * (d_angle / h - x[STEERING_WHEEL_RATE_RADPS])
    friction = dahl_friction(x[STEERING_FRICTION_NM], d_angle, vp[VP_COLUMN_FRICTION_NM],
                             vp[VP_COLUMN_FRICTION_STIFFNESS_NM_PER_RAD])
    x[STEERING_WHEEL_RATE_RADPS] = rate
    x[STEERING_FRICTION_NM] = friction
    x[STEERING_WHEEL_ANGLE_RAD] = angle
    x[STEERING_PRIMED] = 1.0
    x[STEERING_WHEEL_TORQUE_NM] = t_d - vp[VP_COLUMN_DAMPING_NMS_PER_RAD] * rate - friction
