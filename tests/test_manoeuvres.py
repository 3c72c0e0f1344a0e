"""The standard manoeuvres (``simserver.analysis.manoeuvres``, issue 32 item 3): each
figure of the shipped scenarios against an independent computation (a linear steady-state
model of the same car from its parameters, or the raw history read another way), the
pass/fail logic against synthetic histories that meet and break each criterion, the
scenario keys' errors, and the one command that writes the figures and the report."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from simserver.adapters.config import ConfigError, load_vehicle, read_yaml
from simserver.adapters.history import read_history, result_columns, summarize
from simserver.adapters.manoeuvre_report import manoeuvre_figure
from simserver.analysis import manoeuvres as M
from simserver.core import params as P
from simserver.core.layout import GEAR_D, GEAR_R
from simserver.core.tire import BUILTIN_KERNELS, tire_forces
from simserver.core.tire_layout import (
    N_TIRE_OUT,
    OUT_FY,
    OUT_MY,
    OUT_MZ,
    TP_RADIUS_M,
    TP_RELAX_LAT_M,
)
from simserver.sim.scenario import (
    is_world_scenario,
    load_scenario,
    load_world_scenario,
    run_scenario,
    run_world_scenario,
)
from simserver.testing import CONFIGS, REPO
from tests.conftest import slow_enabled

pytestmark = pytest.mark.timeout(600)

SCENARIOS = CONFIGS / "scenarios"
WHEELS = ("fl", "fr", "rl", "rr")


def _run(name: str, **overrides):
    """Run a shipped scenario in-process (``overrides``: top-level keys replaced): the
    columns and summary of each car, keyed by car id (``car0`` for a single car)."""
    path = SCENARIOS / f"{name}.yaml"
    data = dict(read_yaml(path), **overrides)
    if is_world_scenario(data):
        result = run_world_scenario(load_world_scenario(path, data))
        return {cid: (result_columns(r), summarize(r)) for cid, r in result.cars.items()}
    result = run_scenario(load_scenario(path, data))
    return {"car0": (result_columns(result), summarize(result))}


@pytest.fixture(scope="module")
def steady_state():
    return _run("iso4138_steady_state_circular")["car0"]


@pytest.fixture(scope="module")
def step_steer():
    return _run("iso7401_step_steer")["car0"]


@pytest.fixture(scope="module")
def sis():
    return _run("fmvss126_slowly_increasing_steer")["car0"]


@pytest.fixture(scope="module")
def swd():
    return _run("fmvss126_sine_with_dwell")["car0"]


# ------------------------------------------------------------- a linear steady-state model
def _tire(tp, kappa, tan_alpha, gamma, fz, u):
    out = np.zeros(N_TIRE_OUT)
    tire_forces(BUILTIN_KERNELS, tp, kappa, tan_alpha, gamma, fz, 1.0, u, out)
    return out


def linear_steady_state(vehicle_file: Path, fz: list[float], kappa: list[float], u: float):
    """The steady turn of the car per unit lateral acceleration, linearised: a single-track
    model whose axle cornering stiffnesses, trails and camber and load sensitivities are
    the tire model's own (central differences of ``tire_forces`` at each wheel's
    straight-running load ``fz`` and longitudinal slip ``kappa``), with the chassis'
    first-order effects in closed form from the vehicle parameters (docs/model.md
    section 7): roll ``phi / a_y = m h / (K_phi - m_s g h)`` with ``K_phi = k T^2 / 2 +
    k_arb T^2`` per axle, the lateral load transfer ``K_phi,axle phi / T`` it gives, the
    camber it leans the wheels by (section 8.6), the rolling-resistance moments of the
    shifted loads. Returns ``d tan(alpha)/d a_y`` per axle (front, rear), the understeer
    gradient ``K = d(delta - L/R)/d a_y`` (rad per m/s^2) and ``phi / a_y``."""
    veh = load_vehicle(vehicle_file, {})
    vp = veh.vp
    m, ms = vp[P.VP_MASS_KG], vp[P.VP_SPRUNG_MASS_KG]
    a, b, h, g = (vp[P.VP_CG_TO_FRONT_AXLE_M], vp[P.VP_CG_TO_REAR_AXLE_M],
                  vp[P.VP_CG_HEIGHT_M], vp[P.VP_GRAVITY_MPS2])
    track = (vp[P.VP_TRACK_FRONT_M], vp[P.VP_TRACK_REAR_M])
    k_phi = [vp[P.VP_SPRING_FRONT_NPM] * track[0] ** 2 / 2 + vp[P.VP_ANTIROLL_FRONT_NPM]
             * track[0] ** 2,
             vp[P.VP_SPRING_REAR_NPM] * track[1] ** 2 / 2 + vp[P.VP_ANTIROLL_REAR_NPM]
             * track[1] ** 2]
    phi = m * h / (sum(k_phi) - ms * g * h)
    static = (vp[P.VP_CAMBER_STATIC_FRONT_RAD], vp[P.VP_CAMBER_STATIC_REAR_RAD])
    roll_gain = (vp[P.VP_CAMBER_ROLL_GAIN_FRONT], vp[P.VP_CAMBER_ROLL_GAIN_REAR])
    heave_gain = (vp[P.VP_CAMBER_HEAVE_GAIN_FRONT_RADPM], vp[P.VP_CAMBER_HEAVE_GAIN_REAR_RADPM])
    x_wheel = (a, a, -b, -b)
    y_wheel = (track[0] / 2, -track[0] / 2, track[1] / 2, -track[1] / 2)
    # rows: [force, yaw moment] = coefficients on tan(alpha) front, rear; constant per a_y
    coef = np.zeros((2, 2))
    const = np.zeros(2)
    d, dz = 1e-4, 10.0
    for i in range(4):
        axle, left = i // 2, i % 2 == 0
        tp, fz_i, k_i = veh.tp[i], fz[i], kappa[i]
        gamma0 = (-1.0 if left else 1.0) * static[axle]  # ISO inclination (section 8.6)
        p, q = _tire(tp, k_i, d, gamma0, fz_i, u), _tire(tp, k_i, -d, gamma0, fz_i, u)
        fy_a, mz_a = (p[OUT_FY] - q[OUT_FY]) / (2 * d), (p[OUT_MZ] - q[OUT_MZ]) / (2 * d)
        p, q = _tire(tp, k_i, 0.0, gamma0 + d, fz_i, u), _tire(tp, k_i, 0.0, gamma0 - d, fz_i, u)
        fy_g, mz_g = (p[OUT_FY] - q[OUT_FY]) / (2 * d), (p[OUT_MZ] - q[OUT_MZ]) / (2 * d)
        p, q = _tire(tp, k_i, 0.0, gamma0, fz_i + dz, u), _tire(tp, k_i, 0.0, gamma0, fz_i - dz, u)
        fy_z, mz_z = (p[OUT_FY] - q[OUT_FY]) / (2 * dz), (p[OUT_MZ] - q[OUT_MZ]) / (2 * dz)
        rr_per_n = abs(p[OUT_MY] - q[OUT_MY]) / (2 * dz) / tp[TP_RADIUS_M]
        d_gamma = (roll_gain[axle] + heave_gain[axle] * track[axle] / 2) * phi
        d_fz = (k_phi[axle] * phi / track[axle]) * (-1.0 if left else 1.0)  # left turn
        d_fx = -rr_per_n * d_fz  # more load, more rolling resistance
        coef[0, axle] += fy_a
        coef[1, axle] += x_wheel[i] * fy_a + mz_a
        const[0] += fy_g * d_gamma + fy_z * d_fz
        const[1] += (x_wheel[i] * (fy_g * d_gamma + fy_z * d_fz) + mz_g * d_gamma
                     + mz_z * d_fz - y_wheel[i] * d_fx)
    tan_f, tan_r = np.linalg.solve(coef, np.array([m, 0.0]) - const)
    return {"tan_alpha_per_ay": (tan_f, tan_r), "understeer_rad": tan_r - tan_f,
            "roll_rad": phi, "a_m": a, "b_m": b, "wheelbase_m": a + b, "mass_kg": m,
            "yaw_inertia_kgm2": vp[P.VP_YAW_INERTIA_KGM2],
            "steering_ratio": vp[P.VP_STEERING_RATIO], "coef": coef, "const": const,
            "relaxation_m": (veh.tp[0][TP_RELAX_LAT_M], veh.tp[2][TP_RELAX_LAT_M])}


def linear_step_response(ref, u: float, delta_h, t):
    """The linear single-track model's response to the steering-wheel angle ``delta_h(t)``
    (rad) at speed ``u``: lateral velocity, yaw rate and each axle's lagged slip
    ``tan a'`` (``b d(tan a')/dt + u tan a' = v_hub``, docs/model.md section 3, with the
    tire's own relaxation length), the axle forces and moments of ``linear_steady_state``
    and its chassis terms taken as quasi-static in the lateral acceleration. Integrated by
    RK4 on the rows ``t``; returns yaw rate and lateral acceleration."""
    (ff, fr), (mf_yaw, mr_yaw) = ref["coef"]
    c_force, c_moment = ref["const"]
    m, iz, a, b = ref["mass_kg"], ref["yaw_inertia_kgm2"], ref["a_m"], ref["b_m"]
    sig_f, sig_r = ref["relaxation_m"]
    ratio = ref["steering_ratio"]

    def ay_of(x):
        return (ff * x[2] + fr * x[3]) / (m - c_force)

    def f(x, tt):
        v, r, tf, tr = x
        ay = ay_of(x)
        delta = delta_h(tt) / ratio
        return np.array([ay - u * r,
                         (mf_yaw * tf + mr_yaw * tr + c_moment * ay) / iz,
                         (v + a * r - u * delta - u * tf) / sig_f,
                         (v - b * r - u * tr) / sig_r])

    x = np.zeros(4)
    r_out, ay_out = np.zeros_like(t), np.zeros_like(t)
    for k in range(len(t)):
        r_out[k], ay_out[k] = x[1], ay_of(x)
        if k + 1 == len(t):
            break
        h = t[k + 1] - t[k]
        k1 = f(x, t[k])
        k2 = f(x + 0.5 * h * k1, t[k] + 0.5 * h)
        k3 = f(x + 0.5 * h * k2, t[k] + 0.5 * h)
        k4 = f(x + h * k3, t[k] + h)
        x = x + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return r_out, ay_out


def _straight_point(cols, before_s: float):
    """Each wheel's load and longitudinal slip and the speed at the last row before
    ``before_s`` (running straight, ``a_y`` = 0): the model's operating point."""
    k = int(np.searchsorted(cols["time_s"], before_s)) - 1
    assert abs(cols["ay_mps2"][k]) < 1e-3
    return ([cols[f"fz_{w}_n"][k] for w in WHEELS], [cols[f"kappa_{w}"][k] for w in WHEELS],
            float(cols["u_mps"][k]))


