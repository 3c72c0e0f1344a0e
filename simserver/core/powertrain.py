"""Powertrain and brakes: driver pedals to wheel torques (docs/model.md section 13).

Two powertrains, chosen by the powertrain file's ``kind`` (``VP_POWERTRAIN_KIND``):

- **simple** (the default; the first release's): the throttle scales a drive torque at the
  wheels limited by a torque cap (first gear) and a power cap (``T <= P_max / |omega|``).
- **automatic**: an engine (full-load torque curve, drag torque, rotating inertia, an idle
  speed controller), a torque converter (capacity factor ``K`` and torque ratio as curves
  of the speed ratio, a lock-up clutch) and an automatic gearbox (a shift schedule by
  vehicle speed and throttle with hysteresis, kick-down). Its memory is state
  (``core.layout.ENGINE_SPEED_RADPS`` ...): engine speed, gear engaged, lock-up, the idle
  controller's integral, the time since the last shift.

Both take the selector P R N D from the driver's ``gear`` input. The driven axle has an
open differential: equal torque to its two wheels, whatever their speeds; with both axles
driven the split between them is fixed (a centre differential), and the gearbox output
turns at the same weighted mean of the driven wheels' spins (power balance of a lossless
differential). P locks the driven wheels (a brake of unlimited capacity on them).

The powertrain is evaluated once per step, at the state at its start, and its torques
are held over the step like the other inputs (``core.integrator.freeze_inputs``). The
engine speed is advanced by one explicit Euler step: its rate constants (the converter's
``dT/domega`` over the engine inertia, the idle controller's gain over it) are tens per
second, far below the 2000 1/s explicit Euler allows at 1 ms. With the lock-up closed the
engine turns with the turbine and its inertia is left out (the wheels' inertias carry a
driveline share, ``core.params`` ``wheel_inertia_*``); feeding the engine's inertia back
through the explicit step would be unstable in the low gears (``I_e G^2`` exceeds the
wheels' inertias).

Brakes: a capacity per wheel. The pedal's torque is split front/rear by
``brake_front_fraction``; the parking brake acts on the rear wheels. How the capacity is
applied (static friction at zero spin) is the integrator's job, see
``core.integrator.step``. Hill-start assist (``hill_hold``) keeps the pedal's pressure
after the driver releases it at rest on a grade.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from simserver.core.layout import (
    ENGINE_SPEED_RADPS,
    GEAR_D,
    GEAR_ENGAGED,
    GEAR_P,
    GEAR_R,
    HILL_HOLD_ACTIVE,
    HILL_HOLD_PEDAL,
    HILL_HOLD_TIME_S,
    IDLE_CONTROL_NM,
    IN_BRAKE,
    IN_GEAR,
    IN_PARKING_BRAKE,
    IN_THROTTLE,
    LOCKUP_ENGAGED,
    N_FRONT_WHEELS,
    N_WHEELS,
    O_GRAVITY_X_MPS2,
    OMEGA0,
    SHIFT_TIMER_S,
    U_MPS,
)
from simserver.core.params import (
    CONVERTER_CURVE_POINTS,
    DRIVEN_BOTH,
    DRIVEN_FRONT,
    ENGINE_CURVE_POINTS,
    POWERTRAIN_AUTOMATIC,
    VP_BRAKE_FRONT_FRACTION,
    VP_BRAKE_TORQUE_MAX_NM,
    VP_CONVERTER_K_FACTOR_RPM_PER_SQRT_NM,
    VP_CONVERTER_SPEED_RATIO,
    VP_CONVERTER_TORQUE_RATIO,
    VP_DOWNSHIFT_HYSTERESIS_MPS,
    VP_DRIVE_FRONT_FRACTION,
    VP_DRIVE_POWER_MAX_W,
    VP_DRIVE_TORQUE_MAX_NM,
    VP_DRIVEN_AXLE,
    VP_ENGINE_CURVE_SPEED_RPM,
    VP_ENGINE_DRAG_TORQUE_NM,
    VP_ENGINE_DRAG_TORQUE_PER_KRPM_NM,
    VP_ENGINE_FULL_LOAD_TORQUE_NM,
    VP_ENGINE_IDLE_SPEED_RPM,
    VP_ENGINE_INERTIA_KGM2,
    VP_ENGINE_SPEED_MAX_RPM,
    VP_FINAL_DRIVE_RATIO,
    VP_GEAR_COUNT,
    VP_GEAR_RATIOS,
    VP_GRAVITY_MPS2,
    VP_HILL_START_ASSIST,
    VP_HILL_START_ASSIST_HOLD_S,
    VP_HILL_START_ASSIST_MIN_GRADE_PCT,
    VP_IDLE_CONTROL_GAIN_NM_PER_RPM,
    VP_IDLE_CONTROL_INTEGRAL_TIME_S,
    VP_IDLE_CONTROL_TORQUE_MAX_NM,
    VP_KICKDOWN_THROTTLE,
    VP_LOCKUP_ENGAGE_SPEED_RPM,
    VP_LOCKUP_GEAR_MIN,
    VP_LOCKUP_RELEASE_SPEED_RPM,
    VP_MASS_KG,
    VP_PARKING_BRAKE_TORQUE_NM,
    VP_POWERTRAIN_KIND,
    VP_REVERSE_GEAR_RATIO,
    VP_REVERSE_TORQUE_MAX_NM,
    VP_SHIFT_DELAY_S,
    VP_UPSHIFT_SPEED_FULL_MPS,
    VP_UPSHIFT_SPEED_LIGHT_MPS,
)

PARK_LOCK_TORQUE_NM = 1.0e9
"""Capacity standing for the parking pawl: nothing a tire can do overcomes it."""
POWER_LIMIT_MIN_SPEED_RADPS = 1.0
"""Below this wheel speed the power cap is not applied (T_max governs at launch)."""
RADPS_PER_RPM = 2.0 * math.pi / 60.0
PUMP_SPEED_MIN_RADPS = 1.0
"""Floor of the pump speed in the converter's speed ratio (the idle controller keeps the
engine far above it; the floor only keeps the ratio finite)."""
LOCKUP_MIN_SPEED_RATIO = 0.85
"""The lock-up closes only once the converter is near coupling: the engine speed then
steps by at most 15 % to the turbine's (its inertia is left out while locked)."""
HILL_HOLD_PEDAL_ON = 0.05
"""Brake pedal above which the driver is braking (arms the hill-start assist at rest);
below it the pedal counts as released and the hold's timer runs."""
HILL_HOLD_REST_SPEED_MPS = 0.05
"""The car is at rest (the assist may arm) below this body speed."""


