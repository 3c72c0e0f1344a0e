"""The ROS 2 adapter process: a ROS 2 node (as rmw_zenoh makes one) fed by the state topic.

Like the viewer (``simserver.adapters.viewer``), it is a separate process that talks to the server
only through the protocol: it subscribes to the state (a bounded ring, newest wins; the
server's ``state/100hz`` key at rates up to 100 Hz, else the 1 kHz ``state``),
sends DriverCommands, and reads the vehicle with the ``get_config`` control. The 1 kHz
loop never waits for it. Its Python thread runs at normal CPU priority, below the
server's real-time tick: at idle priority (``--idle-priority``,
:func:`idle_python_thread`) a flood of ROS messages on its own receive threads, which
keep normal priority, starved it (issue 34: 2.5 odometry messages a second of 100 under
a flood of valid Ackermann commands, 26 under a malformed one).

Every ``1 / rate_hz`` seconds (absolute deadlines; a late loop skips, never bursts) it:

1. takes the newest state and the newest valid ROS command of each topic received since
   the last period (``ackermann_cmd``, then ``cmd_vel``; the last one is in force),
   decoding at most :data:`COMMAND_RING_DEPTH` samples a topic, newest first, however
   fast they come (:class:`RosSubscription`). A command with a NaN or an infinity is
   ignored (counted as rejected), as if it had not been sent; recurring warnings are
   logged at most once a second, with counts;
2. if the newest ROS command is younger than ``command_timeout_s``, runs the speed
   controller (``simserver.ros2.control``) and sends one DriverCommand. Without a ROS
   command for that long it sends nothing at all, so the server's own watchdog engages
   after its period (throttle 0, brakes hold) exactly as for any silent client: no ROS
   command, no drive;
3. publishes Odometry, Imu, TF and JointState of that state (``simserver.ros2.convert``),
   stamped with the wall clock (``stamp="wall"``, what a real car's drivers do) or the
   simulated time (``stamp="sim"``, which also publishes it on ``/clock`` for nodes run
   with ``use_sim_time``).

The node's graph entities (node, publishers, subscriptions) are announced with
rmw_zenoh's liveliness tokens (``simserver.ros2.wire``), so ``ros2 node list`` shows
``/simserver_<vehicle>`` and ``ros2 topic list`` its topics.
"""

from __future__ import annotations

import json
import logging
import math
import os
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import zenoh

from simserver.ros2 import wire
from simserver.ros2.control import DriveTarget, SpeedController, VehicleLimits, twist_steer_angle
from simserver.ros2.convert import StateConverter
from simserver.server.logfile import RateLimitedLog
from simserver.wire import protocol as proto

log = logging.getLogger("simserver.ros2")

CONFIG_POLL_S = 2.0
"""Re-read the server's configuration this often, to follow a ``load`` of another vehicle."""

COMMAND_RING_DEPTH = 4
"""Samples a command subscription keeps between two periods (the newest; zenoh's threads
overwrite the oldest), so at most this many are decoded a period, newest first, whatever
the rate they come at: only the newest valid command matters (issue 34: a flood of 20 000
commands a second, one line logged and one decode per message, halved the odometry)."""

REJECT_LOG_INTERVAL_S = 1.0
"""A recurring warning (a command that does not decode, a non-finite one) is logged at most
this often, with the count of those in between (issue 34: one line per bad message)."""

T = TypeVar("T")