def test_understeer_gradient_against_the_linear_model(steady_state):
    """ISO 4138 on the mf_hatchback (an MF 6.1 tire has a linear range): the understeer
    gradient at 0.2-1 m/s^2 within 5 % of the linear steady-state model of the same car,
    and the roll, sideslip and steering-wheel angle gradients with it. The plain
    single-track formula ``m/L (b/C_f - a/C_r)`` alone gives 0.064 deg/(m/s^2): the
    trails, the roll camber and the load transfer's effects are a quarter of the car's
    understeer and are in the model (docs/manoeuvres.md section 1)."""
    cols, summary = steady_state
    f = summary["manoeuvre"]["figures"]
    fz, kappa, u = _straight_point(cols, 2.0)
    ref = linear_steady_state(CONFIGS / "vehicles/mf_hatchback/vehicle.yaml", fz, kappa, u)
    k_ref = math.degrees(ref["understeer_rad"])
    print(f"understeer gradient: run {f['understeer_gradient_deg_per_mps2']:.5f}, linear model "
          f"{k_ref:.5f} deg/(m/s^2)")
    assert f["understeer_gradient_deg_per_mps2"] == pytest.approx(k_ref, rel=0.05)
    assert f["roll_gradient_deg_per_mps2"] == pytest.approx(math.degrees(ref["roll_rad"]),
                                                            rel=0.01)
    # beta = tan(alpha_r) + b / R at the CG, 1/R = a_y / V^2
    speed = f["speed_mean_mps"]
    beta_ref = math.degrees(ref["tan_alpha_per_ay"][1] + ref["b_m"] / speed ** 2)
    assert f["sideslip_gradient_deg_per_mps2"] == pytest.approx(beta_ref, rel=0.05)
    sw_ref = math.degrees(ref["steering_ratio"] * (ref["wheelbase_m"] / speed ** 2
                                                   + ref["understeer_rad"]))
    assert f["steering_wheel_angle_gradient_deg_per_mps2"] == pytest.approx(sw_ref, rel=0.02)
    assert summary["manoeuvre"]["passed"]


