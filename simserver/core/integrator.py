"""One fixed step of the whole vehicle: a list of stage calls.

Scheme: fourth-order Runge-Kutta in Lawson's exponential form for the slip states,
with the brakes as static friction resolved once per step.

Why this scheme (docs/model.md section 6):

- Coupled with wheel spin, the longitudinal slip state makes a stiff, undamped oscillator
  at standstill (``w^2 = R^2 C_kappa / (I B)``, 150-300 rad/s on passenger tires, about
  950 rad/s with ``C_kappa = 200 kN`` and ``B = 0.02 m``). Explicit Euler diverges there;
  RK4's stability limit ``|lambda| h < 2.8`` covers it at ``h = 1 ms``.
- The tires' load-dependent coefficients (Magic Formula B, C, D, E, stiffnesses, peaks)
  are prepared once per step per wheel, at the load extrapolated to mid-step; every stage
  evaluates only the slip-dependent part, scaled by its own load (``core.tire``). Within
  1 ms the load moves by a fraction of a per cent (the suspension moves at 1-2 Hz). The
  start-of-step loads of the previous step are state (``FZ_PREV``), not scratch.
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

The step is a list of named stages on the static model and the mutable data
(``core.model``). It allocates nothing: every scratch array lives in the workspace
(``core.model.make_workspace``).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from simserver.core.chassis import (
    corner_loads,
    follow_terrain,
    forces_and_rates,
    hub_velocity,
    record_contacts,
    record_outputs,
    wheel_camber,
    wheel_inertia,
    wheel_position,
)
from simserver.core.damping import (
    DAMPING_OFF,
    DAMPING_PAPER,
    DAMPING_PATCH,
    paper_release,
    paper_trigger,
)
from simserver.core.layout import (
    DAMPING_ACTIVE0,
    FZ_PREV0,
    HUB_U_PREV0,
    IN_BRAKE,
    IN_PARKING_BRAKE,
    IN_STEER,
    IN_THROTTLE,
    KAPPA0,
    N_FRONT_WHEELS,
    N_INTEGRATED,
    N_OUT,
    N_STATE,
    N_WHEELS,
    O_BRAKE_TORQUE0,
    O_KAPPA0,
    O_TAN_ALPHA0,
    OMEGA0,
    STEP_JIT_OPTIONS,
    TAN_ALPHA0,
    TIME_S,
    WHEEL_HELD0,
    WHEELS_PER_AXLE,
)
from simserver.core.model import (
    D_COLUMN_RATE_BLEND,
    D_DRAG_NS2PM2,
    D_KINGPIN_LIFT_ARM0,
    D_SPIN_DAMPING_CAP0,
    D_WHEEL_X0,
    D_WHEEL_Y0,
    G_MU0,
    N_DERIVED,
    RK_DECAY,
    RK_E_HALF,
    RK_K1,
    RK_K2,
    RK_K3,
    RK_K4,
    RK_SPIN0,
    RK_Y,
    W_FX,
    W_FZ,
    W_HUB_U,
    W_KAPPA_SLIDE,
    W_MY,
    W_TAN_ALPHA_SLIDE,
    WI_BRAKE_CAP_NM,
    WI_BRAKE_NM,
    WI_CAMBER_RAD,
    WI_COS_STEER,
    WI_DRIVE_NM,
    WI_HELD,
    WI_SIN_STEER,
    WI_STEER_RAD,
    Data,
    Model,
)
from simserver.core.params import (
    VP_AIR_DENSITY_KGPM3,
    VP_DAMPING_MODEL,
    VP_DAMPING_TRIGGER_V_MPS,
    VP_DRAG_AREA_M2,
    VP_SLIDE_WIDEN_SPEED_MPS,
    VP_SLIP_MODEL,
    VP_STEERING_RATIO,
    VP_STEERING_WHEEL_MAX_RAD,
    VP_TOE_FRONT_RAD,
    VP_TOE_REAR_RAD,
)
from simserver.core.powertrain import wheel_torques
from simserver.core.slip import (
    SLIP_KINEMATIC,
    SLIP_LAGGED_PAPER,
    SLIP_LAGGED_PASSIVE,
    project_to_sliding_limit,
    sliding_ratio_squared,
)
from simserver.core.steering import column_rate_blend, kingpin_lift_arm_m, steering_system
from simserver.core.tire import tire_prepare
from simserver.core.tire_layout import TP_RADIUS_M, TP_RELAX_LAT_M, TP_RELAX_LONG_M

# The integrated states that decay (Lawson's exponential factor): the lagged slip states,
# the last block of the integrated slots; every slot below DECAYING0 has decay 0
DECAYING0 = TAN_ALPHA0
if not (KAPPA0 == TAN_ALPHA0 + N_WHEELS and KAPPA0 + N_WHEELS == N_INTEGRATED):
    raise ImportError("core.integrator.DECAYING0: the slip states are not the last block")


@nb.njit(cache=True)
def derive_constants(vp: np.ndarray, tp: np.ndarray, dt_s: float) -> np.ndarray:
    """The model's derived constants (``core.model.D_*``), once when it is built: what the
    stages computed from the parameters in every step or stage, by the same expressions
    (the same bits)."""
    derived = np.zeros(N_DERIVED)
    for i in range(N_WHEELS):
        derived[D_WHEEL_X0 + i], derived[D_WHEEL_Y0 + i] = wheel_position(vp, i)
        radius = tp[i, TP_RADIUS_M]
        derived[D_SPIN_DAMPING_CAP0 + i] = 2.0 * wheel_inertia(vp, i) / (radius * radius * dt_s)
    for i in range(N_FRONT_WHEELS):
        derived[D_KINGPIN_LIFT_ARM0 + i] = kingpin_lift_arm_m(vp, tp[i, TP_RADIUS_M])
    derived[D_COLUMN_RATE_BLEND] = column_rate_blend(vp, dt_s)
    derived[D_DRAG_NS2PM2] = 0.5 * vp[VP_AIR_DENSITY_KGPM3] * vp[VP_DRAG_AREA_M2]
    return derived


@nb.njit(cache=True)
def road_wheel_angles(vp: np.ndarray, steer_input: float, wheel_in: np.ndarray) -> None:
    """Steering-wheel position [-1, 1] to road-wheel angles (parallel steer, front axle),
    plus each axle's static toe (toe-in steers the left wheel right and the right wheel
    left; no toe: the angles are exactly the steer)."""
    delta = steer_input * vp[VP_STEERING_WHEEL_MAX_RAD] / vp[VP_STEERING_RATIO]
    for i in range(N_WHEELS):
        front = i < N_FRONT_WHEELS
        angle = delta if front else 0.0
        toe = vp[VP_TOE_FRONT_RAD] if front else vp[VP_TOE_REAR_RAD]
        if toe != 0.0:
            angle += -toe if i % WHEELS_PER_AXLE == 0 else toe  # left, then right
        wheel_in[WI_STEER_RAD, i] = angle


@nb.njit(**STEP_JIT_OPTIONS)
def freeze_inputs(model: Model, data: Data) -> None:
    """Stage 1: the inputs held over the step (``ws.wheel_in``): road-wheel angles, drive
    torques, brake capacities; the brakes start released and no wheel held."""
    wheel_in = data.ws.wheel_in
    road_wheel_angles(model.vp, data.inputs[IN_STEER], wheel_in)
    for i in range(N_WHEELS):
        angle = wheel_in[WI_STEER_RAD, i]
        # the right wheel of an axle without toe has the left one's angle (the same value,
        # zero's sign included): the same cosine and sine, not computed again
        if i % WHEELS_PER_AXLE != 0 and angle == wheel_in[WI_STEER_RAD, i - 1]:
            wheel_in[WI_COS_STEER, i] = wheel_in[WI_COS_STEER, i - 1]
            wheel_in[WI_SIN_STEER, i] = wheel_in[WI_SIN_STEER, i - 1]
        elif angle == 0.0:  # straight ahead (a rear wheel without toe): exactly 1 and +-0
            wheel_in[WI_COS_STEER, i] = 1.0
            wheel_in[WI_SIN_STEER, i] = angle
        else:
            wheel_in[WI_COS_STEER, i] = np.cos(angle)
            wheel_in[WI_SIN_STEER, i] = np.sin(angle)
    wheel_torques(data.x, model.vp, data.inputs, data.out, model.tp[:, TP_RADIUS_M],
                  model.dt_s, wheel_in[WI_DRIVE_NM], wheel_in[WI_BRAKE_CAP_NM])
    for i in range(N_WHEELS):
        wheel_in[WI_HELD, i] = 0.0
        wheel_in[WI_BRAKE_NM, i] = 0.0


@nb.njit(**STEP_JIT_OPTIONS)
def prepare_tires(model: Model, data: Data) -> None:
    """Stage 2: the tires' load-dependent coefficients, once per step and wheel.

    Prepared at the load extrapolated to mid-step, ``Fz + (Fz - Fz_prev) / 2`` (RK4's
    symmetric stage weights then keep the load coupling second order, ``core.tire``),
    with ``Fz_prev`` the start load of the previous step (state slot ``FZ_PREV``; negative:
    none yet, prepared at ``Fz``). The start load becomes the next step's ``Fz_prev``.
    """
    x = data.x
    vp, tp, tires = model.vp, model.tp, model.tires
    wheel, tire_coef, wheel_in = data.ws.wheel, data.ws.tire_coef, data.ws.wheel_in
    corner_loads(model, data.ws, x)
    ground = data.ws.ground
    for i in range(N_WHEELS):
        fz = wheel[i, W_FZ]
        fz_prev = x[FZ_PREV0 + i]
        fz_pred = fz + 0.5 * (fz - fz_prev) if fz_prev >= 0.0 else fz
        # camber from the suspension at the start of the step, held over it like the load
        # coefficients (the body's roll moves at 1-2 Hz against the 1 kHz step)
        gamma = wheel_camber(vp, x, i)
        wheel_in[WI_CAMBER_RAD, i] = gamma
        tire_prepare(tires, tp[i], gamma, fz_pred, ground[G_MU0 + i], tire_coef[i])
        x[FZ_PREV0 + i] = fz


@nb.njit(cache=True, inline="always")
def resolve_brakes(model: Model, data: Data) -> None:
    """Stage 4: static-friction brakes: hold a wheel at zero spin when the capacity allows.

    For each wheel, the torque that brings its spin to zero by the end of the step is
    ``T_stop = -I Omega / dt - T_other`` with ``T_other = T_drive - R Fx``. If the
    brake capacity plus the rolling-resistance moment covers ``|T_stop|`` the wheel is
    held (spin set to zero; the brake supplies ``-T_other``); otherwise the brake applies
    its full capacity in the direction of ``T_stop``. The spin rates of ``k1`` (the only
    derivatives that depend on the brakes) are updated accordingly.
    """
    x = data.x
    vp, tp, dt_s = model.vp, model.tp, model.dt_s
    wheel_in, wheel, rk = data.ws.wheel_in, data.ws.wheel, data.ws.rk
    for i in range(N_WHEELS):
        inertia = wheel_inertia(vp, i)
        radius = tp[i, TP_RADIUS_M]
        t_other = wheel_in[WI_DRIVE_NM, i] - radius * wheel[i, W_FX]
        capacity = wheel_in[WI_BRAKE_CAP_NM, i] + wheel[i, W_MY]
        t_stop = -inertia * x[OMEGA0 + i] / dt_s - t_other
        if abs(t_stop) <= capacity:
            wheel_in[WI_HELD, i] = 1.0
            x[OMEGA0 + i] = 0.0
            wheel_in[WI_BRAKE_NM, i] = -t_other
        else:
            wheel_in[WI_HELD, i] = 0.0
            wheel_in[WI_BRAKE_NM, i] = capacity if t_stop > 0.0 else -capacity
    for i in range(N_WHEELS):
        if wheel_in[WI_HELD, i] > 0.5:
            rk[RK_K1, OMEGA0 + i] = 0.0
        else:
            rk[RK_K1, OMEGA0 + i] += wheel_in[WI_BRAKE_NM, i] / wheel_inertia(vp, i)


@nb.njit(cache=True, inline="always")
def _copy_discrete(src: np.ndarray, dst: np.ndarray) -> None:
    for j in range(N_INTEGRATED, N_STATE):
        dst[j] = src[j]


@nb.njit(cache=True, inline="always")
def freeze_decay_rates(model: Model, data: Data) -> None:
    """The slip states' linear decay rates ``|u|/b``, ``|u|/B`` at the step start (zero for
    the kinematic slip model, which has no slip states). Only the slip slots
    ``DECAYING0 .. N_INTEGRATED`` are written: no other state decays."""
    rk, wheel = data.ws.rk, data.ws.wheel
    tp = model.tp
    h = model.dt_s
    for j in range(DECAYING0, N_INTEGRATED):  # the only slots lawson_rk4 reads
        rk[RK_DECAY, j] = 0.0
        rk[RK_E_HALF, j] = 1.0
    if int(model.vp[VP_SLIP_MODEL]) != SLIP_KINEMATIC:
        for i in range(N_WHEELS):
            speed = abs(wheel[i, W_HUB_U])
            for j, length in ((TAN_ALPHA0 + i, tp[i, TP_RELAX_LAT_M]),
                              (KAPPA0 + i, tp[i, TP_RELAX_LONG_M])):
                rk[RK_DECAY, j] = speed / length
                rk[RK_E_HALF, j] = np.exp(-0.5 * h * rk[RK_DECAY, j])


@nb.njit(**STEP_JIT_OPTIONS)
def rates_and_rk4(model: Model, data: Data) -> None:
    """Stages 3-5: ``k1`` at the start state (its loads are stage 2's), the outputs and
    contacts recorded from it, the brakes resolved on it and the decay rates frozen
    (stages 3 and 4), then the exponential (Lawson) RK4 (stage 5).

    The four derivative evaluations are one loop over the stages with one inlined copy of
    ``forces_and_rates`` (``k1`` at ``x``, then ``k2``, ``k3``, ``k4`` at the stage states,
    after their ``corner_loads``): each inlined copy of it was optimised again by LLVM
    (and, while numba inlined it, typed and lowered again), the bulk of a cold compile of
    the step (``python -m benchmarks.bench_compile --by-function``). The same operations
    in the same order as four copies: the same bits.

    The stage states 2, 3 and 4 take turns in one row (``RK_Y``): each is read for the
    last time, slot by slot, just before the next one overwrites that slot, and the
    discrete slots (the same for all three) are copied in once. The start spins are kept
    in the ``RK_SPIN0`` row for the zero-crossing test of stage 6.
    """
    x = data.x
    ws = data.ws
    h = model.dt_s
    rk = ws.rk
    y = rk[RK_Y]
    k1, k2, k3, k4 = rk[RK_K1], rk[RK_K2], rk[RK_K3], rk[RK_K4]
    decay, e_half = rk[RK_DECAY], rk[RK_E_HALF]
    # Only the slip slots (DECAYING0 ..) decay; below them the decay is 0 and its factor
    # exp(0) = 1, so their lines are Lawson's with the factors 1 and the terms 0 taken
    # out: plain RK4, the same values (x * 1.0 is x; k + 0.0 * y is k but for the sign of
    # a zero k). The stage derivatives' rows RK_K1 .. RK_K4 are consecutive (core.model).
    state = x
    for stage in range(4):
        if stage > 0:
            k_prev = rk[RK_K1 + stage - 1]
            for j in range(DECAYING0, N_INTEGRATED):
                k_prev[j] += decay[j] * state[j]
            if stage == 1:  # y2
                for j in range(DECAYING0):
                    y[j] = x[j] + 0.5 * h * k_prev[j]
                for j in range(DECAYING0, N_INTEGRATED):
                    y[j] = e_half[j] * (x[j] + 0.5 * h * k_prev[j])
            elif stage == 2:  # y3
                for j in range(DECAYING0):
                    y[j] = x[j] + 0.5 * h * k_prev[j]
                for j in range(DECAYING0, N_INTEGRATED):
                    y[j] = e_half[j] * x[j] + 0.5 * h * k_prev[j]
            else:  # y4
                for j in range(DECAYING0):
                    y[j] = x[j] + h * k_prev[j]
                for j in range(DECAYING0, N_INTEGRATED):
                    y[j] = e_half[j] * e_half[j] * x[j] + h * e_half[j] * k_prev[j]
            state = y
            corner_loads(model, ws, y)  # k1's loads are prepare_tires'
        # 3. forces and rates at the start (stage 0), then at the stage states
        forces_and_rates(model, ws, state, rk[RK_K1 + stage])
        if stage == 0:
            record_outputs(ws, data.out)
            record_contacts(ws, x)
            resolve_brakes(model, data)  # 4. static-friction brakes
            freeze_decay_rates(model, data)
            _copy_discrete(x, y)
    for i in range(N_WHEELS):
        rk[RK_SPIN0, OMEGA0 + i] = x[OMEGA0 + i]  # for the zero-crossing test
    for j in range(DECAYING0):
        x[j] = x[j] + h / 6.0 * (k1[j] + 2.0 * (k2[j] + k3[j]) + k4[j])
    for j in range(DECAYING0, N_INTEGRATED):
        k4[j] += decay[j] * y[j]
        e_full = e_half[j] * e_half[j]
        x[j] = e_full * x[j] + h / 6.0 * (
            e_full * k1[j] + 2.0 * e_half[j] * (k2[j] + k3[j]) + k4[j]
        )


@nb.njit(cache=True, inline="always")
def catch_stopped_wheels(data: Data) -> None:
    """Stage 6: the brakes catch a wheel whose spin crossed zero; record the held flags
    and the brake torques."""
    x, out = data.x, data.out
    rk, wheel_in = data.ws.rk, data.ws.wheel_in
    for i in range(N_WHEELS):
        omega_start = rk[RK_SPIN0, OMEGA0 + i]
        if wheel_in[WI_HELD, i] > 0.5:
            x[OMEGA0 + i] = 0.0
        elif wheel_in[WI_BRAKE_CAP_NM, i] > 0.0 and omega_start * x[OMEGA0 + i] < 0.0:
            x[OMEGA0 + i] = 0.0
        x[WHEEL_HELD0 + i] = wheel_in[WI_HELD, i]
        out[O_BRAKE_TORQUE0 + i] = wheel_in[WI_BRAKE_NM, i]


@nb.njit(**STEP_JIT_OPTIONS)
def update_discrete_states(model: Model, data: Data) -> None:
    """Stage 7: per wheel, on the new hub velocities: the slip variant's projection
    (``core.slip``), the paper's damping trigger and release (``core.damping``), and the
    hub speed the next trigger compares with."""
    x, out, inputs = data.x, data.out, data.inputs
    wheel_in, wheel = data.ws.wheel_in, data.ws.wheel
    vp = model.vp
    slip_model = int(vp[VP_SLIP_MODEL])
    damping_model = int(vp[VP_DAMPING_MODEL])
    release = paper_release(inputs[IN_BRAKE], inputs[IN_PARKING_BRAKE], inputs[IN_THROTTLE])
    for i in range(N_WHEELS):
        u_w, v_w = hub_velocity(x, model.derived, i, wheel_in[WI_COS_STEER, i],
                                wheel_in[WI_SIN_STEER, i])
        if slip_model == SLIP_LAGGED_PASSIVE:
            # a state within the sliding limit itself (rho <= 1) is within every widened
            # one (rho_max >= 1): the projection would return it as it is, so its hub
            # speed (a square root) and widened limit are not computed
            if not sliding_ratio_squared(x[TAN_ALPHA0 + i], x[KAPPA0 + i],
                                         wheel[i, W_TAN_ALPHA_SLIDE],
                                         wheel[i, W_KAPPA_SLIDE]) <= 1.0:
                x[TAN_ALPHA0 + i], x[KAPPA0 + i] = project_to_sliding_limit(
                    x[TAN_ALPHA0 + i], x[KAPPA0 + i],
                    wheel[i, W_TAN_ALPHA_SLIDE], wheel[i, W_KAPPA_SLIDE],
                    np.sqrt(u_w * u_w + v_w * v_w), vp[VP_SLIDE_WIDEN_SPEED_MPS],
                )
        elif slip_model == SLIP_KINEMATIC:
            # the slots carry the slip the tire saw, for output only
            x[TAN_ALPHA0 + i] = out[O_TAN_ALPHA0 + i]
            x[KAPPA0 + i] = out[O_KAPPA0 + i]
        elif slip_model != SLIP_LAGGED_PAPER:
            raise ValueError("unknown slip model id (core.slip.SLIP_MODELS)")
        if damping_model == DAMPING_PAPER:
            if release:
                x[DAMPING_ACTIVE0 + i] = 0.0
            elif paper_trigger(x[HUB_U_PREV0 + i], u_w, v_w, vp[VP_DAMPING_TRIGGER_V_MPS]):
                x[DAMPING_ACTIVE0 + i] = 1.0
        elif damping_model == DAMPING_PATCH or damping_model == DAMPING_OFF:
            x[DAMPING_ACTIVE0 + i] = 0.0
        else:
            raise ValueError("unknown damping model id (core.damping.DAMPING_MODELS)")
        x[HUB_U_PREV0 + i] = u_w


# Compiled without numba's reference counting (``_nrt=False``). The stages are inlined into
# ``step`` (by LLVM, ``core.layout.STEP_JIT_OPTIONS``, or by numba, ``inline="always"``: a
# call that passes the model and data tuples costs about 80 ns, +19 % on the brush step
# with six such calls), and each takes its arrays out of the tuples; numba counts a
# reference for every array so taken and cannot prune the counts across the stages'
# loops: 150 atomic operations a step, +18 % step cost (measured against the first
# release's step). The step allocates nothing and holds only the caller's arrays and views
# of them, which the caller keeps alive, so the counts protect nothing. (The stages that
# LLVM inlines are compiled with the same options, STEP_JIT_OPTIONS; other callees with
# their own.)
# Compiled with numpy's error model, as the tire kernels are (core.tire_layout): a float
# division by zero gives inf or NaN instead of raising ZeroDivisionError, so no division
# carries a test and branch of its divisor (about 20 a stage; -3 % of the brush step's
# instructions). The values of every other division are the same. A non-finite state is
# what the server's guard catches (vehicle_slot.check_finite: the car stopped at rest).
@nb.njit(cache=True, _nrt=False, error_model="numpy")
def step(model: Model, data: Data) -> None:
    """Advance ``data.x`` by ``model.dt_s`` in place with the inputs ``data.inputs``.

    Writes ``data.out``: forces and accelerations at the state at the *start* of the step.
    The stages, in order: 1 ``freeze_inputs`` and ``follow_terrain``, 2 ``prepare_tires``,
    3 ``vehicle_rates`` at the start state (``forces_and_rates``: its loads are stage 2's),
    ``record_outputs`` and ``record_contacts``, 4 ``resolve_brakes``, 5
    ``freeze_decay_rates`` and the Lawson RK4 (3-5: ``rates_and_rk4``), 6
    ``catch_stopped_wheels``, 7 ``update_discrete_states``, 8 ``steering_system`` (the
    steering-wheel torque from the forces of stage 3: an output, fed back into nothing).
    """
    freeze_inputs(model, data)  # 1. inputs held over the step
    follow_terrain(model, data.ws, data.x)  # 1b. the reference plane, contact frames
    prepare_tires(model, data)  # 2. tire coefficients at the mid-step load
    # 3. forces at the start (its loads are those prepare_tires just computed), 4. the
    # static-friction brakes, 5. the exponential RK4
    rates_and_rk4(model, data)
    catch_stopped_wheels(data)  # 6. brakes catch a wheel crossing zero spin
    update_discrete_states(model, data)  # 7. slip projection, damping latch
    steering_system(model, data)  # 8. the steering-wheel torque (core.steering)
    data.x[TIME_S] += model.dt_s


@nb.njit(cache=True)
def simulate(
    model: Model,
    data: Data,
    inputs_per_step: np.ndarray,
    states: np.ndarray,
    outputs: np.ndarray,
    record_every: int,
) -> None:
    """Run ``len(inputs_per_step)`` steps, recording every ``record_every``-th one.

    Row ``k`` of ``states``/``outputs`` holds the state at the start of step
    ``k * record_every`` and the forces evaluated at it. ``data.inputs`` ends holding the
    last row of ``inputs_per_step``.
    """
    x, out, inputs = data.x, data.out, data.inputs
    n = inputs_per_step.shape[0]
    row = 0
    for k in range(n):
        for j in range(inputs.size):
            inputs[j] = inputs_per_step[k, j]
        if k % record_every == 0:
            for j in range(N_STATE):
                states[row, j] = x[j]
        step(model, data)
        if k % record_every == 0:
            for j in range(N_OUT):
                outputs[row, j] = out[j]
            row += 1
