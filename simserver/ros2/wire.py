"""rmw_zenoh's wire format (ROS 2 Jazzy) and the topics this adapter speaks.

Everything here follows rmw_zenoh's design document (``docs/design.md`` of
github.com/ros2/rmw_zenoh, sections "Topic and Service name mapping to Zenoh key
expressions", "Graph Cache" and "Publishers"):

- **Key expression** of a topic: ``<domain id>/<fully qualified name without the leading
  slash>/<DDS type name>/<type hash>``, e.g.
  ``0/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_3cc97dc7...``. The DDS type name of
  ``pkg/msg/Type`` is ``pkg::msg::dds_::Type_``; the type hash is REP 2016's RIHS01 hash
  of the type description.
- **Payload**: the message in CDR, little-endian, with its 4-byte encapsulation header
  (``00 01 00 00``), exactly what rosbags' ``serialize_cdr`` writes.
- **Attachment** of every sample: 33 bytes, written with zenoh's own serializer as
  rmw_zenoh does: the sequence number (int64, little-endian, from 1), the source
  timestamp (int64 ns since the UNIX epoch, little-endian), then the publisher GID as a
  byte sequence (its length, 16, in one LEB128 byte, then the 16 bytes).
- **Liveliness tokens** announce the graph (``ros2 node list``, ``ros2 topic list`` read
  them): ``@ros2_lv/<domain>/<session id>/<node id>/<node id>/NN/<enclave>/<namespace>/
  <node name>`` for a node and ``@ros2_lv/<domain>/<session id>/<node id>/<entity id>/
  <MP|MS>/<enclave>/<namespace>/<node name>/<topic>/<DDS type name>/<type hash>/<qos>``
  for a publisher or a subscription. Names are *mangled*: every ``/`` becomes ``%`` (the
  root namespace and the default enclave ``/`` become ``%``). The session id is the zenoh
  session's id as zenoh prints it. The QoS chunk lists reliability, durability,
  history and depth, deadline, lifespan and liveliness, each empty when it equals
  rmw_zenoh's default (reliable, volatile, keep-last 42, infinite durations, automatic
  liveliness): ``::,10:,:,:,,`` is a reliable, volatile, keep-last-10 endpoint.

The publisher GID is 16 bytes that identify the publisher; as rmw_zenoh computes it
(``Entity::Entity`` in ``rmw_zenoh_cpp/src/detail/liveliness_utils.cpp``): the XXH3-128 hash
(seed 0, default secret) of the entity's liveliness token key expression, its low 64 bits
then its high 64 bits, each in the machine's byte order (little-endian on every platform
ROS 2 supports): the 128-bit hash value as 16 little-endian bytes.

The message types come from rosbags' type store for Jazzy (``Stores.ROS2_JAZZY``), which
ships the standard definitions and computes RIHS01 hashes offline; ``ackermann_msgs`` is
not in it, so its two definitions are registered here from their ``.msg`` fields (the
hash depends only on field names and types, not on comments).
"""

from __future__ import annotations

import functools
import re
import struct
from dataclasses import dataclass
from typing import Any, Final

import xxhash

ADMIN_SPACE: Final[str] = "@ros2_lv"
"""First chunk of every rmw_zenoh liveliness token (a hermetic zenoh namespace)."""

ATTACHMENT_FORMAT: Final[str] = "<qqB16s"
"""The attachment's layout: seq (int64), source time ns (int64), GID length (16), GID."""

ATTACHMENT_SIZE: Final[int] = struct.calcsize(ATTACHMENT_FORMAT)  # 33
GID_SIZE: Final[int] = 16
CDR_LE_HEADER: Final[bytes] = b"\x00\x01\x00\x00"
"""Encapsulation header of a little-endian plain CDR payload."""

ENTITY_NODE, ENTITY_PUBLISHER, ENTITY_SUBSCRIPTION = "NN", "MP", "MS"

# ackermann_msgs (github.com/ros-drivers/ackermann_msgs), fields only.
ACKERMANN_DEFINITIONS: Final[dict[str, str]] = {
    "ackermann_msgs/msg/AckermannDrive": (
        "float32 steering_angle\n"
        "float32 steering_angle_velocity\n"
        "float32 speed\n"
        "float32 acceleration\n"
        "float32 jerk\n"
    ),
    "ackermann_msgs/msg/AckermannDriveStamped": (
        "std_msgs/Header header\n"
        "AckermannDrive drive\n"
    ),
}