# ---------------------------------------------------------------- simple powertrain
@nb.njit(cache=True)
def axle_torque_shares(vp: np.ndarray, share: np.ndarray) -> None:
    """Fraction of the total drive torque each wheel receives (open differentials)."""
    axle = int(vp[VP_DRIVEN_AXLE])
    if axle == DRIVEN_FRONT:
        front = 1.0
    elif axle == DRIVEN_BOTH:
        front = vp[VP_DRIVE_FRONT_FRACTION]
    else:
        front = 0.0
    share[0] = share[1] = 0.5 * front
    share[2] = share[3] = 0.5 * (1.0 - front)


@nb.njit(cache=True)
def simple_drive_torque(x: np.ndarray, vp: np.ndarray, inputs: np.ndarray,
                        share: np.ndarray) -> float:
    """The simple powertrain's total drive torque at the wheels (N m, + forward)."""
    gear = int(inputs[IN_GEAR])
    throttle = inputs[IN_THROTTLE]
    # mean spin of the driven wheels sets the power limit
    omega_driven = 0.0
    for i in range(N_WHEELS):
        omega_driven += share[i] * x[OMEGA0 + i]
    torque_cap = vp[VP_DRIVE_TORQUE_MAX_NM]
    direction = 0.0
    if gear == GEAR_D:
        direction = 1.0
    elif gear == GEAR_R:
        direction = -1.0
        torque_cap = vp[VP_REVERSE_TORQUE_MAX_NM]
    if abs(omega_driven) > POWER_LIMIT_MIN_SPEED_RADPS:
        torque_cap = min(torque_cap, vp[VP_DRIVE_POWER_MAX_W] / abs(omega_driven))
    x[GEAR_ENGAGED] = direction
    x[ENGINE_SPEED_RADPS] = 0.0
    return direction * throttle * torque_cap