def test_the_speed_hold_holds_the_constant_speed_method(steady_state):
    """The speed hold keeps 80 km/h within 2 % up to 6 m/s^2 (the turn's drag grows
    fifty-fold), by working the throttle: open loop, the same ramp loses 3.8 m/s."""
    cols, _ = steady_state
    rows = cols["ay_mps2"] < 6.0
    speed = np.hypot(cols["u_mps"], cols["v_mps"])[rows]
    assert np.max(np.abs(speed / 22.2222 - 1.0)) < 0.02
    throttle = cols["input_throttle"]
    low = (cols["time_s"] > 4.0) & (cols["ay_mps2"] < 1.0)
    assert throttle[rows][-1] > 2.0 * np.median(throttle[low])


def test_step_steer_figures_recomputed_from_the_history_file(step_steer, tmp_path):
    """ISO 7401 response times read another way: the yaw rate differentiated from the
    heading, the lateral acceleration from the velocity states (``dv/dt + u r``), the step
    timed by the driver's input column; each figure within 2 ms (two rows) or 1 %."""
    cols, summary = step_steer
    f = summary["manoeuvre"]["figures"]
    t = cols["time_s"]
    steer = cols["input_steer"]
    # the state's steering-wheel angle is the input of the step before: one row later
    t50 = t[np.argmax(steer >= 0.5 * steer[-1])] + (t[1] - t[0])
    assert f["t50_s"] == pytest.approx(t50, abs=1.5e-3)
    yaw_rate = np.gradient(cols["yaw_rad"], t)
    ay = np.gradient(cols["v_mps"], t) + cols["u_mps"] * cols["yaw_rate_radps"]
    tail = t >= t[-1] - 1.0
    for name, y, scale in (("yaw_rate", yaw_rate, math.degrees(1.0)), ("ay", ay, 1.0)):
        steady = np.mean(y[tail])
        after = t >= t50
        t90 = t[after][np.argmax(y[after] >= 0.9 * steady)]
        k_peak = np.argmax(np.where(after & ~tail, y, -np.inf))
        assert f[f"{name}_response_time_s"] == pytest.approx(t90 - t50, abs=2e-3)
        assert f[f"{name}_peak_response_time_s"] == pytest.approx(t[k_peak] - t50, abs=2e-3)
        overshoot = 100.0 * (y[k_peak] - steady) / steady
        assert f[f"{name}_overshoot_pct"] == pytest.approx(overshoot, abs=0.1)
        key = "yaw_rate_steady_degps" if name == "yaw_rate" else "ay_steady_mps2"
        assert f[key] == pytest.approx(scale * steady, rel=1e-3)
    assert summary["manoeuvre"]["passed"]


