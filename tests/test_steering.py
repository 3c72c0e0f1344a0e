"""The steering-wheel torque (core/steering.py, docs/model.md section 12).

- in steady turns at 10, 20 and 30 m/s it centres the wheel and equals the hand
  calculation of section 12 from the model's own tire outputs (the history) and the
  vehicle's geometry, computed here independently of the compiled code;
- a wheel turned at standstill builds a torque that stays while the car is still and
  relaxes as it rolls;
- no step or spike in the torque when the car stops or restarts;
- the motion of the car does not depend on the steering system (the torque is an output).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from simserver.core import layout as L
from simserver.core.param_table import Param
from simserver.core.params import STEERING
from simserver.core.tire_layout import TP_RADIUS_M, TP_RELAX_LAT_M
from simserver.sim.scenario import load_scenario, run_scenario
from tests.conftest import CONFIGS

SEDAN = CONFIGS / "vehicles" / "paper_sedan"
HATCH = CONFIGS / "vehicles" / "mf_hatchback"


def _steering_params(vehicle_dir: Path) -> dict[str, float]:
    data = yaml.safe_load((vehicle_dir / "steering.yaml").read_text())
    assert set(data) == {p.yaml_key for p in STEERING if isinstance(p, Param)}
    return {k: float(v) for k, v in data.items()}


def _run(tmp_path: Path, vehicle_dir: Path, u0: float, inputs: list, duration_s: float,
         **extra):
    data = {"name": "steering", "vehicle": str(vehicle_dir / "vehicle.yaml"),
            "initial": {"u_mps": u0}, "duration_s": duration_s, "inputs": inputs, **extra}
    path = tmp_path / "steering.yaml"
    path.write_text(yaml.safe_dump(data))
    return run_scenario(load_scenario(path))


def hand_torque(p: dict[str, float], radius_m: float, out: np.ndarray, twist: np.ndarray,
                friction_nm: float, rate_radps: float) -> float:
    """docs/model.md section 12 by hand, from one row of outputs (the forces of a step)."""
    sigma = p["kingpin_inclination_rad"]
    scrub = p["scrub_radius_m"]
    moment = 0.0
    for i, side in ((L.FL, 1.0), (L.FR, -1.0)):
        fx, fy, fz = out[L.O_FX0 + i], out[L.O_FY0 + i], out[L.O_FZ0 + i]
        mz, delta = out[L.O_MZ0 + i], out[L.O_STEER0 + i]
        moment += (mz - p["caster_trail_m"] * fy - side * scrub * fx
                   - (scrub + radius_m * math.tan(sigma)) * math.sin(sigma) * fz
                   * math.sin(delta)
                   - p["patch_torsion_stiffness_nm_per_rad"] * twist[i])
    load = moment / p["steering_ratio"]
    speed = 0.5 * (abs(out[L.O_HUB_U0 + L.FL]) + abs(out[L.O_HUB_U0 + L.FR]))
    boost = p["assist_boost_highway"] + (p["assist_boost_parking"] - p["assist_boost_highway"]) \
        / (1.0 + (speed / p["assist_fade_speed_mps"]) ** 2)
    assist_max = p["assist_torque_max_nm"]
    if boost > 0 and abs(load) * boost > (1 + boost) * assist_max:
        driver = load - math.copysign(assist_max, load)  # the assist at its limit
    else:
        driver = load / (1.0 + boost)
    return driver - p["column_damping_nm_s_per_rad"] * rate_radps - friction_nm


@pytest.mark.parametrize("vehicle_dir", [SEDAN, HATCH], ids=["brush", "mf61"])
@pytest.mark.parametrize("speed", [10.0, 20.0, 30.0])
def test_steady_turn_torque_centres_and_matches_the_hand_calculation(tmp_path, vehicle_dir,
                                                                     speed):
    # a left turn of about 0.3 g: the steer ramps in over 0.5 s, then holds
    wheelbase = 2.9
    p = _steering_params(vehicle_dir)
    road_wheel = 3.0 * wheelbase / speed**2 + 0.01
    steer = road_wheel * p["steering_ratio"] / p["steering_wheel_max_rad"]
    res = _run(tmp_path, vehicle_dir, speed, [
        {"t": 0.0, "steer": 0.0, "throttle": 0.1, "gear": "D"},
        {"t": 0.5, "steer": 0.0}, {"t": 1.0, "steer": steer}], 5.0)
    radius = res.scenario.scene.vehicle.tp[L.FL, TP_RADIUS_M]  # as the tire file gives it
    torque = res.state(L.STEERING_WHEEL_TORQUE_NM)
    # the steady part: the last 2 s (rows k + 1 hold the torque of the forces of row k)
    rows = np.arange(len(torque) - 2000, len(torque) - 1)
    assert np.all(res.outputs[rows, L.O_FY0 + L.FL] > 0.0)  # a left turn: Fy to the left
    # centring: the torque turns the wheel back to the right, against the steer
    assert np.all(torque[rows + 1] < 0.0)
    # the column friction after the ramp is at its limit (Dahl: T_c exp(-k |dtheta| / T_c)
    # is what remains, 1e-10 of the torque at most) and the rate filter has settled
    swing = steer * p["steering_wheel_max_rad"]
    rate = res.state(L.STEERING_WHEEL_RATE_RADPS)[rows + 1]
    assert np.abs(rate).max() < 1e-12
    twist = res.states[rows + 1, L.PATCH_TWIST0:L.PATCH_TWIST0 + 2]
    expected = np.array([hand_torque(p, radius, res.outputs[k], twist[n],
                                     p["column_friction_nm"], rate[n])
                         for n, k in enumerate(rows)])
    assert p["column_friction_nm"] * math.exp(
        -p["column_friction_stiffness_nm_per_rad"] * swing / p["column_friction_nm"]) \
        < 1e-10 * np.abs(expected).min()
    # the torsion's share is nothing a driver feels (it decays with the distance rolled)
    assert np.abs(twist).max() * p["patch_torsion_stiffness_nm_per_rad"] \
        / p["steering_ratio"] < 1e-6 * np.abs(expected).min()
    # the same arithmetic in another order: equal to rounding (1e-9 of the torque)
    np.testing.assert_allclose(torque[rows + 1], expected, rtol=1e-9,
                               atol=1e-9 * np.max(np.abs(expected)))
    # the aligning part dominates the friction (a torque a driver feels)
    assert np.min(np.abs(expected)) > 2.0 * p["column_friction_nm"]


def test_wheel_turned_at_standstill_keeps_its_torque_and_relaxes_when_rolling(tmp_path):
    p = _steering_params(SEDAN)
    # at rest in D, brake on: turn the wheel by a quarter of its range at 1..1.5 s, hold it,
    # release the brake at 4 s and creep off with a little throttle
    res = _run(tmp_path, SEDAN, 0.0, [
        {"t": 0.0, "steer": 0.0, "throttle": 0.0, "brake": 0.6, "gear": "D"},
        {"t": 1.0, "steer": 0.0}, {"t": 1.5, "steer": 0.25},
        {"t": 4.0, "brake": 0.6, "throttle": 0.0}, {"t": 4.01, "brake": 0.0, "throttle": 0.2},
    ], 8.0)
    b = res.scenario.scene.vehicle.tp[L.FL, TP_RELAX_LAT_M]
    torque = res.state(L.STEERING_WHEEL_TORQUE_NM)
    u = res.state(L.U_MPS)
    t = res.time_s
    held = (t > 1.6) & (t < 4.0)
    assert np.all(np.abs(u[held]) < 1e-6)
    # turned left at rest: the patch resists, the torque pushes the wheel back to the right
    # (what it takes to turn a parked car's wheel, through the assist)
    assert np.all(torque[held] < 0.0)
    # the patch torsion is at its bore-friction limit: (2/3) mu r Fz per wheel
    twist = res.states[held, L.PATCH_TWIST0]
    fz = res.outputs[held, L.O_FZ0]
    np.testing.assert_allclose(p["patch_torsion_stiffness_nm_per_rad"] * twist,
                               p["patch_bore_arm_m"] * fz, rtol=1e-3)
    # it stays while the car is still: unchanged over 2.4 s to 1e-6 of itself (the body
    # settles on its springs, so the loads move a little)
    assert np.ptp(torque[held]) < 1e-3 * np.abs(torque[held]).max()
    # ... and relaxes as the car rolls: the torsion decays with the distance travelled,
    # exp(-s / b) (paper eq. 16's relaxation length b)
    # (row k + 1 holds the torsion after step k, which decays it by exp(-|u_k| dt / b) with
    # u_k the hub speed of row k). From the first row after the release where the bore limit
    # no longer binds (the load moves off the front axle as the car pulls away), over two
    # relaxation lengths rolled:
    tw = res.states[:, L.PATCH_TWIST0]
    limit = (p["patch_bore_arm_m"] * res.outputs[:, L.O_FZ0]
             / p["patch_torsion_stiffness_nm_per_rad"])
    k0 = np.argmax((t > 4.0) & (np.abs(np.roll(tw, -1)) < 0.99 * limit))
    rolled = np.cumsum(np.abs(res.outputs[:, L.O_HUB_U0 + L.FL])) * res.scenario.dt_s
    k1 = np.argmax(rolled > rolled[k0] + 2.0 * b)
    assert k0 > 0 and k1 > k0 and torque[k1] < 0.0
    expected = math.exp(-(rolled[k1] - rolled[k0]) / b)
    assert expected < math.exp(-1.99)
    assert tw[k1 + 1] / tw[k0 + 1] == pytest.approx(expected, rel=1e-9)  # rounding only
    # and the torque has lost what the torsion gave it
    assert abs(torque[k1]) < 0.5 * abs(torque[held]).min()


@pytest.mark.parametrize("vehicle_dir", [SEDAN, HATCH], ids=["brush", "mf61"])
def test_no_step_in_the_torque_when_the_car_stops_or_restarts(tmp_path, vehicle_dir):
    # a slow left turn, braked to rest, held, then driven off again, the steer held
    p = _steering_params(vehicle_dir)
    steer = 0.15 * p["steering_ratio"] / p["steering_wheel_max_rad"]
    res = _run(tmp_path, vehicle_dir, 4.0, [
        {"t": 0.0, "steer": steer, "throttle": 0.05, "brake": 0.0, "gear": "D"},
        {"t": 2.0, "throttle": 0.05, "brake": 0.0}, {"t": 2.2, "throttle": 0.0, "brake": 0.3},
        {"t": 5.0, "throttle": 0.0, "brake": 0.3}, {"t": 5.2, "throttle": 0.3, "brake": 0.0},
    ], 8.0)
    torque = res.state(L.STEERING_WHEEL_TORQUE_NM)
    u = res.state(L.U_MPS)
    assert np.abs(u[4500]) < 1e-3 and u[-1] > 1.0  # it stopped, and it drove off
    # the largest change from one 1 ms step to the next over the stop and the restart,
    # against the torque's own scale: a step would be a jump of the order of the torque
    # (from 1.5 s: the car starts with its wheels steered and its slips at zero)
    jumps = np.abs(np.diff(torque[1500:]))
    scale = np.abs(torque[1500:]).max()
    assert scale > 0.5
    assert jumps.max() < 0.01 * scale, (jumps.max(), scale)


def test_the_motion_does_not_depend_on_the_steering_system(tmp_path):
    """Change every steering-system parameter: the car moves bit for bit the same."""
    base = yaml.safe_load((SEDAN / "vehicle.yaml").read_text())
    for key in ("chassis", "suspension", "brakes", "powertrain"):
        base[key] = str(SEDAN / base[key])
    steering = yaml.safe_load((SEDAN / "steering.yaml").read_text())
    other = dict(steering, caster_trail_m=0.05, scrub_radius_m=-0.02, kingpin_inclination_rad=0.3,
                 patch_torsion_stiffness_nm_per_rad=900.0, assist_boost_parking=0.0,
                 column_friction_nm=3.0, column_damping_nm_s_per_rad=1.0)
    base["tires"] = {k: str((SEDAN / v).resolve()) for k, v in base["tires"].items()}
    results = []
    for name, values in (("a", steering), ("b", other)):
        (tmp_path / f"steer_{name}.yaml").write_text(yaml.safe_dump(values))
        (tmp_path / f"car_{name}.yaml").write_text(
            yaml.safe_dump(dict(base, steering=str(tmp_path / f"steer_{name}.yaml"))))
        data = {"name": "motion", "vehicle": str(tmp_path / f"car_{name}.yaml"),
                "initial": {"u_mps": 12.0}, "duration_s": 3.0,
                "inputs": [{"t": 0.0, "steer": 0.0, "gear": "D"}, {"t": 0.5, "steer": 0.3},
                           {"t": 1.5, "brake": 0.0}, {"t": 1.6, "brake": 0.7}]}
        path = tmp_path / f"run_{name}.yaml"
        path.write_text(yaml.safe_dump(data))
        results.append(run_scenario(load_scenario(path)))
    a, b = results
    first_steering_slot = L.STEERING_WHEEL_ANGLE_RAD
    assert np.array_equal(a.states[:, :first_steering_slot], b.states[:, :first_steering_slot])
    assert np.array_equal(a.outputs, b.outputs)
    assert not np.array_equal(a.state(L.STEERING_WHEEL_TORQUE_NM),
                              b.state(L.STEERING_WHEEL_TORQUE_NM))
