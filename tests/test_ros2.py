"""The ROS 2 adapter (issue 19), end to end with real parts and no ROS installation.

A real server (``simserver serve`` on the 10 % hill scene), the adapter as a subprocess
(``simserver ros2``), and this test as the ROS side: a zenoh session in router mode
standing in for ``rmw_zenohd``, and a peer session connected to it as a ROS node is (so
everything between the node and the adapter goes through the router, as on a ROS
machine). Everything the test checks is built here from rmw_zenoh's design document
(``docs/design.md`` of github.com/ros2/rmw_zenoh) and source (the publisher GID), and
decoded with rosbags' own type store and CDR deserialiser, not with the adapter's
modules: key expressions, type hashes, the 33-byte attachment and its GID, the liveliness
tokens, and the messages' contents against the server's state. Commands are published
the way rmw_zenoh publishes them (key, CDR, attachment, liveliness tokens of a node and
its publisher). ``serve`` starting and stopping the adapter from its config is checked
on servers of its own.

The server, its clients and the adapter's process come from the project's harness
(``simserver.testing``). Tests wait on conditions with deadlines; the only pacing is the
20 Hz at which the ROS side publishes commands, as a ROS node would.
"""

from __future__ import annotations

import math
import os
import re
import signal
import struct
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import xxhash
import zenoh

from benchmarks.ros2_flood import typestore
from simserver.adapters.zenoh_io import make_zenoh_config
from simserver.testing import (
    CONFIGS,
    Client,
    OutputProcess,
    ServerProcess,
    loopback_endpoint,
    process_argv,
    wait_until,
)
from simserver.wire import protocol as proto

REPO = Path(__file__).resolve().parents[1]
HILL_SCENE = CONFIGS / "scenes" / "hill_10pct_paper_sedan.yaml"
FLAT_SCENE = CONFIGS / "scenes" / "flat_paper_sedan.yaml"
DOMAIN = 7  # not the default 0: the adapter must honour --domain-id
NODE = "simserver_car0"
GRAVITY = 9.81  # the scene's model default
GRADE_RAD = math.atan(0.10)
WATCHDOG = proto.StateFlag.WATCHDOG

# Known RIHS01 hashes of ROS 2 Jazzy: Odometry from the issue, AckermannDriveStamped as
# ROS 2's generated code for ackermann_msgs has it, String from rmw_zenoh's design doc.
ODOMETRY_HASH = "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0"
ACKERMANN_HASH = "RIHS01_48ca7612a08d3bb72744fd98b71b7cf2ea24c6ad50fa4e1aa0bbad963c90d8cf"
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"

PUBLISHED = {  # topic -> (ROS type, QoS chunk of the token)
    "odom": ("nav_msgs/msg/Odometry", "::,10:,:,:,,"),
    "imu": ("sensor_msgs/msg/Imu", "::,10:,:,:,,"),
    "tf": ("tf2_msgs/msg/TFMessage", "::,100:,:,:,,"),
    "joint_states": ("sensor_msgs/msg/JointState", "::,10:,:,:,,"),
}
SUBSCRIBED = {
    "ackermann_cmd": "ackermann_msgs/msg/AckermannDriveStamped",
    "cmd_vel": "geometry_msgs/msg/Twist",
}


TS = typestore()  # rosbags' CDR, independent of simserver.ros2 (benchmarks.ros2_flood)


def dds_name(ros_type: str) -> str:
    pkg, _, name = ros_type.split("/")
    return f"{pkg}::msg::dds_::{name}_"


def topic_key(topic: str, ros_type: str) -> str:
    """``<domain>/<topic>/<DDS type>/<RIHS01 hash>`` (design doc, key expressions)."""
    return f"{DOMAIN}/{topic}/{dds_name(ros_type)}/{TS.hash_rihs01(ros_type)}"


def rmw_zenoh_gid(token: str) -> bytes:
    """A publisher's GID by rmw_zenoh's rule (``Entity::Entity`` in its
    ``liveliness_utils.cpp``): XXH3-128 of the entity's liveliness token key expression,
    copied as ``low64`` then ``high64``, each in the (little-endian) machine's byte order.

    Written here from the canonical (big-endian ``high64 || low64``) digest, not from the
    adapter's integer route.
    """
    canonical = xxhash.xxh3_128_digest(token.encode())
    high64, low64 = canonical[:8], canonical[8:]
    return low64[::-1] + high64[::-1]


def start_adapter(endpoint: str, settings: dict[str, Any]) -> OutputProcess:
    """``simserver ros2`` with the command line serve uses for a config's ``ros2:`` section."""
    from simserver.ros2.cli import adapter_command

    proc = OutputProcess(adapter_command(endpoint, "simserver", "car0", settings),
                         ready="simserver ros2: node")
    if not proc.wait_ready(120) or not proc.alive():
        proc.kill()
        raise RuntimeError("the adapter did not start:\n" + proc.text())
    return proc


@pytest.fixture(scope="module")
def server() -> Iterator[ServerProcess]:
    """``simserver serve`` on the 10 % hill."""
    with ServerProcess(scene=HILL_SCENE, ready_timeout_s=180) as proc:
        yield proc