def test_step_steer_steady_state_against_the_linear_model(step_steer):
    """The step's steady yaw-rate gain against the linear model's, ``r / delta_H = V /
    (i_s (L + K V^2))``: at 4 m/s^2 the tires are past their linear range, so the run's
    gain is lower, by the understeer the ISO 4138 run shows growing over 0-4 m/s^2
    (within 12 %)."""
    cols, summary = step_steer
    fz, kappa, u = _straight_point(cols, 2.0)
    ref = linear_steady_state(CONFIGS / "vehicles/mf_hatchback/vehicle.yaml", fz, kappa, u)
    gain = u / (ref["steering_ratio"] * (ref["wheelbase_m"] + ref["understeer_rad"] * u ** 2))
    run = summary["manoeuvre"]["figures"]["yaw_rate_gain_per_s"]
    assert gain * 0.88 < run < gain


def test_small_step_against_the_linear_single_track_response():
    """The shipped step steer at 4 deg instead of 24 (0.7 m/s^2, the tires' linear range)
    against the linear single-track model with lagged slip (``linear_step_response``,
    the same steering ramp): response and peak response times within 5 %, overshoots
    within half a point, steady values within 2 %. (The ISO level, 24 deg, is past the
    linear range: there the run's yaw overshoot is 7.2 % against the model's 2.9 %.)"""
    step = math.radians(4.0)
    inputs = [{"t": 0.0, "steer": 0.0, "throttle": 0.0, "gear": "D"}, {"t": 2.0, "steer": 0.0},
              {"t": 2.1, "steer": step / 8.2}]  # the hatchback's steering_wheel_max_rad
    cols, summary = _run("iso7401_step_steer", inputs=inputs)["car0"]
    run = summary["manoeuvre"]["figures"]
    fz, kappa, u = _straight_point(cols, 2.0)
    vehicle = CONFIGS / "vehicles/mf_hatchback/vehicle.yaml"
    ref = linear_steady_state(vehicle, fz, kappa, u)
    t = cols["time_s"]
    # the state's steering-wheel angle is the step's input one row later (1 ms)
    r, ay = linear_step_response(
        ref, u, lambda tt: step * min(1.0, max(0.0, (tt - 2.001) / 0.1)), t)
    lin = M.iso7401_step_steer({"time_s": t, "steering_wheel_angle_rad":
                                cols["steering_wheel_angle_rad"], "yaw_rate_radps": r,
                                "ay_mps2": ay, "u_mps": cols["u_mps"]},
                               M.car_facts(load_vehicle(vehicle, {}).vp))["figures"]
    for name in ("yaw_rate", "ay"):
        for key in (f"{name}_response_time_s", f"{name}_peak_response_time_s"):
            assert run[key] == pytest.approx(lin[key], rel=0.05), key
        assert run[f"{name}_overshoot_pct"] == pytest.approx(lin[f"{name}_overshoot_pct"],
                                                             abs=0.5)
    assert run["yaw_rate_steady_degps"] == pytest.approx(lin["yaw_rate_steady_degps"], rel=0.02)
    assert run["ay_steady_mps2"] == pytest.approx(lin["ay_steady_mps2"], rel=0.02)


def test_sis_angle_and_the_sine_with_dwell_scenario_it_sets(sis, swd):
    """A from the slowly increasing steer: the steering-wheel angle at 0.3 g of a line
    refitted (np.polyfit) to the rows between 0.1 and 0.375 g picked from ``V r`` (the
    path's acceleration, not the ay column), within 1 %; the shipped sine with dwell is
    the generator's text for this A (its amplitude 6.5 A)."""
    cols, summary = sis
    f = summary["manoeuvre"]["figures"]
    g = M.G_MPS2
    ay_path = np.hypot(cols["u_mps"], cols["v_mps"]) * cols["yaw_rate_radps"] / g
    rising = np.arange(len(ay_path)) <= np.argmax(ay_path)
    rows = rising & (ay_path >= 0.1) & (ay_path <= 0.375)
    slope, icept = np.polyfit(np.degrees(cols["steering_wheel_angle_rad"][rows]),
                              cols["ay_mps2"][rows] / g, 1)
    assert f["A_deg"] == pytest.approx((0.3 - icept) / slope, rel=0.01)
    text = M.sine_with_dwell_scenario(f["A_deg"], "../vehicles/mf_hatchback/vehicle.yaml",
                                      8.2)
    assert (SCENARIOS / "fmvss126_sine_with_dwell.yaml").read_text() == text
    amplitude = swd[1]["manoeuvre"]["figures"]["amplitude_deg"]
    assert amplitude == pytest.approx(6.5 * f["A_deg"], abs=0.06)


