"""The built-in driver (issue 30 item 2, ``simserver.core.driver``, docs/model.md section 15).

Every figure is measured from the run's history (the states the car step wrote) and the
road's geometry, not from what the driver itself saw: the lateral error against the lane's
centre sampled from the OpenDRIVE file, the gaps from the cars' road-plane positions and
their bumpers (CG to axle plus the driver's overhangs of 0.85 m, the viewer's bodies).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from benchmarks.hill_queue_rollback import (
    bumper_gap,
    figures_line,
    hill_queue_figures,
    run_hill_queue,
)
from simserver.adapters.config import ConfigError, load_vehicle, read_yaml
from simserver.adapters.history import CAR_ID_COLUMN, read_history
from simserver.adapters.opendrive import lane_start, load_opendrive
from simserver.core import driver as D
from simserver.core import layout as L
from simserver.core import params as P
from simserver.core.contact import body_box
from simserver.core.param_table import slot_constants_source
from simserver.core.params import VP_CG_HEIGHT_M, VP_CG_TO_FRONT_AXLE_M, VP_CG_TO_REAR_AXLE_M
from simserver.core.pose import world_pose
from simserver.core.road import road_axes
from simserver.sim.scenario import (
    load_scenario,
    load_world_scenario,
    run_scenario,
    run_world_scenario,
)
from simserver.testing import REPO
from tests.conftest import slow_enabled

SCENARIOS = REPO / "configs" / "scenarios"
LANE = SCENARIOS / "driver_lane_follow_curves.yaml"
FOLLOW = SCENARIOS / "driver_follow_brake_to_stop.yaml"
HILL = SCENARIOS / "hill_queue_15pct.yaml"
XODR = REPO / "configs" / "roads" / "curves_elevation.xodr"
VEHICLE = REPO / "configs" / "vehicles" / "paper_sedan" / "vehicle.yaml"


# ---------------------------------------------------------------- the lane of curves_elevation
def lane_error_m(result) -> np.ndarray:
    """Distance of the CG (world x, y from the history's states, ``core.pose.world_pose``
    on each row's reference plane) to lane -1's centre of road 1: the polyline through
    its points every 5 cm from ``lane_start`` (the lane's geometry from the file; the
    chords miss the arcs by under 0.1 mm)."""
    od = load_opendrive(XODR)
    road = od.roads[0]
    s = np.arange(0.0, road.length, 0.05)
    centre = np.array([lane_start(od, road.id, float(si), -1)[:2] for si in s])
    vp = result.scenario.scene.vehicle.vp
    pose = np.zeros(L.N_POSE)
    cg = np.empty((len(result.states), 2))
    for k, x in enumerate(result.states):
        world_pose(x, road_axes(x[L.REF_GRADE_PCT], x[L.REF_CROSS_SLOPE_PCT]),
                   vp[VP_CG_HEIGHT_M], pose)
        cg[k] = pose[L.POSE_X_M], pose[L.POSE_Y_M]
    err = np.empty(len(cg))
    for lo in range(0, len(cg), 512):  # the nearest sample, then its two segments
        p = cg[lo:lo + 512]
        d = p[:, None, :] - centre[None, :, :]
        i = np.clip(np.argmin(np.sum(d * d, axis=2), axis=1), 1, len(centre) - 2)
        best = np.full(len(p), np.inf)
        for j0 in (i - 1, i):
            a, b = centre[j0], centre[j0 + 1]
            e = b - a
            t = np.clip(np.sum((p - a) * e, axis=1) / np.sum(e * e, axis=1), 0.0, 1.0)
            r = p - a - t[:, None] * e
            best = np.minimum(best, np.sqrt(np.sum(r * r, axis=1)))
        err[lo:lo + 512] = best
    return err


@pytest.mark.parametrize("duration_s", [
    pytest.param(30.0, id="30s"),
    pytest.param(60.0, id="60s", marks=pytest.mark.slow),
])
def test_follows_a_lane_of_curves_elevation_at_15_mps_within_0p3_m_rms(duration_s, request):
    """Acceptance: lane -1 of curves_elevation.xodr at 15 m/s, lateral error under 0.3 m
    RMS. The short form covers the first 450 m (the straight, the long left arc of 143 m
    radius and the spirals into the right turn); the long form 900 m."""
    if duration_s > 40.0 and not slow_enabled(request.config.getoption("markexpr")):
        pytest.skip("long form: run with -m slow or SIMSERVER_SLOW=1")
    scenario = dataclasses.replace(load_world_scenario(LANE).cars["driven"],
                                   duration_s=duration_s)
    result = run_scenario(scenario)
    assert np.isfinite(result.states).all()
    err = lane_error_m(result)
    rms = float(np.sqrt(np.mean(err ** 2)))
    assert rms < 0.3, rms
    u = result.states[:, L.U_MPS]
    assert abs(float(np.mean(u)) - 15.0) < 0.2 and u.min() > 14.5, (u.mean(), u.min())
    # the driver's own record agrees with the independent measure (to its 0.5 m polyline)
    own = np.abs(result.driver_states[:, D.DS_LATERAL_M])
    assert np.max(np.abs(own - err)) < 0.02
    # the driver drove: the inputs in the history are its steer and pedals
    assert np.ptp(result.inputs[:, L.IN_STEER]) > 0.05
    assert (result.inputs[:, L.IN_GEAR] == L.GEAR_D).all()


# ---------------------------------------------------------------- a car that brakes to a stop
@pytest.fixture(scope="module")
def follow():
    return run_world_scenario(load_world_scenario(FOLLOW))


def idm_gap_m(v_mps: float, v0_mps: float, t_s: float, s0_m: float, delta: float) -> float:
    """The IDM's equilibrium gap behind a car at constant speed (Treiber et al. 2000):
    s* = (s0 + v T) / sqrt(1 - (v/v0)^delta)."""
    return (s0_m + v_mps * t_s) / math.sqrt(1.0 - (v_mps / v0_mps) ** delta)


def test_keeps_a_2_s_time_gap_behind_a_car_at_15_mps(follow):
    """Settled (30 .. 40 s, before the lead brakes at about 41 s): the gap is the IDM's
    closed form for the lead's speed to 0.5 % (what is left of the settling: the gap's
    error decays with a time constant of about 6 s from 3 % at the start), and the time
    gap (gap - s0) / v is 2 s to 2 %: the closed form itself puts it 1 % above T, by
    the factor 1 / sqrt(1 - (v/v0)^4) with v/v0 = 15/40."""
    lead, follower = follow.cars["lead"], follow.cars["follower"]
    vp = follower.scenario.scene.vehicle.vp
    gap = bumper_gap(lead, follower, vp)
    t = follower.time_s
    window = (t >= 30.0) & (t <= 40.0)
    v_lead = lead.states[window, L.U_MPS]
    v = follower.states[window, L.U_MPS]
    assert np.abs(v_lead - 15.0).max() < 0.01  # a constant-speed lead
    expected = np.array([idm_gap_m(vl, 40.0, 2.0, 2.0, 4.0) for vl in v_lead])
    assert np.abs(gap[window] / expected - 1.0).max() < 0.005
    time_gap = (gap[window] - 2.0) / v
    assert np.abs(time_gap / 2.0 - 1.0).max() < 0.02, (time_gap.min(), time_gap.max())


def test_stops_within_2p5_m_behind_a_car_braking_to_a_stop_without_touching(follow):
    lead, follower = follow.cars["lead"], follow.cars["follower"]
    vp = follower.scenario.scene.vehicle.vp
    gap = bumper_gap(lead, follower, vp)
    assert lead.states[:, L.U_MPS].min() < 1e-3  # the lead did stop ...
    braking = np.diff(lead.states[:, L.U_MPS]) / np.diff(lead.time_s)
    assert braking.min() < -2.5  # ... braking at 3 m/s^2
    assert abs(follower.states[-1, L.U_MPS]) < 1e-3
    assert 2.0 <= gap[-1] <= 2.5, gap[-1]
    assert gap.min() > 1.9, gap.min()  # never closer: no contact (the bodies are 0 m apart)
    # held with the brake at the end
    assert follower.driver_states[-1, D.DS_MODE] == D.MODE_HOLD
    assert follower.inputs[-1, L.IN_BRAKE] > 0.0


# ---------------------------------------------------------------- the hill queue
@pytest.fixture(scope="module")
def hill():
    return run_world_scenario(load_world_scenario(HILL))


def test_hill_queue_stops_1_m_behind_holds_and_follows_at_2_s(hill):
    driven, traffic = hill.cars["driven"], hill.cars["traffic"]
    vp = traffic.scenario.scene.vehicle.vp
    t = traffic.time_s
    gap = bumper_gap(driven, traffic, vp)
    # the traffic car stops 1.0 m behind (the IDM's s0) and never comes closer than 0.99 m
    assert gap.min() >= 0.99, gap.min()
    held = (t >= 22.0) & (t < 25.0)
    assert np.all((gap[held] >= 1.0) & (gap[held] <= 1.02)), (gap[held].min(), gap[held].max())
    assert (traffic.driver_states[held, D.DS_MODE] == D.MODE_HOLD).all()
    # the hold on 15 %: creep under 1 mm (from a second after the stop to the drive-off)
    x = traffic.states[:, L.X_M]
    assert np.ptp(x[held]) < 1e-3, np.ptp(x[held])
    # the driven car drives off at 25 s: its rollback under 1 mm
    xd = driven.states[:, L.X_M]
    off = t >= 25.0
    assert xd[off][0] - xd[off].min() < 1e-3
    # the traffic car drives off behind it, without rolling back
    after = t >= 25.0
    assert x[after][0] - x[after].min() < 1e-3, x[after][0] - x[after].min()
    assert x[-1] - x[after][0] > 30.0
    # ... and follows at a 2 s time gap: the lead still gathers speed (0.08 m/s^2), so
    # the follower's gap runs a little behind the closed form's; 5 %
    late = t >= 50.0
    time_gap = (gap[late] - 1.0) / traffic.states[late, L.U_MPS]
    assert np.abs(time_gap / 2.0 - 1.0).max() < 0.05, (time_gap.min(), time_gap.max())
    # it started from rest on the grade (a launch from its own hold): no rollback either
    start = t < 2.0
    assert x[0] - x[start].min() < 1e-3
    # the figures docs/model.md section 15 quotes (python -m benchmarks.hill_queue_rollback)
    figures = hill_queue_figures(hill)
    print("\n" + figures_line("lagged", figures))
    assert figures["driven_rollback_m"] == xd[off][0] - xd[off].min()
    assert figures["gap_min_m"] == gap.min()


def test_hill_queue_with_kinematic_slip_creeps_and_rolls_back():
    """The same scene with the kinematic slip variant (both cars): the held cars creep down
    the grade (about 53 mm over the 3 s before the drive-off, 0.35 m over 20 s) and roll
    back at the drive-off (about 11 mm the driven car, 23 mm the traffic car): the rollback
    the paper warns about, which the lagged slip states do not show (the test above). The
    driver keeps its queue gap all the same (both cars creep alike). The figures are
    ``benchmarks.hill_queue_rollback``'s (the same windows: the hold 22 to 25 s, the
    rollback from 25 s), printed with ``-s``."""
    figures = hill_queue_figures(run_hill_queue("kinematic"))
    print("\n" + figures_line("kinematic", figures))  # docs/model.md section 15 quotes it
    for car in ("driven", "traffic"):
        assert figures[f"{car}_creep_m"] > 0.02, figures
        assert figures[f"{car}_rollback_m"] > 0.005, figures
    assert figures["gap_min_m"] >= 0.99


def test_stop_point_hold_with_the_parking_brake_and_go_on_15pct(tmp_path):
    """A single driven car on 15 %: stops with its front bumper at station 60 m, holds
    with brake and parking brake (creep under 1 mm over 8 s), and drives off at the go
    time with no rollback beyond 1 mm."""
    data = {
        "name": "stop_and_go", "vehicle": str(VEHICLE), "road": {"grade_pct": 15.0},
        "initial": {"x_m": 0.0, "u_mps": 8.0, "relaxed": 1}, "duration_s": 30.0,
        "record_every": 10,
        "driver": {"path": {"points": [[-10.0, 0.0], [500.0, 0.0]]}, "idm": {"v0_mps": 8.0},
                   "stop_s_m": 60.0, "go_t_s": 22.0, "hold_parking_brake": 1.0},
    }
    result = run_scenario(load_scenario(tmp_path / "stop_and_go.yaml", data))
    t = result.time_s
    ds = result.driver_states
    x = result.states[:, L.X_M]
    vp = result.scenario.scene.vehicle.vp
    held = (t >= 13.0) & (t < 22.0)
    assert (ds[held, D.DS_MODE] == D.MODE_HOLD).all()
    assert (result.inputs[held, L.IN_PARKING_BRAKE] == 1.0).all()
    assert np.ptp(x[held]) < 1e-3, np.ptp(x[held])
    # the front bumper at station 60 m: the path starts at world x = -10 m and its
    # stations run along the grade; the CG's world x from its road-plane state (the
    # plane's axes, the CG's height along the plane's normal: core.pose.world_pose)
    axes = road_axes(15.0, 0.0)
    row = result.states[np.argmax(held)]
    lift = vp[VP_CG_HEIGHT_M] + row[L.HEAVE_M]
    world_x = row[L.X_M] * axes[0, 0] + lift * axes[2, 0]
    front = (world_x + 10.0) * math.hypot(1.0, 0.15) + body_box(vp)[0]
    assert 59.97 <= front <= 60.01, front
    after = t >= 22.0
    assert x[after][0] - x[after].min() < 1e-3
    assert result.states[-1, L.U_MPS] > 2.0 and ds[-1, D.DS_MODE] == D.MODE_DRIVE


# ---------------------------------------------------------------- the IDM's closed form
def test_idm_steady_state_gap_is_the_closed_form_behind_a_constant_speed_car(tmp_path):
    """A lead held at 10 m/s by its own driver, a follower with v0 = 20 m/s, T = 1.5 s,
    s0 = 2 m, delta = 4: the settled bumper gap is s* = (s0 + vT)/sqrt(1 - (v/v0)^delta)
    (17.56 m) to 0.3 % (the settling left after 50 s; the lead's speed is taken as
    measured)."""
    path = {"points": [[-50.0, 0.0], [2000.0, 0.0]]}
    car = {"vehicle": str(VEHICLE)}
    data = {"name": "idm_closed_form", "duration_s": 60.0, "record_every": 50, "cars": [
        {**car, "id": "lead", "initial": {"x_m": 30.0, "u_mps": 10.0, "relaxed": 1},
         "driver": {"path": path, "idm": {"v0_mps": 10.0}}},
        {**car, "id": "follower", "initial": {"x_m": 0.0, "u_mps": 10.0, "relaxed": 1},
         "driver": {"path": path, "idm": {"v0_mps": 20.0, "T_s": 1.5, "s0_m": 2.0,
                                          "delta": 4.0}}},
    ]}
    result = run_world_scenario(load_world_scenario(tmp_path / "idm.yaml", data))
    lead, follower = result.cars["lead"], result.cars["follower"]
    gap = bumper_gap(lead, follower, follower.scenario.scene.vehicle.vp)
    late = follower.time_s >= 50.0
    v_lead = lead.states[late, L.U_MPS]
    assert np.abs(v_lead - 10.0).max() < 0.01
    expected = np.array([idm_gap_m(v, 20.0, 1.5, 2.0, 4.0) for v in v_lead])
    assert np.abs(gap[late] / expected - 1.0).max() < 0.003, (gap[late][-1], expected[-1])
    # the kernel's IDM is zero at the closed form's gap (the equilibrium it defines)
    dp = np.zeros(D.N_DRIVER_PARAM)
    for p in D.IDM:
        dp[p.slot] = p.default
    dp[D.DP_IDM_T_S], dp[D.DP_IDM_S0_M] = 1.5, 2.0
    assert abs(D.idm_accel(10.0, 20.0, idm_gap_m(10.0, 20.0, 1.5, 2.0, 4.0), 10.0, dp)) < 1e-12


def test_closed_loop_runs_are_bit_for_bit_repeatable(tmp_path):
    data = read_yaml(HILL)
    data = {**data, "duration_s": 3.0}
    a = run_world_scenario(load_world_scenario(HILL, data))
    b = run_world_scenario(load_world_scenario(HILL, data))
    for cid in a.cars:
        assert np.array_equal(a.cars[cid].states, b.cars[cid].states)
        assert np.array_equal(a.cars[cid].inputs, b.cars[cid].inputs)


def test_slot_constants_are_generated_from_the_tables():
    text = (REPO / "simserver" / "core" / "driver.py").read_text(encoding="utf-8")
    block = text.split("# --- generated slot constants\n")[1].split("# --- end of generated")[0]
    assert block == slot_constants_source(D.DRIVER_TABLES, "DP_")


# ---------------------------------------------------------------- bad driver configs
def _lane_scenario(tmp_path, driver: dict) -> dict:
    return {"name": "bad", "vehicle": str(VEHICLE), "duration_s": 1.0,
            "terrain": {"kind": "opendrive", "file": str(XODR), "cell_m": 0.5},
            "start": {"road": "1", "s": 20.0, "lane": -1}, "driver": driver}


@pytest.mark.parametrize(("driver", "key", "words"), [
    ({"path": {"road": "1", "lane": -5}}, "driver.path.lane", "no lane -5"),
    ({"path": {"road": "7", "lane": -1}}, "driver.path.road", "no road '7'"),
    ({"path": {"points": [[0.0, 0.0], [50.0, 0.0], [50.0, 80.0]]}}, "driver.path",
     "leaves the road"),
    ({"path": {"road": "1", "lane": -1}, "idm": {"T_s": -1.0}}, "driver.idm.T_s", "outside"),
    ({"path": {"road": "1", "lane": -1}, "preview_time_s": "far"},
     "driver.preview_time_s", "expected a number"),
    ({"path": {"road": "1", "lane": -1}, "speed_profile": [{"s_m": 10, "v_mps": 5},
                                                            {"s_m": 5, "v_mps": 5}]},
     "driver.speed_profile[1].s_m", "increase"),
])
def test_bad_driver_config_names_the_file_and_the_key(tmp_path, driver, key, words):
    path = tmp_path / "bad_driver.yaml"
    with pytest.raises(ConfigError) as exc:
        load_scenario(path, _lane_scenario(tmp_path, driver))
    message = str(exc.value)
    assert str(path) in message and f"'{key}'" in message and words in message, message
    assert "\n" not in message


def test_bad_driver_keys_name_the_car():
    data = copy.deepcopy(read_yaml(HILL))
    data["cars"][1]["driver"]["idm"]["tau_s"] = 1.0
    with pytest.raises(ConfigError) as exc:
        load_world_scenario(HILL, data)
    message = str(exc.value)
    assert "car 'traffic'" in message and "'tau_s'" in message and str(HILL) in message


def test_run_scenario_runs_the_hill_queue_closed_loop(tmp_path):
    """``simserver run-scenario`` as a real subprocess: the history holds the inputs the
    driver applied (the traffic car's brake held at the queue, its throttle after), and
    the summary the driver's section for the driven car only."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "simserver.cli", "run-scenario", str(HILL),
                           "--out", str(out), "--no-plots"], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    cols = read_history(out / "history.parquet")
    traffic = cols[CAR_ID_COLUMN] == "traffic"
    t = cols["time_s"][traffic]
    brake = cols["input_brake"][traffic]
    throttle = cols["input_throttle"][traffic]
    queued = (t > 22.0) & (t < 25.0)
    assert (brake[queued] == 0.5).all() and (throttle[queued] == 0.0).all()
    assert throttle[t > 40.0].min() > 0.1
    summary = json.loads((out / "summary.json").read_text())
    drv = summary["cars"]["traffic"]["driver"]
    assert 1.0 <= drv["gap_min_m"] <= 1.02 and drv["held_s"] > 3.0
    assert "driver" not in summary["cars"]["driven"]