@dataclass
class Ros2Options:
    """How the adapter connects and what it names things (``simserver ros2`` flags)."""

    connect: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    zenoh_config: Path | None = None
    ros_router: str | None = None  # rmw_zenohd's endpoint: the ROS node joins it as a client
    prefix: str = proto.DEFAULT_PREFIX
    vehicle_id: str = proto.DEFAULT_VEHICLE
    domain_id: int = 0
    namespace: str = "/"
    node_name: str | None = None  # default simserver_<vehicle id>
    rate_hz: float = 100.0
    command_timeout_s: float = 0.5
    topics: dict[str, str] = field(default_factory=dict)  # option -> ROS name overrides
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    stamp: str = "wall"
    duration_s: float | None = None
    idle_priority: bool = False  # SCHED_IDLE for its Python thread (--idle-priority)

    def check(self) -> Ros2Options:
        """Validate; :class:`simserver.ros2.wire.Ros2WireError` names the bad option."""
        wire.check_domain_id(self.domain_id)
        self.namespace = wire.validate_namespace(self.namespace)
        self.node_name = wire.validate_node_name(self.node_name
                                                 or wire.node_name_for(self.vehicle_id))
        if not 1.0 <= self.rate_hz <= 1000.0:
            raise wire.Ros2WireError(f"rate_hz: {self.rate_hz} is not in [1, 1000]")
        if not 0.01 <= self.command_timeout_s <= 60.0:
            raise wire.Ros2WireError(
                f"command_timeout_s: {self.command_timeout_s} is not in [0.01, 60]")
        if self.stamp not in ("wall", "sim"):
            raise wire.Ros2WireError(f"stamp: {self.stamp!r} is not 'wall' or 'sim'")
        if self.ros_router is not None and "/" not in self.ros_router:
            raise wire.Ros2WireError(f"ros_router: {self.ros_router!r} is not an endpoint "
                                     "<protocol>/<address> (e.g. tcp/127.0.0.1:7447)")
        for option, name in self.topics.items():
            if option not in wire.TOPIC_BY_OPTION:
                raise wire.Ros2WireError(
                    f"topic: {option!r} is not one of {', '.join(wire.TOPIC_BY_OPTION)}")
            wire.fully_qualified_name(self.namespace, name)
        return self


@dataclass
class Ros2Stats:
    """What the adapter did."""

    states_received: int = 0
    messages_published: int = 0
    ros_commands: int = 0
    ros_commands_rejected: int = 0
    ros_commands_superseded: int = 0
    commands_sent: int = 0
    periods: int = 0
    periods_missed: int = 0  # deadlines skipped because a period ran late
    cpu_priority: str = "normal"


class RosPublisher:
    """A ROS 2 publisher as rmw_zenoh makes one: key, CDR payload, attachment, token."""

    def __init__(self, node: RosNode, fq_topic: str, ros_type: str, qos: wire.QoS) -> None:
        self.topic = fq_topic
        self.ros_type = ros_type
        self.key = wire.topic_keyexpr(node.domain_id, fq_topic, ros_type)
        self.token_key = node.endpoint_token(wire.ENTITY_PUBLISHER, fq_topic, ros_type, qos)
        self.gid = wire.gid_for(self.token_key)
        self.seq = 0
        # rmw_zenoh: a KEEP_LAST publisher drops rather than blocks on congestion
        self._pub = node.session.declare_publisher(
            self.key, congestion_control=zenoh.CongestionControl.DROP)
        self._token = node.session.liveliness().declare_token(self.token_key)

    def put(self, message: Any) -> None:
        """Serialise and publish one message."""
        self.seq += 1
        self._pub.put(wire.serialize(message, self.ros_type),
                      attachment=wire.encode_attachment(self.seq, time.time_ns(), self.gid))

    def close(self) -> None:
        for obj in (self._token, self._pub):
            try:
                obj.undeclare()
            except zenoh.ZError:
                pass