def test_the_series_file_and_its_mirrored_runs(sis):
    """The shipped two-series file is the generator's text for the A of the slowly
    increasing steer; its right-first runs are the left-first ones mirrored (the car is
    symmetric: the same figures, the steering and yaw rate of opposite sign), run here for
    the 6.5 A pair and the final 270 deg pair (the full file: 50 runs)."""
    a_deg = sis[1]["manoeuvre"]["figures"]["A_deg"]
    path = SCENARIOS / "fmvss126_sine_with_dwell_series.yaml"
    assert path.read_text() == M.sine_with_dwell_series_scenario(
        a_deg, "../vehicles/mf_hatchback/vehicle.yaml", 8.2)
    data = read_yaml(path)
    ids = [c["id"] for c in data["cars"]]
    assert len(ids) == 2 * len(M.swd_amplitudes_deg(a_deg))
    pick = [f"{side}_{amp}deg" for side in ("left", "right") for amp in ("131p4", "270p0")]
    data["cars"] = [c for c in data["cars"] if c["id"] in pick]
    result = run_world_scenario(load_world_scenario(path, data))
    figures = {cid: summarize(r)["manoeuvre"]["figures"] for cid, r in result.cars.items()}
    for amp in ("131p4", "270p0"):
        left, right = figures[f"left_{amp}deg"], figures[f"right_{amp}deg"]
        assert left["first_left"] and not right["first_left"]
        for key in ("amplitude_deg", "yaw_rate_peak_degps", "yaw_rate_ratio_1p0_s_pct",
                    "yaw_rate_ratio_1p75_s_pct", "lateral_displacement_1p07_s_m", "cos_s"):
            assert right[key] == pytest.approx(left[key], rel=1e-6, abs=1e-9), key


def test_swd_amplitude_series():
    """S7.9: 1.5 A up in 0.5 A steps to the final run, the greater of 6.5 A and 270 deg,
    300 deg when 6.5 A is over 300 deg."""
    small = M.swd_amplitudes_deg(20.0)
    assert small[:3] == [30.0, 40.0, 50.0] and small[-2:] == [260.0, 270.0]
    assert len(small) == 25  # 1.5 A .. 13 A and 270
    mid = M.swd_amplitudes_deg(44.0)  # 6.5 A = 286 deg
    assert mid[-1] == pytest.approx(286.0) and mid[-2] == pytest.approx(264.0)
    big = M.swd_amplitudes_deg(50.0)  # 6.5 A = 325 deg
    assert big[-1] == 300.0 and big[-2] == pytest.approx(275.0)  # 6 A = 300 is the final


def test_sine_with_dwell_figures_recomputed(swd):
    """The yaw-rate ratios with the yaw rate differentiated from the heading, COS from the
    regulation's timing (start + 1/0.7 Hz + 0.5 s, one row later in the state), the peak
    by argmax; the lateral displacement from the body velocities integrated along the
    heading (trapezoids) instead of the positions."""
    cols, summary = swd
    f = summary["manoeuvre"]["figures"]
    t = cols["time_s"]
    dt = t[1] - t[0]
    cos_ = M.SWD_SCENARIO_START_S + 1.0 / 0.7 + 0.5 + dt
    assert f["cos_s"] == pytest.approx(cos_, abs=1.5e-3)
    r = -np.gradient(cols["yaw_rad"], t)  # the second lobe turns right
    window = (t > f["steer_sign_change_s"]) & (t < cos_)
    peak = np.max(r[window])
    assert f["yaw_rate_peak_degps"] == pytest.approx(math.degrees(peak), rel=2e-3)
    for after, key in ((1.0, "yaw_rate_ratio_1p0_s_pct"), (1.75, "yaw_rate_ratio_1p75_s_pct")):
        assert f[key] == pytest.approx(100.0 * np.interp(cos_ + after, t, r) / peak, abs=0.3)
    psi = cols["yaw_rad"]
    vy_world = cols["u_mps"] * np.sin(psi) + cols["v_mps"] * np.cos(psi)
    vx_world = cols["u_mps"] * np.cos(psi) - cols["v_mps"] * np.sin(psi)
    k0 = int(np.argmax(t >= f["bos_s"]))
    k1 = int(np.argmax(t >= f["bos_s"] + 1.07))
    x = np.concatenate(([0.0], np.cumsum(0.5 * (vx_world[1:] + vx_world[:-1]) * dt)))
    y = np.concatenate(([0.0], np.cumsum(0.5 * (vy_world[1:] + vy_world[:-1]) * dt)))
    lateral = -(x[k1] - x[k0]) * math.sin(psi[k0]) + (y[k1] - y[k0]) * math.cos(psi[k0])
    assert f["lateral_displacement_1p07_s_m"] == pytest.approx(lateral, abs=0.03)
    # the bare car (no ESC) spins: the ratios fail their limits, the displacement passes
    crit = {c["name"]: c["passed"] for c in summary["manoeuvre"]["criteria"]}
    assert crit == {"yaw rate 1 s after COS / first peak": False,
                    "yaw rate 1.75 s after COS / first peak": False,
                    "lateral displacement 1.07 s after BOS": True}


