"""What the compiled step takes: a static model apart from the mutable data.

- ``Model``: what is simulated. The vehicle parameters (``core.params``), the tire
  parameters per wheel, the terrain with its road (``core.terrain``), the step and the
  registered tire kernels. Changed only between steps, by ``core.road.set_road`` (the
  terrain's road) or by loading another vehicle.
- ``Data``: what the step reads and writes: the state (everything that lives from one
  step to the next, ``core.layout``), the driver inputs, the outputs of the last step,
  and the workspace (scratch: nothing in it survives a step).

Both are ``NamedTuple``\\ s of arrays, valid (and cacheable) arguments of compiled
functions, so every stage of the step takes ``(model, data)`` instead of a list of
positional arrays. ``simserver.sim.simulation.Simulation`` builds them from a scene.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from simserver.core import layout as L
from simserver.core.terrain import Terrain, empty_cell_memo
from simserver.core.tire_layout import N_TIRE_COEF, N_TIRE_OUT, TireKernels

# ---- per-wheel inputs held over a step (ws.wheel_in[WI_*, i]: a row per quantity)
WI_STEER_RAD = 0  # road-wheel angle (rad)
WI_COS_STEER = 1  # its cosine and sine
WI_SIN_STEER = 2
WI_DRIVE_NM = 3  # drive torque (N m)
WI_BRAKE_CAP_NM = 4  # brake capacity (N m)
WI_BRAKE_NM = 5  # brake + rolling-resistance torque applied, signed (N m)
WI_HELD = 6  # 1 = wheel held at zero spin by its brake
WI_CAMBER_RAD = 7  # inclination angle to the road, ISO 8855 (rad), chassis.wheel_camber
N_WI = 8

# ---- per-wheel quantities of the state being evaluated (ws.wheel[i, W_*])
W_FZ = 0  # normal load (N)
W_FX = 1  # tire Fx incl. damping, wheel frame (N)
W_FY = 2  # tire Fy incl. damping, wheel frame (N)
W_MZ = 3  # aligning moment (N m)
W_MY = 4  # rolling-resistance moment magnitude (N m)
W_KAPPA_SLIDE = 5  # the tire's sliding limits at this load
W_TAN_ALPHA_SLIDE = 6
W_FX_PEAK = 7  # peak pure-slip forces at this load and friction (N)
W_FY_PEAK = 8
W_HUB_U = 9  # hub velocity, wheel frame (m/s)
W_HUB_V = 10
W_DAMPING_FX = 11  # auxiliary damping share of Fx, Fy (N)
W_DAMPING_FY = 12
W_KAPPA = 13  # slip fed to the tire model
W_TAN_ALPHA = 14
W_FZ_DYN = 15  # normal load beyond the static share: what the corner pushes onto the body (N)
# terrain (core.terrain, docs/model.md section 11)
W_FX_PLANE = 16  # contact force along the wheel heading in the reference plane (N)
W_FY_PLANE = 17  # contact force across it, in the reference plane (N)
W_GAP_M = 18  # surface height above the reference plane under the wheel (m, along n)
W_GAP_RATE_MPS = 19  # its rate as the wheel moves (m/s)
# ... frozen over the step (core.chassis.follow_terrain): the surface under the wheel as
# its tangent plane at the step start, and the wheel's contact frame on it
W_CONTACT_S1_M = 20  # contact point at the step start, in the reference plane (m)
W_CONTACT_S2_M = 21
W_GAP0_M = 22  # gap there (m)
W_GAP_D1 = 23  # d(gap)/ds along the reference plane's e1 and e2
W_GAP_D2 = 24
W_TILT = 25  # 1 / n_z of the contact normal (n_z along the reference plane's normal)
W_N0 = 26  # contact normal: along the wheel heading, across it (reference-plane axes)
W_N1 = 27
W_TX0 = 28  # contact frame's x axis (the heading on the tangent plane), same components
W_TX1 = 29
W_TY0 = 30  # its y axis
W_TY1 = 31
N_W = 32

# ---- whole-body quantities of the state being evaluated (ws.body[B_*])
B_AX_MPS2 = 0
B_AY_MPS2 = 1
B_YAW_ACC_RADPS2 = 2
B_GRAVITY_X_MPS2 = 3
B_GRAVITY_Y_MPS2 = 4
B_FX_SUM_N = 5
B_FY_SUM_N = 6
# ... and what another car applies through a contact over the step (core.contact,
# docs/model.md section 16): written by the world's contact stage before the car step,
# held over the step; B_CONTACT_ACTIVE 0 (the contact stage's reset, and a fresh
# workspace): no contact, and the body's rates do exactly what they did without contacts
B_CONTACT_ACTIVE = 7  # 1 when another car pushes on this one over the step
B_CONTACT_E1_N = 8  # the contact force along the reference plane's e1, e2 (N)
B_CONTACT_E2_N = 9
B_CONTACT_MZ_NM = 10  # its moment about the CG, about the plane's normal (N m)
N_BODY = 11

# ---- the reference plane of the step (ws.ground[G_*], core.terrain)
G_GRAVITY_E1_MPS2 = 0  # gravity along the reference plane's e1, e2, and pressing onto it
G_GRAVITY_E2_MPS2 = 1
G_GRAVITY_N_MPS2 = 2
G_AXES = 3  # 9 slots: rows e1, e2, n in world axes (core.road.road_frame)
G_MU0 = 12  # friction scale under each wheel at the step start, 4 slots
G_X0_M = 16  # the body's planar pose at the step start (terrain_gaps moves from it)
G_Y0_M = 17
G_YAW0_RAD = 18
G_COS_YAW0 = 19
G_SIN_YAW0 = 20
G_AXES_GRADE_PCT = 21  # the grade and cross-slope G_AXES were computed for: the next step
G_AXES_CROSS_SLOPE_PCT = 22  # starts on that plane and reuses them (NaN: none yet)
G_STATIC_FRONT_N = 23  # static normal load of a front and of a rear wheel on this plane
G_STATIC_REAR_N = 24  # (N, chassis.static_share with G_GRAVITY_N_MPS2): once per step
N_GROUND = 25

# ---- rows of the Runge-Kutta scratch (ws.rk[RK_*]; the derivative rows use the first
# N_INTEGRATED columns)
RK_Y = 0  # the stage state of stages 2, 3 and 4 in turn (each is used up before the next)
RK_SPIN0 = 1  # the wheels' start spins (OMEGA0 columns), for the zero-crossing test
RK_K1, RK_K2, RK_K3, RK_K4 = 2, 3, 4, 5  # stage derivatives (consecutive: lawson_rk4 loops)
RK_DECAY = 6  # linear decay rates frozen at the step start
RK_E_HALF = 7  # exp(-decay h / 2)
N_RK = 8


# ---- constants derived from the parameters and the step, once when the model is built
# (``core.integrator.derive_constants``, ``Model.derived[D_*]``) instead of in every step or
# stage. Each is the very expression the stage evaluated before (the same bits). They read
# nothing of the road (the terrain's, the only array changed in place while a model runs:
# ``core.road.set_road``); loading another vehicle builds another model.
D_WHEEL_X0 = 0  # each wheel's contact point ahead of the CG, body axes (m), 4 slots
D_WHEEL_Y0 = 4  # ... and to the left of it (m), 4 slots (chassis.wheel_position)
D_SPIN_DAMPING_CAP0 = 8  # the patch damper's cap 2 I / (R^2 dt) per wheel (N s/m), 4 slots
D_KINGPIN_LIFT_ARM0 = 12  # the front wheels' kingpin lift arm d_c sin(sigma) (m), 2 slots
D_COLUMN_RATE_BLEND = 14  # the column rate filter's blend over a step, 1 - exp(-dt / tau)
D_DRAG_NS2PM2 = 15  # the body's drag coefficient 0.5 rho C_d A (N s^2/m^2)
N_DERIVED = 16


class Model(NamedTuple):
    """The static model of one car: vehicle and tire parameters, the terrain (with the
    road), step, tire kernels, and the constants derived from them (``D_*``)."""

    vp: np.ndarray  # float64[N_VEHICLE_PARAM] (core.params)
    tp: np.ndarray  # float64[N_WHEELS, N_TIRE_PARAM] (core.tire_layout)
    dt_s: float
    tires: TireKernels  # the registered tire models' kernels, by model id
    terrain: Terrain  # the ground and its road (core.terrain; the world's, shared)
    derived: np.ndarray  # float64[N_DERIVED] (D_*): core.integrator.derive_constants


class Workspace(NamedTuple):
    """Scratch of one step (``make_workspace``): nothing here lives from one step to the
    next but memos keyed by their own inputs (the reference plane's axes, ``G_AXES`` with
    ``G_AXES_GRADE_PCT``, ``G_AXES_CROSS_SLOPE_PCT``: a pure function of the two; each
    wheel's height-map cell, ``cells``: of the terrain's contents and the cell), so a
    workspace shared between states is never wrong. Few arrays with named slots, so that
    the stages pass little."""

    rk: np.ndarray  # float64[N_RK, N_STATE]
    wheel_in: np.ndarray  # float64[N_WI, N_WHEELS]
    wheel: np.ndarray  # float64[N_WHEELS, N_W]
    body: np.ndarray  # float64[N_BODY]
    tire_out: np.ndarray  # float64[N_WHEELS, N_TIRE_OUT]: each wheel's tire outputs
    tire_coef: np.ndarray  # prepared tire coefficients, float64[N_WHEELS, N_TIRE_COEF]
    ground: np.ndarray  # float64[N_GROUND]: the reference plane of the step (G_*)
    axes: np.ndarray  # float64[2, 3, 3]: scratch of the reference plane's rebase
    contact: np.ndarray  # float64[3, N_WHEELS]: scratch of the plane fit (x, y, z)
    cells: np.ndarray  # float64[N_WHEELS, N_CELL]: each wheel's height-map cell memo


class Data(NamedTuple):
    """The mutable data: state, inputs, outputs, workspace."""

    x: np.ndarray  # float64[N_STATE], core.layout
    inputs: np.ndarray  # float64[N_INPUT], validated and clamped
    out: np.ndarray  # float64[N_OUT]: forces at the state at the start of the last step
    ws: Workspace


def make_workspace() -> Workspace:
    """Allocate the scratch ``step`` needs (once, before the loop)."""
    n_w = L.N_WHEELS
    ground = np.zeros(N_GROUND)
    ground[G_AXES_GRADE_PCT] = ground[G_AXES_CROSS_SLOPE_PCT] = np.nan  # no axes memo yet
    return Workspace(rk=np.zeros((N_RK, L.N_STATE)), wheel_in=np.zeros((N_WI, n_w)),
                     wheel=np.zeros((n_w, N_W)), body=np.zeros(N_BODY),
                     tire_out=np.zeros((n_w, N_TIRE_OUT)), tire_coef=np.zeros((n_w, N_TIRE_COEF)),
                     ground=ground, axes=np.zeros((2, 3, 3)),
                     contact=np.zeros((3, n_w)), cells=empty_cell_memo(n_w))


def make_data(x: np.ndarray | None = None) -> Data:
    """New data: state ``x`` (copied; zeros if None), gear P, zero outputs."""
    state = np.zeros(L.N_STATE) if x is None else np.array(x, dtype=np.float64)
    inputs = np.zeros(L.N_INPUT)
    inputs[L.IN_GEAR] = L.GEAR_P
    return Data(x=state, inputs=inputs, out=np.zeros(L.N_OUT), ws=make_workspace())