class RosSubscription:
    """A ROS 2 subscription: a small ring of the newest samples, of which each period decodes
    the newest (rosbags), and older ones only while the newer did not decode or was refused.

    A publisher flooding the topic (valid or not) thus costs this process's period at most
    :data:`COMMAND_RING_DEPTH` decodes, however fast it sends: the ring keeps the newest
    samples (zenoh's threads overwrite the oldest), and older ones behind a valid one are
    dropped unread (counted in ``superseded``). Decoding failures are counted in
    ``rejected`` and logged at most once a second, with the count of those in between.
    """

    def __init__(self, node: RosNode, fq_topic: str, ros_type: str, qos: wire.QoS) -> None:
        self.topic = fq_topic
        self.ros_type = ros_type
        self.key = wire.topic_keyexpr(node.domain_id, fq_topic, ros_type)
        self.token_key = node.endpoint_token(wire.ENTITY_SUBSCRIPTION, fq_topic, ros_type, qos)
        self._sub = node.session.declare_subscriber(
            self.key, zenoh.handlers.RingChannel(max(1, min(qos.depth, COMMAND_RING_DEPTH))))
        self._token = node.session.liveliness().declare_token(self.token_key)
        self.rejected = 0  # samples that did not decode
        self.superseded = 0  # samples dropped unread: a newer one of the same period decoded
        self.reject_log = RateLimitedLog(REJECT_LOG_INTERVAL_S, log)

    def newest(self, accept: Callable[[Any], T | None]) -> tuple[T | None, int]:
        """The newest sample received since the last call that decodes and that ``accept``
        turns into a value (not None), and how many ``accept`` refused; never blocks.

        At most :data:`COMMAND_RING_DEPTH` samples are decoded, newest first.
        """
        samples = []
        sample = self._sub.try_recv()
        while sample is not None:  # at most the ring's depth
            samples.append(sample)
            sample = self._sub.try_recv()
        refused = 0
        for tried, sample in enumerate(reversed(samples)):
            try:
                message = wire.deserialize(sample.payload.to_bytes(), self.ros_type)
            except Exception as exc:  # rosbags raises several kinds on a bad payload
                self.rejected += 1
                self.reject_log.warn(f"{self.key}: cannot decode a {self.ros_type} ({exc})")
                continue
            value = accept(message)
            if value is not None:
                self.superseded += len(samples) - tried - 1
                return value, refused
            refused += 1
        return None, refused

    def close(self) -> None:
        for obj in (self._token, self._sub):
            try:
                obj.undeclare()
            except zenoh.ZError:
                pass


class RosNode:
    """One ROS 2 node on a zenoh session (rmw_zenoh's graph tokens), node id 0."""

    def __init__(self, session: zenoh.Session, domain_id: int, namespace: str,
                 node_name: str) -> None:
        self.session = session
        self.domain_id = domain_id
        self.namespace = namespace
        self.node_name = node_name
        self.session_id = str(session.info.zid())
        self.node_id = 0
        self._next_entity_id = 1
        self.token_key = wire.node_token(domain_id, self.session_id, self.node_id, namespace,
                                         node_name)
        self._token = session.liveliness().declare_token(self.token_key)
        self._entities: list[RosPublisher | RosSubscription] = []

    def endpoint_token(self, kind: str, fq_topic: str, ros_type: str, qos: wire.QoS) -> str:
        entity_id = self._next_entity_id
        self._next_entity_id += 1
        return wire.endpoint_token(self.domain_id, self.session_id, self.node_id, entity_id,
                                   kind, self.namespace, self.node_name, fq_topic, ros_type,
                                   qos)

    def publisher(self, fq_topic: str, ros_type: str, qos: wire.QoS) -> RosPublisher:
        pub = RosPublisher(self, fq_topic, ros_type, qos)
        self._entities.append(pub)
        return pub

    def subscription(self, fq_topic: str, ros_type: str, qos: wire.QoS) -> RosSubscription:
        sub = RosSubscription(self, fq_topic, ros_type, qos)
        self._entities.append(sub)
        return sub

    def close(self) -> None:
        while self._entities:
            self._entities.pop().close()
        try:
            self._token.undeclare()
        except zenoh.ZError:
            pass


def _vehicle_from_config(config: dict[str, Any]) -> tuple[VehicleLimits, float, str]:
    """Controller limits, gravity and a change marker from a ``get_config`` reply."""
    from simserver.adapters.config import load_vehicle
    from simserver.adapters.config_paths import local_config_file

    vehicle_path = local_config_file(config["vehicle"]["path"])  # shown relative to configs/
    model = config["scene"].get("model") or {}
    vehicle = load_vehicle(vehicle_path, model)
    limits = VehicleLimits.from_vehicle(vehicle.vp, vehicle.tp)
    return limits, limits.gravity_mps2, f"{vehicle_path}|{sorted(model.items())}"