@pytest.fixture(scope="module")
def router() -> Iterator[tuple[zenoh.Session, str]]:
    """A zenoh router session standing in for ``rmw_zenohd``; yields it and its endpoint."""
    endpoint = loopback_endpoint()
    session = zenoh.open(make_zenoh_config(listen=[endpoint], mode="router"))
    yield session, endpoint
    session.close()


@pytest.fixture(scope="module")
def ros_node(router: tuple[zenoh.Session, str]) -> Iterator[zenoh.Session]:
    """The test's ROS node: a peer of the router listening on loopback, as rmw_zenoh's are."""
    session = zenoh.open(make_zenoh_config(listen=["tcp/127.0.0.1:0"], connect=[router[1]],
                                           mode="peer"))
    yield session
    session.close()


@pytest.fixture(scope="module")
def watcher(server: ServerProcess) -> Iterator[Client]:
    """A plain protocol client of the server (every state kept, controls)."""
    with Client(server, state_capacity=1 << 15, keep_history=True) as client:
        yield client


@pytest.fixture(scope="module")
def adapter(server: ServerProcess, router: tuple[zenoh.Session, str],
            ros_node: zenoh.Session) -> Iterator[OutputProcess]:
    """``simserver ros2`` connected to the server, its ROS node a client of the router."""
    proc = start_adapter(server.endpoint, {
        "router": router[1], "domain_id": DOMAIN, "normal_priority": True})
    # the node is in the graph, seen from a node
    wait_until(lambda: liveliness_tokens(ros_node), timeout_s=30,
               what="a liveliness token from the adapter")
    yield proc
    assert proc.stop() == 0, proc.text()


def liveliness_tokens_of(session: zenoh.Session, domain: int) -> list[str]:
    replies = session.liveliness().get(f"@ros2_lv/{domain}/**", timeout=1.0)
    return sorted(str(r.ok.key_expr) for r in replies if r.ok is not None)


def liveliness_tokens(session: zenoh.Session) -> list[str]:
    return liveliness_tokens_of(session, DOMAIN)


def receive(sub: Any, take: Callable[[zenoh.Sample], None], progress: Callable[[], Any],
            enough: Callable[[Any], bool], timeout_s: float, what: str) -> None:
    """Hand every sample of ``sub`` to ``take`` until ``enough(progress())``."""
    def drain() -> Any:
        while (sample := sub.try_recv()) is not None:
            take(sample)
        return progress()

    wait_until(drain, enough, timeout_s=timeout_s, what=what)


def states_of(client: Client) -> list[np.void]:
    """Every state the client received since its history was last cut."""
    client.drain_states()
    return client.history


def keep_only_newest(client: Client) -> None:
    client.history[:] = client.history[-1:]


class RosPublisherLikeRmwZenoh:
    """A ROS node's publisher written from the design doc: key, CDR, attachment, tokens."""

    def __init__(self, session: zenoh.Session, topic: str, ros_type: str) -> None:
        self.session = session
        self.ros_type = ros_type
        zid = str(session.info.zid())
        base = f"@ros2_lv/{DOMAIN}/{zid}/0"
        node = "test_driver"
        self.tokens = [
            session.liveliness().declare_token(f"{base}/0/NN/%/%/{node}"),
            session.liveliness().declare_token(
                f"{base}/10/MP/%/%/{node}/%{topic}/{dds_name(ros_type)}/"
                f"{TS.hash_rihs01(ros_type)}/::,10:,:,:,,"),
        ]
        self.pub = session.declare_publisher(topic_key(topic, ros_type))
        self.gid = bytes(range(16))
        self.seq = 0

    def put(self, message) -> None:
        self.seq += 1
        attachment = struct.pack("<qqB16s", self.seq, time.time_ns(), 16, self.gid)
        self.pub.put(bytes(TS.serialize_cdr(message, self.ros_type)), attachment=attachment)

    def close(self) -> None:
        for token in self.tokens:
            token.undeclare()
        self.pub.undeclare()


def ackermann(speed: float, steer: float = 0.0, accel: float = 0.0):
    t = TS.types
    return t["ackermann_msgs/msg/AckermannDriveStamped"](
        header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0),
                                        frame_id="base_link"),
        drive=t["ackermann_msgs/msg/AckermannDrive"](
            steering_angle=steer, steering_angle_velocity=0.0, speed=speed,
            acceleration=accel, jerk=0.0))


def twist(speed: float, yaw_rate: float = 0.0):
    t = TS.types
    v3 = t["geometry_msgs/msg/Vector3"]
    return t["geometry_msgs/msg/Twist"](linear=v3(x=speed, y=0.0, z=0.0),
                                        angular=v3(x=0.0, y=0.0, z=yaw_rate))


def drive_until(pub: RosPublisherLikeRmwZenoh, message, client: Client,
                done: Callable[[list[np.void]], bool], timeout_s: float, what: str) -> None:
    """Publish ``message`` at 20 Hz (as a ROS node would) until ``done(history)``."""
    def publish_and_poll() -> np.void | None:
        pub.put(message)
        client.drain_states()
        return client.last

    wait_until(publish_and_poll, lambda last: bool(client.history) and done(client.history),
               timeout_s=timeout_s, what=what, interval_s=0.05)


