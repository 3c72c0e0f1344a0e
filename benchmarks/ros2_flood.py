"""Floods on the ROS 2 adapter (issue 34): the flooder process and the measurement.

The flooder is a process of its own (``python benchmarks/ros2_flood.py --connect ...``),
a ROS node as rmw_zenoh makes one, publishing one command topic for ``--seconds`` as fast
as it can or at ``--rate``: ``ackermann`` sends valid ``AckermannDriveStamped`` commands,
``malformed`` sends ``cmd_vel`` payloads that do not decode as a ``Twist`` (a CDR header
and 7 bytes).
Payloads, key expressions and attachments are built here with rosbags and the design
document of rmw_zenoh, not with ``simserver.ros2``.

:func:`measure_floods` runs ``simserver serve`` with the adapter (as ``serve`` starts it
for a user, its ROS node a client of a router standing in for ``rmw_zenohd``), counts the
odometry a ROS node receives (this process; the flooder is another) and the server's late
ticks in a window without a flood, then in a window of each flood, then again without;
:mod:`benchmarks.bench_ros2` (``--floods``) prints them and ``tests/test_ros2_floods.py``
checks them.
"""

from __future__ import annotations

import argparse
import statistics
import struct
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

ACKERMANN = "ackermann_msgs/msg/AckermannDriveStamped"
TWIST = "geometry_msgs/msg/Twist"
ODOMETRY = "nav_msgs/msg/Odometry"
MALFORMED = b"\x00\x01\x00\x00" + b"\x05" * 7
"""A CDR little-endian header and 7 bytes: no Twist (48 bytes of float64) decodes from it."""

KINDS = {"ackermann": ("ackermann_cmd", ACKERMANN), "malformed": ("cmd_vel", TWIST)}


def typestore() -> Any:
    """rosbags' Jazzy store plus ackermann_msgs (which it lacks)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    types.update(get_types_from_msg(
        "float32 steering_angle\nfloat32 steering_angle_velocity\nfloat32 speed\n"
        "float32 acceleration\nfloat32 jerk\n", "ackermann_msgs/msg/AckermannDrive"))
    types.update(get_types_from_msg("std_msgs/Header header\nAckermannDrive drive\n",
                                    ACKERMANN))
    store.register(types)
    return store


def topic_key(store: Any, domain: int, topic: str, ros_type: str) -> str:
    """``<domain>/<topic>/<DDS type name>/<RIHS01 hash>`` (rmw_zenoh's design document)."""
    pkg, _, name = ros_type.split("/")
    return f"{domain}/{topic}/{pkg}::msg::dds_::{name}_/{store.hash_rihs01(ros_type)}"


def ackermann_payload(store: Any, speed_mps: float) -> bytes:
    t = store.types
    msg = t[ACKERMANN](
        header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0),
                                        frame_id="base_link"),
        drive=t["ackermann_msgs/msg/AckermannDrive"](
            steering_angle=0.0, steering_angle_velocity=0.0, speed=speed_mps,
            acceleration=0.0, jerk=0.0))
    return bytes(store.serialize_cdr(msg, ACKERMANN))


def flood(connect: str, domain: int, kind: str, seconds: float, rate_hz: float = 0.0) -> int:
    """Publish ``kind`` for ``seconds`` at ``rate_hz`` (in bursts every 5 ms), or as fast
    as this process can (0); how many were sent."""
    store = typestore()
    topic, ros_type = KINDS[kind]
    payload = ackermann_payload(store, 1.0) if kind == "ackermann" else MALFORMED
    from simserver.adapters.zenoh_io import make_zenoh_config

    with zenoh.open(make_zenoh_config(listen=[], connect=[connect], mode="peer")) as session:
        pub = session.declare_publisher(topic_key(store, domain, topic, ros_type))
        gid = bytes(range(16))
        print("flood: start", flush=True)
        burst_s = 0.005
        sent, start = 0, time.monotonic()
        end = start + seconds
        while (now := time.monotonic()) < end:
            due = int((now - start + burst_s) * rate_hz) if rate_hz > 0 else sent + 100
            while sent < due:
                sent += 1
                pub.put(payload, attachment=struct.pack("<qqB16s", sent, time.time_ns(), 16,
                                                        gid))
            if rate_hz > 0:
                time.sleep(max(0.0, start + sent / rate_hz - burst_s - time.monotonic()))
        pub.undeclare()
    return sent