# ---------------------------------------------------------------- who is a leader
def _first_drive(tmp_path, other: dict, driver: dict | None = None) -> np.ndarray:
    """The driven car's driver state after the first ``drive`` of a world where it runs
    at 10 m/s along +x from x = 0 and ``other`` (a car the driver does not drive) is
    ahead in its lane."""
    path = {"points": [[-50.0, 0.0], [2000.0, 0.0]]}
    data = {"name": "leader", "duration_s": 0.002, "record_every": 1, "cars": [
        {"vehicle": str(VEHICLE), "id": "driven",
         "initial": {"x_m": 0.0, "u_mps": 10.0, "relaxed": 1},
         "driver": {"path": path, "idm": {"v0_mps": 10.0}, **(driver or {})}},
        {"vehicle": str(VEHICLE), "id": "other", "initial": {"relaxed": 1, **other},
         "inputs": [{"t": 0.0, "throttle": 0.0, "brake": 0.0, "gear": "N"}]},
    ]}
    result = run_world_scenario(load_world_scenario(tmp_path / "leader.yaml", data))
    return result.cars["driven"].driver_states[0]


def test_an_oncoming_or_crossing_car_in_the_lane_is_an_obstacle_at_rest(tmp_path):
    """docs/model.md section 15: a car ahead in the lane is followed at its speed only when
    it heads along the path (within 30 degrees of its tangent). An oncoming car (heading
    back at 10 m/s) and a crossing one (60 degrees off, at 10 m/s) are obstacles at rest:
    the driver asks for exactly what it asks for behind a car standing with its facing
    bumper at the same place (an oncoming car is measured to its front bumper). With
    ``oncoming_stop: 0`` (a car overtaking in the oncoming lane) the oncoming car is no
    obstacle at all, while a car going its way still is."""
    vp = load_vehicle(VEHICLE).vp
    front, rear, _ = body_box(vp)  # the contact stage's box, the driver's too
    bumper_x = 40.0  # the facing bumper of the car ahead, on the path's axis
    standing = _first_drive(tmp_path, {"x_m": bumper_x + rear, "yaw_rad": 0.0, "u_mps": 0.0})
    assert standing[D.DS_LEADER] == 1.0
    assert standing[D.DS_ACCEL_CMD_MPS2] < -0.5  # it brakes for it: 40 m at 10 m/s
    oncoming = _first_drive(tmp_path, {"x_m": bumper_x + front, "yaw_rad": math.pi,
                                       "u_mps": 10.0})
    crossing = _first_drive(tmp_path, {"x_m": bumper_x + rear, "yaw_rad": math.radians(60.0),
                                       "u_mps": 10.0})
    for seen in (oncoming, crossing):
        assert seen[D.DS_LEADER] == 1.0
        assert seen[D.DS_GAP_M] == pytest.approx(standing[D.DS_GAP_M], abs=1e-6)
        assert seen[D.DS_ACCEL_CMD_MPS2] == pytest.approx(standing[D.DS_ACCEL_CMD_MPS2],
                                                          abs=1e-6)
    passing = _first_drive(tmp_path, {"x_m": bumper_x + front, "yaw_rad": math.pi,
                                      "u_mps": 10.0}, {"oncoming_stop": 0.0})
    assert passing[D.DS_LEADER] == -1.0 and passing[D.DS_GAP_M] == math.inf
    ahead = _first_drive(tmp_path, {"x_m": bumper_x + rear, "yaw_rad": 0.0, "u_mps": 0.0},
                         {"oncoming_stop": 0.0})
    assert ahead[D.DS_LEADER] == 1.0
    assert ahead[D.DS_ACCEL_CMD_MPS2] == standing[D.DS_ACCEL_CMD_MPS2]