# ---------------------------------------------------------------- automatic: curves
@nb.njit(cache=True)
def interp_curve(vp: np.ndarray, xs_slot: int, ys_slot: int, n: int, s: float) -> float:
    """Piecewise-linear curve through the points ``(vp[xs_slot + k], vp[ys_slot + k])``,
    constant beyond its ends. A list padded with its last value (``core.param_table``)
    repeats its last point, never selected as a segment."""
    if s <= vp[xs_slot]:
        return vp[ys_slot]
    for k in range(n - 1):
        x1 = vp[xs_slot + k + 1]
        if s < x1:
            x0 = vp[xs_slot + k]
            y0 = vp[ys_slot + k]
            return y0 + (vp[ys_slot + k + 1] - y0) * (s - x0) / (x1 - x0)
    return vp[ys_slot + n - 1]


@nb.njit(cache=True)
def engine_drag_nm(vp: np.ndarray, omega_e: float) -> float:
    """Friction and pumping torque with the throttle closed (N m, >= 0)."""
    above_idle_rpm = max(omega_e / RADPS_PER_RPM - vp[VP_ENGINE_IDLE_SPEED_RPM], 0.0)
    return (vp[VP_ENGINE_DRAG_TORQUE_NM]
            + vp[VP_ENGINE_DRAG_TORQUE_PER_KRPM_NM] * above_idle_rpm / 1000.0)


@nb.njit(cache=True)
def engine_full_load_nm(vp: np.ndarray, omega_e: float) -> float:
    """Net torque at wide-open throttle (N m), zero above the fuel cut."""
    rpm = omega_e / RADPS_PER_RPM
    if rpm > vp[VP_ENGINE_SPEED_MAX_RPM]:
        return -engine_drag_nm(vp, omega_e)
    return interp_curve(vp, VP_ENGINE_CURVE_SPEED_RPM, VP_ENGINE_FULL_LOAD_TORQUE_NM,
                        ENGINE_CURVE_POINTS, rpm)


@nb.njit(cache=True)
def engine_torque_nm(x: np.ndarray, vp: np.ndarray, throttle: float, dt_s: float) -> float:
    """Net engine torque (N m) at the state's engine speed for the throttle, with the idle
    controller; advances the controller's integral (``x[IDLE_CONTROL_NM]``).

    ``T = max(throttle (T_full + T_drag), T_idle) - T_drag``: the throttle scales the
    indicated torque between closed (``-T_drag``) and wide open (``T_full``); the idle
    controller (PI on the speed below idle, output in [0, its authority], the integral
    clamped there too: no wind-up) opens it at least as far as idling needs.
    """
    omega_e = x[ENGINE_SPEED_RADPS]
    drag = engine_drag_nm(vp, omega_e)
    full = engine_full_load_nm(vp, omega_e)
    t_max = vp[VP_IDLE_CONTROL_TORQUE_MAX_NM]
    error_rpm = vp[VP_ENGINE_IDLE_SPEED_RPM] - omega_e / RADPS_PER_RPM
    proportional = vp[VP_IDLE_CONTROL_GAIN_NM_PER_RPM] * error_rpm
    integral = x[IDLE_CONTROL_NM] + proportional * dt_s / vp[VP_IDLE_CONTROL_INTEGRAL_TIME_S]
    integral = min(max(integral, 0.0), t_max)
    x[IDLE_CONTROL_NM] = integral
    idle = min(max(proportional + integral, 0.0), t_max)
    indicated = min(max(throttle * (full + drag), idle), full + drag)
    return indicated - drag


@nb.njit(cache=True)
def converter_torques(vp: np.ndarray, omega_p: float, omega_t: float) -> tuple[float, float]:
    """Pump and turbine torques of the converter (N m): ``T_p = (omega_p / K(SR))^2``,
    ``T_t = TR(SR) T_p`` with ``SR = omega_t / omega_p``.

    Above the curves' last point the capacity ``1/K^2`` falls linearly to zero at ``SR =
    1`` and the torque ratio to 1. Beyond 1 (overrun: the wheels drive the engine) the
    roles swap and the converter is a coupling: ``T_p = T_t = -omega_t^2 / K(1/SR)^2``.
    A turbine turning backwards (``SR < 0``) sees the stall point's values.
    """
    omega_p = max(omega_p, PUMP_SPEED_MIN_RADPS)
    sr = omega_t / omega_p
    overrun = sr > 1.0
    if overrun:
        sr = omega_p / max(omega_t, PUMP_SPEED_MIN_RADPS)
    sr = max(sr, 0.0)
    n = CONVERTER_CURVE_POINTS
    sr_last = vp[VP_CONVERTER_SPEED_RATIO + n - 1]
    k_radps = interp_curve(vp, VP_CONVERTER_SPEED_RATIO, VP_CONVERTER_K_FACTOR_RPM_PER_SQRT_NM,
                           n, sr) * RADPS_PER_RPM
    capacity = 1.0 / (k_radps * k_radps)
    ratio = interp_curve(vp, VP_CONVERTER_SPEED_RATIO, VP_CONVERTER_TORQUE_RATIO, n, sr)
    if sr > sr_last:
        fade = (1.0 - sr) / (1.0 - sr_last)
        capacity *= fade
        ratio = 1.0 + (ratio - 1.0) * fade
    if overrun:
        torque = capacity * omega_t * omega_t
        return -torque, -torque
    torque = capacity * omega_p * omega_p
    return torque, ratio * torque


