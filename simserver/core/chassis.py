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
- Gravity is resolved from the road plane into body axes with the heading (``core.params.
  set_road``), so grade and cross-slope work at any heading.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from simserver.core.damping import (
    DAMPING_PAPER,
    DAMPING_PATCH,
    damping_coefficients,
    low_speed_fade,
)
from simserver.core.layout import (
    DAMPING_ACTIVE0,
    HEAVE_M,
    HEAVE_RATE_MPS,
    KAPPA0,
    N_WHEELS,
    O_AX_MPS2,
    O_AY_MPS2,
    O_BRAKE_TORQUE0,
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
    ROLL_RAD,
    ROLL_RATE_RADPS,
    TAN_ALPHA0,
    U_MPS,
    V_MPS,
    X_M,
    Y_M,
    YAW_RAD,
    YAW_RATE_RADPS,
)
from simserver.core.params import (
    VP_AIR_DENSITY_KGPM3,
    VP_ANTIROLL_FRONT_NPM,
    VP_ANTIROLL_REAR_NPM,
    VP_CG_HEIGHT_M,
    VP_CG_TO_FRONT_AXLE_M,
    VP_CG_TO_REAR_AXLE_M,
    VP_DAMPER_FRONT_NSPM,
    VP_DAMPER_REAR_NSPM,
    VP_DAMPING_FADE_SPEED_MPS,
    VP_DAMPING_MODEL,
    VP_DAMPING_RATIO,
    VP_DRAG_AREA_M2,
    VP_GRAVITY_E1_MPS2,
    VP_GRAVITY_E2_MPS2,
    VP_GRAVITY_MPS2,
    VP_GRAVITY_N_MPS2,
    VP_KINEMATIC_U_MIN_MPS,
    VP_MASS_KG,
    VP_PITCH_INERTIA_KGM2,
    VP_ROAD_FRICTION_SCALE,
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
from simserver.core.slip import SLIP_KINEMATIC, kinematic_slip, lagged_slip_rates
from simserver.core.tire import tire_evaluate, tire_prepare
from simserver.core.tire_layout import (
    N_TIRE_COEF,
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
    TP_RADIUS_M,
    TP_RELAX_LAT_M,
    TP_RELAX_LONG_M,
)

# per-wheel scratch written by chassis_rhs for the integrator (wheel-major, W_* slots)
W_FX = 0  # tire Fx incl. damping (N)
W_MY = 1  # rolling-resistance moment magnitude (N m)
W_KAPPA_SLIDE = 2
W_TAN_ALPHA_SLIDE = 3
W_HUB_U = 4
W_HUB_V = 5
N_W = 6


@nb.njit(cache=True)
def wheel_position(vp: np.ndarray, i: int) -> tuple[float, float]:
    """Contact-point position (x, y) of wheel ``i`` relative to the CG in body axes (m)."""
    if i < 2:
        return vp[VP_CG_TO_FRONT_AXLE_M], (0.5 if i == 0 else -0.5) * vp[VP_TRACK_FRONT_M]
    return -vp[VP_CG_TO_REAR_AXLE_M], (0.5 if i == 2 else -0.5) * vp[VP_TRACK_REAR_M]


@nb.njit(cache=True)
def wheel_inertia(vp: np.ndarray, i: int) -> float:
    """Spin inertia of wheel ``i`` (kg m^2)."""
    return vp[VP_WHEEL_INERTIA_FRONT_KGM2] if i < 2 else vp[VP_WHEEL_INERTIA_REAR_KGM2]


@nb.njit(cache=True)
def static_wheel_load(vp: np.ndarray, i: int) -> float:
    """Static normal load of wheel ``i`` on the road plane (N)."""
    a = vp[VP_CG_TO_FRONT_AXLE_M]
    b = vp[VP_CG_TO_REAR_AXLE_M]
    weight_n = vp[VP_MASS_KG] * vp[VP_GRAVITY_N_MPS2]
    if i < 2:
        return 0.5 * weight_n * b / (a + b)
    return 0.5 * weight_n * a / (a + b)


@nb.njit(cache=True)
def hub_velocity(
    x: np.ndarray, vp: np.ndarray, i: int, cos_steer: float, sin_steer: float
) -> tuple[float, float]:
    """Hub velocity of wheel ``i`` in its own heading frame (u along the wheel, v left),
    given the cosine and sine of its road-wheel angle."""
    px, py = wheel_position(vp, i)
    r = x[YAW_RATE_RADPS]
    u_c = x[U_MPS] - r * py
    v_c = x[V_MPS] + r * px
    return cos_steer * u_c + sin_steer * v_c, -sin_steer * u_c + cos_steer * v_c


@nb.njit(cache=True)
def chassis_rhs(
    x: np.ndarray,
    vp: np.ndarray,
    tp: np.ndarray,
    steer_rad: np.ndarray,
    steer_cs: np.ndarray,
    drive_nm: np.ndarray,
    brake_nm: np.ndarray,
    held: np.ndarray,
    dt_s: float,
    dx: np.ndarray,
    wheel: np.ndarray,
    tire_out: np.ndarray,
    out: np.ndarray,
    record: bool,
    tire_coef: np.ndarray,
    prepare_tires: bool,
) -> None:
    """Time derivatives of the integrated states.

    Parameters
    ----------
    x : float64[N_STATE]
        State (the discrete slots are read, not differentiated).
    vp : float64[N_VEHICLE_PARAM]
        Vehicle parameters.
    tp : float64[4, N_TIRE_PARAM]
        Tire parameters per wheel.
    steer_rad, drive_nm, brake_nm, held : float64[4]
        Road-wheel angles, drive torques, applied brake torques (signed, incl. rolling
        resistance) and held flags (1 = wheel held at zero spin by its brake), frozen over
        the step by the integrator.
    steer_cs : float64[8]
        Cosines then sines of the road-wheel angles (computed once per step).
    dt_s : float
        The step, used only to limit the patch damping to what the step resolves.
    dx : float64[N_INTEGRATED]
        Written: the derivatives.
    wheel : float64[4 * N_W]
        Written: per-wheel quantities the integrator needs (``W_*`` slots).
    tire_out : float64[N_TIRE_OUT]
        Scratch.
    out : float64[N_OUT]
        Written when ``record`` is true (``O_*`` slots).
    record : bool
        Fill ``out``.
    """
    mass = vp[VP_MASS_KG]
    sprung = vp[VP_SPRUNG_MASS_KG]
    h_cg = vp[VP_CG_HEIGHT_M]
    g = vp[VP_GRAVITY_MPS2]
    g_n = vp[VP_GRAVITY_N_MPS2]
    mu = vp[VP_ROAD_FRICTION_SCALE]
    slip_model = int(vp[VP_SLIP_MODEL])
    damping_model = int(vp[VP_DAMPING_MODEL])
    zeta = vp[VP_DAMPING_RATIO]

    yaw = x[YAW_RAD]
    cos_yaw = np.cos(yaw)
    sin_yaw = np.sin(yaw)
    g_x = vp[VP_GRAVITY_E1_MPS2] * cos_yaw + vp[VP_GRAVITY_E2_MPS2] * sin_yaw
    g_y = -vp[VP_GRAVITY_E1_MPS2] * sin_yaw + vp[VP_GRAVITY_E2_MPS2] * cos_yaw
    u = x[U_MPS]
    v = x[V_MPS]
    r = x[YAW_RATE_RADPS]
    heave = x[HEAVE_M]
    heave_rate = x[HEAVE_RATE_MPS]
    roll = x[ROLL_RAD]
    roll_rate = x[ROLL_RATE_RADPS]
    pitch = x[PITCH_RAD]
    pitch_rate = x[PITCH_RATE_RADPS]

    fx_sum = 0.0
    fy_sum = 0.0
    mz_sum = 0.0
    heave_force = 0.0
    roll_moment = 0.0
    pitch_moment = 0.0

    for axle in range(2):
        left = 2 * axle
        px, py_left = wheel_position(vp, left)
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
        arb = k_arb * (comp_l - comp_r)
        static = static_wheel_load(vp, left)
        for side in range(2):
            i = left + side
            if side == 0:
                f_susp = k_s * comp_l + c_s * rate_l + arb
                py = py_left
            else:
                f_susp = k_s * comp_r + c_s * rate_r - arb
                py = -py_left
            fz = max(0.0, static + f_susp)
            dyn = fz - static  # what the corner pushes onto the body beyond static
            heave_force += dyn
            roll_moment += py * dyn
            pitch_moment -= px * dyn

            # ---- tire
            c_d = steer_cs[i]
            s_d = steer_cs[N_WHEELS + i]
            u_w, v_w = hub_velocity(x, vp, i, c_d, s_d)
            radius = tp[i, TP_RADIUS_M]
            relax_lat = tp[i, TP_RELAX_LAT_M]
            relax_long = tp[i, TP_RELAX_LONG_M]
            omega = x[OMEGA0 + i]
            if slip_model == SLIP_KINEMATIC:
                tan_alpha, kappa = kinematic_slip(
                    u_w, v_w, omega, radius, vp[VP_KINEMATIC_U_MIN_MPS]
                )
                d_tan_alpha = 0.0
                d_kappa = 0.0
            else:
                tan_alpha = x[TAN_ALPHA0 + i]
                kappa = x[KAPPA0 + i]
                d_tan_alpha, d_kappa = lagged_slip_rates(
                    tan_alpha, kappa, u_w, v_w, omega, radius, relax_lat, relax_long
                )
            if prepare_tires:
                fz_prev = tire_coef[i, N_TIRE_COEF]
                fz_pred = fz + 0.5 * (fz - fz_prev) if fz_prev >= 0.0 else fz
                tire_prepare(tp[i], 0.0, fz_pred, mu, tire_coef[i])
                tire_coef[i, N_TIRE_COEF] = fz
            tire_evaluate(tp[i], tire_coef[i], kappa, tan_alpha, fz, u_w, tire_out)
            fx = tire_out[OUT_FX]
            fy = tire_out[OUT_FY]

            # ---- auxiliary low-speed damping (paper Appendix A, core.damping)
            damp_x = 0.0
            damp_y = 0.0
            if damping_model == DAMPING_PAPER and x[DAMPING_ACTIVE0 + i] > 0.5:
                c_x, c_y = damping_coefficients(
                    fz, tire_out[OUT_C_KAPPA], tire_out[OUT_C_ALPHA], relax_long, relax_lat,
                    zeta, g,
                )
                damp_x = -c_x * u_w
                damp_y = -c_y * v_w
            elif damping_model == DAMPING_PATCH and slip_model != SLIP_KINEMATIC:
                fade = low_speed_fade(np.sqrt(u_w * u_w + v_w * v_w),
                                      vp[VP_DAMPING_FADE_SPEED_MPS])
                if fade > 0.0:
                    c_x, c_y = damping_coefficients(
                        fz, tire_out[OUT_C_KAPPA], tire_out[OUT_C_ALPHA], relax_long,
                        relax_lat, zeta, g,
                    )
                    # The damper also loads the wheel's spin: c R^2 / I is its rate there.
                    # Beyond 2/dt it is faster than the step can resolve (and than any
                    # physical carcass damping); cap it so the explicit stages stay stable.
                    c_x = min(c_x, 2.0 * wheel_inertia(vp, i) / (radius * radius * dt_s))
                    damp_x = fade * c_x * relax_long * d_kappa
                    damp_y = -fade * c_y * relax_lat * d_tan_alpha
                    # a damper in series with sliding cannot push beyond the friction limit
                    lim_x = max(tire_out[OUT_FX_PEAK], abs(fx))
                    lim_y = max(tire_out[OUT_FY_PEAK], abs(fy))
                    damp_x = min(max(fx + damp_x, -lim_x), lim_x) - fx
                    damp_y = min(max(fy + damp_y, -lim_y), lim_y) - fy
            fx += damp_x
            fy += damp_y

            # ---- wheel spin
            if held[i] > 0.5:
                d_omega = 0.0
            else:
                d_omega = (drive_nm[i] - radius * fx + brake_nm[i]) / wheel_inertia(vp, i)
            dx[OMEGA0 + i] = d_omega
            dx[TAN_ALPHA0 + i] = d_tan_alpha
            dx[KAPPA0 + i] = d_kappa

            # ---- into body axes
            fx_body = c_d * fx - s_d * fy
            fy_body = s_d * fx + c_d * fy
            fx_sum += fx_body
            fy_sum += fy_body
            mz_sum += px * fy_body - py * fx_body + tire_out[OUT_MZ]

            base = i * N_W
            wheel[base + W_FX] = fx
            wheel[base + W_MY] = tire_out[OUT_MY]
            wheel[base + W_KAPPA_SLIDE] = tire_out[OUT_KAPPA_SLIDE]
            wheel[base + W_TAN_ALPHA_SLIDE] = tire_out[OUT_TAN_ALPHA_SLIDE]
            wheel[base + W_HUB_U] = u_w
            wheel[base + W_HUB_V] = v_w

            if record:
                out[O_FX0 + i] = fx
                out[O_FY0 + i] = fy
                out[O_FZ0 + i] = fz
                out[O_MZ0 + i] = tire_out[OUT_MZ]
                out[O_HUB_U0 + i] = u_w
                out[O_HUB_V0 + i] = v_w
                out[O_STEER0 + i] = steer_rad[i]
                out[O_DRIVE_TORQUE0 + i] = drive_nm[i]
                out[O_BRAKE_TORQUE0 + i] = brake_nm[i]
                fx_avail = max(tire_out[OUT_FX_PEAK], 1e-9)
                fy_avail = max(tire_out[OUT_FY_PEAK], 1e-9)
                out[O_FRICTION_USE0 + i] = np.sqrt((fx / fx_avail) ** 2 + (fy / fy_avail) ** 2)
                out[O_DAMPING_FX0 + i] = damp_x
                out[O_DAMPING_FY0 + i] = damp_y
                out[O_KAPPA0 + i] = kappa
                out[O_TAN_ALPHA0 + i] = tan_alpha

    drag = 0.5 * vp[VP_AIR_DENSITY_KGPM3] * vp[VP_DRAG_AREA_M2] * u * abs(u)
    force_x = fx_sum + mass * g_x - drag
    force_y = fy_sum + mass * g_y
    ax = force_x / mass
    ay = force_y / mass
    yaw_acc = mz_sum / vp[VP_YAW_INERTIA_KGM2]

    dx[X_M] = u * cos_yaw - v * sin_yaw
    dx[Y_M] = u * sin_yaw + v * cos_yaw
    dx[YAW_RAD] = r
    dx[U_MPS] = ax + v * r
    dx[V_MPS] = ay - u * r
    dx[YAW_RATE_RADPS] = yaw_acc
    dx[HEAVE_M] = heave_rate
    dx[HEAVE_RATE_MPS] = heave_force / sprung
    dx[ROLL_RAD] = roll_rate
    dx[ROLL_RATE_RADPS] = (
        roll_moment + h_cg * fy_sum + sprung * g_n * h_cg * roll
    ) / vp[VP_ROLL_INERTIA_KGM2]
    dx[PITCH_RAD] = pitch_rate
    dx[PITCH_RATE_RADPS] = (
        pitch_moment - h_cg * fx_sum + sprung * g_n * h_cg * pitch
    ) / vp[VP_PITCH_INERTIA_KGM2]

    if record:
        out[O_AX_MPS2] = ax
        out[O_AY_MPS2] = ay
        out[O_YAW_ACC_RADPS2] = yaw_acc
        out[O_GRAVITY_X_MPS2] = g_x
        out[O_GRAVITY_Y_MPS2] = g_y
        out[O_FX_BODY_SUM_N] = fx_sum
        out[O_FY_BODY_SUM_N] = fy_sum