def test_the_gap_is_measured_between_the_cars_contact_boxes(tmp_path):
    """The driver's bumpers are the cars' contact boxes (the vehicle's ``body_*``
    overhangs, docs/model.md section 16) unless its block gives others: behind a hatchback
    (body 0.58 m behind its rear axle) the gap the driver keeps is the gap between the two
    boxes, the one the contact stage sees, so a queue's s0 is s0 of air. Before, every car
    was taken to have the sedan's 0.85 m overhangs: 0.27 m of the gap behind a hatchback
    was its body that is not there."""
    hatch = REPO / "configs" / "vehicles" / "mf_hatchback" / "vehicle.yaml"
    path = {"points": [[-50.0, 0.0], [2000.0, 0.0]]}
    lead_x_m = 40.0
    data = {"name": "boxes", "duration_s": 0.002, "record_every": 1, "cars": [
        {"vehicle": str(VEHICLE), "id": "driven",
         "initial": {"x_m": 0.0, "u_mps": 10.0, "relaxed": 1},
         "driver": {"path": path, "idm": {"v0_mps": 10.0}}},
        {"vehicle": str(hatch), "id": "other", "initial": {"x_m": lead_x_m, "relaxed": 1},
         "inputs": [{"t": 0.0, "throttle": 0.0, "brake": 0.0, "gear": "N"}]},
    ]}
    result = run_world_scenario(load_world_scenario(tmp_path / "boxes.yaml", data))
    seen = result.cars["driven"].driver_states[0]
    mine = result.cars["driven"].scenario.scene.vehicle.vp
    theirs = result.cars["other"].scenario.scene.vehicle.vp
    assert theirs[P.VP_BODY_REAR_OVERHANG_M] == 0.58  # the premise: not the sedan's
    boxes_gap_m = ((result.cars["other"].states[0, L.X_M] - theirs[VP_CG_TO_REAR_AXLE_M]
                    - theirs[P.VP_BODY_REAR_OVERHANG_M])
                   - (result.cars["driven"].states[0, L.X_M] + mine[VP_CG_TO_FRONT_AXLE_M]
                      + mine[P.VP_BODY_FRONT_OVERHANG_M]))
    assert seen[D.DS_LEADER] == 1.0
    # within one step's travel (1 cm at 10 m/s: the driver's state and the row may be a
    # step apart), far inside the 0.27 m a sedan's overhang would put there
    assert seen[D.DS_GAP_M] == pytest.approx(boxes_gap_m, abs=0.011)