@nb.njit(cache=True)
def overall_ratio(vp: np.ndarray, gear: int) -> float:
    """Engine-side speed per unit of the driven wheels' mean spin for a gear engaged
    (negative in reverse, 0 in none)."""
    if gear >= 1:
        return vp[VP_GEAR_RATIOS + gear - 1] * vp[VP_FINAL_DRIVE_RATIO]
    if gear == -1:
        return -vp[VP_REVERSE_GEAR_RATIO] * vp[VP_FINAL_DRIVE_RATIO]
    return 0.0


@nb.njit(cache=True)
def upshift_speed_mps(vp: np.ndarray, gear: int, schedule_throttle: float) -> float:
    """Vehicle speed of the upshift from ``gear`` to ``gear + 1`` (linear in throttle)."""
    light = vp[VP_UPSHIFT_SPEED_LIGHT_MPS + gear - 1]
    full = vp[VP_UPSHIFT_SPEED_FULL_MPS + gear - 1]
    return light + schedule_throttle * (full - light)


@nb.njit(cache=True)
def scheduled_gear(vp: np.ndarray, gear: int, speed_mps: float, throttle: float,
                   shift_allowed: bool) -> int:
    """The forward gear the schedule selects from ``gear`` (0: entering D, any gear may be
    chosen). One gear at a time, after the shift delay; kick-down may drop several at
    once at any time. A downshift waits until the speed is ``downshift_hysteresis_mps``
    below the upshift speed into the current gear."""
    n_gears = int(vp[VP_GEAR_COUNT])
    kickdown = throttle >= vp[VP_KICKDOWN_THROTTLE]
    schedule = 1.0 if kickdown else throttle / vp[VP_KICKDOWN_THROTTLE]
    hysteresis = vp[VP_DOWNSHIFT_HYSTERESIS_MPS]
    if gear <= 0:  # entering D: the gear for this speed
        gear = 1
        while gear < n_gears and speed_mps >= upshift_speed_mps(vp, gear, schedule):
            gear += 1
        return gear
    if not (shift_allowed or kickdown):
        return gear
    if gear < n_gears and speed_mps >= upshift_speed_mps(vp, gear, schedule):
        return gear + 1
    while gear > 1 and speed_mps < upshift_speed_mps(vp, gear - 1, schedule) - hysteresis:
        gear -= 1
        if not kickdown:
            break
    return gear


