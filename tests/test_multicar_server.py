"""Several cars in one live server, end to end (issue 30 items 1 and 4): a real server
process with two cars, two real client processes each driving one, real zenoh sessions on
loopback. Each client sees the other car in the world message; the cars are discovered by
liveliness; a single-car client works unchanged against car0."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from clients import world as cw
from simserver.testing import Client, OutputProcess, ServerProcess, client_config, wait_until
from simserver.wire import protocol as proto
from tests.conftest import TWO_CARS, player

pytestmark = pytest.mark.timeout(300)

REPO = Path(__file__).resolve().parents[1]


def test_two_clients_drive_two_cars_and_each_sees_the_other(two_cars, tmp_path):
    scenario = tmp_path / "creep.yaml"
    scenario.write_text("name: creep\nduration_s: 3.5\ninputs:\n"
                        "  - {t: 0.0, gear: D, throttle: 0.25, brake: 0.0}\n")
    p0, p1 = player(two_cars, "car0", scenario), player(two_cars, "car1", scenario)
    with p0, p1:
        assert p0.wait(60) == 0, p0.text()
        assert p1.wait(60) == 0, p1.text()
    # car0 starts 25 m behind car1 (configs/server/two_cars.yaml): each names the other
    ahead = [line for line in p0.output if "| ahead car1 " in line]
    behind = [line for line in p1.output if "behind car0 " in line]
    assert ahead and behind, p0.text() + p1.text()
    assert "ahead -" in behind[-1]  # nothing ahead of car1
    distance = float(ahead[-1].split("| ahead car1 ")[1].split(" m")[0])
    assert 15.0 < distance < 30.0  # CG to CG, both cars driving the same inputs


def test_discovery_the_world_message_and_a_single_car_client(two_cars):
    from simserver.adapters.zenoh_io import ZenohEndpoint

    with ZenohEndpoint(client_config(two_cars.endpoint)) as ep:
        assert wait_until(lambda: cw.discover_cars(ep, "simserver", 0.5),
                          lambda cars: cars == ["car0", "car1"], timeout_s=10)
        watch = cw.WorldWatch(ep, "simserver")
        world = wait_until(watch.poll, timeout_s=10)
        assert world.ids == ("car0", "car1")
        # car1 starts 25 m ahead of car0 (the other test may have driven both since)
        assert world.car("car1")["x_m"] - world.car("car0")["x_m"] > 15.0
        assert world.cars["driven_by"].tolist() == [0, 0]
        ticks: set[int] = set()

        def more() -> set[int]:
            ticks.add(watch.poll().tick)
            return ticks

        wait_until(more, lambda t: len(t) >= 6, timeout_s=5)
        assert all(t % 10 == 0 for t in ticks)  # 100 Hz of a 1 kHz clock
    # a single-car client of car0 (the test harness's, as any older client) drives it
    with Client(two_cars) as car0:
        state = car0.drive(1.0, throttle=0.4, gear=proto.Gear.D)
        assert state["u_mps"] > 0.1 and not state["flags"] & proto.StateFlag.WATCHDOG
        config = car0.request("get_config")["config"]
        assert config["keys"]["cmd"] == "simserver/car0/cmd"
    out = OutputProcess([sys.executable, "-m", "clients.world", "--once", "--seconds", "20",
                         "--connect", two_cars.endpoint])
    with out:
        assert out.wait(60) == 0, out.text()
    line = json.loads(next(x for x in out.output if x.startswith("{")))
    assert set(line["world"]) == {"car0", "car1"}


ON_ROAD = "{road: '1', s: 20, lane: -1}"


def test_the_keyboard_driver_shows_the_car_ahead(two_cars):
    """The keyboard driver of car0 in a pseudo-terminal names car1 ahead, with the
    distance and closing speed, from the world message. (With the other tests of the
    module's ``two_cars``: it ends with the last of them, tests/conftest.py.)"""
    from test_clients import PtyProcess

    from simserver.testing import client_command

    drv = PtyProcess(client_command("driver", "--rate", "200", "--connect",
                                    two_cars.endpoint, "--vehicle-id", "car0"))
    try:
        drv.wait_for("health", 30)
        drv.wait_for("traffic ahead car1 ", 20)
        screen = drv.text()
        drv.send(b"q")
        assert drv.wait(15) == 0, drv.text()
    finally:
        drv.close()
    line = screen[screen.rindex("traffic ahead car1 "):].splitlines()[0]
    distance = float(line.split("traffic ahead car1 ")[1].split(" m")[0])
    assert 15.0 < distance < 60.0 and "behind -" in line, line


@pytest.mark.parametrize(("scene", "cars", "error"), [
    ("flat_paper_sedan", "[{id: a}, {id: a, pose: {x_m: 30, y_m: 0}}]",
     "cars[1] (a): key 'id'"),
    ("flat_paper_sedan", "[{id: a}, {id: b, pose: {x_m: 2, y_m: 0}}]",
     "cars[1] (b): its start"),
    ("flat_paper_sedan",
     "[{id: a}, {id: b, pose: {x_m: 30, y_m: 0}}, {id: c, pose: {x_m: 60, y_m: 0}}]",
     "key 'cars': 3 cars, more than max_cars (2)"),
    # a car off the road, and a driver's path that leaves it (the one car of its list)
    ("curves_elevation_paper_sedan", f"[{{id: a, start: {ON_ROAD}}}, "
     "{id: b, pose: {x_m: 0, y_m: 500}}]", "cars[1] (b): the start (0.00, 500.00) m is "
     "off the road"),
    ("curves_elevation_paper_sedan", f"[{{id: a, start: {ON_ROAD}, driven_by: driver, "
     "driver: {path: {points: [[0, 0], [50, 0], [50, 80]]}}}]",
     "cars[0] (a): key 'driver.path'"),
])
def test_a_bad_cars_list_stops_the_server_naming_the_file_and_the_car(tmp_path, scene, cars,
                                                                      error):
    from simserver.testing import free_port

    config = tmp_path / "server.yaml"
    config.write_text(f"scene: {REPO / 'configs' / 'scenes' / (scene + '.yaml')}\n"
                      f"max_cars: 2\ncars: {cars}\n")
    with OutputProcess([sys.executable, "-m", "simserver", "serve", "--config", str(config),
                        "--listen", f"tcp/127.0.0.1:{free_port()}", "--viewer", "off"]) as p:
        assert p.wait(120) == 2, p.text()
    assert f"error: {config}: {error}" in p.text()
    assert "ready on" not in p.text()


def test_a_car_added_and_removed_over_zenoh_while_the_world_runs(tmp_path):
    from simserver.adapters.zenoh_io import ZenohEndpoint

    config = tmp_path / "server.yaml"
    config.write_text(TWO_CARS.read_text().replace("../", f"{TWO_CARS.parent}/../")
                      + f"command_log: {tmp_path / 'run.jsonl'}\n")
    with ServerProcess(config=config, scene=None) as server, \
            ZenohEndpoint(client_config(server.endpoint)) as ep:
        cars = cw.CarsWatch(ep, "simserver")
        wait_until(cars.poll, lambda c: c == {"car0", "car1"}, timeout_s=10)
        bad = ep.request_world("add_car", {"id": "car2", "pose": {  # the load worker may
            "x_m": 0.5, "y_m": 0.0, "yaw_rad": 0.0}}, timeout_s=120)  # still warm up
        assert not bad["ok"] and bad["field"] == "pose" and "overlaps car 'car0'" in \
            bad["error"], bad
        reply = ep.request_world("add_car", {"id": "car2", "pose": {
            "x_m": 60.0, "y_m": 0.0, "yaw_rad": 0.0}}, timeout_s=60)
        assert reply == {"ok": True, "car": "car2", "cars": ["car0", "car1", "car2"]}, reply
        wait_until(cars.poll, lambda c: "car2" in c, timeout_s=10)
        with Client(server, vehicle_id="car2") as car2:
            state = car2.drive(1.0, throttle=0.5, gear=proto.Gear.D)
            assert state["x_m"] > 60.0 and state["u_mps"] > 0.1
        world = wait_until(cw.WorldWatch(ep, "simserver").poll, timeout_s=10)
        assert world.ids == ("car0", "car1", "car2")
        assert ep.request_world("remove_car", {"id": "car1"})["cars"] == ["car0", "car2"]
        wait_until(cars.poll, lambda c: c == {"car0", "car2"}, timeout_s=10)
        config_reply = ep.request_world("get_config")
        assert [c["id"] for c in config_reply["cars"]] == ["car0", "car2"]
    assert server.returncode == 0, server.text()
    from simserver.server.command_log import replay_command_log

    for car in ("car0", "car1", "car2"):  # the removed car's log ends where it left
        replay = replay_command_log(tmp_path / f"run.{car}.jsonl")
        assert replay.final_state_matches, car


def test_a_single_car_list_driven_by_the_driver_drives(tmp_path):
    """A server config whose ``cars:`` list has one car, driven by the built-in driver:
    the driver drives it (before, the tick stepped a lone car without calling the driver,
    and the car, refusing commands, stood still at its start forever)."""
    from simserver.adapters.zenoh_io import ZenohEndpoint

    config = tmp_path / "server.yaml"
    config.write_text(f"scene: {REPO / 'configs' / 'scenes' / 'flat_paper_sedan.yaml'}\n"
                      "cars:\n  - id: solo\n    driven_by: driver\n    driver:\n"
                      "      path: {points: [[-50.0, 0.0], [2000.0, 0.0]]}\n"
                      "      idm: {v0_mps: 5.0}\n")
    with ServerProcess(config=config, scene=None) as server, \
            ZenohEndpoint(client_config(server.endpoint)) as ep:
        watch = cw.WorldWatch(ep, "simserver")
        world = wait_until(watch.poll, lambda w: w is not None and
                           w.car("solo")["u_mps"] > 1.0, timeout_s=60)
        assert world.ids == ("solo",)
        assert world.car("solo")["x_m"] > 0.1
        assert proto.DRIVEN_BY_CODES[int(world.car("solo")["driven_by"])] == "driver"


CURVES_XODR = REPO / "configs" / "roads" / "curves_elevation.xodr"


def test_a_car_added_with_the_built_in_driver_drives_its_lane_and_bad_ones_change_nothing(
        tmp_path):
    """``add_car`` with ``driven_by: driver`` and a driver block (issue 30 item 1): the car
    joins the running world and the built-in driver drives it: its speed rises toward the
    block's target and it follows its lane into the curve. An add whose driver path leaves
    the road, or whose start is off the road, is refused with an error naming the car and
    the argument, and the world goes on as it was (its one car, no new token). The added
    car's command log replays it alone to its final state (the driver's inputs logged)."""
    import numpy as np

    from simserver.adapters.opendrive import lane_start, load_opendrive
    from simserver.adapters.zenoh_io import ZenohEndpoint

    od = load_opendrive(CURVES_XODR)
    # the lane's centre (road 1, lane -1) every 0.25 m: straight to s = 50, a spiral to
    # s = 100, then an arc of radius 143 m (curvature 0.007 1/m) to s = 324
    centre = np.array([lane_start(od, "1", s, -1)[:2] for s in np.arange(0.0, 320.0, 0.25)])
    x0, y0, yaw0 = lane_start(od, "1", 60.0, -1)  # 40 m ahead of car0 (s = 20) on its lane
    pose = {"x_m": x0, "y_m": y0, "yaw_rad": yaw0}
    v0_mps = 8.0
    driver = {"path": {"road": "1", "lane": -1}, "idm": {"v0_mps": v0_mps}}
    with ServerProcess(scene="curves_elevation_paper_sedan",
                       command_log=tmp_path / "run.jsonl") as server, \
            ZenohEndpoint(client_config(server.endpoint)) as ep:
        cars = cw.CarsWatch(ep, "simserver")
        wait_until(cars.poll, lambda c: c == {"car0"}, timeout_s=10)
        watch = cw.WorldWatch(ep, "simserver")
        before = wait_until(watch.poll, timeout_s=10)
        # a driver path that leaves the road (it turns off at x = 50 m across the arc's
        # inside), from a start on the road; the load worker may still warm up
        bad = ep.request_world("add_car", {
            "id": "bot", "pose": pose, "driven_by": "driver",
            "driver": {"path": {"points": [[0, 0], [50, 0], [50, 80]]}}}, timeout_s=120)
        assert not bad["ok"] and bad["field"] == "driver.path", bad
        assert bad["error"].startswith("add_car (bot): key 'driver.path': point 2 (50, 80) "
                                       "leaves the road"), bad
        # a start off the road, with a good driver block
        bad = ep.request_world("add_car", {
            "id": "bot", "pose": {"x_m": 0.0, "y_m": 500.0, "yaw_rad": 0.0},
            "driven_by": "driver", "driver": driver}, timeout_s=60)
        assert not bad["ok"] and bad["field"] == "pose", bad
        assert bad["error"].startswith("add_car (bot): the start (0.00, 500.00) m is off the "
                                       "road"), bad
        bad = ep.request_world("add_car", {  # past the road's end (1154 m)
            "id": "bot", "start": {"road": "1", "s": 5000.0, "lane": -1},
            "driven_by": "driver", "driver": driver}, timeout_s=60)
        assert not bad["ok"] and bad["field"] == "start.s", bad
        assert bad["error"].startswith("add_car (bot): key 'start.s': s = 5000.0 m is off "
                                       "road 1"), bad
        # nothing changed: the world's one car, served on (its ticks go on), no new token
        assert ep.request_world("get_config")["cars"] == [{"id": "car0",
                                                           "driven_by": "client"}]
        after = wait_until(watch.poll, lambda w: w.tick > before.tick + 100, timeout_s=10)
        assert after.ids == ("car0",) and cars.poll() == {"car0"}
        # the good one joins, driven by the driver, started by road, s and lane (the
        # place of `pose` above)
        reply = ep.request_world("add_car", {"id": "bot", "start": {
            "road": "1", "s": 60.0, "lane": -1}, "driven_by": "driver", "driver": driver},
            timeout_s=60)
        assert reply == {"ok": True, "car": "bot", "cars": ["car0", "bot"]}, reply
        assert ep.request_world("get_config")["cars"] == [
            {"id": "car0", "driven_by": "client"}, {"id": "bot", "driven_by": "driver"}]
        wait_until(cars.poll, lambda c: c == {"car0", "bot"}, timeout_s=10)
        seen: list[tuple[float, float, float]] = []

        def drive_on() -> list[tuple[float, float, float]]:
            world = watch.poll()
            if world is not None and "bot" in world.ids:
                car = world.car("bot")
                seen.append((float(car["x_m"]), float(car["y_m"]), float(car["u_mps"])))
                assert proto.DRIVEN_BY_CODES[int(car["driven_by"])] == "driver"
            return seen

        # until it is 60 m on (s = 120: 20 m into the arc) at 90 % of its target speed
        wait_until(drive_on, lambda s: bool(s) and np.hypot(s[-1][0] - x0, s[-1][1] - y0)
                   > 60.0 and s[-1][2] > 0.9 * v0_mps, timeout_s=90,
                   what="the added car driving on at its target speed")
    assert server.returncode == 0, server.text()
    from simserver.server.command_log import replay_command_log

    assert replay_command_log(tmp_path / "run.bot.jsonl").final_state_matches
    track = np.array(seen)
    # toward the target, not past it: IDM's approach is from below (model.md section 15),
    # 3 % for the speed controller's overshoot
    assert track[:, 2].max() < 1.03 * v0_mps, track[:, 2].max()
    # on its lane: every position within 0.5 m of the lane's centre (the driver's
    # acceptance is 0.3 m RMS at 15 m/s; a car driving straight on would be 4 m off by
    # s = 120 on this arc)
    lateral = np.sqrt(((track[:, None, :2] - centre[None, :, :]) ** 2).sum(-1)).min(axis=1)
    assert lateral.max() < 0.5, lateral.max()
