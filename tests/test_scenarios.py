"""The paper's four examples and the stop / hold / restart cases (issue 3: E1-E7).

Every scenario is a file in configs/scenarios/ run headless exactly as
``simserver run-scenario`` runs it. Tolerances are stated next to each assertion.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scenario_checks import (
    braked_speed_rebound,
    first_stop_index,
    shear_force_sums,
    speed,
    travel_along_heading,
)

from simserver.adapters.config import apply_model_options, model_option_values
from simserver.core import layout as L
from simserver.core.params import VP_DAMPING_TRIGGER_V_MPS, VP_GRAVITY_MPS2, VP_MASS_KG
from simserver.sim.scenario import load_scenario, run_scenario
from tests.conftest import CONFIGS

SCEN = CONFIGS / "scenarios"
_cache: dict = {}


def run(name: str, dt_s: float | None = None, **model):
    """Run a scenario file (cached), optionally with other model options or step."""
    key = (name, dt_s, tuple(sorted(model.items())))
    if key not in _cache:
        sc = load_scenario(SCEN / f"{name}.yaml")
        if model:
            opts = dict(sc.scene.model_options)
            opts.update(model)
            apply_model_options(sc.scene.vehicle.vp, model_option_values(opts, "test"))
        if dt_s is not None:
            sc.record_every = max(1, int(round(sc.record_every * sc.dt_s / dt_s)))
            sc.dt_s = dt_s
        result = run_scenario(sc)
        assert np.all(np.isfinite(result.states)) and np.all(np.isfinite(result.outputs))
        _cache[key] = result
    return _cache[key]


def weight(result) -> float:
    vp = result.scenario.scene.vehicle.vp
    return vp[VP_MASS_KG] * vp[VP_GRAVITY_MPS2]


# ---------------------------------------------------------------- E1
def test_e1_oscillates_about_zero_at_the_tire_spring_frequency():
    """Undamped, the stopped car rings on its tire springs: f = sqrt(sum C_kappa/(B m))/2 pi.

    15 % tolerance (issue 3): the brush tire is softer than its zero-slip stiffness around
    the pre-stressed rest point, which lowers the frequency a few per cent (measured 3.38
    against 3.50 Hz; ``test_e1_frequency_is_lowered_by_the_tire_not_the_pitch``).
    """
    r = run("e1_stop_downslope_no_damping")
    stop = first_stop_index(r, after_s=1.0)
    u = r.state(L.U_MPS)[stop:]
    t = r.time_s[stop:]
    crossings = t[np.nonzero(np.diff(np.signbit(u)))[0]]
    assert crossings.size > 20  # it keeps oscillating: nothing damps it
    measured = 1.0 / (2.0 * np.median(np.diff(crossings)))
    vp = r.scenario.scene.vehicle.vp
    from simserver.core.tire_layout import TP_RELAX_LONG_M

    c_kappa_sum = 4 * 22500.0  # configs/tires/paper_sti.yaml, linear in load: sum is fixed
    expected = math.sqrt(c_kappa_sum / (r.scenario.scene.vehicle.tp[0, TP_RELAX_LONG_M]
                                        * vp[VP_MASS_KG])) / (2 * math.pi)
    assert abs(measured / expected - 1.0) < 0.15, (measured, expected)
    assert abs(expected - 3.5) < 0.05  # the paper's 3.5 Hz
    assert np.abs(u).max() < 1.0  # an oscillation about zero, not a runaway



def e1_ringing(stiffer: float):
    """E1 with the suspension springs and anti-roll bars ``stiffer`` times stiffer (dampers
    sqrt(stiffer): the body modes keep their damping ratio). Returns the half-period
    frequencies of u after the stop (Hz), their times, the load-weighted slope of the brush
    curve at each row (1 = the zero-slip stiffness) and the pitch's peak-to-peak (rad)."""
    from simserver.core.params import (
        VP_ANTIROLL_FRONT_NPM,
        VP_ANTIROLL_REAR_NPM,
        VP_DAMPER_FRONT_NSPM,
        VP_DAMPER_REAR_NSPM,
        VP_SPRING_FRONT_NPM,
        VP_SPRING_REAR_NPM,
    )

    sc = load_scenario(SCEN / "e1_stop_downslope_no_damping.yaml")
    vp = sc.scene.vehicle.vp
    for k in (VP_SPRING_FRONT_NPM, VP_SPRING_REAR_NPM, VP_ANTIROLL_FRONT_NPM,
              VP_ANTIROLL_REAR_NPM):
        vp[k] *= stiffer
    for k in (VP_DAMPER_FRONT_NSPM, VP_DAMPER_REAR_NSPM):
        vp[k] *= math.sqrt(stiffer)
    r = run_scenario(sc)
    stop = first_stop_index(r, after_s=1.0)
    u, t = r.state(L.U_MPS)[stop:], r.time_s[stop:]
    crossings = t[np.nonzero(np.diff(np.signbit(u)))[0]]
    # configs/tires/paper_sti.yaml, the simple (brush) model: C = C_nom Fz / Fz_nom, so the
    # normalised slip is s = C_nom |k'| / (mu Fz_nom) and the curve's slope f'(s) is
    # 1 - 2 s/3 + s^2/9 (tire_simple.py); each wheel's stiffness is C_nom Fz/Fz_nom f'(s).
    s_norm = np.minimum(22500.0 * np.abs(r.states[stop:, L.KAPPA]) / (0.9 * 5005.0), 3.0)
    fz = r.outputs[stop:, L.O_FZ]
    slope = ((1.0 - 2.0 * s_norm / 3.0 + s_norm**2 / 9.0) * fz).sum(axis=1) / fz.sum(axis=1)
    return (1.0 / (2.0 * np.diff(crossings)), crossings[1:], slope, t,
            np.ptp(r.state(L.PITCH_RAD)[stop:]))


