"""The cars of a live server (``cars:``, simserver.server.fleet): parsing and the start checks.

Each bad list gets one error naming the config file and the car; the checks are the
issue 30 acceptance's bad inputs (two cars on one id, overlapping start poses, a car off
the road, more cars than the limit)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from simserver.adapters.config import ConfigError
from simserver.adapters.opendrive import lane_start, road_extent
from simserver.core import params as P
from simserver.core.contact import bodies_overlap, body_box
from simserver.server import cars_config, fleet
from simserver.sim.scene import load_scene, on_lane

REPO = Path(__file__).resolve().parents[1]
FLAT = REPO / "configs" / "scenes" / "flat_paper_sedan.yaml"
CREST = REPO / "configs" / "scenes" / "crest_curve_paper_sedan.yaml"
SEDAN = REPO / "configs" / "vehicles" / "paper_sedan" / "vehicle.yaml"
HATCH = REPO / "configs" / "vehicles" / "mf_hatchback" / "vehicle.yaml"


@pytest.fixture(scope="module")
def flat():
    return load_scene(FLAT)


@pytest.fixture(scope="module")
def crest():
    return load_scene(CREST)


def _cfg(tmp_path: Path) -> Path:
    path = tmp_path / "server.yaml"
    path.write_text("scene: x\n")
    return path


def test_two_cars_on_the_flat_get_their_poses_and_vehicles(tmp_path, flat):
    path = _cfg(tmp_path)
    cars = cars_config.parse_cars(path, [
        {"id": "car0"},
        {"id": "car1", "vehicle": str(HATCH), "pose": {"x_m": 10.0, "y_m": 0.5,
                                                       "yaw_rad": 0.1}}])
    assert [c.id for c in cars] == ["car0", "car1"]
    assert cars[1].vehicle == HATCH.resolve() and cars[1].driven_by == "client"
    scenes = cars_config.car_scenes(cars, flat)
    assert scenes["car0"].initial == {**flat.initial, "u_mps": 0.0}
    assert scenes["car1"].initial["x_m"] == 10.0 and scenes["car1"].initial["yaw_rad"] == 0.1
    assert scenes["car1"].vehicle.path == HATCH.resolve()
    assert scenes["car0"].vehicle is flat.vehicle
    assert scenes["car1"].terrain is flat.terrain  # one terrain: the world's


def test_duplicate_id_names_the_file_and_both_cars(tmp_path):
    path = _cfg(tmp_path)
    with pytest.raises(ConfigError) as err:
        cars_config.parse_cars(path, [{"id": "a"}, {"id": "b", "pose": {"x_m": 10, "y_m": 0}},
                                {"id": "a", "pose": {"x_m": 20, "y_m": 0}}])
    msg = str(err.value)
    assert msg.startswith(f"{path}: cars[2] (a): key 'id'") and "cars[0]" in msg


@pytest.mark.parametrize(("car_id", "why"), [
    ("world", "reserved"), ("a/b", "'/'"), ("x" * 33, "longer than 32"), ("c*", "wildcard"),
    (7, "expected a string")])
def test_bad_ids_are_named(tmp_path, car_id, why):
    with pytest.raises(ConfigError, match=why):
        cars_config.parse_cars(_cfg(tmp_path), [{"id": car_id}])


def test_more_cars_than_the_limit(tmp_path):
    path = _cfg(tmp_path)
    cars = [{"id": f"c{k}", "pose": {"x_m": 10.0 * k, "y_m": 0.0}} for k in range(5)]
    assert len(cars_config.parse_cars(path, cars, max_cars=5)) == 5
    with pytest.raises(ConfigError, match=r"key 'cars': 5 cars, more than max_cars \(4\)"):
        cars_config.parse_cars(path, cars, max_cars=4)


def test_entry_errors_name_the_car(tmp_path):
    path = _cfg(tmp_path)
    with pytest.raises(ConfigError, match=r"cars\[0\] \(a\).*unknown key 'colour'"):
        cars_config.parse_cars(path, [{"id": "a", "colour": "red"}])
    with pytest.raises(ConfigError, match=r"cars\[0\] \(a\): key 'driven_by'"):
        cars_config.parse_cars(path, [{"id": "a", "driven_by": "ghost"}])
    with pytest.raises(ConfigError, match=r"cars\[0\] \(a\): key 'keyframes'"):
        cars_config.parse_cars(path, [{"id": "a", "driven_by": "keyframes"}])
    with pytest.raises(ConfigError, match=r"cars\[0\] \(a\): key 'vehicle'.*no_such"):
        cars_config.parse_cars(path, [{"id": "a", "vehicle": "no_such.yaml"}])
    with pytest.raises(ConfigError, match=r"cars\[0\] \(a\): key 'start': give pose or"):
        cars_config.parse_cars(path, [{"id": "a", "pose": {"x_m": 0, "y_m": 0},
                                 "start": {"road": "0", "s": 1, "lane": -1}}])
    with pytest.raises(ConfigError, match=r"cars\[0\] \(a\): key 'pose.x_m'"):
        cars_config.parse_cars(path, [{"id": "a", "pose": {"x_m": float("nan"), "y_m": 0}}])


def test_overlapping_starts_name_both_cars(tmp_path, flat):
    path = _cfg(tmp_path)
    box = body_box(flat.vehicle.vp)
    length = box[0] + box[1]
    apart = cars_config.parse_cars(path, [{"id": "a", "pose": {"x_m": 0, "y_m": 0}},
                                    {"id": "b", "pose": {"x_m": length + 0.01, "y_m": 0}}])
    cars_config.car_scenes(apart, flat)  # bumper to bumper, 1 cm apart: fine
    close = cars_config.parse_cars(path, [{"id": "a", "pose": {"x_m": 0, "y_m": 0}},
                                    {"id": "b", "pose": {"x_m": length - 0.01, "y_m": 0}}])
    with pytest.raises(ConfigError) as err:
        cars_config.car_scenes(close, flat)
    assert str(err.value).startswith(f"{path}: cars[1] (b): its start") and "'a'" in str(err.value)
    # side by side, turned: rectangles that overlap only through a corner
    beside = cars_config.parse_cars(path, [{"id": "a", "pose": {"x_m": 0, "y_m": 0}},
                                     {"id": "b", "pose": {"x_m": 0, "y_m": 2 * box[2] + 0.05,
                                                          "yaw_rad": 0.0}}])
    cars_config.car_scenes(beside, flat)
    turned = cars_config.parse_cars(path, [{"id": "a", "pose": {"x_m": 0, "y_m": 0}},
                                     {"id": "b", "pose": {"x_m": 0, "y_m": 2 * box[2] + 0.05,
                                                          "yaw_rad": 0.3}}])
    with pytest.raises(ConfigError, match="overlaps"):
        cars_config.car_scenes(turned, flat)


def test_two_cars_on_the_scene_start_overlap(tmp_path, flat):
    cars = cars_config.parse_cars(_cfg(tmp_path), [{"id": "a"}, {"id": "b"}])
    with pytest.raises(ConfigError, match=r"cars\[1\] \(b\): its start .* overlaps"):
        cars_config.car_scenes(cars, flat)


def test_separating_axis_against_a_grid_of_points(flat):
    """bodies_overlap() (core.contact) agrees with a brute-force test (a dense grid of
    points of one rectangle inside the other) for rotated pairs."""
    box = (2.0, 1.5, 0.9)
    rng = __import__("numpy").random.default_rng(3)
    for _ in range(200):
        a = {"x_m": 0.0, "y_m": 0.0, "yaw_rad": float(rng.uniform(-3, 3))}
        b = {"x_m": float(rng.uniform(-5, 5)), "y_m": float(rng.uniform(-4, 4)),
             "yaw_rad": float(rng.uniform(-3, 3))}
        brute = _brute_overlap(a, b, box)
        if brute is None:
            continue  # within the grid's resolution of touching
        assert bodies_overlap(a, box, b, box) == brute


def _brute_overlap(a, b, box, n=60):
    import numpy as np

    front, rear, half = box
    u, v = np.meshgrid(np.linspace(-rear, front, n), np.linspace(-half, half, n))
    ca, sa = math.cos(a["yaw_rad"]), math.sin(a["yaw_rad"])
    px = a["x_m"] + ca * u - sa * v
    py = a["y_m"] + sa * u + ca * v
    cb, sb = math.cos(b["yaw_rad"]), math.sin(b["yaw_rad"])
    du, dv = px - b["x_m"], py - b["y_m"]
    lu, lv = cb * du + sb * dv, -sb * du + cb * dv
    margin = np.minimum(np.minimum(front - lu, lu + rear), np.minimum(half - lv, lv + half))
    if margin.max() > 0.05:
        return True
    if margin.max() < -0.05:
        return False
    return None


def test_off_the_road_on_opendrive(tmp_path, crest):
    path = _cfg(tmp_path)
    road = crest.roads.roads[0]
    right, left = road_extent(road, 100.0)
    x, y, yaw = lane_start(crest.roads, road.id, 100.0, -1)
    on = cars_config.parse_cars(path, [{"id": "a", "start": {"road": road.id, "s": 100.0,
                                                       "lane": -1}},
                                 {"id": "b", "pose": {"x_m": x + 30 * math.cos(yaw),
                                                      "y_m": y + 30 * math.sin(yaw),
                                                      "yaw_rad": yaw}}])
    scenes = cars_config.car_scenes(on, crest)
    assert scenes["a"].initial["x_m"] == pytest.approx(x)
    # half a metre beyond the outermost right lane's edge, beside lane -1's start
    rx, ry, hdg = road.reference(100.0)
    off_x, off_y = rx + math.sin(hdg) * (-right + 0.5), ry - math.cos(hdg) * (-right + 0.5)
    assert not on_lane(crest.roads, off_x, off_y)
    inside = -right - 0.1
    assert on_lane(crest.roads, rx + math.sin(hdg) * inside,
                               ry - math.cos(hdg) * inside)
    off = cars_config.parse_cars(path, [{"id": "a"}, {"id": "ditch", "pose": {
        "x_m": off_x, "y_m": off_y, "yaw_rad": hdg}}])
    with pytest.raises(ConfigError) as err:
        cars_config.car_scenes(off, crest)
    assert str(err.value).startswith(f"{path}: cars[1] (ditch): the start") and \
        "off the road" in str(err.value) and "crest-curve.xodr" in str(err.value)
    bad_lane = cars_config.parse_cars(path, [{"id": "a", "start": {"road": road.id, "s": 100.0,
                                                             "lane": -9}}])
    with pytest.raises(ConfigError, match=r"cars\[0\] \(a\): key 'start.lane'"):
        cars_config.car_scenes(bad_lane, crest)


def test_the_cars_world_steps_each_car_as_alone(tmp_path, flat):
    """build_world: one world of both cars; each car's bits are those of its run alone."""
    import numpy as np

    from simserver.sim.simulation import Simulation

    cars = cars_config.parse_cars(_cfg(tmp_path), [
        {"id": "a"}, {"id": "b", "vehicle": str(HATCH), "pose": {"x_m": 12.0, "y_m": 1.0}}])
    scenes = cars_config.car_scenes(cars, flat)
    sims = fleet.build_world(scenes, 0.001)
    world = sims["a"].world
    assert sims["b"].world is world and world.ids == ["a", "b"]
    alone = {cid: Simulation(scenes[cid], 0.001, car_id=cid) for cid in scenes}
    for k in range(400):
        for cid, throttle in (("a", 0.3), ("b", 0.5)):
            for sim in (sims[cid], alone[cid]):
                sim.inputs[:] = (0.1 * math.sin(k / 50), throttle, 0.0, 0.0, 3.0)
        world.step()
        for sim in alone.values():
            sim.step()
    for cid in scenes:
        assert np.array_equal(sims[cid].x, alone[cid].x), cid
    assert sims["b"].x[0] > 12.0  # it drove