def _finite(target: DriveTarget) -> DriveTarget | None:
    values = (target.speed_mps, target.accel_limit_mps2, target.steer_rad,
              target.steer_rate_limit_radps)
    return target if all(math.isfinite(v) for v in values) else None


def _target_from_ackermann(msg: Any) -> DriveTarget | None:
    """An AckermannDriveStamped's target, or None when a value is NaN or infinite."""
    d = msg.drive
    return _finite(DriveTarget(
        speed_mps=float(d.speed), accel_limit_mps2=abs(float(d.acceleration)),
        steer_rad=float(d.steering_angle),
        steer_rate_limit_radps=abs(float(d.steering_angle_velocity))))


def _target_from_twist(msg: Any, limits: VehicleLimits) -> DriveTarget | None:
    """A Twist's target (``linear.x``, ``angular.z``), or None when one is not finite."""
    speed, yaw_rate = float(msg.linear.x), float(msg.angular.z)
    if not (math.isfinite(speed) and math.isfinite(yaw_rate)):
        return None
    return DriveTarget(speed_mps=speed, steer_rad=twist_steer_angle(speed, yaw_rate, limits))


class Ros2Adapter:
    """The adapter's state between periods; :meth:`period` is its list of stages.

    Parameters
    ----------
    opts : Ros2Options
        Checked options.
    ep : ZenohEndpoint
        The session bound to the server's keys.
    ros_session : zenoh.Session, optional
        The session of the ROS node (a client of rmw_zenohd); default ``ep``'s.
    stats : Ros2Stats
        Updated as it runs.
    """

    def __init__(self, opts: Ros2Options, ep: Any, stats: Ros2Stats,
                 ros_session: zenoh.Session | None = None) -> None:
        self.opts = opts
        self.ep = ep
        self.stats = stats
        # the server's 100 Hz state key when that is fast enough: this process then wakes
        # for a tenth of the states, and the 1 kHz key has one subscriber less (issue 19:
        # the tick's lateness p99 rose 3.7x with the adapter on the 1 kHz key)
        self.states = ep.declare_state_inbox(
            capacity=64, decimated=opts.rate_hz <= proto.STATE_DECIMATED_HZ)
        self.cmd_pub = ep.declare_command_publisher()
        reply = ep.request("get_config", timeout_s=5.0)
        if not reply.get("ok"):
            raise RuntimeError(f"get_config failed: {reply}")
        self.limits, gravity, self.vehicle_marker = _vehicle_from_config(reply["config"])
        self.controller = SpeedController(self.limits)
        self.converter = StateConverter(opts.odom_frame, opts.base_frame, gravity)
        self.node = RosNode(ros_session or ep.session, opts.domain_id, opts.namespace,
                            opts.node_name)
        self.pubs: dict[str, RosPublisher] = {}
        self.subs: dict[str, RosSubscription] = {}
        for t in wire.TOPICS:
            if t.sim_time_only and opts.stamp != "sim":
                continue
            fq = wire.fully_qualified_name(opts.namespace, opts.topics.get(t.option, t.name))
            if t.direction == wire.PUBLISH:
                self.pubs[t.option] = self.node.publisher(fq, t.ros_type, t.qos)
            else:
                self.subs[t.option] = self.node.subscription(fq, t.ros_type, t.qos)
        self.rec: Any = None  # the newest decoded state
        self.target = DriveTarget()
        self.last_ros_command: float | None = None  # monotonic time of the newest
        self.last_control_time_s: float | None = None  # sim time of the last command sent
        self.rejected_targets = 0
        self.nonfinite_log = RateLimitedLog(REJECT_LOG_INTERVAL_S, log)
        self.seq = 0
        self.last_config_poll = time.monotonic()

    def describe(self) -> str:
        """One line for the log: the node and its topics' keys."""
        out = ", ".join(p.topic for p in self.pubs.values())
        into = ", ".join(s.topic for s in self.subs.values())
        name = f"{self.opts.namespace.rstrip('/')}/{self.opts.node_name}"
        return (f"node {name} on domain {self.opts.domain_id} for {self.ep.keys.base} "
                f"({out} out; {into} in)")

    def period(self, now: float) -> None:
        """One period: follow the vehicle, take input, drive, publish."""
        self.follow_vehicle(now)
        self.take_state()
        self.take_ros_commands(now)
        self.drive(now)
        self.publish()

    def follow_vehicle(self, now: float) -> None:
        """Re-read the server's vehicle now and then (a ``load`` may change it)."""
        if now - self.last_config_poll < CONFIG_POLL_S:
            return
        self.last_config_poll = now
        try:
            reply = self.ep.request("get_config", timeout_s=1.0)
        except TimeoutError:
            return
        if reply.get("ok"):
            limits, gravity, marker = _vehicle_from_config(reply["config"])
            if marker != self.vehicle_marker:
                self.limits, self.vehicle_marker = limits, marker
                self.controller = SpeedController(limits)
                self.converter.gravity_mps2 = gravity

    def take_state(self) -> None:
        """Keep the newest valid state of those that arrived."""
        for payload in reversed(self.states.drain_newest()):
            try:
                self.rec = proto.decode_state(payload)
            except proto.ProtocolError:
                continue
            self.stats.states_received += 1
            return

    def take_ros_commands(self, now: float) -> None:
        """The newest valid command of each topic since the last period (of both, cmd_vel's
        is in force); older ones are not decoded (:class:`RosSubscription`)."""
        ackermann, refused = self.subs["ackermann_cmd"].newest(_target_from_ackermann)
        twist, refused_twist = self.subs["cmd_vel"].newest(
            lambda m: _target_from_twist(m, self.limits))
        refused += refused_twist
        if refused:  # NaN or infinity: no command at all
            self.rejected_targets += refused
            self.nonfinite_log.warn(f"{refused} ROS command(s) with a non-finite value "
                                    "ignored")
        for target in (ackermann, twist):
            if target is not None:
                self.target = target
                self.last_ros_command = now
                self.stats.ros_commands += 1
        self.stats.ros_commands_rejected = self.rejected_targets + sum(
            s.rejected for s in self.subs.values())
        self.stats.ros_commands_superseded = sum(s.superseded for s in self.subs.values())

    def drive(self, now: float) -> None:
        """One DriverCommand while ROS commands are fresh; silence (the watchdog) otherwise."""
        fresh = self.last_ros_command is not None \
            and now - self.last_ros_command <= self.opts.command_timeout_s
        if not fresh or self.rec is None:
            if self.last_control_time_s is not None:
                self.controller.reset()
                self.last_control_time_s = None
            return
        time_s = float(self.rec["sim_time_s"])
        last = self.last_control_time_s
        if last is not None and time_s < last:
            self.controller.reset()  # the server was reset or loaded
        dt = 0.0 if last is None or time_s < last else time_s - last
        self.last_control_time_s = time_s
        pedals = self.controller.update(self.target, float(self.rec["u_mps"]),
                                        float(self.rec["pitch_rad"]), dt)
        self.seq = (self.seq + 1) & 0xFFFFFFFF
        self.cmd_pub.put(proto.encode_command(pedals.steer, pedals.throttle, pedals.brake,
                                              gear=pedals.gear, seq=self.seq))
        self.stats.commands_sent += 1

    def publish(self) -> None:
        """Odometry, Imu, TF and JointState of the newest state."""
        if self.rec is None:
            return
        stamp_ns = time.time_ns() if self.opts.stamp == "wall" \
            else int(round(float(self.rec["sim_time_s"]) * 1e9))
        for option, (_, message) in self.converter.messages(self.rec, stamp_ns).items():
            self.pubs[option].put(message)
            self.stats.messages_published += 1
        if "clock" in self.pubs:
            self.pubs["clock"].put(self.converter.clock(stamp_ns))
            self.stats.messages_published += 1

    def close(self) -> None:
        """Withdraw the node from the ROS graph (tokens first, with their entities)."""
        self.node.close()


