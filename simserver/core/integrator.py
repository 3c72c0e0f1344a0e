"""One fixed step of the whole vehicle: a list of stage calls.

Scheme: fourth-order Runge-Kutta in Lawson's exponential form for the slip states,
with the brakes as static friction resolved once per step.

Why this scheme (model.md section 6):

- Coupled with wheel spin, the longitudinal slip state makes a stiff, undamped oscillator
  at standstill (``w^2 = R^2 C_kappa / (I B)``, 150-300 rad/s on passenger tires, about
  950 rad/s with ``C_kappa = 200 kN`` and ``B = 0.02 m``). Explicit Euler diverges there;
  RK4's stability limit ``|lambda| h < 2.8`` covers it at ``h = 1 ms``.
- The tires' load-dependent coefficients (Magic Formula B, C, D, E, stiffnesses, peaks)
  are prepared once per step per wheel, at the load extrapolated to mid-step; every stage
  evaluates only the slip-dependent part, scaled by its own load (``core.tire``). Within
  1 ms the load moves by a fraction of a per cent (the suspension moves at 1-2 Hz).
- At speed the slip states relax at ``|u|/B``: 3500 1/s at 70 m/s with ``B = 0.02 m``,
  beyond RK4's limit. That part of the equation is linear in the state, so it is
  integrated exactly: with ``A = |u|/B`` frozen at the step start, ``y' = -A y + g(y)``
  is advanced by Lawson's RK4 (RK4 on ``e^{A t} y``), exact for the relaxation and
  fourth-order for the rest, with no step-size limit from the relaxation. Only the
  residual ``(A_0 - A(t)) y`` (the change of speed within one step) is explicit.
- Brakes at zero wheel speed are static friction, not a smoothed sign function (a
  tanh or viscous brake lets the car creep down a slope). Once per step, per wheel, the
  torque that would stop the wheel by the end of the step is computed; if the brake's
  capacity (plus the rolling-resistance moment, which acts the same way) covers it the
  wheel is held at exactly zero spin for the step and the brake supplies the reaction;
  otherwise the brake applies its full capacity toward stopping the wheel. A wheel
  whose spin crosses zero while braked is caught at zero.
- After the step the passive slip variant projects the states onto the sliding limit
  (``core.slip.project_to_sliding_limit``) and the paper's damping trigger and release
  are evaluated on the new hub velocities (``core.damping``).

The step allocates nothing: every scratch array lives in the workspace ``ws``
(``N_WORKSPACE`` floats, ``make_workspace``).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from simserver.core.chassis import (
    N_W,
    W_FX,
    W_HUB_U,
    W_KAPPA_SLIDE,
    W_MY,
    W_TAN_ALPHA_SLIDE,
    chassis_rhs,
    hub_velocity,
    wheel_inertia,
)
from simserver.core.damping import DAMPING_PAPER, paper_release, paper_trigger
from simserver.core.layout import (
    DAMPING_ACTIVE0,
    HUB_U_PREV0,
    IN_BRAKE,
    IN_PARKING_BRAKE,
    IN_STEER,
    IN_THROTTLE,
    KAPPA0,
    N_INTEGRATED,
    N_OUT,
    N_STATE,
    N_WHEELS,
    O_BRAKE_TORQUE0,
    O_KAPPA0,
    O_TAN_ALPHA0,
    OMEGA0,
    TAN_ALPHA0,
    TIME_S,
    WHEEL_HELD0,
)
from simserver.core.params import (
    VP_DAMPING_MODEL,
    VP_DAMPING_TRIGGER_V_MPS,
    VP_SLIDE_WIDEN_SPEED_MPS,
    VP_SLIP_MODEL,
    VP_STEERING_RATIO,
    VP_STEERING_WHEEL_MAX_RAD,
)
from simserver.core.powertrain import wheel_torques
from simserver.core.slip import (
    SLIP_KINEMATIC,
    SLIP_LAGGED_PASSIVE,
    project_to_sliding_limit,
)
from simserver.core.tire_layout import (
    N_TIRE_COEF,
    N_TIRE_OUT,
    TP_RADIUS_M,
    TP_RELAX_LAT_M,
    TP_RELAX_LONG_M,
)

# ---- workspace layout (offsets into ws)
_WS_Y2 = 0
_WS_Y3 = _WS_Y2 + N_STATE
_WS_Y4 = _WS_Y3 + N_STATE
_WS_K1 = _WS_Y4 + N_STATE
_WS_K2 = _WS_K1 + N_INTEGRATED
_WS_K3 = _WS_K2 + N_INTEGRATED
_WS_K4 = _WS_K3 + N_INTEGRATED
_WS_A = _WS_K4 + N_INTEGRATED  # frozen linear decay rates
_WS_E_HALF = _WS_A + N_INTEGRATED  # exp(-A h / 2), once per step
_WS_STEER = _WS_E_HALF + N_INTEGRATED
_WS_STEER_CS = _WS_STEER + N_WHEELS  # cos, then sin of the road-wheel angles
_WS_DRIVE = _WS_STEER_CS + 2 * N_WHEELS
_WS_BRAKE_CAP = _WS_DRIVE + N_WHEELS
_WS_BRAKE = _WS_BRAKE_CAP + N_WHEELS
_WS_HELD = _WS_BRAKE + N_WHEELS
_WS_WHEEL = _WS_HELD + N_WHEELS
_WS_TIRE = _WS_WHEEL + N_WHEELS * N_W
# Per wheel: the tire's load-dependent coefficients, prepared once per step at the load
# extrapolated to mid-step (Fz + (Fz - Fz_prev)/2: RK4's symmetric stage weights then keep
# the load coupling second order), followed by Fz_prev (-1: none yet).
_WS_COEF = _WS_TIRE + N_TIRE_OUT
N_WORKSPACE = _WS_COEF + N_WHEELS * (N_TIRE_COEF + 1)


def forget_tire_loads(ws: np.ndarray) -> None:
    """Forget the previous step's loads (a new run, a reset): no extrapolation next step."""
    for i in range(N_WHEELS):
        ws[_WS_COEF + (i + 1) * (N_TIRE_COEF + 1) - 1] = -1.0