@nb.njit(cache=True)
def automatic_drive_torque(x: np.ndarray, vp: np.ndarray, inputs: np.ndarray,
                           share: np.ndarray, dt_s: float) -> float:
    """The automatic powertrain's total drive torque at the wheels (N m, + forward);
    advances its states by one step (module docstring)."""
    selector = int(inputs[IN_GEAR])
    throttle = inputs[IN_THROTTLE]
    gear = int(x[GEAR_ENGAGED])
    x[SHIFT_TIMER_S] += dt_s
    if selector == GEAR_D:
        new_gear = scheduled_gear(vp, gear, x[U_MPS], throttle,
                                  x[SHIFT_TIMER_S] >= vp[VP_SHIFT_DELAY_S])
    elif selector == GEAR_R:
        new_gear = -1
    else:
        new_gear = 0
    if new_gear != gear:
        gear = new_gear
        x[GEAR_ENGAGED] = gear
        x[SHIFT_TIMER_S] = 0.0
        x[LOCKUP_ENGAGED] = 0.0
    ratio = overall_ratio(vp, gear)
    omega_carrier = 0.0
    for i in range(N_WHEELS):
        omega_carrier += share[i] * x[OMEGA0 + i]
    omega_t = ratio * omega_carrier
    omega_e = x[ENGINE_SPEED_RADPS]

    # lock-up clutch: closes above its speed, near coupling, after the shift delay
    kickdown = throttle >= vp[VP_KICKDOWN_THROTTLE]
    lockup_allowed = (gear >= vp[VP_LOCKUP_GEAR_MIN] and not kickdown
                      and x[SHIFT_TIMER_S] >= vp[VP_SHIFT_DELAY_S])
    if x[LOCKUP_ENGAGED] > 0.5:
        if not lockup_allowed or omega_t < vp[VP_LOCKUP_RELEASE_SPEED_RPM] * RADPS_PER_RPM:
            x[LOCKUP_ENGAGED] = 0.0
    elif (lockup_allowed and omega_t >= vp[VP_LOCKUP_ENGAGE_SPEED_RPM] * RADPS_PER_RPM
          and omega_t >= LOCKUP_MIN_SPEED_RATIO * omega_e):
        x[LOCKUP_ENGAGED] = 1.0
    locked = x[LOCKUP_ENGAGED] > 0.5
    if locked:
        x[ENGINE_SPEED_RADPS] = omega_t

    t_engine = engine_torque_nm(x, vp, throttle, dt_s)
    if locked:
        return ratio * t_engine
    if gear == 0:
        t_pump, t_turbine = 0.0, 0.0
    else:
        t_pump, t_turbine = converter_torques(vp, x[ENGINE_SPEED_RADPS], omega_t)
    x[ENGINE_SPEED_RADPS] += dt_s * (t_engine - t_pump) / vp[VP_ENGINE_INERTIA_KGM2]
    return ratio * t_turbine


# ---------------------------------------------------------------- hill-start assist
@nb.njit(cache=True, inline="always")
def hill_opposes(vp: np.ndarray, direction: float, grade_pull: float) -> bool:
    """The grade pulls against the selected direction (``direction`` +1 D, -1 R, 0 none)
    by more than the assist's minimum grade. Only asked with the assist on."""
    g = vp[VP_GRAVITY_MPS2]
    slope = vp[VP_HILL_START_ASSIST_MIN_GRADE_PCT] / 100.0
    return direction != 0.0 and grade_pull > g * slope / math.sqrt(1.0 + slope * slope)


@nb.njit(cache=True)
def hill_hold(x: np.ndarray, vp: np.ndarray, inputs: np.ndarray, gravity_x_mps2: float,
              drive_force_n: float, dt_s: float) -> float:
    """Hill-start assist: the brake pedal to apply this step (>= the driver's).

    Armed when the car is at rest in D or R with the pedal on, on a grade steeper than
    ``hill_start_assist_min_grade_pct`` that pulls against the selected direction; it keeps
    the highest pedal of the stop (``x[HILL_HOLD_PEDAL]``). When the driver lets the pedal
    off, the kept pedal holds the car until the drive force along the selected direction
    overcomes the grade's pull, or for ``hill_start_assist_hold_s`` after the pedal fell
    below ``HILL_HOLD_PEDAL_ON``. ``gravity_x_mps2``: gravity along body x at the last
    step (``out[O_GRAVITY_X_MPS2]``); ``drive_force_n``: the drive torques over the tire
    radii, + forward.
    """
    pedal = inputs[IN_BRAKE]
    x[HILL_HOLD_ACTIVE] = 0.0
    gear = int(inputs[IN_GEAR])
    direction = 1.0 if gear == GEAR_D else (-1.0 if gear == GEAR_R else 0.0)
    grade_pull = -direction * gravity_x_mps2  # gravity against the selected direction
    if vp[VP_HILL_START_ASSIST] < 0.5 or not hill_opposes(vp, direction, grade_pull):
        x[HILL_HOLD_PEDAL] = 0.0
        x[HILL_HOLD_TIME_S] = 0.0
        return pedal
    kept = x[HILL_HOLD_PEDAL]
    if kept <= 0.0:  # not armed: arm at rest with the pedal on
        if abs(x[U_MPS]) < HILL_HOLD_REST_SPEED_MPS and pedal >= HILL_HOLD_PEDAL_ON:
            x[HILL_HOLD_PEDAL] = pedal
        return pedal
    if pedal >= kept:  # the driver brakes at least as hard: the pedal governs
        x[HILL_HOLD_PEDAL] = pedal
        x[HILL_HOLD_TIME_S] = 0.0
        return pedal
    if pedal < HILL_HOLD_PEDAL_ON:
        x[HILL_HOLD_TIME_S] += dt_s
    grade_force_n = vp[VP_MASS_KG] * grade_pull
    if (x[HILL_HOLD_TIME_S] >= vp[VP_HILL_START_ASSIST_HOLD_S]
            or direction * drive_force_n >= grade_force_n):
        x[HILL_HOLD_PEDAL] = 0.0
        x[HILL_HOLD_TIME_S] = 0.0
        return pedal
    x[HILL_HOLD_ACTIVE] = 1.0
    return kept


