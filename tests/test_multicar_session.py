"""A recorded live session of three cars, end to end (issue 30, acceptance: "a recorded
live session of 3 cars (two clients, one traffic car, one contact) replays bit for bit;
its .rrd opened with Rerun's reader has every car's entities; its ROS 2 topics decode with
an independent CDR library under each car's namespace").

Real processes only: ``simserver serve`` with three cars in one world on the flat (car0
and car1 driven by two ``clients.player`` processes over zenoh on loopback, ``traffic``
by the built-in driver, which drives it up the road and stops it), the server's own ROS 2
adapter (its config's ``ros2:``; one process, a node a car) joined to a zenoh router
standing in for ``rmw_zenohd``, and ``simserver view --sink save:FILE`` recording the
world. car0's player drives it into the back of the stopped traffic car: the collision
arrives on ``{prefix}/world/collision``. Then: the ``.rrd`` read back with
``rerun.chunk.RrdReader`` has each car under ``world/cars/<id>``; the ROS topics received
by a ROS-side zenoh session are each car's under ``/<id>/...`` and ``<id>/base_link`` in
``/tf``, decoded with rosbags (not the adapter's code); and ``simserver replay`` of the
three command logs, in one world, gives every car's live final state bit for bit, with
the contact.
"""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest
import zenoh

from simserver.adapters.zenoh_io import ZenohEndpoint, make_zenoh_config
from simserver.testing import (
    CONFIGS,
    OutputProcess,
    ServerProcess,
    client_config,
    loopback_endpoint,
    wait_until,
)
from simserver.wire import protocol as proto
from tests.conftest import player

pytestmark = pytest.mark.timeout(400)

FLAT = CONFIGS / "scenes" / "flat_paper_sedan.yaml"
DOMAIN = 13
CARS = ("car0", "car1", "traffic")
CONFIG = """scene: {scene}
viewer: off
max_cars: 4
world_hz: 100
command_log: {log}
ros2: {{router: "{router}", domain_id: {domain}, normal_priority: true}}
cars:
  - {{id: car0, pose: {{x_m: 0.0, y_m: 0.0, yaw_rad: 0.0}}}}
  - {{id: car1, pose: {{x_m: 0.0, y_m: 6.0, yaw_rad: 0.0}}}}
  - id: traffic
    pose: {{x_m: 9.0, y_m: 0.0, yaw_rad: 0.0}}
    driven_by: driver
    driver:   # up the road along x at 1.5 m/s; its front bumper stops at x = 18 m, held
      path: {{points: [[-50.0, 0.0], [2000.0, 0.0]]}}
      idm: {{v0_mps: 1.5, T_s: 2.0, s0_m: 1.0}}
      stop_s_m: 68.0
"""
# car0 closes the ~13 m to the stopped traffic car's rear and pushes it (keyframes are
# linear between them: each value is held by a second keyframe); car1 drives beside
CAR0 = ("name: bump\nduration_s: 9.0\ninputs:\n"
        "  - {t: 0.0, gear: D, throttle: 0.3, brake: 0.0}\n"
        "  - {t: 8.0, throttle: 0.3, brake: 0.0}\n"
        "  - {t: 8.1, throttle: 0.0, brake: 0.6}\n")
CAR1 = ("name: beside\nduration_s: 9.0\ninputs:\n"
        "  - {t: 0.0, gear: D, throttle: 0.25, brake: 0.0, steer: 0.0}\n"
        "  - {t: 8.0, throttle: 0.25, brake: 0.0, steer: 0.05}\n"
        "  - {t: 8.1, throttle: 0.0, brake: 0.5, steer: 0.05}\n")


def nodes(session: zenoh.Session) -> list[str]:
    """The ROS graph's node tokens of the test's domain (rmw_zenoh's liveliness)."""
    replies = session.liveliness().get(f"@ros2_lv/{DOMAIN}/**", timeout=1.0)
    return [str(r.ok.key_expr) for r in replies if r.ok is not None
            and "/NN/" in str(r.ok.key_expr)]