def make_workspace() -> np.ndarray:
    """Allocate the scratch array ``step`` needs (once, before the loop)."""
    ws = np.zeros(N_WORKSPACE, dtype=np.float64)
    forget_tire_loads(ws)
    return ws


@nb.njit(cache=True)
def road_wheel_angles(vp: np.ndarray, steer_input: float, steer_rad: np.ndarray) -> None:
    """Steering-wheel position [-1, 1] to road-wheel angles (parallel steer, front axle)."""
    delta = steer_input * vp[VP_STEERING_WHEEL_MAX_RAD] / vp[VP_STEERING_RATIO]
    steer_rad[0] = delta
    steer_rad[1] = delta
    steer_rad[2] = 0.0
    steer_rad[3] = 0.0


@nb.njit(cache=True)
def resolve_brakes(
    x: np.ndarray,
    vp: np.ndarray,
    tp: np.ndarray,
    dt_s: float,
    drive_nm: np.ndarray,
    brake_cap_nm: np.ndarray,
    wheel: np.ndarray,
    brake_nm: np.ndarray,
    held: np.ndarray,
) -> None:
    """Static-friction brakes: hold a wheel at zero spin when the capacity allows it.

    For each wheel, the torque that brings its spin to zero by the end of the step is
    ``T_stop = -I Omega / dt - T_other`` with ``T_other = T_drive - R Fx``. If the
    brake capacity plus the rolling-resistance moment covers ``|T_stop|`` the wheel is
    held (spin set to zero; the brake supplies ``-T_other``); otherwise the brake applies
    its full capacity in the direction of ``T_stop``.
    """
    for i in range(N_WHEELS):
        inertia = wheel_inertia(vp, i)
        radius = tp[i, TP_RADIUS_M]
        t_other = drive_nm[i] - radius * wheel[i * N_W + W_FX]
        capacity = brake_cap_nm[i] + wheel[i * N_W + W_MY]
        t_stop = -inertia * x[OMEGA0 + i] / dt_s - t_other
        if abs(t_stop) <= capacity:
            held[i] = 1.0
            x[OMEGA0 + i] = 0.0
            brake_nm[i] = -t_other
        else:
            held[i] = 0.0
            brake_nm[i] = capacity if t_stop > 0.0 else -capacity


@nb.njit(cache=True)
def _copy_discrete(src: np.ndarray, dst: np.ndarray) -> None:
    for j in range(N_INTEGRATED, N_STATE):
        dst[j] = src[j]