def _travel(cols, k0, way=1.0):
    c, s = math.cos(cols["yaw_rad"][k0]), math.sin(cols["yaw_rad"][k0])
    return way * ((cols["x_m"] - cols["x_m"][k0]) * c + (cols["y_m"] - cols["y_m"][k0]) * s)


@pytest.mark.parametrize("grade", [20, 30])
def test_hill_start_rollback_and_time_from_positions(grade):
    """Rollback from the positions: the largest travel against the gear's direction from
    the last held row, over the run after the release (the cars do not roll back once
    moving); the time to 2 m/s from the first row at that speed; facing from the
    heading, uphill reverse backing up the hill."""
    for cid, (cols, summary) in _run(f"hill_start_{grade}pct").items():
        f = summary["manoeuvre"]["figures"]
        t = cols["time_s"]
        release = int(np.argmax(cols["input_brake"] < 0.02))
        # the last row held: the release's, or the one before when the car moves at once
        k0 = release if abs(cols["u_mps"][release]) < 1e-3 else release - 1
        way = -1.0 if cid.endswith("reverse") else 1.0
        assert f["gear"] == ("R" if way < 0 else "D")
        assert f["facing"] == ("uphill" if cid in ("uphill_forward", "downhill_reverse")
                               else "downhill")
        back = -_travel(cols, k0, way)[k0:]
        assert f["rollback_m"] == pytest.approx(max(0.0, back.max()), abs=1e-12)
        fast = np.flatnonzero(way * cols["u_mps"] >= 2.0)
        assert f["time_to_2_mps_s"] == pytest.approx(t[fast[0]] - t[release], abs=1e-9)
        assert f["rollback_m"] < 1e-4  # the hill-start assist holds through the foot move


def test_fmvss105_creep_from_positions():
    """Travel and creep over the parking-brake hold from the positions, both ways. The
    default suite holds 30 s (the figures' arithmetic); with -m slow or SIMSERVER_SLOW=1
    the shipped five minutes, judged."""
    full = slow_enabled(None)
    runs = _run("fmvss105_parking_brake_30pct", **({} if full else {"duration_s": 33.0}))
    for cid, (cols, summary) in runs.items():
        m = summary["manoeuvre"]
        f = m["figures"]
        t = cols["time_s"]
        k0 = int(np.argmax((cols["input_brake"] < 0.02) & (cols["input_parking_brake"] > 0.5)))
        k_settle = int(np.argmax(t >= t[k0] + 1.0))
        travel = _travel(cols, k0)
        assert f["hold_start_s"] == pytest.approx(2.3, abs=0.05)
        assert f["travel_mm"] == pytest.approx(1e3 * travel[-1], rel=1e-6)
        assert f["creep_mm"] == pytest.approx(1e3 * (travel[-1] - travel[k_settle]), rel=1e-6,
                                              abs=1e-9)
        assert abs(f["creep_mm"]) < 0.1, cid
        hold_ok = {c["name"]: c["passed"] for c in m["criteria"]}
        assert hold_ok["held by the parking brake alone for"] is full
        assert m["passed"] is full


# ------------------------------------------------------------- the pass/fail logic
def _car():
    return M.Car(wheelbase_m=2.6, steering_ratio=15.0, mass_kg=1500.0)


def _swd_history(decay_s: float):
    """A synthetic sine with dwell: the yaw rate follows the steering 0.1 s late at
    0.2 rad/s per rad and, from COS, decays with time constant ``decay_s``; the path
    integrates a lateral speed of 6 m/s per rad of steering."""
    t = np.arange(0.0, 5.0, 0.001)
    steer = M.sine_with_dwell_steer(math.radians(120.0), t - 1.0)
    cos_ = 1.0 + 1.0 / 0.7 + 0.5
    lagged = M.sine_with_dwell_steer(math.radians(120.0), t - 1.1)
    r = 0.2 * lagged
    k = t > cos_
    r[k] = 0.2 * np.interp(cos_, t, lagged) * np.exp(-(t[k] - cos_) / decay_s)
    y = np.cumsum(6.0 * steer) * 0.001
    return {"time_s": t, "steering_wheel_angle_rad": steer, "yaw_rate_radps": r,
            "yaw_rad": np.zeros_like(t), "x_m": 22.0 * t, "y_m": y}


def test_swd_criteria_flip():
    good = M.fmvss126_sine_with_dwell(_swd_history(0.2), _car(), sis_angle_deg=18.0)
    bad = M.fmvss126_sine_with_dwell(_swd_history(20.0), _car(), sis_angle_deg=18.0)
    assert good["passed"] and not bad["passed"]
    peak = 0.2 * math.radians(120.0)  # the lagged dwell's yaw rate
    f = bad["figures"]
    assert f["yaw_rate_peak_degps"] == pytest.approx(math.degrees(peak), rel=1e-3)
    assert f["yaw_rate_ratio_1p0_s_pct"] > 35.0 and f["yaw_rate_ratio_1p75_s_pct"] > 20.0
    assert good["figures"]["yaw_rate_ratio_1p0_s_pct"] < 1.0
    # the lateral displacement criterion only for amplitudes of 5 A and more
    low = M.fmvss126_sine_with_dwell(_swd_history(0.2), _car(), sis_angle_deg=30.0)
    assert [c["name"] for c in low["criteria"]] == [
        "yaw rate 1 s after COS / first peak", "yaw rate 1.75 s after COS / first peak"]
    short = _swd_history(0.2)
    short["y_m"] = short["y_m"] * 0.1
    assert not M.fmvss126_sine_with_dwell(short, _car(), sis_angle_deg=18.0)["passed"]