def test_keyframe_table_samples_the_file_and_names_the_car(tmp_path):
    scenario = REPO / "configs" / "scenarios" / "e3_stop_from_turn.yaml"
    path = _cfg(tmp_path)
    car, = cars_config.parse_cars(path, [{"id": "k", "driven_by": "keyframes",
                                    "keyframes": str(scenario)}])
    table = cars_config.keyframe_table(car, 0.001)
    from simserver.sim.scenario import load_scenario, start_run

    sc = load_scenario(scenario)
    _, inputs = start_run(sc)
    n = min(len(inputs), len(table))
    assert np.array_equal(table[:n], inputs[:n])
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nduration_s: 1\ninputs: [{t: 0, gear: Q}]\n")
    car, = cars_config.parse_cars(path, [{"id": "k", "driven_by": "keyframes",
                                          "keyframes": str(bad)}])
    with pytest.raises(ConfigError, match=r"cars\[0\] \(k\): key 'keyframes'.*bad.yaml"):
        cars_config.keyframe_table(car, 0.001)


@pytest.mark.parametrize(("gap_m", "touch"), [(0.1, False), (1e-3, False), (-1e-3, True)])
def test_the_start_check_and_the_contact_agree_on_the_body(tmp_path, flat, gap_m, touch):
    """The start check's box is the contact stage's (the vehicle's ``body_*``
    parameters): two hatchbacks (body 0.80 m ahead of the front axle, 0.58 m behind the
    rear one) ``gap_m`` apart bumper to bumper are refused exactly when the contact stage
    finds them touching. Before, the check used the sedan's 0.85 m overhangs for every
    car: it refused hatchbacks 10 cm apart, and would pass a longer body into a start
    already in contact."""
    from simserver.core import layout as L
    from simserver.core.contact import N_CAR_CONTACT, POLY_MAX, pair_contact
    from simserver.core.contact import footprint as contact_footprint

    hatch = cars_config.car_scenes(cars_config.parse_cars(_cfg(tmp_path), [
        {"id": "a", "vehicle": str(HATCH)}]), flat)["a"]
    vp = hatch.vehicle.vp
    length_m = float(vp[P.VP_CG_TO_FRONT_AXLE_M] + vp[P.VP_BODY_FRONT_OVERHANG_M]
                     + vp[P.VP_CG_TO_REAR_AXLE_M] + vp[P.VP_BODY_REAR_OVERHANG_M])
    dx_m = length_m + gap_m
    boxes = []
    for x_m in (0.0, dx_m):  # the contact stage's view of the two cars at rest
        x = np.zeros(L.N_STATE)
        x[L.X_M] = x_m
        cc = np.zeros(N_CAR_CONTACT)
        contact_footprint(vp, x, np.zeros((3, 3)), True, cc)
        boxes.append(cc)
    depth = pair_contact(vp, vp, *boxes, np.zeros((2, POLY_MAX, 2)), 0.001, np.zeros(8), 0.0)
    assert (depth > 0.0) == touch
    cars = cars_config.parse_cars(_cfg(tmp_path), [
        {"id": "a", "vehicle": str(HATCH), "pose": {"x_m": 0.0, "y_m": 0.0}},
        {"id": "b", "vehicle": str(HATCH), "pose": {"x_m": dx_m, "y_m": 0.0}}])
    if touch:
        with pytest.raises(ConfigError, match=r"\(b\): its start .* overlaps the start of "
                                              "car 'a'"):
            cars_config.car_scenes(cars, flat)
    else:
        cars_config.car_scenes(cars, flat)