def open_ros_session(router: str) -> zenoh.Session:
    """A zenoh client session of the rmw_zenohd router at ``router``.

    Client, not peer: a router routes everything of its clients, whereas between two
    peers it expects a direct link, and rmw_zenoh's nodes listen on loopback only
    (``tcp/localhost:0``), which no other machine can reach. Zenoh's other defaults are
    kept (those of rmw_zenoh's own sessions), multicast scouting excepted.
    """
    from simserver.adapters.zenoh_io import ZenohOpenError

    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", json.dumps([router]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    try:
        return zenoh.open(cfg)
    except zenoh.ZError as exc:
        raise ZenohOpenError(f"cannot join the ROS router at {router}: {exc}") from None


def idle_python_thread() -> str:
    """Put this (the Python) thread, and threads it starts, at idle CPU priority; what was
    applied, for the log.

    Only this thread: zenoh's threads, started when the sessions opened, keep normal
    priority, so they drain the server's 1 kHz state stream into the ring as it comes
    (a few microseconds a sample), while the decoding, control and CDR work of this thread
    (``SCHED_IDLE``) only uses time the server does not want. A starved zenoh reader would
    let the link's socket fill, and the server's state publisher (congestion control
    BLOCK, written from its loop thread) would wait: on a loaded machine that made the
    server's ticks tens of milliseconds late. Elsewhere this thread's lowest ``nice``.
    """
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
        return "SCHED_IDLE (zenoh's threads normal)"
    except (AttributeError, OSError):
        pass
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
        return "nice 19 (zenoh's threads normal)"
    except (AttributeError, OSError) as exc:
        return f"normal (could not lower: {exc})"