@dataclass
class Window:
    """One measured window."""

    label: str
    seconds: float
    odometry: int  # Odometry messages the ROS node received
    late_ticks: int  # the server's ticks more than 1 ms late (its diagnostics)
    log_lines: int  # lines the server and the adapter printed
    commands: int  # DriverCommands the server received (the adapter's)
    ticks: int  # the server's ticks in the window
    sent: int = 0  # flood messages sent
    lines: list[str] = field(default_factory=list)  # what was printed

    @property
    def odometry_per_s(self) -> float:
        return self.odometry / self.seconds


@dataclass
class FloodRun:
    """The windows of one run and the server's output."""

    windows: list[Window] = field(default_factory=list)
    output: str = ""

    def by_label(self, label: str) -> Window:
        return next(w for w in self.windows if w.label == label)


@contextmanager
def adapter_under_test(domain: int, settings: str = "",
                       ready_timeout_s: float = 600.0) -> Iterator[tuple[Any, str, Any]]:
    """``simserver serve`` with its adapter, a router standing in for rmw_zenohd, and a
    subscription of this process's ROS node to the odometry; yields (server, router
    endpoint, odometry subscriber) once odometry arrives."""
    from simserver.adapters.zenoh_io import make_zenoh_config
    from simserver.testing import CONFIGS, ServerProcess, loopback_endpoint, wait_until

    store = typestore()
    router_ep = loopback_endpoint()
    with zenoh.open(make_zenoh_config(listen=[router_ep], mode="router")) as router, \
            zenoh.open(make_zenoh_config(listen=[], connect=[router_ep], mode="peer")) as node, \
            tempfile.TemporaryDirectory(prefix="simserver_ros2_flood_") as tmp:
        del router  # routes only
        sub = node.declare_subscriber(topic_key(store, domain, "odom", ODOMETRY),
                                      zenoh.handlers.FifoChannel(1 << 16))
        config = Path(tmp) / "server.yaml"
        config.write_text(f"scene: {CONFIGS / 'scenes' / 'flat_paper_sedan.yaml'}\n"
                          f"ros2: {{router: '{router_ep}', domain_id: {domain}{settings}}}\n",
                          encoding="utf-8")
        with ServerProcess(scene=None, config=config, ready_timeout_s=ready_timeout_s) as server:
            server.wait_for_line("simserver ros2: node", timeout_s=ready_timeout_s)
            wait_until(lambda: count(sub), timeout_s=60, what="odometry from the adapter")
            yield server, router_ep, sub
        sub.undeclare()


def count(sub: Any) -> int:
    """Samples waiting in ``sub`` (taken)."""
    n = 0
    while sub.try_recv() is not None:
        n += 1
    return n


def measure_window(server: Any, client: Any, sub: Any, label: str, seconds: float,
                   flooder: Any = None) -> Window:
    """Count odometry, late ticks and output lines for ``seconds`` (while ``flooder``, a
    started :class:`simserver.testing.OutputProcess`, floods)."""
    d0 = client.diagnostics()
    lines0 = len(server.output)
    count(sub)
    t0 = time.monotonic()
    received = 0
    while time.monotonic() - t0 < seconds:
        time.sleep(0.05)
        received += count(sub)
    received += count(sub)
    elapsed = time.monotonic() - t0
    d1 = client.diagnostics()
    sent = 0
    if flooder is not None:
        flooder.wait(60)
        line = flooder.wait_for_line("flood: sent", timeout_s=10)
        sent = int(line.split()[2])
    lines = server.output[lines0:]
    return Window(label, elapsed, received, int(d1["late_ticks"]) - int(d0["late_ticks"]),
                  len(lines), int(d1["cmd_received"]) - int(d0["cmd_received"]),
                  int(d1["tick"]) - int(d0["tick"]), sent, lines)