class Ros2WireError(ValueError):
    """A name, id or payload that rmw_zenoh's format cannot carry; the message names it."""


# ============================================================================ types

@functools.lru_cache(maxsize=1)
def typestore() -> Any:
    """rosbags' ROS 2 Jazzy type store with ``ackermann_msgs`` registered (built once)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict[str, Any] = {}
    for name, text in ACKERMANN_DEFINITIONS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def dds_type_name(ros_type: str) -> str:
    """``nav_msgs/msg/Odometry`` -> ``nav_msgs::msg::dds_::Odometry_`` (the CDR type name)."""
    parts = ros_type.split("/")
    if len(parts) != 3 or parts[1] != "msg" or not all(parts):
        raise Ros2WireError(f"type: {ros_type!r} is not of the form package/msg/Type")
    return f"{parts[0]}::msg::dds_::{parts[2]}_"


def type_hash(ros_type: str) -> str:
    """The RIHS01 type hash of ``ros_type`` (``RIHS01_<64 hex digits>``)."""
    return typestore().hash_rihs01(ros_type)


def serialize(message: Any, ros_type: str) -> bytes:
    """CDR, little-endian, with the encapsulation header (rosbags' serialiser)."""
    return bytes(typestore().serialize_cdr(message, ros_type))


def deserialize(payload: bytes | bytearray | memoryview, ros_type: str) -> Any:
    """Decode a CDR payload of ``ros_type`` (rosbags' deserialiser)."""
    return typestore().deserialize_cdr(bytes(payload), ros_type)


# ============================================================================ names

_NAME_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def _check_tokens(what: str, name: str, tokens: list[str]) -> None:
    for token in tokens:
        if not _NAME_TOKEN.fullmatch(token):
            raise Ros2WireError(
                f"{what}: {name!r} is not a valid ROS name (tokens of letters, digits and "
                "_, not starting with a digit, separated by /)")


def validate_node_name(name: str) -> str:
    """A ROS node name: one token (``simserver_car0``)."""
    _check_tokens("node_name", name, [name])
    return name


def validate_namespace(namespace: str) -> str:
    """``/`` or an absolute namespace ``/a/b`` (a missing leading slash is added)."""
    ns = namespace if namespace.startswith("/") else "/" + namespace
    if ns != "/":
        ns = ns.rstrip("/")
        _check_tokens("namespace", namespace, ns[1:].split("/"))
    return ns


def node_name_for(vehicle_id: str) -> str:
    """A valid node name for a vehicle id (``car-0.a`` -> ``simserver_car_0_a``)."""
    return "simserver_" + re.sub(r"[^A-Za-z0-9_]", "_", vehicle_id)


def fully_qualified_name(namespace: str, topic: str) -> str:
    """The fully qualified topic name: ``/ns/topic``, or ``topic`` itself when absolute."""
    if topic.startswith("/"):
        _check_tokens("topic", topic, topic[1:].split("/"))
        return topic
    _check_tokens("topic", topic, topic.split("/"))
    ns = validate_namespace(namespace)
    return f"/{topic}" if ns == "/" else f"{ns}/{topic}"


def mangle(name: str) -> str:
    """rmw_zenoh's mangling for liveliness tokens: every ``/`` becomes ``%``."""
    return name.replace("/", "%")


# ============================================================================ QoS

RELIABILITY_RELIABLE, RELIABILITY_BEST_EFFORT = 1, 2  # rmw_qos_reliability_policy_e
DURABILITY_TRANSIENT_LOCAL, DURABILITY_VOLATILE = 1, 2  # rmw_qos_durability_policy_e
HISTORY_KEEP_LAST, HISTORY_KEEP_ALL = 1, 2  # rmw_qos_history_policy_e
RMW_ZENOH_DEFAULT_DEPTH = 42


@dataclass(frozen=True)
class QoS:
    """The QoS policies this adapter declares (durations and liveliness stay default)."""

    depth: int = 10
    reliability: int = RELIABILITY_RELIABLE
    durability: int = DURABILITY_VOLATILE
    history: int = HISTORY_KEEP_LAST

    def keyexpr(self) -> str:
        """The token's QoS chunk; a policy equal to rmw_zenoh's default is left empty."""
        def field(value: int, default: int) -> str:
            return "" if value == default else str(value)

        return (f"{field(self.reliability, RELIABILITY_RELIABLE)}:"
                f"{field(self.durability, DURABILITY_VOLATILE)}:"
                f"{field(self.history, HISTORY_KEEP_LAST)},"
                f"{field(self.depth, RMW_ZENOH_DEFAULT_DEPTH)}:"
                ",:"  # deadline sec, nsec: infinite (default)
                ",:"  # lifespan sec, nsec: infinite (default)
                ",,")  # liveliness kind, lease sec, lease nsec: automatic, infinite


# ============================================================================ keys

def check_domain_id(domain_id: int) -> int:
    """ROS_DOMAIN_ID: an integer in [0, 232] (the range ROS 2 documents)."""
    if isinstance(domain_id, bool) or not isinstance(domain_id, int) \
            or not 0 <= domain_id <= 232:
        raise Ros2WireError(f"domain_id: {domain_id!r} is not an integer in [0, 232]")
    return domain_id


def topic_keyexpr(domain_id: int, fq_topic: str, ros_type: str) -> str:
    """The key expression a topic's samples are put on."""
    return (f"{check_domain_id(domain_id)}/{fq_topic.strip('/')}/{dds_type_name(ros_type)}/"
            f"{type_hash(ros_type)}")


def node_token(domain_id: int, session_id: str, node_id: int, namespace: str,
               node_name: str, enclave: str = "/") -> str:
    """The liveliness token of a node (kind ``NN``; its entity id is its node id)."""
    return "/".join((ADMIN_SPACE, str(check_domain_id(domain_id)), session_id, str(node_id),
                     str(node_id), ENTITY_NODE, mangle(enclave),
                     mangle(validate_namespace(namespace)), validate_node_name(node_name)))


def endpoint_token(domain_id: int, session_id: str, node_id: int, entity_id: int, kind: str,
                   namespace: str, node_name: str, fq_topic: str, ros_type: str, qos: QoS,
                   enclave: str = "/") -> str:
    """The liveliness token of a publisher (``MP``) or a subscription (``MS``)."""
    if kind not in (ENTITY_PUBLISHER, ENTITY_SUBSCRIPTION):
        raise Ros2WireError(f"kind: {kind!r} is not MP or MS")
    return "/".join((ADMIN_SPACE, str(check_domain_id(domain_id)), session_id, str(node_id),
                     str(entity_id), kind, mangle(enclave),
                     mangle(validate_namespace(namespace)), validate_node_name(node_name),
                     mangle(fq_topic), dds_type_name(ros_type), type_hash(ros_type),
                     qos.keyexpr()))


def gid_for(token: str) -> bytes:
    """The 16-byte GID rmw_zenoh gives the entity of ``token``: XXH3-128 of the token's
    key expression, low 64 bits then high 64 bits, little-endian."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(GID_SIZE, "little")


# ============================================================================ attachment

def encode_attachment(seq: int, source_time_ns: int, gid: bytes) -> bytes:
    """The 33-byte attachment, written with zenoh's serializer (as rmw_zenoh does)."""
    from zenoh.ext import Int64, z_serialize

    if len(gid) != GID_SIZE:
        raise Ros2WireError(f"gid: {len(gid)} bytes, expected {GID_SIZE}")
    return z_serialize((Int64(seq), Int64(source_time_ns), bytes(gid))).to_bytes()


@dataclass(frozen=True)
class Attachment:
    """A decoded rmw_zenoh attachment."""

    seq: int
    source_time_ns: int
    gid: bytes


def decode_attachment(data: bytes | bytearray | memoryview) -> Attachment:
    """Parse a 33-byte attachment; :class:`Ros2WireError` names what is wrong."""
    data = bytes(data)
    if len(data) != ATTACHMENT_SIZE:
        raise Ros2WireError(f"attachment: {len(data)} bytes, expected {ATTACHMENT_SIZE}")
    seq, stamp, n, gid = struct.unpack(ATTACHMENT_FORMAT, data)
    if n != GID_SIZE:
        raise Ros2WireError(f"attachment: GID length {n}, expected {GID_SIZE}")
    return Attachment(seq, stamp, gid)


# ============================================================================ topics

PUBLISH, SUBSCRIBE = "publish", "subscribe"


@dataclass(frozen=True)
class TopicSpec:
    """One topic of the adapter (a row of the table in docs/ros2.md).

    ``option`` is the adapter's name for it (``--topic option=name`` renames it); ``name``
    the default ROS name, relative to the node's namespace.
    """

    option: str
    name: str
    ros_type: str
    direction: str
    qos: QoS
    mapping: str
    sim_time_only: bool = False  # declared only with simulated-time stamps


TOPICS: Final[tuple[TopicSpec, ...]] = (
    TopicSpec("odom", "odom", "nav_msgs/msg/Odometry", PUBLISH, QoS(depth=10),
              "pose of `base_link` (the CG) in `odom` (the world frame), twist in "
              "`base_link`: body velocities u, v, w and rates p, q, r"),
    TopicSpec("imu", "imu", "sensor_msgs/msg/Imu", PUBLISH, QoS(depth=10),
              "frame `base_link`: attitude, body rates, specific force (kinematic "
              "acceleration ax, ay, 0 minus gravity; reads +g up at rest)"),
    TopicSpec("tf", "/tf", "tf2_msgs/msg/TFMessage", PUBLISH, QoS(depth=100),
              "`odom` -> `base_link`, the same pose as `odom`"),
    TopicSpec("joint_states", "joint_states", "sensor_msgs/msg/JointState", PUBLISH,
              QoS(depth=10),
              "wheel spin angles (integrated) and rates, front road-wheel steer angles"),
    TopicSpec("clock", "/clock", "rosgraph_msgs/msg/Clock", PUBLISH,
              QoS(depth=1, reliability=RELIABILITY_BEST_EFFORT),
              "only with `--stamp sim`: the simulated time, for nodes with `use_sim_time`",
              sim_time_only=True),
    TopicSpec("ackermann_cmd", "ackermann_cmd", "ackermann_msgs/msg/AckermannDriveStamped",
              SUBSCRIBE, QoS(depth=10),
              "`drive.speed` (m/s, < 0 reverses), `drive.acceleration` (ramp limit, 0 = as "
              "fast as the car can), `drive.steering_angle` (rad, road wheel, + left), "
              "`drive.steering_angle_velocity` (rate limit, 0 = none)"),
    TopicSpec("cmd_vel", "cmd_vel", "geometry_msgs/msg/Twist", SUBSCRIBE, QoS(depth=10),
              "`linear.x` target speed (m/s), `angular.z` target yaw rate (rad/s) -> road-"
              "wheel angle atan(wheelbase * yaw rate / speed)"),
)
"""Every topic of the adapter: the one source of the code's declarations and of the doc."""

TOPIC_BY_OPTION: Final[dict[str, TopicSpec]] = {t.option: t for t in TOPICS}


def topics_markdown() -> str:
    """The topic table of docs/ros2.md (generated; ``tests/test_ros2.py`` checks it)."""
    rows = ["| topic (default name) | type | direction | QoS (rmw_zenoh token) | mapping |",
            "|---|---|---|---|---|"]
    for t in TOPICS:
        reliability = "reliable" if t.qos.reliability == RELIABILITY_RELIABLE \
            else "best effort"
        rows.append(f"| `{t.name}` | `{t.ros_type}` | {t.direction} | {reliability}, "
                    f"volatile, keep last {t.qos.depth} (`{t.qos.keyexpr()}`) | "
                    f"{t.mapping} |")
    return "\n".join(rows)


def type_hashes_markdown() -> str:
    """The RIHS01 hashes of the topics' types (generated)."""
    rows = ["| type | DDS type name | RIHS01 hash (ROS 2 Jazzy) |", "|---|---|---|"]
    for ros_type in dict.fromkeys(t.ros_type for t in TOPICS):
        rows.append(f"| `{ros_type}` | `{dds_type_name(ros_type)}` | `{type_hash(ros_type)}` |")
    return "\n".join(rows)


def doc_sections() -> dict[str, str]:
    """The generated sections of docs/ros2.md, by marker name."""
    return {"topics": topics_markdown(), "type_hashes": type_hashes_markdown()}


def update_doc(text: str) -> str:
    """``text`` with every ``<!-- BEGIN GENERATED: name -->`` section regenerated."""
    sections = doc_sections()

    def sub(m: re.Match) -> str:
        return f"{m.group(1)}\n{sections[m.group(2)]}\n{m.group(3)}"

    return re.sub(r"(<!-- BEGIN GENERATED: (\w+) -->)\n.*?\n(<!-- END GENERATED -->)", sub,
                  text, flags=re.S)


def main(argv: list[str] | None = None) -> int:
    """``python -m simserver.ros2.wire --write docs/ros2.md``: regenerate its tables."""
    import argparse
    from pathlib import Path

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--write", type=Path, required=True, metavar="DOC")
    args = parser.parse_args(argv)
    args.write.write_text(update_doc(args.write.read_text(encoding="utf-8")), encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