@nb.njit(cache=True)
def step(
    x: np.ndarray,
    vp: np.ndarray,
    tp: np.ndarray,
    inputs: np.ndarray,
    dt_s: float,
    ws: np.ndarray,
    out: np.ndarray,
) -> None:
    """Advance the vehicle state ``x`` by ``dt_s`` in place.

    Parameters
    ----------
    x : float64[N_STATE]
        State, advanced in place.
    vp : float64[N_VEHICLE_PARAM]
        Vehicle parameters (``core.params``).
    tp : float64[4, N_TIRE_PARAM]
        Tire parameters per wheel (``core.tire``).
    inputs : float64[N_INPUT]
        Driver inputs (``core.layout.IN_*``), already validated and clamped.
    dt_s : float
        Step (s).
    ws : float64[N_WORKSPACE]
        Scratch (``make_workspace``).
    out : float64[N_OUT]
        Written: forces and accelerations at the state at the *start* of the step.
    """
    y2 = ws[_WS_Y2:_WS_Y2 + N_STATE]
    y3 = ws[_WS_Y3:_WS_Y3 + N_STATE]
    y4 = ws[_WS_Y4:_WS_Y4 + N_STATE]
    k1 = ws[_WS_K1:_WS_K1 + N_INTEGRATED]
    k2 = ws[_WS_K2:_WS_K2 + N_INTEGRATED]
    k3 = ws[_WS_K3:_WS_K3 + N_INTEGRATED]
    k4 = ws[_WS_K4:_WS_K4 + N_INTEGRATED]
    decay = ws[_WS_A:_WS_A + N_INTEGRATED]
    e_half = ws[_WS_E_HALF:_WS_E_HALF + N_INTEGRATED]
    steer = ws[_WS_STEER:_WS_STEER + N_WHEELS]
    steer_cs = ws[_WS_STEER_CS:_WS_STEER_CS + 2 * N_WHEELS]
    drive = ws[_WS_DRIVE:_WS_DRIVE + N_WHEELS]
    brake_cap = ws[_WS_BRAKE_CAP:_WS_BRAKE_CAP + N_WHEELS]
    brake = ws[_WS_BRAKE:_WS_BRAKE + N_WHEELS]
    held = ws[_WS_HELD:_WS_HELD + N_WHEELS]
    wheel = ws[_WS_WHEEL:_WS_WHEEL + N_WHEELS * N_W]
    tire_out = ws[_WS_TIRE:_WS_TIRE + N_TIRE_OUT]
    tire_coef = ws[_WS_COEF:_WS_COEF + N_WHEELS * (N_TIRE_COEF + 1)].reshape(
        (N_WHEELS, N_TIRE_COEF + 1))
    slip_model = int(vp[VP_SLIP_MODEL])
    h = dt_s

    # 1. inputs frozen over the step
    road_wheel_angles(vp, inputs[IN_STEER], steer)
    for i in range(N_WHEELS):
        steer_cs[i] = np.cos(steer[i])
        steer_cs[N_WHEELS + i] = np.sin(steer[i])
    wheel_torques(x, vp, inputs, drive, brake_cap)

    # 2. forces at the start state (free wheels), then the static-friction brakes
    for i in range(N_WHEELS):
        held[i] = 0.0
        brake[i] = 0.0
    chassis_rhs(x, vp, tp, steer, steer_cs, drive, brake, held, h, k1, wheel, tire_out, out, True,
                tire_coef, True)
    resolve_brakes(x, vp, tp, h, drive, brake_cap, wheel, brake, held)
    for i in range(N_WHEELS):  # only the spin rates depend on the brakes
        if held[i] > 0.5:
            k1[OMEGA0 + i] = 0.0
        else:
            k1[OMEGA0 + i] += brake[i] / wheel_inertia(vp, i)

    # 3. exponential (Lawson) RK4; decay rates |u|/b, |u|/B frozen at the start
    for j in range(N_INTEGRATED):
        decay[j] = 0.0
        e_half[j] = 1.0
    if slip_model != SLIP_KINEMATIC:
        for i in range(N_WHEELS):
            speed = abs(wheel[i * N_W + W_HUB_U])
            for j, length in ((TAN_ALPHA0 + i, tp[i, TP_RELAX_LAT_M]),
                              (KAPPA0 + i, tp[i, TP_RELAX_LONG_M])):
                decay[j] = speed / length
                e_half[j] = np.exp(-0.5 * h * decay[j])
    _copy_discrete(x, y2)
    _copy_discrete(x, y3)
    _copy_discrete(x, y4)
    for j in range(N_INTEGRATED):
        k1[j] += decay[j] * x[j]
        y2[j] = e_half[j] * (x[j] + 0.5 * h * k1[j])
    chassis_rhs(y2, vp, tp, steer, steer_cs, drive, brake, held, h, k2, wheel, tire_out, out, False,
                tire_coef, False)
    for j in range(N_INTEGRATED):
        k2[j] += decay[j] * y2[j]
        y3[j] = e_half[j] * x[j] + 0.5 * h * k2[j]
    chassis_rhs(y3, vp, tp, steer, steer_cs, drive, brake, held, h, k3, wheel, tire_out, out, False,
                tire_coef, False)
    for j in range(N_INTEGRATED):
        k3[j] += decay[j] * y3[j]
        y4[j] = e_half[j] * e_half[j] * x[j] + h * e_half[j] * k3[j]
    chassis_rhs(y4, vp, tp, steer, steer_cs, drive, brake, held, h, k4, wheel, tire_out, out, False,
                tire_coef, False)
    for i in range(N_WHEELS):
        y2[OMEGA0 + i] = x[OMEGA0 + i]  # keep the start spins for the zero-crossing test
    for j in range(N_INTEGRATED):
        k4[j] += decay[j] * y4[j]
        e_full = e_half[j] * e_half[j]
        x[j] = e_full * x[j] + h / 6.0 * (
            e_full * k1[j] + 2.0 * e_half[j] * (k2[j] + k3[j]) + k4[j]
        )

    # 4. brakes catch a wheel whose spin crossed zero; record the held flags
    for i in range(N_WHEELS):
        omega_start = y2[OMEGA0 + i]
        if held[i] > 0.5:
            x[OMEGA0 + i] = 0.0
        elif brake_cap[i] > 0.0 and omega_start * x[OMEGA0 + i] < 0.0:
            x[OMEGA0 + i] = 0.0
        x[WHEEL_HELD0 + i] = held[i]
        out[O_BRAKE_TORQUE0 + i] = brake[i]

    # 5. per-wheel discrete updates on the new hub velocities
    damping_paper = int(vp[VP_DAMPING_MODEL]) == DAMPING_PAPER
    release = paper_release(inputs[IN_BRAKE], inputs[IN_PARKING_BRAKE], inputs[IN_THROTTLE])
    for i in range(N_WHEELS):
        u_w, v_w = hub_velocity(x, vp, i, steer_cs[i], steer_cs[N_WHEELS + i])
        if slip_model == SLIP_LAGGED_PASSIVE:
            x[TAN_ALPHA0 + i], x[KAPPA0 + i] = project_to_sliding_limit(
                x[TAN_ALPHA0 + i], x[KAPPA0 + i],
                wheel[i * N_W + W_TAN_ALPHA_SLIDE], wheel[i * N_W + W_KAPPA_SLIDE],
                np.sqrt(u_w * u_w + v_w * v_w), vp[VP_SLIDE_WIDEN_SPEED_MPS],
            )
        elif slip_model == SLIP_KINEMATIC:
            # the slots carry the slip the tire saw, for output only
            x[TAN_ALPHA0 + i] = out[O_TAN_ALPHA0 + i]
            x[KAPPA0 + i] = out[O_KAPPA0 + i]
        if damping_paper:
            if release:
                x[DAMPING_ACTIVE0 + i] = 0.0
            elif paper_trigger(x[HUB_U_PREV0 + i], u_w, v_w, vp[VP_DAMPING_TRIGGER_V_MPS]):
                x[DAMPING_ACTIVE0 + i] = 1.0
        else:
            x[DAMPING_ACTIVE0 + i] = 0.0
        x[HUB_U_PREV0 + i] = u_w
    x[TIME_S] += h


@nb.njit(cache=True)
def simulate(
    x: np.ndarray,
    vp: np.ndarray,
    tp: np.ndarray,
    inputs_per_step: np.ndarray,
    dt_s: float,
    ws: np.ndarray,
    states: np.ndarray,
    outputs: np.ndarray,
    record_every: int,
) -> None:
    """Run ``len(inputs_per_step)`` steps, recording every ``record_every``-th one.

    Row ``k`` of ``states``/``outputs`` holds the state at the start of step
    ``k * record_every`` and the forces evaluated at it.
    """
    out = np.zeros(N_OUT)
    n = inputs_per_step.shape[0]
    row = 0
    for k in range(n):
        if k % record_every == 0:
            for j in range(N_STATE):
                states[row, j] = x[j]
        step(x, vp, tp, inputs_per_step[k], dt_s, ws, out)
        if k % record_every == 0:
            for j in range(N_OUT):
                outputs[row, j] = out[j]
            row += 1