def test_a_run_without_the_manoeuvre_fails_without_an_error():
    """An analysis given a history that lacks its manoeuvre (a steering step the car does
    not answer, no hold) reports a failed criterion instead of raising (the sine with
    dwell raised an IndexError on a steering input of one sign)."""
    t = np.arange(0.0, 5.0, 0.001)
    zero = np.zeros_like(t)
    step = np.where(t > 1.0, math.radians(20.0), 0.0)
    cols = {"time_s": t, "steering_wheel_angle_rad": step, "yaw_rate_radps": zero,
            "yaw_rad": zero, "x_m": 20.0 * t, "y_m": zero, "ay_mps2": zero,
            "u_mps": np.full_like(t, 20.0), "v_mps": zero, "roll_rad": zero,
            "ax_mps2": zero, "input_brake": zero, "input_throttle": zero,
            "input_parking_brake": zero, "input_gear": np.full_like(t, float(GEAR_D)),
            "ref_grade_pct": zero}
    for name, (function, _) in M.ANALYSES.items():
        result = function(cols, _car())
        assert not result["passed"], name


def test_parking_brake_and_hill_start_criteria_flip():
    t = np.arange(0.0, 310.0, 0.05)
    held = t >= 2.0
    base = {"time_s": t, "y_m": np.zeros_like(t), "yaw_rad": np.zeros_like(t),
            "u_mps": np.zeros_like(t), "ax_mps2": np.zeros_like(t),
            "input_brake": np.where(held, 0.0, 0.6), "input_throttle": np.zeros_like(t),
            "input_parking_brake": np.ones_like(t), "input_gear": np.full_like(t, 2.0),
            "ref_grade_pct": np.full_like(t, 30.0)}
    for creep_mm, ok in ((0.5, True), (2.0, False)):
        x = np.where(held, creep_mm * 1e-3 * (t - 2.0) / (t[-1] - 2.0), 0.0)
        result = M.fmvss105_parking_brake(dict(base, x_m=x), _car())
        assert result["passed"] is ok and result["figures"]["creep_mm"] == pytest.approx(
            creep_mm * (t[-1] - 3.0) / (t[-1] - 2.0), rel=1e-3)
    flat = dict(base, x_m=np.zeros_like(t), ref_grade_pct=np.full_like(t, 20.0))
    assert not M.fmvss105_parking_brake(flat, _car())["passed"]
    # hill start: held 1-3 s, then rolls back 0.3 m before driving off at 1 m/s^2
    t = np.arange(0.0, 10.0, 0.005)
    tau = t - 3.0
    u = np.where(tau <= 0.0, 0.0, np.where(tau < 1.0, -0.6 * tau, -0.6 + (tau - 1.0)))
    u = np.where(np.abs(u) < 1e-12, 0.0, u)
    x = np.concatenate(([0.0], np.cumsum(0.5 * (u[1:] + u[:-1]) * 0.005)))
    cols = {"time_s": t, "x_m": x, "y_m": np.zeros_like(t), "yaw_rad": np.zeros_like(t),
            "u_mps": u, "ax_mps2": np.gradient(u, t), "input_brake": np.where(tau <= 0, 0.6, 0),
            "input_throttle": np.where(tau > 0, 0.5, 0.0), "input_parking_brake":
            np.zeros_like(t), "input_gear": np.full_like(t, float(GEAR_D)),
            "ref_grade_pct": np.full_like(t, 20.0)}
    result = M.hill_start(cols, _car())
    assert result["figures"]["rollback_m"] == pytest.approx(0.3 + 0.6 ** 2 / 2, abs=1e-3)
    assert not result["passed"]
    assert M.hill_start(cols, _car(), rollback_max_m=1.0)["passed"]
    cols["input_gear"] = np.full_like(t, float(GEAR_R))  # reverse: that was forward travel
    assert M.hill_start(cols, _car())["figures"]["rollback_m"] == pytest.approx(0.0, abs=1e-9)