# ---------------------------------------------------------------- the stage
# Inlined into the step (its stage 1, core.integrator.freeze_inputs): called, it took
# eight arrays, each passed as seven words, about 60 instructions a step before its own
# work (the callees stay compiled on their own)
@nb.njit(cache=True, inline="always")
def wheel_torques(
    x: np.ndarray,
    vp: np.ndarray,
    inputs: np.ndarray,
    out: np.ndarray,
    radius_m: np.ndarray,
    dt_s: float,
    drive_nm: np.ndarray,
    brake_cap_nm: np.ndarray,
) -> None:
    """Drive torque and brake capacity per wheel for the current pedals, gear and spin;
    advances the powertrain's and the hill-start assist's states by one step.

    ``drive_nm`` is signed (positive drives forward); ``brake_cap_nm`` is a magnitude.
    ``out``: the outputs of the last step (the grade the assist sees); ``radius_m``: the
    tires' rolling radii (``tp[:, TP_RADIUS_M]``).
    """
    axle_torque_shares(vp, drive_nm)  # shares first, scaled below
    if int(vp[VP_POWERTRAIN_KIND]) == POWERTRAIN_AUTOMATIC:
        total = automatic_drive_torque(x, vp, inputs, drive_nm, dt_s)
    else:
        total = simple_drive_torque(x, vp, inputs, drive_nm)
    gear = int(inputs[IN_GEAR])
    drive_force_n = 0.0
    if x[HILL_HOLD_PEDAL] > 0.0:  # hill_hold reads the drive force only with a kept pedal
        for i in range(N_WHEELS):
            drive_force_n += total * drive_nm[i] / radius_m[i]
    pedal = hill_hold(x, vp, inputs, out[O_GRAVITY_X_MPS2], drive_force_n, dt_s)

    brake_total = pedal * vp[VP_BRAKE_TORQUE_MAX_NM]
    front = vp[VP_BRAKE_FRONT_FRACTION]
    park = inputs[IN_PARKING_BRAKE] * vp[VP_PARKING_BRAKE_TORQUE_NM]
    for i in range(N_WHEELS):
        share = drive_nm[i]
        drive_nm[i] = total * share
        if i < N_FRONT_WHEELS:
            brake_cap_nm[i] = 0.5 * front * brake_total
        else:
            brake_cap_nm[i] = 0.5 * (1.0 - front) * brake_total + park
        if gear == GEAR_P and share > 0.0:
            brake_cap_nm[i] = PARK_LOCK_TORQUE_NM


def creep_torque_at_stall_nm(vp: np.ndarray) -> float:
    """The automatic's drive torque at the wheels at rest in D with the engine idling:
    first gear times the converter's stall torque ratio times its stall torque at idle,
    ``G_1 TR(0) (omega_idle / K(0))^2`` (0 on the simple powertrain, which has no creep)."""
    if int(vp[VP_POWERTRAIN_KIND]) != POWERTRAIN_AUTOMATIC:
        return 0.0
    k0 = vp[VP_CONVERTER_K_FACTOR_RPM_PER_SQRT_NM] * RADPS_PER_RPM
    idle = vp[VP_ENGINE_IDLE_SPEED_RPM] * RADPS_PER_RPM
    return float(overall_ratio(vp, 1) * vp[VP_CONVERTER_TORQUE_RATIO] * (idle / k0) ** 2)


def creep_hold_brake_pedal(vp: np.ndarray) -> float:
    """The brake pedal above which the car stays at rest in D on the flat: its brake
    torque (all four wheels) equals the creep torque at stall (docs/model.md section 13)."""
    return creep_torque_at_stall_nm(vp) / vp[VP_BRAKE_TORQUE_MAX_NM]