def run_ros2(options: Ros2Options) -> Ros2Stats:
    """Run the adapter until SIGINT/SIGTERM (or ``duration_s``); returns its statistics.

    Raises
    ------
    simserver.ros2.wire.Ros2WireError
        For a bad option (nothing is opened).
    TimeoutError
        When the server does not answer ``get_config``.
    """
    from simserver.adapters.zenoh_io import ZenohEndpoint, make_zenoh_config

    opts = options.check()
    stats = Ros2Stats()
    running = [True]

    def stop(*_: Any) -> None:
        running[0] = False

    previous = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
    cfg = make_zenoh_config(listen=[], connect=opts.connect, config_file=opts.zenoh_config)
    ros_session = None
    try:
        with ZenohEndpoint(cfg, prefix=opts.prefix, vehicle=opts.vehicle_id) as ep:
            if opts.ros_router is not None:
                ros_session = open_ros_session(opts.ros_router)
            adapter = Ros2Adapter(opts, ep, stats, ros_session)
            if opts.idle_priority:  # after the sessions: zenoh's threads keep theirs
                stats.cpu_priority = idle_python_thread()
            try:
                print(f"simserver ros2: {adapter.describe()}", flush=True)
                period = 1.0 / opts.rate_hz
                t_start = next_t = time.monotonic()
                while running[0]:
                    now = time.monotonic()
                    if opts.duration_s is not None and now - t_start > opts.duration_s:
                        break
                    adapter.period(now)
                    stats.periods += 1
                    next_t += period  # absolute deadlines
                    delay = next_t - time.monotonic()
                    if delay > 0.0:
                        time.sleep(delay)
                    else:  # late: skip the missed deadlines instead of bursting
                        missed = math.floor(-delay / period)
                        stats.periods_missed += missed
                        next_t += period * missed
            finally:
                adapter.close()
    finally:
        if ros_session is not None:
            ros_session.close()
        for s, h in previous.items():
            signal.signal(s, h)
    return stats
