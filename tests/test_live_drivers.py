"""Cars ``driven_by: driver`` in a live server's config and world (issue 30): the checks of
the ``cars:`` entry, and the driver arrays reassembled when the world's cars change
(``simserver.server.live_drivers``) keeping each driven car's driver state by id."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from simserver.adapters.config import ConfigError
from simserver.core import driver as D
from simserver.server.cars_config import car_scenes, driver_spec, parse_cars
from simserver.server.fleet import build_world
from simserver.server.live_drivers import LiveDrivers
from simserver.sim.scene import load_scene

REPO = Path(__file__).resolve().parents[1]
SCENE = REPO / "configs" / "scenes" / "hill_15pct_paper_sedan.yaml"
DRIVER = {"path": {"points": [[-50.0, 0.0], [2000.0, 0.0]]},
          "idm": {"v0_mps": 20.0, "T_s": 2.0, "s0_m": 1.0}}


@pytest.mark.parametrize(("entry", "error"), [
    ({"id": "b", "driven_by": "driver"}, "cars[1] (b): key 'driver': a car driven by the "
                                         "driver needs a driver: block"),
    ({"id": "b", "driver": DRIVER}, "cars[1] (b): key 'driver': only a car driven_by "
                                    "driver takes a driver: block"),
    ({"id": "b", "driven_by": "robot"}, "cars[1] (b): key 'driven_by': expected one of "
                                        "client, keyframes, driver, got 'robot'"),
])
def test_a_bad_driven_car_names_the_file_and_the_car(tmp_path, entry, error):
    path = tmp_path / "server.yaml"
    with pytest.raises(ConfigError) as exc:
        parse_cars(path, [{"id": "a"}, {**entry, "pose": {"x_m": 30.0, "y_m": 0.0}}])
    assert str(exc.value).startswith(f"{path}: {error}"), exc.value


def test_a_bad_driver_block_names_the_file_and_the_car(tmp_path):
    path = tmp_path / "server.yaml"
    cars = parse_cars(path, [{"id": "a"}, {"id": "b", "pose": {"x_m": 30.0, "y_m": 0.0},
                                           "driven_by": "driver",
                                           "driver": {**DRIVER, "idm": {"T_s": -1.0}}}])
    scenes = car_scenes(cars, load_scene(SCENE))
    with pytest.raises(ConfigError, match=r"server\.yaml: cars\[1\] \(b\): key "
                                          r"'driver\.idm\.T_s'"):
        driver_spec(cars[1], scenes["b"])


def test_drivers_reassembled_keep_each_driven_cars_state_by_id(tmp_path):
    path = tmp_path / "server.yaml"
    cars = parse_cars(path, [
        {"id": "lead", "pose": {"x_m": 40.0, "y_m": 0.0}},
        {"id": "t1", "pose": {"x_m": 20.0, "y_m": 0.0}, "driven_by": "driver", "driver": DRIVER},
        {"id": "t2", "pose": {"x_m": 0.0, "y_m": 0.0}, "driven_by": "driver",
         "driver": {**DRIVER, "stop_s_m": 30.0}}])
    scenes = car_scenes(cars, load_scene(SCENE))
    sims = build_world(scenes, 0.001)
    world = sims["lead"].world
    live = LiveDrivers()
    for car in cars[1:]:
        live.prepare(car.id, driver_spec(car, scenes[car.id]), world.model.terrain)
    drivers = live.assemble(world)
    assert drivers.params[:, D.DP_ENABLED].tolist() == [0.0, 1.0, 1.0]
    assert drivers.path_rows.shape[0] == 1  # the same path once
    assert drivers.state[2, D.DS_STOP_STATION_M] == 30.0
    assert (drivers.state[1:, D.DS_MODE] == D.MODE_HOLD).all()  # at rest: held
    # the world's cars change: lead removed; t1's and t2's states (as the driver left
    # them) carried over by id, not by row
    drivers.state[1, D.DS_MODE] = D.MODE_DRIVE
    drivers.state[1, D.DS_SPEED_REF_MPS] = 3.25
    drivers.state[2, D.DS_SPEED_REF_MPS] = 1.5
    before = drivers.state.copy()
    old_ids = list(world.ids)
    world.remove_car("lead")
    again = live.assemble(world, drivers, old_ids)
    assert list(world.ids) == ["t1", "t2"]
    assert np.array_equal(again.state, before[1:])
    assert again.params[:, D.DP_ENABLED].tolist() == [1.0, 1.0]
    # a world with no driven car has no drivers
    live.forget("t1")
    live.forget("t2")
    assert live.assemble(world) is None


WARM_SCRIPT = """
import json
import sys
from simserver.core.driver import drive
from simserver.server import fleet
from simserver.server.cars_config import car_scenes, driver_spec, parse_cars
from simserver.server.config import load_server_config
from simserver.server.live_drivers import LiveDrivers
from simserver.sim.scene_files import load_scene

cfg = load_server_config(sys.argv[1])
scene = load_scene(cfg.scene)
fleet.prepare_drivers(fleet.make_cars(cfg, scene), cfg.max_cars)
warm = len(drive.signatures)
# the world a driven car added while running makes: two cars, one driven
cars = parse_cars(cfg.path, [{"id": "car0"}, {"id": "bot", "pose": {"x_m": 30.0, "y_m": 0.0},
                              "driven_by": "driver", "driver": json.loads(sys.argv[2])}])
scenes = car_scenes(cars, scene)
world = fleet.build_world(scenes, cfg.period_s)["car0"].world
live = LiveDrivers()
live.prepare("bot", driver_spec(cars[1], scenes["bot"]), world.model.terrain)
drive(world.model, world.data, live.assemble(world))
print("signatures", warm, len(drive.signatures))
"""


@pytest.mark.parametrize(("max_cars", "warm"), [(1, 0), (2, 1)])
def test_drive_is_compiled_at_the_start_when_a_driven_car_may_be_added(tmp_path, max_cars,
                                                                       warm):
    """A server of client cars compiles (or loads from the cache) ``core.driver.drive`` as
    it starts when ``max_cars`` lets ``add_car`` bring a driven car, so the first tick after
    that add does not compile it: the call then has the start's signature (one compiled
    signature after both). With ``max_cars: 1`` no car can be added: nothing compiled. A
    fresh process, so that no other test has called ``drive`` before."""
    import json
    import subprocess
    import sys

    config = tmp_path / "server.yaml"
    config.write_text(f"scene: {SCENE}\nmax_cars: {max_cars}\ncars: [{{id: car0}}]\n")
    out = subprocess.run([sys.executable, "-c", WARM_SCRIPT, str(config),
                          json.dumps(DRIVER)], capture_output=True,
                         text=True, timeout=600, check=False, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    line = next(x for x in out.stdout.splitlines() if x.startswith("signatures"))
    assert line.split()[1:] == [str(warm), "1"], line
