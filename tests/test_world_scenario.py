"""Headless scenarios with several cars on one terrain (``cars:``, issue 29).

The shipped two-car hill scenario: one car braked at rest on a 15 % grade, one driving up
behind it and stopping 2 m short. Each car's history equals that car run alone, bit for
bit, and the order of the cars in the file changes nothing.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from simserver.adapters.config import ConfigError, read_yaml
from simserver.adapters.history import CAR_ID_COLUMN, read_history, write_world_history
from simserver.core import layout as L
from simserver.core.params import VP_CG_TO_FRONT_AXLE_M, VP_CG_TO_REAR_AXLE_M
from simserver.sim.scenario import load_world_scenario, run_scenario, run_world_scenario
from simserver.testing import REPO

HILL = REPO / "configs" / "scenarios" / "two_car_hill_stop_short.yaml"
OVERHANG_M = 0.85  # the viewer's body boxes (adapters.rerun_scene.CarGeometry.body_boxes)


@pytest.fixture(scope="module")
def hill():
    return run_world_scenario(load_world_scenario(HILL))


def _same(a, b) -> None:
    for name in ("states", "outputs", "inputs", "final_state", "time_s"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


def test_each_car_of_the_hill_is_that_car_alone_bit_for_bit(hill):
    world = load_world_scenario(HILL)
    assert list(hill.cars) == ["lead", "follower"]
    for cid, scenario in world.cars.items():
        _same(hill.cars[cid], run_scenario(scenario))


def test_the_follower_stops_2_m_short_of_the_braked_lead(hill):
    """Bumper to bumper along the grade (the cars drive along world x on a plane with no
    cross-slope: the road-plane x is the distance along the road)."""
    lead, follower = hill.cars["lead"], hill.cars["follower"]
    vp = load_world_scenario(HILL).first.scene.vehicle.vp
    a, b = vp[VP_CG_TO_FRONT_AXLE_M], vp[VP_CG_TO_REAR_AXLE_M]
    x_lead = lead.states[:, L.X_M]
    x_follow = follower.states[:, L.X_M]
    gap = (x_lead - b - OVERHANG_M) - (x_follow + a + OVERHANG_M)
    assert abs(gap[-1] - 2.0) < 0.05, gap[-1]
    assert gap.min() > 1.9  # it never came closer
    assert np.abs(x_lead - x_lead[0]).max() < 0.01  # the lead stays put (tire springs)
    assert abs(follower.states[-1, L.U_MPS]) < 1e-3 and abs(lead.states[-1, L.U_MPS]) < 1e-3
    assert x_follow.max() - x_follow[0] > 5.0  # the follower did drive up


def test_the_order_of_the_cars_in_the_file_changes_nothing(hill):
    data = dict(read_yaml(HILL))
    data["cars"] = list(reversed(data["cars"]))
    swapped = run_world_scenario(load_world_scenario(HILL, data))
    assert list(swapped.cars) == ["follower", "lead"]
    for cid in hill.cars:
        _same(swapped.cars[cid], hill.cars[cid])


def test_one_history_with_a_car_id_column(hill, tmp_path):
    path = write_world_history(hill.cars, tmp_path / "history.parquet")
    cols = read_history(path)
    assert next(iter(cols)) == CAR_ID_COLUMN
    ids = cols[CAR_ID_COLUMN]
    for cid, result in hill.cars.items():
        rows = ids == cid
        assert rows.sum() == len(result.time_s)
        assert np.array_equal(cols["x_m"][rows], result.states[:, L.X_M])
        assert np.array_equal(cols["time_s"][rows], result.time_s)


def test_a_car_with_a_bad_key_is_named(tmp_path):
    data = dict(read_yaml(HILL))
    data["cars"] = [dict(c) for c in data["cars"]]
    data["cars"][1]["initial"] = {"x_m": 0.0, "speed": 3.0}
    with pytest.raises(ConfigError, match=r"^car 'follower' \(cars\[1\]\): .*'speed'"):
        load_world_scenario(HILL, data)
    data["cars"][1] = dict(data["cars"][0])
    with pytest.raises(ConfigError, match=r"key 'cars\[1\]\.id': 'lead' is given twice"):
        load_world_scenario(HILL, data)
    with pytest.raises(ConfigError, match=r"key 'cars': expected a non-empty list"):
        load_world_scenario(HILL, {**data, "cars": []})


def test_overlapping_starts_are_refused_naming_the_file_and_both_cars():
    """A headless world refuses what the live server's ``cars:`` refuses (issue 30, Bad
    input): two starts whose bodies overlap (the contact stage's boxes, one check:
    ``simserver.sim.scene.check_starts_apart``), the error naming the file and both cars
    in the server's words. Before, a headless world of overlapping cars ran: the contact
    threw them apart on the first step."""
    from simserver.core.contact import body_box
    from simserver.server import cars_config

    data = dict(read_yaml(HILL))
    data["cars"] = [dict(c) for c in data["cars"]]
    vp = load_world_scenario(HILL).first.scene.vehicle.vp
    front_m, rear_m, half_m = body_box(vp)
    for x_m, overlaps in ((front_m + rear_m + 0.01, False), (front_m + rear_m - 0.01, True)):
        data["cars"][1]["initial"] = {"x_m": data["cars"][0]["initial"]["x_m"] - x_m}
        if not overlaps:  # bumper to bumper, 1 cm apart: fine
            load_world_scenario(HILL, data)
            continue
        with pytest.raises(ConfigError) as err:
            load_world_scenario(HILL, data)
        assert str(err.value).startswith(f"{HILL}: cars[1] (follower): its start "), err.value
        assert "overlaps the start of car 'lead'" in str(err.value)
        # the live server's words for the same two cars (its where: FILE: cars[k] (id))
        specs = cars_config.parse_cars(HILL, [
            {"id": "lead", "pose": {"x_m": 20.82, "y_m": 0.0}},
            {"id": "follower", "pose": {"x_m": 20.82 - x_m, "y_m": 0.0}}])
        scene = load_world_scenario(HILL, {**data, "cars": data["cars"][:1]}).first.scene
        with pytest.raises(ConfigError) as live:
            cars_config.car_scenes(specs, scene)
        assert str(live.value) == str(err.value)
    # side by side, one turned: the rectangles meet at a corner only
    data["cars"][1]["initial"] = {"x_m": 20.82, "y_m": 2 * half_m + 0.05, "yaw_rad": 0.3}
    with pytest.raises(ConfigError, match=r"cars\[1\] \(follower\): its start .* overlaps"):
        load_world_scenario(HILL, data)


def test_more_cars_than_max_cars_and_an_id_twice_are_refused():
    data = dict(read_yaml(HILL))
    cars = [dict(data["cars"][0], id=f"car{k}", initial={"x_m": 10.0 * k}) for k in range(3)]
    assert len(load_world_scenario(HILL, {**data, "cars": cars}).cars) == 3
    with pytest.raises(ConfigError, match=rf"^{HILL}: key 'cars': 3 cars, more than "
                                          r"max_cars \(2\)$"):
        load_world_scenario(HILL, {**data, "max_cars": 2, "cars": cars})
    with pytest.raises(ConfigError, match=rf"^{HILL}: key 'max_cars'"):
        load_world_scenario(HILL, {**data, "max_cars": 0, "cars": cars})
    cars[2]["id"] = "car0"
    with pytest.raises(ConfigError, match=r"key 'cars\[2\]\.id': 'car0' is given twice \(the "
                                          r"id of cars\[0\] \(car0\) too\)"):
        load_world_scenario(HILL, {**data, "cars": cars})


def test_a_start_off_the_road_is_refused_naming_the_file_and_the_car():
    """A headless world's starts are checked as the live server's (``simserver.sim.scene.
    check_on_road``): on an OpenDRIVE terrain on a lane, on a height map on its grid.
    Before, a car half a metre beyond the road's edge, or off the map, ran."""
    import math

    from simserver.adapters.opendrive import load_opendrive, road_extent

    lane = REPO / "configs" / "scenarios" / "driver_lane_follow_curves.yaml"
    data = dict(read_yaml(lane))
    road = load_opendrive(REPO / "configs" / "roads" / "curves_elevation.xodr").roads[0]
    right, _ = road_extent(road, 100.0)
    rx, ry, hdg = road.reference(100.0)
    keyed = {"vehicle": data["cars"][0]["vehicle"],
             "inputs": [{"t": 0.0, "brake": 0.5, "gear": "D"}]}

    def beside(offset_m: float) -> dict:  # a car beside the road's right edge at s 100 m
        t_m = -right + offset_m
        return {"id": "ditch", **keyed, "initial": {
            "x_m": rx + math.sin(hdg) * t_m, "y_m": ry - math.cos(hdg) * t_m,
            "yaw_rad": hdg}}

    load_world_scenario(lane, {**data, "cars": [data["cars"][0], beside(-0.1)]})  # on it
    with pytest.raises(ConfigError) as err:
        load_world_scenario(lane, {**data, "cars": [data["cars"][0], beside(0.5)]})
    assert str(err.value).startswith(f"{lane}: cars[1] (ditch): the start ("), err.value
    assert "is off the road: not on a lane of curves_elevation.xodr" in str(err.value)
    hills = REPO / "configs" / "scenarios" / "terrain_hills_heightmap.yaml"
    one = {k: v for k, v in read_yaml(hills).items() if k not in ("vehicle", "initial",
                                                                 "inputs")}
    on_map = {"id": "a", **keyed, "vehicle": "../vehicles/paper_sedan/vehicle.yaml",
              "initial": {"x_m": 55.0, "y_m": 0.0}}
    off_map = {**on_map, "id": "b", "initial": {"x_m": 55.0, "y_m": -50.0}}
    load_world_scenario(hills, {**one, "cars": [on_map]})
    with pytest.raises(ConfigError, match=rf"^{hills}: cars\[1\] \(b\): the start "
                                          r"\(55.00, -50.00\) m is off the height map"):
        load_world_scenario(hills, {**one, "cars": [on_map, off_map]})