def within(history: list[np.void], since_s: float) -> list[np.void]:
    """The states of the last ``since_s`` simulated seconds."""
    end = float(history[-1]["sim_time_s"])
    return [s for s in history if float(s["sim_time_s"]) >= end - since_s]


def assert_reaches_and_holds(pub, message, client: Client, target: float) -> None:
    """The car comes within 5 % of ``target``, then stays within 5 % for 3 s."""
    def close(s: np.void) -> bool:
        return abs(float(s["u_mps"]) - target) <= 0.05 * abs(target)

    drive_until(pub, message, client, lambda h: close(h[-1]), 30.0, f"within 5 % of {target}")
    keep_only_newest(client)
    start = float(client.history[0]["sim_time_s"])
    drive_until(pub, message, client, lambda h: float(h[-1]["sim_time_s"]) >= start + 3.0,
                10.0, "3 s more")
    worst = max(abs(float(s["u_mps"]) - target) for s in client.history)
    assert worst <= 0.05 * abs(target), f"left the 5 % band by {worst:.3f} m/s"


def stopped_and_held(history: list[np.void]) -> bool:
    s = history[-1]
    return abs(float(s["u_mps"])) < 0.01 and bool(int(s["flags"]) & proto.StateFlag.BRAKE_HOLD)


def reset_at_rest(client: Client) -> None:
    """``reset``, then forget every state from before it."""
    reply = client.request("reset", timeout_s=5.0)
    assert reply["ok"], reply
    client.history.clear()

    def first_after_reset() -> int | None:
        return next((i for i, s in enumerate(states_of(client))
                     if float(s["sim_time_s"]) < 0.5), None)

    first = wait_until(first_after_reset, lambda i: i is not None, timeout_s=10,
                       what="a state after the reset")
    del client.history[:first]


def assert_stop_and_hold_without_creep(pub, message, client: Client) -> None:
    """Zero target: the car stops, the brake holds, and it does not creep down the 10 %."""
    drive_until(pub, message, client, stopped_and_held, 20.0, "stop")
    stop_s = float(client.history[-1]["sim_time_s"])

    def settled(history: list[np.void]) -> bool:
        # the held car rocks on its tires (the paper's 3.5 Hz fore-aft mode) for about a
        # second, within a fraction of a millimetre; then it must not move
        window = within(history, 0.5)
        return float(window[0]["sim_time_s"]) >= stop_s and \
            all(abs(float(s["u_mps"])) < 1e-3 for s in window)

    drive_until(pub, message, client, settled, 5.0, "settle")
    keep_only_newest(client)
    start = client.history[0]
    drive_until(pub, message, client,
                lambda h: float(h[-1]["sim_time_s"]) - float(start["sim_time_s"]) >= 3.0,
                10.0, "hold for 3 s")
    held = client.history
    creep_m = max(math.hypot(float(s["x_m"]) - float(start["x_m"]),
                             float(s["y_m"]) - float(start["y_m"])) for s in held)
    assert creep_m < 1e-4, f"the car crept {creep_m * 1e3:.3f} mm in 3 s on the 10 % grade"
    assert max(abs(float(s["u_mps"])) for s in held) < 0.01
    for s in held:  # held by the adapter's commands (brake pedal), not by the watchdog
        assert not int(s["flags"]) & WATCHDOG, "the server's watchdog engaged during the hold"
        assert float(s["throttle"]) == 0.0 and float(s["brake"]) >= 0.3


# ---------------------------------------------------------------- the wire format

