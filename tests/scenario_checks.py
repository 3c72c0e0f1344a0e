"""Measurements on scenario results shared by the scenario tests and the E6 comparison."""

from __future__ import annotations

import numpy as np

from simserver.core import layout as L
from simserver.sim.scenario import ScenarioResult


def travel_along_heading(result: ScenarioResult) -> np.ndarray:
    """Distance travelled along the initial heading (m): the integral of u, signed."""
    yaw0 = result.states[0, L.YAW_RAD]
    dx = result.state(L.X_M) - result.states[0, L.X_M]
    dy = result.state(L.Y_M) - result.states[0, L.Y_M]
    return dx * np.cos(yaw0) + dy * np.sin(yaw0)


def first_stop_index(result: ScenarioResult, after_s: float = 0.0) -> int:
    """First row after ``after_s`` where u has crossed zero (the car has stopped)."""
    u = result.state(L.U_MPS)
    t = result.time_s
    moving_sign = np.sign(u[np.argmax(t >= after_s)])
    crossed = (t >= after_s) & (np.sign(u) != moving_sign)
    if not crossed.any():
        raise AssertionError("the car never stopped")
    return int(np.argmax(crossed))


def speed(result: ScenarioResult) -> np.ndarray:
    """CG speed in the road plane (m/s)."""
    return np.hypot(result.state(L.U_MPS), result.state(L.V_MPS))


def shear_force_sums(result: ScenarioResult, row: int) -> tuple[float, float, float]:
    """Sum of the tire shear forces along body x and y (N) and their yaw moment (N m)."""
    from simserver.core.chassis import wheel_position

    vp = result.scenario.scene.vehicle.vp
    o = result.outputs[row]
    fx_b = fy_b = mz = 0.0
    for i in range(L.N_WHEELS):
        d = o[L.O_STEER0 + i]
        fx = o[L.O_FX0 + i]
        fy = o[L.O_FY0 + i]
        fxb = np.cos(d) * fx - np.sin(d) * fy
        fyb = np.sin(d) * fx + np.cos(d) * fy
        px, py = wheel_position(vp, i)
        fx_b += fxb
        fy_b += fyb
        mz += px * fyb - py * fxb
    return fx_b, fy_b, mz


def braked_speed_rebound(result: ScenarioResult, threshold: float = 0.5) -> float:
    """Largest speed reached after the speed fell below ``threshold`` with the brake on,
    while the brake (pedal or parking) stayed applied; 0 if it never fell below."""
    v = speed(result)
    braked = (result.inputs[:, L.IN_BRAKE] > 0.02) | (result.inputs[:, L.IN_PARKING_BRAKE] > 0.5)
    worst = 0.0
    k = 0
    n = v.size
    while k < n:
        if braked[k] and v[k] < threshold:
            j = k
            while j < n and braked[j]:
                worst = max(worst, v[j])
                j += 1
            k = j
        else:
            k += 1
    return worst