def test_step_steer_and_steady_state_validity_flip():
    t = np.arange(0.0, 6.0, 0.001)
    resp = 1.0 - np.exp(-np.clip(t - 2.0, 0.0, None) / 0.1)
    for rise_s, ok in ((0.1, True), (0.3, False)):
        steer = np.clip((t - 2.0) / rise_s, 0.0, 1.0) * 0.4
        cols = {"time_s": t, "steering_wheel_angle_rad": steer, "yaw_rate_radps": 0.2 * resp,
                "ay_mps2": 4.0 * resp, "u_mps": np.full_like(t, 22.0)}
        result = M.iso7401_step_steer(cols, _car())
        assert result["passed"] is ok
        # a first-order response with time constant 0.1 s from the step's start: 90 % at
        # 0.1 ln 10 s after 2 s, measured from the steering's 50 % point
        t50 = 2.0 + 0.5 * rise_s
        assert result["figures"]["yaw_rate_response_time_s"] == pytest.approx(
            2.0 + 0.1 * math.log(10.0) - t50, abs=1.5e-3)
        assert result["figures"]["yaw_rate_overshoot_pct"] == pytest.approx(0.0, abs=1e-3)
    # ISO 4138: K = 0.002 rad/(m/s^2) by construction; a speed that drifts fails
    t = np.arange(0.0, 40.0, 0.01)
    ay = 0.1 * t
    for drift, ok in ((0.0, True), (0.5, False)):  # 20 to 22.5 m/s over the fitted rows
        speed = 20.0 * (1.0 + drift * t / 40.0)
        r = ay / speed
        delta_h = 15.0 * (2.6 * r / speed + 0.002 * ay)
        cols = {"time_s": t, "ay_mps2": ay, "u_mps": speed, "v_mps": np.zeros_like(t),
                "yaw_rate_radps": r, "steering_wheel_angle_rad": delta_h,
                "roll_rad": 0.01 * ay}
        result = M.iso4138_steady_state_circular(cols, _car())
        assert result["passed"] is ok
        assert result["figures"]["understeer_gradient_deg_per_mps2"] == pytest.approx(
            math.degrees(0.002), rel=1e-6)
        assert result["figures"]["roll_gradient_deg_per_mps2"] == pytest.approx(
            math.degrees(0.01), rel=1e-6)


def test_a_criterion_without_a_value_fails():
    assert not M.criterion("x", None, 1.0, "<=", "s")["passed"]
    assert not M.criterion("x", float("nan"), 1.0, ">=", "s")["passed"]
    assert M.criterion("x", 1.0, 1.0, "<=", "s")["passed"]


# ------------------------------------------------------------- scenario keys
@pytest.mark.parametrize(("key", "value", "message"), [
    ("analysis", "iso9999", "key 'analysis.name': 'iso9999' is not one of"),
    ("analysis", {"name": "iso7401_step_steer", "steady_window_s": -1},
     "key 'analysis.steady_window_s'"),
    ("analysis", {"name": "hill_start", "sis_angle_deg": 3}, "sis_angle_deg"),
    ("analysis", 7, "key 'analysis': expected a name or a mapping"),
    ("speed_hold", {"speed_mps": 20.0, "gain": 1}, "gain"),
    ("speed_hold", {"gain_per_mps": 0.1}, "speed_mps"),
    ("speed_hold", {"speed_mps": 20.0, "from_s": 5.0, "until_s": 2.0},
     "key 'speed_hold.until_s'"),
    ("speed_hold", {"speed_mps": 20.0, "keep_throttle": 2}, "key 'speed_hold.keep_throttle'"),
    ("driver", {"path": {"points": [[0.0, 0.0], [300.0, 0.0]]}},
     "key 'speed_hold': the driver holds its own speed"),
])
def test_bad_manoeuvre_keys_name_the_file_and_key(key, value, message):
    path = SCENARIOS / "iso7401_step_steer.yaml"
    data = dict(read_yaml(path), **{key: value})
    with pytest.raises(ConfigError) as err:
        load_scenario(path, data)
    assert str(path) in str(err.value) and message in str(err.value)


# ------------------------------------------------------------- one command
@pytest.mark.parametrize(("name", "plots"), [("iso7401_step_steer", True),
                                             ("hill_start_20pct", False)])
def test_one_command_writes_the_figures_and_the_report(name, plots, tmp_path):
    """``simserver run-scenario`` (a real subprocess) writes the manoeuvre section, the
    report naming every criterion, and its plot (the four-car run without plots: its
    two dozen per-car PNGs cost the suite 20 s; the plot is drawn in-process below)."""
    out = tmp_path / "out"
    command = [sys.executable, "-m", "simserver", "run-scenario",
               str(SCENARIOS / f"{name}.yaml"), "--out", str(out), "--quiet"]
    proc = subprocess.run(command + ([] if plots else ["--no-plots"]), capture_output=True,
                          text=True, cwd=REPO, timeout=300)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    sections = ({"car0": summary["manoeuvre"]} if "manoeuvre" in summary
                else {cid: c["manoeuvre"] for cid, c in summary["cars"].items()})
    report = (out / "manoeuvre.md").read_text()
    for m in sections.values():
        for c in m["criteria"]:
            assert c["name"] in report and c["source"] in report
    assert "manoeuvre.md" in proc.stdout
    cols = read_history(out / "history.parquet")
    if plots:
        assert (out / "manoeuvre.png").stat().st_size > 10_000
    else:
        assert not (out / "manoeuvre.png").exists()
        by_car = {cid: {k: v[cols["car_id"] == cid] for k, v in cols.items() if k != "car_id"}
                  for cid in sections}
        fig = manoeuvre_figure(name, sections, by_car)
        assert len(fig.axes) == 2 and len(fig.axes[0].lines) == len(sections)