def test_three_cars_recorded_live_replay_bit_for_bit_with_ros2_and_rerun(tmp_path):
    from test_viewer_multicar import DRAWN_BYTES, _column, _entities

    from benchmarks.ros2_flood import typestore
    from simserver.adapters.rerun_fleet import car_path
    from simserver.server.world_replay import replay_world

    ts = typestore()  # rosbags' CDR, independent of simserver.ros2
    router_ep = loopback_endpoint()
    router = zenoh.open(make_zenoh_config(listen=[router_ep], mode="router"))
    ros_node = zenoh.open(make_zenoh_config(listen=["tcp/127.0.0.1:0"], connect=[router_ep],
                                            mode="peer"))
    ros_samples: dict[str, list[bytes]] = {}

    def take(sample: zenoh.Sample) -> None:  # zenoh's thread: a few appends a message
        ros_samples.setdefault(str(sample.key_expr), []).append(sample.payload.to_bytes())

    ros_sub = ros_node.declare_subscriber(f"{DOMAIN}/**", take)
    config = tmp_path / "server.yaml"
    config.write_text(CONFIG.format(scene=FLAT, log=tmp_path / "run.jsonl", router=router_ep,
                                    domain=DOMAIN))
    (tmp_path / "car0.yaml").write_text(CAR0)
    (tmp_path / "car1.yaml").write_text(CAR1)
    rrd = tmp_path / "session.rrd"
    env = dict(os.environ, XDG_CONFIG_HOME=str(tmp_path / "xdg_config"),
               XDG_DATA_HOME=str(tmp_path / "xdg_data"))
    collisions: list[dict] = []
    try:
        with ServerProcess(config=config, scene=None, ready_timeout_s=300) as server, \
                ZenohEndpoint(client_config(server.endpoint)) as ep:
            inbox = ep.declare_inbox(proto.world_keys("simserver").collision, 64)
            viewer = OutputProcess(
                [sys.executable, "-m", "simserver", "view", "--sink", f"save:{rrd}",
                 "--connect", server.endpoint, "--car", "car0", "--normal-priority"],
                env=env)
            try:
                server.wait_for_line("simserver ros2: node", timeout_s=120)
                # the viewer draws the world (its static scene and first frames) before
                # the cars move, so the recording holds the whole drive
                wait_until(lambda: rrd.exists() and rrd.stat().st_size > DRAWN_BYTES
                           or not viewer.alive(), timeout_s=120.0,
                           what="the viewer to draw the world", interval_s=0.05)
                assert viewer.alive(), viewer.text()
                p0 = player(server, "car0", tmp_path / "car0.yaml")
                p1 = player(server, "car1", tmp_path / "car1.yaml")
                with p0, p1:
                    assert p0.wait(120) == 0, p0.text()
                    assert p1.wait(120) == 0, p1.text()
                collisions += [proto.decode_collision(p) for p in wait_until(
                    inbox.drain_newest, timeout_s=10, what="a collision message; car0's "
                    "player said:\n" + p0.text())]
                # every car's odometry under its namespace has come through the router
                wait_until(lambda: {k.split("/")[1] for k in ros_samples
                                    if "/odom/" in k}, lambda cars: cars >= set(CARS),
                           timeout_s=30, what="each car's odometry")
                # a car added while the world runs gets its node, a car removed loses it
                added = ep.request_world("add_car", {"id": "car2", "pose": {
                    "x_m": -30.0, "y_m": 0.0, "yaw_rad": 0.0}}, timeout_s=120)
                assert added["ok"], added
                try:  # the adapter reads the world's cars every 2 s
                    wait_until(lambda: [k for k in ros_samples if k.startswith(
                        f"{DOMAIN}/car2/odom/")], timeout_s=60, what="car2's odometry")
                except TimeoutError as exc:
                    raise AssertionError(server.text()[-3000:]) from exc
                assert ep.request_world("remove_car", {"id": "car1"})["ok"]
                wait_until(lambda: [t for t in nodes(ros_node) if "simserver_car1" in t],
                           lambda left: not left, timeout_s=30,
                           what="car1's node withdrawn from the ROS graph")
                assert any("simserver_car2" in t for t in nodes(ros_node))
                assert viewer.alive(), viewer.text()
                assert viewer.stop(timeout_s=60.0) == 0, viewer.text()
            finally:
                viewer.kill()
            collisions += [proto.decode_collision(p) for p in inbox.drain_newest()]
        assert server.returncode == 0, server.text()
    finally:
        ros_sub.undeclare()
        ros_node.close()
        router.close()

    # the contact: car0 into the traffic car, published live
    assert collisions and all({c["car_a"], c["car_b"]} == {"car0", "traffic"}
                              for c in collisions), collisions
    assert collisions[0]["closing_speed_mps"] > 0.5

    # the replay of the three logs in one world: every car's final state bit for bit,
    # and the contact events the server published
    logs = [tmp_path / f"run.{car}.jsonl" for car in (*CARS, "car2")]
    replay = replay_world(logs)
    for car in (*CARS, "car2"):
        assert replay.cars[car].final_state_matches, car
    assert replay.contact_events == max(c["seq"] for c in collisions)
    assert replay.cars["car1"].left_at is not None and replay.cars["car2"].joined_at > 0
    assert replay.cars["traffic"].final_state[0] > 12.0  # driven up the road, pushed
    cli = OutputProcess([sys.executable, "-m", "simserver", "replay", *map(str, logs)])
    with cli:
        assert cli.wait(120) == 0, cli.text()
    assert cli.text().count("identical to the live run's") == 4, cli.text()

    # the recording: every car under world/cars/<id>, car0 followed (drawn in full)
    entities = _entities(rrd)
    for car in CARS:
        cols = entities.get("/" + car_path(car))
        assert cols, f"no /{car_path(car)} in {sorted(entities)}"
        xyz = np.array(_column(cols, "translation"), dtype=float).reshape(-1, 3)
        assert len(xyz) > 5 and np.isfinite(xyz).all()
    assert _column(entities["/" + car_path("traffic") + "/box"], ":labels") == [["traffic"]]

    # ROS 2: each car's topics under /<id>, decoded by rosbags; its frames in /tf
    for car in CARS:
        for topic, ros_type in (("odom", "nav_msgs/msg/Odometry"),
                                ("imu", "sensor_msgs/msg/Imu"),
                                ("joint_states", "sensor_msgs/msg/JointState")):
            pkg, _, name = ros_type.split("/")
            key = f"{DOMAIN}/{car}/{topic}/{pkg}::msg::dds_::{name}_/{ts.hash_rihs01(ros_type)}"
            assert ros_samples.get(key), f"nothing on {key}: {sorted(ros_samples)}"
            message = ts.deserialize_cdr(ros_samples[key][-1], ros_type)
            if topic == "odom":
                assert (message.header.frame_id, message.child_frame_id) == \
                    ("odom", f"{car}/base_link")
                final = replay.cars[car].final_state
                assert abs(message.pose.pose.position.x - final[0]) < 1.0, car
            elif topic == "imu":
                assert message.header.frame_id == f"{car}/base_link"
    tf_key = (f"{DOMAIN}/tf/tf2_msgs::msg::dds_::TFMessage_/"
              f"{ts.hash_rihs01('tf2_msgs/msg/TFMessage')}")
    children = {t.child_frame_id for p in ros_samples[tf_key]
                for t in ts.deserialize_cdr(p, "tf2_msgs/msg/TFMessage").transforms}
    assert children == {f"{car}/base_link" for car in (*CARS, "car2")}
    # no topic outside a car's namespace but /tf (and no /clock: wall stamps)
    assert {k.split("/")[1] for k in ros_samples} == {*CARS, "car2", "tf"}
