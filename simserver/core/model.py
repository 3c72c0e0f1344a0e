"""What the compiled step takes: a static model apart from the mutable data.

- ``Model``: what is simulated. The vehicle parameters (road included, ``core.params``),
  the tire parameters per wheel, the step and the registered tire kernels. Changed only
  between steps, by ``core.road.set_road`` or by loading another vehicle.
- ``Data``: what the step reads and writes: the state (everything that lives from one
  step to the next, ``core.layout``), the driver inputs, the outputs of the last step,
  and the workspace (scratch: nothing in it survives a step).

Both are ``NamedTuple``\\ s of arrays, valid (and cacheable) arguments of compiled
functions, so every stage of the step takes ``(model, data)`` instead of a list of
positional arrays. ``simserver.simulation.Simulation`` builds them from a scene.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from simserver.core import layout as L
from simserver.core.tire_layout import N_TIRE_COEF, N_TIRE_OUT, TireKernels

# ---- per-wheel quantities of the state being evaluated (ws.wheel[i, W_*])
W_FX = 0  # tire Fx incl. damping, wheel frame (N)
W_FY = 1  # tire Fy incl. damping, wheel frame (N)
W_MZ = 2  # aligning moment (N m)
W_MY = 3  # rolling-resistance moment magnitude (N m)
W_KAPPA_SLIDE = 4  # the tire's sliding limits at this load
W_TAN_ALPHA_SLIDE = 5
W_FX_PEAK = 6  # peak pure-slip forces at this load and friction (N)
W_FY_PEAK = 7
W_HUB_U = 8  # hub velocity, wheel frame (m/s)
W_HUB_V = 9
W_DAMPING_FX = 10  # auxiliary damping share of Fx, Fy (N)
W_DAMPING_FY = 11
W_KAPPA = 12  # slip fed to the tire model
W_TAN_ALPHA = 13
N_W = 14

# ---- whole-body quantities of the state being evaluated (ws.body[B_*])
B_AX_MPS2 = 0
B_AY_MPS2 = 1
B_YAW_ACC_RADPS2 = 2
B_GRAVITY_X_MPS2 = 3
B_GRAVITY_Y_MPS2 = 4
B_FX_SUM_N = 5
B_FY_SUM_N = 6
N_BODY = 7


class Model(NamedTuple):
    """The static model: vehicle and tire parameters, road, step, tire kernels."""

    vp: np.ndarray  # float64[N_VEHICLE_PARAM] (core.params; the road slots included)
    tp: np.ndarray  # float64[N_WHEELS, N_TIRE_PARAM] (core.tire_layout)
    dt_s: float
    tires: TireKernels  # the registered tire models' kernels, by model id


class Workspace(NamedTuple):
    """Scratch of one step (``make_workspace``): nothing here lives from one step to the next."""

    y2: np.ndarray  # RK4 stage states, float64[N_STATE]
    y3: np.ndarray
    y4: np.ndarray
    k1: np.ndarray  # RK4 stage derivatives, float64[N_INTEGRATED]
    k2: np.ndarray
    k3: np.ndarray
    k4: np.ndarray
    decay: np.ndarray  # linear decay rates frozen at the step start, float64[N_INTEGRATED]
    e_half: np.ndarray  # exp(-decay h / 2), float64[N_INTEGRATED]
    steer_rad: np.ndarray  # road-wheel angles over the step, float64[N_WHEELS]
    cos_steer: np.ndarray
    sin_steer: np.ndarray
    drive_nm: np.ndarray  # drive torque per wheel over the step
    brake_cap_nm: np.ndarray  # brake capacity per wheel over the step
    brake_nm: np.ndarray  # brake + rolling-resistance torque applied (signed)
    held: np.ndarray  # 1 = wheel held at zero spin by its brake over the step
    fz_n: np.ndarray  # normal loads of the state being evaluated, float64[N_WHEELS]
    wheel: np.ndarray  # float64[N_WHEELS, N_W]
    body: np.ndarray  # float64[N_BODY]
    tire_out: np.ndarray  # float64[N_TIRE_OUT]
    tire_coef: np.ndarray  # prepared tire coefficients, float64[N_WHEELS, N_TIRE_COEF]


class Data(NamedTuple):
    """The mutable data: state, inputs, outputs, workspace."""

    x: np.ndarray  # float64[N_STATE], core.layout
    inputs: np.ndarray  # float64[N_INPUT], validated and clamped
    out: np.ndarray  # float64[N_OUT]: forces at the state at the start of the last step
    ws: Workspace


def make_workspace() -> Workspace:
    """Allocate the scratch ``step`` needs (once, before the loop)."""
    def vec(n: int) -> np.ndarray:
        return np.zeros(n, dtype=np.float64)

    n_int = L.N_INTEGRATED
    n_w = L.N_WHEELS
    return Workspace(
        y2=vec(L.N_STATE), y3=vec(L.N_STATE), y4=vec(L.N_STATE),
        k1=vec(n_int), k2=vec(n_int), k3=vec(n_int), k4=vec(n_int),
        decay=vec(n_int), e_half=vec(n_int),
        steer_rad=vec(n_w), cos_steer=vec(n_w), sin_steer=vec(n_w),
        drive_nm=vec(n_w), brake_cap_nm=vec(n_w), brake_nm=vec(n_w), held=vec(n_w),
        fz_n=vec(n_w), wheel=np.zeros((n_w, N_W)), body=vec(N_BODY),
        tire_out=vec(N_TIRE_OUT), tire_coef=np.zeros((n_w, N_TIRE_COEF)),
    )


def make_data(x: np.ndarray | None = None) -> Data:
    """New data: state ``x`` (copied; zeros if None), gear P, zero outputs."""
    state = np.zeros(L.N_STATE) if x is None else np.array(x, dtype=np.float64)
    inputs = np.zeros(L.N_INPUT)
    inputs[L.IN_GEAR] = L.GEAR_P
    return Data(x=state, inputs=inputs, out=np.zeros(L.N_OUT), ws=make_workspace())