def flooder_process(router_ep: str, domain: int, kind: str, seconds: float,
                    rate_hz: float = 0.0) -> Any:
    """The flooder, started, once its session is open (its ready line)."""
    from simserver.testing import OutputProcess

    proc = OutputProcess([sys.executable, __file__, "--connect",
                          router_ep, "--domain", str(domain), "--kind", kind, "--seconds",
                          str(seconds), "--rate", str(rate_hz)], ready="flood: start")
    if not proc.wait_ready(60):
        proc.kill()
        raise RuntimeError("the flooder did not start:\n" + proc.text())
    return proc


def measure_floods(seconds: float = 4.0, domain: int = 43, settings: str = "",
                   kinds: tuple[str, ...] = ("ackermann", "malformed"),
                   rate_hz: float = 0.0, repeats: int = 1) -> FloodRun:
    """A window without a flood, then for each flood ``repeats`` times the flood and a
    window without: the windows of one server and adapter, labelled ``baseline 0``,
    ``ackermann 1``, ``baseline 1``, ``ackermann 2``, ``baseline 2``, ... ``malformed 1``
    ... (each flood between two windows without one); ``rate_hz`` as :func:`flood`'s."""
    from simserver.testing import Client

    run = FloodRun()
    with adapter_under_test(domain, settings) as (server, router_ep, sub), \
            Client(server) as client:
        run.windows.append(measure_window(server, client, sub, "baseline 0", seconds))
        n = 0
        for kind in kinds:
            for i in range(1, repeats + 1):
                flooder = flooder_process(router_ep, domain, kind, seconds, rate_hz)
                run.windows.append(measure_window(server, client, sub, f"{kind} {i}",
                                                  seconds, flooder))
                n += 1
                run.windows.append(measure_window(server, client, sub, f"baseline {n}",
                                                  seconds))
        run.output = server.text()
    return run


def floods_of(run: FloodRun, kind: str) -> list[Window]:
    """The windows of flood ``kind``."""
    return [w for w in run.windows if w.label.rsplit(" ", 1)[0] == kind]


def bracketing_baselines(run: FloodRun, label: str) -> tuple[Window, Window]:
    """The windows without a flood just before and just after the flood ``label``."""
    i = next(i for i, w in enumerate(run.windows) if w.label == label)
    return run.windows[i - 1], run.windows[i + 1]


def odometry_share(run: FloodRun, label: str) -> float:
    """The odometry rate during flood ``label`` over the mean rate of the windows without
    a flood just before and after it."""
    before, after = bracketing_baselines(run, label)
    return run.by_label(label).odometry_per_s / (0.5 * (before.odometry_per_s
                                                         + after.odometry_per_s))


def median_odometry_share(run: FloodRun, kind: str) -> float:
    """The median over the windows of flood ``kind`` of :func:`odometry_share`: a burst of
    other work on the machine during one window does not decide it."""
    return float(statistics.median(odometry_share(run, w.label)
                                   for w in floods_of(run, kind)))


def format_run(run: FloodRun) -> str:
    """One line a window."""
    rows = []
    for w in run.windows:
        share = f" ({100 * odometry_share(run, w.label):5.1f} % of the windows around)" \
            if w.sent else ""
        rows.append(f"{w.label:>10}: odometry {w.odometry_per_s:6.1f}/s{share}, "
                    f"late ticks {w.late_ticks:3d} of {w.ticks}, output lines "
                    f"{w.log_lines:5d}" + (f", flood {w.sent / w.seconds:7.0f} msg/s"
                                           if w.sent else ""))
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connect", required=True)
    parser.add_argument("--domain", type=int, required=True)
    parser.add_argument("--kind", choices=tuple(KINDS), required=True)
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--rate", type=float, default=0.0,
                        help="messages a second (default 0: as fast as it can)")
    args = parser.parse_args(argv)
    sent = flood(args.connect, args.domain, args.kind, args.seconds, args.rate)
    print(f"flood: sent {sent}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