def test_e1_frequency_is_lowered_by_the_tire_not_the_pitch():
    """Why E1 rings below the linear 3.50 Hz (README, E1). Not the body's pitch: with the
    springs 100 times stiffer the pitch swings 80 times less and the frequency stays within
    2 % (a pitch coupling worth the 3.5 % deficit would move it at least twice that toward
    3.50 Hz). The brush tire: around the rest point, pre-stressed by the 1000 N that holds
    the car on the slope, and over the swing its slope is below the zero-slip stiffness;
    the time-averaged slope predicts the frequency of the decaying second half of the
    ringing within 2 % (the average of a tangent stiffness is a first-order estimate)."""
    f1, _, _, _, pitch1 = e1_ringing(1.0)
    f100, tc, slope, t, pitch100 = e1_ringing(100.0)
    linear_hz = math.sqrt(4 * 22500.0 / (0.091 * 2041.0)) / (2 * math.pi)
    late = tc >= tc[len(tc) // 2]
    rows = (t >= tc[late][0] - 1.0 / (2.0 * f100[late][0])) & (t <= tc[-1])
    predicted = linear_hz * math.sqrt(slope[rows].mean())
    print(f"E1: {np.median(f1):.3f} Hz (pitch p-p {math.degrees(pitch1):.2f} deg); springs x100: "
          f"{np.median(f100):.3f} Hz (pitch p-p {math.degrees(pitch100):.3f} deg); linear tire "
          f"{linear_hz:.3f} Hz; second half {np.median(f100[late]):.3f} Hz, tire slope "
          f"{slope[rows].mean():.3f} -> {predicted:.3f} Hz")
    assert pitch100 < pitch1 / 50.0
    assert abs(np.median(f100) / np.median(f1) - 1.0) < 0.02
    assert np.median(f100) < 0.98 * linear_hz  # still well below the linear value
    assert abs(np.median(f100[late]) / predicted - 1.0) < 0.02


# ---------------------------------------------------------------- E2
def test_e2_paper_damping_stops_and_holds_with_the_papers_force():
    r = run("e2_stop_downslope_paper_damping")
    stop = first_stop_index(r, after_s=1.0)
    t_stop = r.time_s[stop]
    u = r.state(L.U_MPS)
    after = r.time_s >= t_stop + 2.0
    assert np.abs(u[after]).max() < 1e-3  # |u| < 1 mm/s within 2 s of the first stop
    # residual tire forces along the slope hold the car: m g sin(atan 0.05), within 1 %
    fx_sum, fy_sum, _ = shear_force_sums(r, -1)
    expected = weight(r) * math.sin(math.atan(0.05))
    assert abs(-fx_sum / expected - 1.0) < 0.01, (fx_sum, expected)
    assert abs(fy_sum) < 1.0
    # the paper's pattern with a 70/30 split: brake force in front, a slightly smaller
    # tractive force at the rear (docs/model.md section 4b item 4)
    o = r.outputs[-1]
    front = o[L.O_FX0] + o[L.O_FX0 + 1]
    rear = o[L.O_FX0 + 2] + o[L.O_FX0 + 3]
    print(f"E2 at rest: front {front:.0f} N, rear {rear:.0f} N, sum {front + rear:.0f} N")
    assert front < 0 < rear
    # the damping was triggered by the sign change of u, on every wheel
    assert np.all(r.final_state[L.DAMPING_ACTIVE] == 1.0)
    active = r.states[:, L.DAMPING_ACTIVE0]
    assert not active[: stop - 1].any()  # never before the stop


# ---------------------------------------------------------------- E3
def test_e3_stop_from_a_steady_turn_leaves_no_net_force():
    r = run("e3_stop_from_turn")
    # the turn before braking is about 0.4 g
    turning = (r.time_s > 4.0) & (r.time_s < 5.0)
    ay_g = r.output(L.O_AY_MPS2)[turning].mean() / 9.81
    assert 0.35 < ay_g < 0.5, ay_g
    assert speed(r)[-1] < 1e-3
    fx_sum, fy_sum, mz = shear_force_sums(r, -1)
    w = weight(r)
    vp = r.scenario.scene.vehicle.vp
    from simserver.core.params import VP_CG_TO_FRONT_AXLE_M, VP_CG_TO_REAR_AXLE_M

    wheelbase = vp[VP_CG_TO_FRONT_AXLE_M] + vp[VP_CG_TO_REAR_AXLE_M]
    assert math.hypot(fx_sum, fy_sum) < 0.01 * w
    assert abs(mz) < 0.01 * w * wheelbase


# ---------------------------------------------------------------- E4
def test_e4_braked_spinout_on_a_sideslope_comes_to_rest():
    r = run("e4_spinout_sideslope")
    yaw = r.state(L.YAW_RAD)
    assert abs(yaw.max() - yaw[0]) > math.radians(90)
    u = r.state(L.U_MPS)
    assert u.min() < 0.0 < u.max()  # u changes sign: the car slides backwards
    assert speed(r)[-1] < 1e-3
    assert speed(r)[r.time_s > r.time_s[-1] - 2.0].max() < 1e-3



def plain_form_spinout_60s(steer: float | None = None):
    """E4 with the paper's plain form (``lagged_paper`` + Appendix A ``paper`` damping) run
    for 60 s; ``steer``: another steering-wheel position for the turn (the file: 0.12)."""
    sc = load_scenario(SCEN / "e4_spinout_sideslope.yaml")
    opts = dict(sc.scene.model_options)
    opts.update(slip_model="lagged_paper", damping_model="paper")
    apply_model_options(sc.scene.vehicle.vp, model_option_values(opts, "test"))
    sc.duration_s = 60.0
    if steer is not None:
        for key in sc.keyframes:
            if key.get("steer", 0.0) > 0.0:
                key["steer"] = steer
    result = run_scenario(sc)
    assert np.all(np.isfinite(result.states)) and np.all(np.isfinite(result.outputs))
    return result


def hub_u_crossings(r) -> list[np.ndarray]:
    """Per wheel, |v| of the hub (wheel frame, m/s) at every sign change of its u."""
    out = []
    for i in range(L.N_WHEELS):
        hub_u, hub_v = r.output(L.O_HUB_U0 + i), r.output(L.O_HUB_V0 + i)
        changed = np.nonzero(np.diff(np.signbit(hub_u)))[0] + 1
        out.append(np.abs(hub_v[changed]))
    return out


def test_e4_papers_plain_form_never_stops_on_the_files_inputs():
    """The paper's plain form on E4 (docs/model.md section 4b item 5): the Appendix A
    trigger (u changes sign while |v| < eps = 0.15 m/s, per wheel, hub velocity in the
    wheel frame) is never met, so nothing damps the car; it keeps sliding sideways back and
    forth on its wound-up lateral tire springs, braked, and walks down the slope.

    Thresholds: the car "at rest" elsewhere in this file is below 1 mm/s; here its speed
    from 15 s to 60 s averages more than 1 m/s (measured 2.39) and it loses more than
    0.5 m of height (measured 1.05 m; 0.1 m would already be a car that is not held).
    """
    r = plain_form_spinout_60s()
    t = r.time_s
    vp = r.scenario.scene.vehicle.vp
    eps = vp[VP_DAMPING_TRIGGER_V_MPS]
    assert eps == 0.15  # the paper's value
    closest = [float(v.min()) for v in hub_u_crossings(r)]
    crossings = [v.size for v in hub_u_crossings(r)]
    late = t >= 15.0
    v_mean = speed(r)[late].mean()
    height_m = r.state(L.Y_M) * 0.1 / math.sqrt(1.01)  # 10 % cross slope rises along y
    drop_m = height_m[late][0] - height_m[-1]
    braked = (r.inputs[late, L.IN_PARKING_BRAKE] > 0.5).all()
    print(f"E4 paper's plain form, 60 s: hub u sign changes {crossings}, |v| at them >= "
          f"{min(closest):.3f} m/s (eps {eps}); mean speed 15-60 s {v_mean:.2f} m/s, "
          f"height lost {drop_m:.2f} m, "
          f"max |tan a'| {np.abs(r.states[late, L.TAN_ALPHA]).max():.2f}")
    assert min(crossings) > 20  # u keeps changing sign ...
    assert min(closest) > eps  # ... never with |v| < eps
    assert not r.states[:, L.DAMPING_ACTIVE].any()  # so the damping never switches on
    assert braked and v_mean > 1.0 and drop_m > 0.5  # braked, never at rest, going down


def test_e4_papers_plain_form_stops_when_one_crossing_meets_the_trigger():
    """Beside it: 8 % less steer (0.11 instead of 0.12) and a hub's u changes sign with
    |v| < eps during the spin-out; the damping latches and the same equations bring the car
    to rest (below 1 mm/s, this file's rest threshold) well before 20 s (measured 15.5 s).
    Whether the paper's form stops on E4 hangs on one crossing, not on the equations."""
    r = plain_form_spinout_60s(steer=0.11)
    t = r.time_s
    eps = r.scenario.scene.vehicle.vp[VP_DAMPING_TRIGGER_V_MPS]
    assert min(float(v.min()) for v in hub_u_crossings(r)) < eps
    assert r.states[:, L.DAMPING_ACTIVE].any()
    moving = speed(r) > 1e-3
    last_moving_s = t[np.nonzero(moving)[0][-1]]
    print(f"E4 paper's plain form, steer 0.11: at rest from {last_moving_s:.2f} s")
    assert last_moving_s < 20.0


# ---------------------------------------------------------------- E5
E5_CASES = {
    "e5_hold_restart_uphill": +1.0,  # driving direction along the initial heading
    "e5_hold_restart_downhill": +1.0,
    "e5_hold_restart_reverse_uphill": -1.0,
    "e5_hold_restart_reverse_downhill": -1.0,
}
RELEASE_S = 66.0


def hold_and_restart(r, direction: float):
    """(creep over the 60 s hold, rollback after release, time to 2 m/s after release)."""
    s = travel_along_heading(r)
    t = r.time_s
    stop = first_stop_index(r, after_s=1.0)
    hold = (t >= t[stop] + 2.0) & (t <= RELEASE_S)
    assert t[hold][-1] - t[hold][0] >= 59.0  # held for at least 60 s
    creep = np.ptp(s[hold])
    after = t > RELEASE_S
    s_rel = s[np.argmax(after)]
    rollback = max(0.0, -direction * (s[after] - s_rel).min())
    driving = direction * r.state(L.U_MPS)
    reached = after & (driving >= 2.0)
    t_2mps = t[np.argmax(reached)] - RELEASE_S if reached.any() else math.inf
    return creep, rollback, t_2mps


@pytest.mark.parametrize("name", list(E5_CASES))
def test_e5_stop_hold_and_restart_on_a_10_percent_grade(name):
    r = run(name)
    creep, rollback, t_2mps = hold_and_restart(r, E5_CASES[name])
    print(f"{name}: creep {creep * 1e3:.4f} mm, rollback {rollback:.4f} m, "
          f"2 m/s after {t_2mps:.2f} s")
    assert creep < 1e-3
    assert rollback < 0.15
    assert t_2mps < 4.0


def test_e5_parking_brake_alone_holds_on_10_percent():
    r = run("e5_parking_brake_hold")
    t = r.time_s
    foot_off = t >= 5.3
    assert np.all(r.inputs[foot_off, L.IN_BRAKE] == 0.0)
    s = travel_along_heading(r)
    window = t >= 7.0  # 28 s on the parking brake alone
    assert np.ptp(s[window]) < 1e-3
    assert speed(r)[window].max() < 1e-3


@pytest.mark.parametrize("name", ["e2_stop_downslope_paper_damping", "e5_hold_restart_uphill"])
def test_same_outcome_at_half_the_step(name):
    """E2 and E5 at dt = 0.5 ms and 1 ms: a low-speed law that depends on the step would
    change how the car stops and holds. Resting forces within 0.5 % of the weight share
    they carry, the settling after the stop within 2 mm."""
    a = run(name)
    b = run(name, dt_s=0.0005)
    # how far the car moves once it has stopped (the low-speed law at work); the stopping
    # distance itself differs by the integration error of a 60 m stop (about 1e-4)
    settle = [travel_along_heading(r)[-1] - travel_along_heading(r)[first_stop_index(r, 1.0)]
              for r in (a, b)]
    assert abs(settle[0] - settle[1]) < 2e-3, settle
    if name.startswith("e2"):
        fa = a.outputs[-1, L.O_FX]
        fb = b.outputs[-1, L.O_FX]
        assert np.all(np.abs(fa - fb) < 0.005 * weight(a) / 4), (fa, fb)
    else:
        ca = hold_and_restart(a, 1.0)
        cb = hold_and_restart(b, 1.0)
        assert ca[0] < 1e-3 and cb[0] < 1e-3
        assert abs(ca[1] - cb[1]) < 0.01 and abs(ca[2] - cb[2]) < 0.05


# ---------------------------------------------------------------- E6
def test_e6_kinematic_baseline_cannot_hold_the_car():
    """The eq. (1) baseline on E2 and E5: with u replaced by max(|u|, u_min) the tire sees
    almost no slip at standstill, so the brakes cannot make it hold: the car creeps down
    the slope where the lagged model holds to the micrometre."""
    lagged = run("e2_stop_downslope_paper_damping")
    kin = run("e6_kinematic_stop_downslope")
    late = kin.time_s > kin.time_s[-1] - 3.0
    s_kin = travel_along_heading(kin)
    s_lag = travel_along_heading(lagged)
    creep_kin = np.ptp(s_kin[late])
    creep_lag = np.ptp(s_lag[late])
    print(f"E6 downslope, last 3 s: kinematic creeps {creep_kin:.3f} m, "
          f"lagged {creep_lag * 1e3:.4f} mm")
    assert creep_lag < 1e-4
    assert creep_kin > 100 * creep_lag and creep_kin > 0.01

    kin5 = run("e6_kinematic_hold_restart_uphill")
    t = kin5.time_s
    s = travel_along_heading(kin5)
    hold = (t > 10.0) & (t <= RELEASE_S)
    print(f"E6 uphill hold: kinematic creeps {np.ptp(s[hold]):.3f} m over the hold")
    assert np.ptp(s[hold]) > 1e-2  # no hold


# ---------------------------------------------------------------- E7
BRAKED_STOPS = ["e2_stop_downslope_paper_damping", "e3_stop_from_turn", "e4_spinout_sideslope",
                "e5_hold_restart_uphill", "e5_hold_restart_reverse_uphill",
                "e7_brake_release_ringing"]
DEFAULT = {"slip_model": "lagged_passive", "damping_model": "patch"}


@pytest.mark.parametrize("name", BRAKED_STOPS)
def test_e7_tires_never_feed_energy_into_a_braked_car(name):
    r = run(name, **DEFAULT)
    assert braked_speed_rebound(r) <= 0.5


def test_e7_papers_plain_form_does_in_the_spinout():
    """Beside it: the paper's plain form on the E4 spin-out picks the car up again after it
    has slowed below 0.5 m/s under braking (the stored sliding deflection pays back)."""
    plain = run("e4_spinout_sideslope", slip_model="lagged_paper", damping_model="paper")
    rebound = braked_speed_rebound(plain)
    print(f"E4 paper's plain form: speed back up to {rebound:.2f} m/s under braking")
    assert rebound > 0.5


def ringing(r, release_s: float, wheel: int) -> tuple[float, float]:
    """First swing of Fx after the release and the largest swing after 0.3 s (N)."""
    t = r.time_s
    fx = r.output(L.O_FX0 + wheel)
    final = fx[t > release_s + 1.5].mean()
    first = np.abs(fx[(t > release_s) & (t <= release_s + 0.1)] - final).max()
    late = np.abs(fx[(t > release_s + 0.3) & (t <= release_s + 1.5)] - final).max()
    return first, late


def test_e7_brake_release_ringing_decays_within_0_3_s():
    r = run("e7_brake_release_ringing")
    p = run("e7_brake_release_ringing", slip_model="lagged_paper", damping_model="paper")
    for i in range(L.N_WHEELS):
        first, late = ringing(r, 4.0, i)
        pf, pl = ringing(p, 4.0, i)
        print(f"wheel {L.WHEEL_NAMES[i]}: default {first:.0f} -> {late:.0f} N; "
              f"paper's form {pf:.0f} -> {pl:.0f} N")
        assert first > 100.0  # there was something to ring
        assert late < 0.1 * first