def test_wire_format_reproduces_the_design_doc_examples() -> None:
    """simserver.ros2.wire writes the design doc's own examples byte for byte."""
    from simserver.ros2 import wire

    assert wire.topic_keyexpr(0, "/chatter", "std_msgs/msg/String") == (
        f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}")
    assert wire.topic_keyexpr(0, "/robot1/chatter", "std_msgs/msg/String") == (
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}")
    assert wire.node_token(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "/", "listener") == (
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener")
    assert wire.endpoint_token(
        2, "8b20917502ee955ac4476e0266340d5c", 0, 10, "MP", "/", "talker", "/chatter",
        "std_msgs/msg/String", wire.QoS(depth=7)) == (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
        f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,")
    assert wire.type_hash("nav_msgs/msg/Odometry") == ODOMETRY_HASH
    assert wire.type_hash("ackermann_msgs/msg/AckermannDriveStamped") == ACKERMANN_HASH
    att = wire.encode_attachment(3, 1_700_000_000_123_456_789, bytes(range(16)))
    assert att == struct.pack("<qqB16s", 3, 1_700_000_000_123_456_789, 16, bytes(range(16)))


def test_gid_is_rmw_zenohs_xxh3_128_of_the_token() -> None:
    from simserver.ros2 import wire

    # xxHash's own test vector: XXH3-128 (seed 0) of no bytes is 0x99aa06d3014798d8_
    # 6001c324468d497f, so rmw_zenoh's GID of it is low64 then high64, little-endian
    assert wire.gid_for("") == bytes.fromhex("7f498d4624c30160" "d8984701d306aa99")
    token = ("@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
             f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,")
    assert wire.gid_for(token) == rmw_zenoh_gid(token)
    assert len(wire.gid_for(token)) == 16


def test_docs_tables_are_generated_from_the_code() -> None:
    from simserver.ros2 import wire

    text = (REPO / "docs" / "ros2.md").read_text(encoding="utf-8")
    assert wire.update_doc(text) == text, (
        "docs/ros2.md is stale: python -m simserver.ros2.wire --write docs/ros2.md")


@pytest.mark.parametrize(("flags", "field"), [
    (["--domain-id", "300"], "domain_id"),
    (["--namespace", "/1bad"], "namespace"),
    (["--topic", "speed=/x"], "topic"),
    (["--rate", "0"], "rate_hz"),
    (["--cars", "car0,car-1"], "car 'car-1'"),
    (["--cars", "a,,b"], "cars"),
])
def test_bad_options_are_refused_naming_the_option(flags, field, capsys) -> None:
    from simserver.cli import main

    assert main(["ros2", "--connect", "tcp/127.0.0.1:9", *flags]) == 2
    assert field in capsys.readouterr().err


def test_a_bad_ros_domain_id_in_the_environment_is_named(monkeypatch, capsys) -> None:
    from simserver.cli import main

    monkeypatch.setenv("ROS_DOMAIN_ID", "seven")
    assert main(["ros2", "--connect", "tcp/127.0.0.1:9"]) == 2
    assert "ROS_DOMAIN_ID" in capsys.readouterr().err


@pytest.mark.parametrize(("settings", "key"), [
    ({"domain": 1}, "domain"), ({"domain_id": "1"}, "domain_id"),
    ({"topics": ["odom"]}, "topics"), ({"normal_priority": 1}, "normal_priority"),
])
def test_serve_settings_are_checked_naming_the_key(settings, key) -> None:
    from simserver.ros2.cli import adapter_command

    with pytest.raises(ValueError, match=f"server.yaml: ros2.*{key}"):
        adapter_command("tcp/127.0.0.1:7447", "simserver", "car0", settings,
                        source="server.yaml: ros2")


def test_several_cars_each_under_its_namespace_one_car_unchanged() -> None:
    """A server of several cars: each car a node of its own under ``{namespace}/<id>``
    with ``<id>/base_link``, the world frame shared (docs/ros2.md, "Several cars"); a
    server of one car keeps the single car's names."""
    from simserver.ros2.adapter import Ros2Options, car_options
    from simserver.ros2.cli import adapter_command

    car = car_options(Ros2Options(cars="all").check(), "traffic")
    assert (car.vehicle_id, car.namespace, car.node_name) == ("traffic", "/traffic",
                                                              "simserver_traffic")
    assert (car.odom_frame, car.base_frame, car.cars) == ("odom", "traffic/base_link", None)
    under = car_options(Ros2Options(namespace="/sim", node_name="sim").check(), "b")
    assert (under.namespace, under.node_name) == ("/sim/b", "sim_b")
    several = adapter_command("tcp/127.0.0.1:7447", "simserver", "car0", {},
                              several_cars=True)
    assert several[-2:] == ["--cars", "all"]
    assert "--cars" not in adapter_command("tcp/127.0.0.1:7447", "simserver", "car0", {})


def test_published_topics_as_rmw_zenoh_writes_them(adapter, ros_node, watcher) -> None:
    """Keys, type hashes, CDR payloads, attachments and contents of all four topics."""
    received: dict[str, list] = {}
    expected = {topic_key(t, ros_type): t for t, (ros_type, _) in PUBLISHED.items()}

    def take(sample: zenoh.Sample) -> None:
        received.setdefault(str(sample.key_expr), []).append(
            (sample.payload.to_bytes(), sample.attachment.to_bytes()
             if sample.attachment is not None else None, time.time_ns()))

    sub = ros_node.declare_subscriber(f"{DOMAIN}/**", zenoh.handlers.FifoChannel(1 << 14))
    try:
        receive(sub, take, lambda: {k: len(v) for k, v in received.items()},
                lambda counts: all(counts.get(k, 0) >= 20 for k in expected), 20.0,
                "20 samples of each of the four topics")
    finally:
        sub.undeclare()
    assert set(received) == set(expected), "keys other than the four topics'"
    gids = set()
    for key, samples in received.items():
        ros_type = PUBLISHED[expected[key]][0]
        seqs = []
        for payload, attachment, t_rx in samples:
            assert payload[:4] == b"\x00\x01\x00\x00", "not little-endian CDR"
            TS.deserialize_cdr(payload, ros_type)  # decodes completely
            assert attachment is not None and len(attachment) == 33
            seq, stamp_ns, gid_len, gid = struct.unpack("<qqB16s", attachment)
            assert gid_len == 16
            assert abs(t_rx - stamp_ns) < 2e9, "source timestamp not ns since the epoch"
            seqs.append(seq)
            gids.add((key, gid))
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "sequence gaps"
    assert len({gid for _, gid in gids}) == len(expected), "one GID per publisher"
    assert len(gids) == len(expected)
    # each GID is rmw_zenoh's for the publisher's liveliness token
    token_of = {t.split("/")[9].replace("%", "/").lstrip("/"): t
                for t in liveliness_tokens(ros_node) if t.split("/")[5] == "MP"}
    for key, gid in gids:
        assert gid == rmw_zenoh_gid(token_of[expected[key]]), f"GID of {expected[key]}"
    # contents: at rest, held by the server's watchdog (no ROS command yet: no drive)
    state = watcher.newest()
    assert int(state["last_cmd_seq"]) == 0, "the adapter drove without a ROS command"
    odom = TS.deserialize_cdr(received[topic_key("odom", "nav_msgs/msg/Odometry")][-1][0],
                              "nav_msgs/msg/Odometry")
    assert (odom.header.frame_id, odom.child_frame_id) == ("odom", "base_link")
    q = odom.pose.pose.orientation
    pitch = math.asin(2.0 * (q.w * q.y - q.z * q.x))
    assert pitch == pytest.approx(float(state["pitch_rad"]), abs=2e-3)
    assert pitch == pytest.approx(-GRADE_RAD, abs=0.01), "nose up on the uphill grade"
    assert odom.pose.pose.position.x == pytest.approx(float(state["x_m"]), abs=0.01)
    assert odom.pose.pose.position.z == pytest.approx(float(state["z_m"]), abs=0.01)
    imu = TS.deserialize_cdr(received[topic_key("imu", "sensor_msgs/msg/Imu")][-1][0],
                             "sensor_msgs/msg/Imu")
    assert imu.header.frame_id == "base_link"
    a = imu.linear_acceleration  # specific force at rest: gravity's reaction, nose up
    assert a.x == pytest.approx(GRAVITY * math.sin(GRADE_RAD), abs=0.05)
    assert a.z == pytest.approx(GRAVITY * math.cos(GRADE_RAD), abs=0.05)
    tf = TS.deserialize_cdr(received[topic_key("tf", "tf2_msgs/msg/TFMessage")][-1][0],
                            "tf2_msgs/msg/TFMessage")
    (transform,) = tf.transforms
    assert (transform.header.frame_id, transform.child_frame_id) == ("odom", "base_link")
    assert transform.transform.translation.x == pytest.approx(odom.pose.pose.position.x,
                                                              abs=0.01)
    joints = TS.deserialize_cdr(
        received[topic_key("joint_states", "sensor_msgs/msg/JointState")][-1][0],
        "sensor_msgs/msg/JointState")
    assert joints.name == ["front_left_wheel_joint", "front_right_wheel_joint",
                           "rear_left_wheel_joint", "rear_right_wheel_joint",
                           "front_left_steer_joint", "front_right_steer_joint"]
    assert len(joints.position) == len(joints.velocity) == 6


def test_liveliness_tokens_announce_the_node_and_its_endpoints(adapter, ros_node) -> None:
    tokens = [t.split("/") for t in liveliness_tokens(ros_node)]
    adapter_zids = {t[2] for t in tokens} - {str(ros_node.info.zid())}
    assert len(adapter_zids) == 1, "one session holds the adapter's node"
    ours = [t for t in tokens if t[2] in adapter_zids]
    zid = ours[0][2]
    assert re.fullmatch(r"[0-9a-f]{1,32}", zid)
    node = [t for t in ours if t[5] == "NN"]
    assert ["/".join(t) for t in node] == [f"@ros2_lv/{DOMAIN}/{zid}/0/0/NN/%/%/{NODE}"]
    endpoints = [t for t in ours if t[5] in ("MP", "MS")]
    assert len(endpoints) == len(PUBLISHED) + len(SUBSCRIBED) == len(ours) - 1
    assert len({t[4] for t in endpoints}) == len(endpoints), "entity ids must be unique"
    for t in endpoints:
        assert t[:4] == ["@ros2_lv", str(DOMAIN), zid, "0"] and t[6:9] == ["%", "%", NODE]
        assert len(t) == 13
        topic = t[9].replace("%", "/").lstrip("/")
        if t[5] == "MP":
            ros_type, qos = PUBLISHED[topic]
        else:
            ros_type, qos = SUBSCRIBED[topic], "::,10:,:,:,,"
        assert t[10:13] == [dds_name(ros_type), TS.hash_rihs01(ros_type), qos]
    assert {t[9] for t in endpoints if t[5] == "MP"} == {"%" + p for p in PUBLISHED}
    assert {t[9] for t in endpoints if t[5] == "MS"} == {"%" + s for s in SUBSCRIBED}


def test_sim_time_stamps_and_clock(server, router, ros_node, watcher) -> None:
    """``stamp: sim``: stamps are the simulated time, also published on /clock."""
    domain = DOMAIN + 1  # a second adapter beside the first, on its own domain
    clock_type = "rosgraph_msgs/msg/Clock"
    clock_key = f"{domain}/clock/{dds_name(clock_type)}/{TS.hash_rihs01(clock_type)}"
    clocks, odoms = [], []

    def take(sample: zenoh.Sample) -> None:
        if str(sample.key_expr) == clock_key:
            msg = TS.deserialize_cdr(sample.payload.to_bytes(), clock_type)
            clocks.append(msg.clock.sec + 1e-9 * msg.clock.nanosec)
        elif str(sample.key_expr).startswith(f"{domain}/odom/"):
            msg = TS.deserialize_cdr(sample.payload.to_bytes(), "nav_msgs/msg/Odometry")
            odoms.append(msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec)

    sub = ros_node.declare_subscriber(f"{domain}/**", zenoh.handlers.FifoChannel(1 << 12))
    proc = start_adapter(server.endpoint, {
        "router": router[1], "domain_id": domain, "stamp": "sim", "normal_priority": True})
    try:
        receive(sub, take, lambda: (len(clocks), len(odoms)), lambda n: min(n) >= 20, 20.0,
                "20 /clock and 20 odom messages")
        # the simulated time now from a new session: the long-lived watcher's 1 kHz link
        # can lag seconds behind on a loaded machine (its socket buffers hold that much),
        # while the adapter reads the 100 Hz key
        with Client(server, state_capacity=64) as fresh:
            sim_now = float(fresh.wait_state(what="a state of a new session")["sim_time_s"])
        assert clocks == sorted(clocks) and clocks[-1] > clocks[0]
        assert sim_now - 1.0 < clocks[-1] <= sim_now + 0.1, "not the simulated time"
        assert sim_now - 1.0 < odoms[-1] <= sim_now + 0.1
        tokens = [t for t in liveliness_tokens_of(ros_node, domain) if "/MP/" in t]
        (clock_token,) = [t for t in tokens if "/%clock/" in t]
        assert clock_token.endswith(f"/{dds_name(clock_type)}/{TS.hash_rihs01(clock_type)}/"
                                    "2::,1:,:,:,,")  # best effort, keep last 1
    finally:
        sub.undeclare()
        code = proc.stop()
    assert code == 0, proc.text()


# ---------------------------------------------------------------- driving

@pytest.fixture
def ackermann_pub(adapter, ros_node) -> Iterator[RosPublisherLikeRmwZenoh]:
    """A ROS node's AckermannDriveStamped publisher on the adapter's command topic."""
    pub = RosPublisherLikeRmwZenoh(ros_node, "ackermann_cmd",
                                   "ackermann_msgs/msg/AckermannDriveStamped")
    yield pub
    pub.close()


@pytest.fixture
def twist_pub(adapter, ros_node) -> Iterator[RosPublisherLikeRmwZenoh]:
    """A ROS node's Twist publisher on ``cmd_vel``."""
    pub = RosPublisherLikeRmwZenoh(ros_node, "cmd_vel", "geometry_msgs/msg/Twist")
    yield pub
    pub.close()


def test_ackermann_reaches_and_holds_speed_then_stops_and_holds_on_10pct(
        ackermann_pub, watcher) -> None:
    pub = ackermann_pub
    reset_at_rest(watcher)
    assert_reaches_and_holds(pub, ackermann(6.0), watcher, 6.0)  # up the 10 % grade
    steer = 0.05
    drive_until(pub, ackermann(6.0, steer=steer), watcher,
                lambda h: float(h[-1]["steer_rad"][0]) == pytest.approx(steer, rel=1e-3),
                5.0, "road-wheel angle 0.05 rad")
    drive_until(pub, ackermann(6.0), watcher,
                lambda h: abs(float(h[-1]["steer_rad"][0])) < 1e-6, 5.0, "straight")
    assert_stop_and_hold_without_creep(pub, ackermann(0.0), watcher)
    assert_reaches_and_holds(pub, ackermann(-2.0), watcher, -2.0)  # reverse, downhill
    assert int(watcher.history[-1]["gear"]) == proto.Gear.R
    assert_stop_and_hold_without_creep(pub, ackermann(0.0), watcher)


def test_cmd_vel_reaches_and_holds_speed_then_stops_and_holds_on_10pct(
        twist_pub, watcher) -> None:
    pub = twist_pub
    reset_at_rest(watcher)
    assert_reaches_and_holds(pub, twist(4.0), watcher, 4.0)  # up the 10 % grade
    wheelbase = 1.35 + 1.55  # configs/vehicles/paper_sedan/chassis.yaml
    angle = math.atan(wheelbase * 0.2 / 4.0)
    drive_until(pub, twist(4.0, 0.2), watcher,
                lambda h: float(h[-1]["steer_rad"][0]) == pytest.approx(angle, rel=1e-3),
                5.0, "yaw rate 0.2 rad/s as a road-wheel angle")
    assert_stop_and_hold_without_creep(pub, twist(0.0), watcher)


def test_no_ros_command_no_drive(ackermann_pub, watcher) -> None:
    """ROS commands stop (or turn to NaN): the adapter goes silent, the watchdog holds."""
    pub = ackermann_pub
    reset_at_rest(watcher)
    drive_until(pub, ackermann(3.0), watcher,
                lambda h: float(h[-1]["u_mps"]) > 1.0 and not int(h[-1]["flags"]) & WATCHDOG,
                20.0, "driving")
    last_ros_command = time.monotonic()
    nan_command = ackermann(float("nan"))  # keeps arriving, but is no command
    drive_until(pub, nan_command, watcher, lambda h: int(h[-1]["flags"]) & WATCHDOG, 5.0,
                "the watchdog engaging")
    engaged_after_s = time.monotonic() - last_ros_command
    # the adapter's timeout (0.5 s) plus the server's watchdog (0.2 s), not sooner
    assert engaged_after_s > 0.6, engaged_after_s
    seq = int(watcher.history[-1]["last_cmd_seq"])
    end = float(watcher.history[-1]["sim_time_s"]) + 0.5
    drive_until(pub, nan_command, watcher, lambda h: float(h[-1]["sim_time_s"]) >= end,
                5.0, "0.5 s more")
    assert int(watcher.history[-1]["last_cmd_seq"]) == seq, "commands after the timeout"
    assert float(watcher.history[-1]["throttle"]) == 0.0


# ---------------------------------------------------------------- the controller alone

def paper_sedan_limits():
    from simserver.adapters.config import load_vehicle
    from simserver.ros2.control import VehicleLimits

    vehicle = load_vehicle(REPO / "configs" / "vehicles" / "paper_sedan" / "vehicle.yaml")
    return VehicleLimits.from_vehicle(vehicle.vp, vehicle.tp)


def test_zero_target_holds_the_brake_pedal_as_documented() -> None:
    from simserver.ros2 import control as C

    limits = paper_sedan_limits()
    ctl = C.SpeedController(limits)
    pedals = ctl.update(C.DriveTarget(speed_mps=0.0), 0.0, -GRADE_RAD, 0.01)
    expected = (C.STOP_DECEL_MPS2 + limits.gravity_mps2 * math.sin(GRADE_RAD)) \
        / limits.brake_decel_max_mps2
    assert pedals.throttle == 0.0 and pedals.brake == pytest.approx(max(expected, 0.3))
    gentle = ctl.update(C.DriveTarget(speed_mps=0.0, accel_limit_mps2=0.5), 0.0, 0.0, 0.01)
    assert gentle.brake == C.HOLD_PEDAL_MIN  # never less than the hold


def test_integral_does_not_wind_up_while_the_throttle_is_saturated() -> None:
    from simserver.ros2 import control as C

    ctl = C.SpeedController(paper_sedan_limits())
    for _ in range(500):  # 5 s far below a 30 m/s target, full throttle
        pedals = ctl.update(C.DriveTarget(speed_mps=30.0), 2.0, 0.0, 0.01)
        assert pedals.throttle == 1.0 and pedals.brake == 0.0
    assert ctl.integral_mps2 == 0.0


def test_reverse_waits_for_the_car_to_stop_before_shifting() -> None:
    from simserver.ros2 import control as C
    from simserver.wire.protocol import Gear

    ctl = C.SpeedController(paper_sedan_limits())
    rolling = ctl.update(C.DriveTarget(speed_mps=-2.0), 3.0, 0.0, 0.01)
    assert rolling.gear == Gear.D and rolling.brake > 0.0 and rolling.throttle == 0.0
    stopped = ctl.update(C.DriveTarget(speed_mps=-2.0), 0.05, 0.0, 0.01)
    assert stopped.gear == Gear.R and stopped.throttle > 0.0


def test_steering_maps_road_wheel_angle_through_the_ratio() -> None:
    from simserver.ros2 import control as C

    limits = paper_sedan_limits()
    assert C.steer_command(0.1, limits) == pytest.approx(0.1 * 17.0 / 9.42)
    assert C.steer_command(1.0, limits) == 1.0  # beyond the lock: clipped
    assert C.twist_steer_angle(4.0, 0.2, limits) == pytest.approx(math.atan(2.9 * 0.2 / 4.0))
    assert C.twist_steer_angle(0.0, 0.5, limits) == 0.0  # no turning on the spot


# ------------------------------------------------- serve starts it (servers of their own)
# After the tests of the module's server, which ends with its last test (tests/conftest.py):
# these servers do not run beside it.

def ros2_children(server: ServerProcess) -> list[int]:
    """Process ids of the server's ``simserver ros2`` children."""
    return [pid for pid in server.children()
            if process_argv(pid)[1:4] == ["-m", "simserver", "ros2"]]


def test_serve_starts_the_adapter_when_configured_and_stops_it(router, ros_node,
                                                               tmp_path) -> None:
    """A server config's ``ros2:`` section: the ROS graph shows the car's node and topics
    once the server is ready; stopping the server stops the adapter (no orphan)."""
    domain = DOMAIN + 2
    config = tmp_path / "server.yaml"
    config.write_text(f"scene: {FLAT_SCENE}\n"
                      f"ros2:\n  router: {router[1]}\n  domain_id: {domain}\n"
                      "  normal_priority: true\n", encoding="utf-8")
    endpoints = len(PUBLISHED) + len(SUBSCRIBED)
    with ServerProcess(scene=None, config=config) as server:
        server.wait_for_line("simserver ros2: node", timeout_s=120)
        tokens = wait_until(lambda: liveliness_tokens_of(ros_node, domain),
                            lambda ts: len(ts) == 1 + endpoints, timeout_s=30,
                            what="the adapter's node and endpoint tokens")
        assert [t.split("/")[8] for t in tokens if "/NN/" in t] == [NODE]
        (adapter_pid,) = ros2_children(server)
    assert server.returncode == 0, server.text()
    orphan = Path(f"/proc/{adapter_pid}").exists()
    if orphan:  # leave no process behind, then fail
        os.kill(adapter_pid, signal.SIGKILL)
    assert not orphan, "the adapter outlived the server"
    assert "ros2: " in server.text(), "the adapter did not end cleanly (no summary line)"
    wait_until(lambda: liveliness_tokens_of(ros_node, domain), lambda ts: not ts,
               timeout_s=10, what="the adapter's tokens gone from the graph")


def test_serve_ros2_flag_and_a_killed_adapter_is_restarted_within_2_s() -> None:
    """``serve --ros2`` starts it with the defaults, at normal priority; killed with -9
    (issue 34: it stayed gone, ROS users lost the car without a word), the server says so,
    starts it again within 2 s, and ``get_config`` tells its state; the server serves on."""
    with ServerProcess(scene="flat_paper_sedan", extra_args=["--ros2"]) as server, \
            Client(server) as client:
        line = server.wait_for_line("simserver ros2: node", timeout_s=120)
        assert "/simserver_car0 on domain" in line
        (adapter_pid,) = ros2_children(server)
        # normal priority, below the server's real-time tick: at idle priority a flood on
        # its own receive threads starved it (tests/test_ros2_floods.py)
        assert os.sched_getscheduler(adapter_pid) == os.SCHED_OTHER
        status = client.request("get_config", timeout_s=5.0)["config"]["ros2"]
        assert status == {"state": "running", "restarts": 0, "last_exit_code": None,
                          "pid": adapter_pid}
        os.kill(adapter_pid, signal.SIGKILL)
        killed = time.monotonic()

        def new_adapter() -> list[int]:
            return [pid for pid in ros2_children(server) if pid != adapter_pid]

        (restarted,) = wait_until(new_adapter, timeout_s=2.0, interval_s=0.01,
                                  what="the adapter restarted within 2 s of its kill -9")
        restart_s = time.monotonic() - killed
        server.wait_for_line(f"the ROS 2 adapter (pid {adapter_pid}) ended with exit code "
                             f"{-signal.SIGKILL}", timeout_s=10)
        server.wait_for_line(f"the ROS 2 adapter restarted (pid {restarted}, restart 1)",
                             timeout_s=10)
        status = client.request("get_config", timeout_s=5.0)["config"]["ros2"]
        assert status == {"state": "running", "restarts": 1,
                          "last_exit_code": -signal.SIGKILL, "pid": restarted}
        # the new one comes up as a node again (its ready line, a second time)
        server.wait_for_line("simserver ros2: node", timeout_s=120,
                             start=server.output.index(line) + 1)
        tick = int(client.fresh_state()["tick"])
        client.wait_state(lambda s: int(s["tick"]) > tick + 100, what="the server serving on")
        assert server.alive()
    assert server.returncode == 0, server.text()
    orphan = Path(f"/proc/{restarted}").exists()
    if orphan:  # leave no process behind, then fail
        os.kill(restarted, signal.SIGKILL)
    assert not orphan, "the restarted adapter outlived the server"
    print(f"adapter restarted {restart_s:.2f} s after its kill -9")


@pytest.mark.parametrize(("section", "message"), [
    ("ros2: {domain_id: 300}", "ros2: domain_id: 300 is not an integer in [0, 232]"),
    ("ros2: {domain: 1}", "ros2: unknown key 'domain'"),
    ("ros2: {rate_hz: fast}", "ros2.rate_hz: expected a float"),
    ("ros2: {topics: {speed: /x}}", "ros2: topic: 'speed' is not one of"),
    ("ros2: 5", "ros2: expected off, on or a mapping"),
])
def test_a_bad_ros2_section_is_refused_at_load_naming_file_and_key(section, message,
                                                                   tmp_path) -> None:
    from simserver.adapters.config import ConfigError
    from simserver.server.config import load_server_config

    config = tmp_path / "server.yaml"
    config.write_text(f"scene: {FLAT_SCENE}\n{section}\n", encoding="utf-8")
    with pytest.raises(ConfigError) as err:
        load_server_config(config)
    assert str(err.value).startswith(f"{config}: ") and message in str(err.value)


def test_ros2_section_and_flags_decide_together(tmp_path) -> None:
    from simserver.server.config import load_server_config

    config = tmp_path / "server.yaml"
    config.write_text(f"scene: {FLAT_SCENE}\nros2: {{domain_id: 3}}\n", encoding="utf-8")
    assert load_server_config(config).ros2 == {"domain_id": 3}
    assert load_server_config(config, ros2=True).ros2 == {"domain_id": 3}
    assert load_server_config(config, ros2=False).ros2 is None
    config.write_text(f"scene: {FLAT_SCENE}\nros2: off\n", encoding="utf-8")
    assert load_server_config(config).ros2 is None
    assert load_server_config(config, ros2=True).ros2 == {}
    config.write_text(f"scene: {FLAT_SCENE}\n", encoding="utf-8")
    assert load_server_config(config).ros2 is None
    assert load_server_config(CONFIGS / "server" / "default.yaml").ros2 is None
