"""``simserver ros2``: the arguments and the entry of the ROS 2 adapter process.

Kept apart from ``simserver.cli`` (which only registers it) and light to import: rosbags
and the adapter load when the command runs.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

HELP = "the car on ROS 2 topics through rmw_zenoh (a separate process)"
DESCRIPTION = ("Be a ROS 2 node as rmw_zenoh (ROS 2 Jazzy) makes one: publish the car's "
               "odometry, IMU, TF and joint states from the server's state topic, and drive "
               "it from ackermann_msgs/AckermannDriveStamped or geometry_msgs/Twist commands "
               "through a speed controller. No ROS installation needed; see docs/ros2.md.")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags of ``simserver ros2``."""
    parser.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                        help="zenoh endpoint to connect to, repeatable: the server's "
                             "(default tcp/127.0.0.1:7447) and, for ROS nodes on other "
                             "processes or machines, the rmw_zenohd router's")
    parser.add_argument("--zenoh-config", type=Path, default=None, metavar="FILE",
                        help="a zenoh JSON5 config instead of --connect")
    parser.add_argument("--vehicle-id", default="car0")
    parser.add_argument("--prefix", default="simserver")
    parser.add_argument("--domain-id", type=int,
                        default=int(os.environ.get("ROS_DOMAIN_ID", "0") or 0),
                        help="ROS_DOMAIN_ID (default: the environment's, else 0)")
    parser.add_argument("--namespace", default="/", help="the node's ROS namespace (default /)")
    parser.add_argument("--node-name", default=None,
                        help="the node's name (default simserver_<vehicle id>)")
    parser.add_argument("--rate", type=float, default=100.0, metavar="HZ",
                        help="publish and control rate (default 100 Hz)")
    parser.add_argument("--command-timeout", type=float, default=0.5, metavar="S",
                        help="with no ROS command for S seconds the adapter stops sending, "
                             "and the server's watchdog holds the car (default 0.5)")
    parser.add_argument("--topic", action="append", default=[], metavar="NAME=ROSNAME",
                        help="rename a topic: odom, imu, tf, joint_states, ackermann_cmd, "
                             "cmd_vel (e.g. --topic ackermann_cmd=/drive)")
    parser.add_argument("--odom-frame", default="odom")
    parser.add_argument("--base-frame", default="base_link")
    parser.add_argument("--stamp", choices=("wall", "sim"), default="wall",
                        help="header stamps: wall clock (default) or simulated time")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="stop after S wall seconds (default: until Ctrl-C)")
    parser.add_argument("--normal-priority", action="store_true",
                        help="keep normal CPU priority (default: idle priority, so the "
                             "adapter only uses CPU time a server on the same machine does "
                             "not want)")


def run(args: argparse.Namespace) -> int:
    """Run the adapter; errors in the flags exit 2, no server exits 3."""
    from simserver.cli import CliError
    from simserver.ros2.adapter import Ros2Options, run_ros2
    from simserver.ros2.wire import Ros2WireError

    topics = {}
    for item in args.topic:
        option, sep, name = item.partition("=")
        if not sep or not name:
            raise CliError(f"--topic: {item!r} is not NAME=ROSNAME", exit_code=2)
        topics[option] = name
    connect = args.connect or ([] if args.zenoh_config else ["tcp/127.0.0.1:7447"])
    options = Ros2Options(
        connect=connect, zenoh_config=args.zenoh_config, prefix=args.prefix,
        vehicle_id=args.vehicle_id, domain_id=args.domain_id, namespace=args.namespace,
        node_name=args.node_name, rate_hz=args.rate, command_timeout_s=args.command_timeout,
        topics=topics, odom_frame=args.odom_frame, base_frame=args.base_frame,
        stamp=args.stamp, duration_s=args.duration, idle_priority=not args.normal_priority)
    try:
        stats = run_ros2(options)
    except Ros2WireError as exc:
        raise CliError(str(exc), exit_code=2) from exc
    except TimeoutError as exc:
        raise CliError(f"no server answered: {exc}", exit_code=3) from exc
    print(f"ros2: {stats.states_received} states, {stats.messages_published} messages out, "
          f"{stats.ros_commands} ROS commands in ({stats.ros_commands_rejected} rejected), "
          f"{stats.commands_sent} commands sent; CPU priority {stats.cpu_priority}", flush=True)
    return 0