def test_an_openscenario_file_with_overlapping_entities_is_refused(tmp_path):
    """The OpenSCENARIO player builds its world through the same loader: entities placed
    into each other are refused, naming the .xosc file."""
    from simserver.sim.xosc_run import setup

    src = REPO / "configs" / "openscenario" / "simserver" / "hill_queue_15pct.xosc"
    setup(src, 1.0)  # as shipped: 3 cars apart
    text = src.read_text()
    lane_s = re.compile(r'(<LanePosition [^>]*\bs=")[^"]*(")')
    assert len(lane_s.findall(text)) == 3
    shutil.copytree(src.parents[1], tmp_path / "openscenario")  # its catalogs and road
    bad = tmp_path / "openscenario" / "simserver" / src.name
    bad.write_text(lane_s.sub(r"\g<1>20\g<2>", text))  # every car at s = 20 m of one lane
    with pytest.raises(ConfigError, match=rf"^{bad}: cars\[1\] \(\w+\): its start .* overlaps "
                                          r"the start of car"):
        setup(bad, 1.0)


def test_run_scenario_writes_one_history_and_plots_every_car(tmp_path):
    """``simserver run-scenario`` as a real subprocess on the two-car scenario."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "simserver.cli", "run-scenario", str(HILL),
                           "--out", str(out)], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    cols = read_history(out / "history.parquet")
    assert sorted(set(cols[CAR_ID_COLUMN])) == ["follower", "lead"]
    assert (out / "cars.png").stat().st_size > 10_000
    for cid in ("lead", "follower"):
        assert (out / cid / "speed.png").is_file()
    assert "2 cars" in proc.stdout
