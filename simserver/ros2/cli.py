"""``simserver ros2``: the arguments and the entry of the ROS 2 adapter process.

Kept apart from ``simserver.cli`` (which only registers it) and light to import: rosbags
and the adapter load when the command runs.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any

HELP = "the car on ROS 2 topics through rmw_zenoh (a separate process)"
DESCRIPTION = ("Be a ROS 2 node as rmw_zenoh (ROS 2 Jazzy) makes one: publish the car's "
               "odometry, IMU, TF and joint states from the server's state topic, and drive "
               "it from ackermann_msgs/AckermannDriveStamped or geometry_msgs/Twist commands "
               "through a speed controller. No ROS installation needed; see docs/ros2.md.")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags of ``simserver ros2``."""
    parser.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                        help="the server's zenoh endpoint (default tcp/127.0.0.1:7447)")
    parser.add_argument("--ros-router", default=None, metavar="ENDPOINT",
                        help="the rmw_zenohd router the ROS nodes use (e.g. "
                             "tcp/127.0.0.1:7447 on a ROS machine): the adapter's ROS node "
                             "joins it as a zenoh client. Without it the node lives on the "
                             "server's zenoh network")
    parser.add_argument("--zenoh-config", type=Path, default=None, metavar="FILE",
                        help="a zenoh JSON5 config instead of --connect")
    parser.add_argument("--vehicle-id", default="car0")
    parser.add_argument("--cars", default=None, metavar="all|ID,ID",
                        help="several cars of one server, each a node of its own under "
                             "NAMESPACE/ID (/ID/odom, ID/base_link in /tf): 'all' (every "
                             "car of the server's world, followed as cars are added and "
                             "removed) or a list of ids; 'serve' passes 'all' for a "
                             "server of several cars")
    parser.add_argument("--prefix", default="simserver")
    parser.add_argument("--domain-id", type=int, default=None,
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
                        help="rename a topic: odom, imu, tf, joint_states, clock, "
                             "ackermann_cmd, cmd_vel (e.g. --topic ackermann_cmd=/drive)")
    parser.add_argument("--odom-frame", default="odom")
    parser.add_argument("--base-frame", default="base_link")
    parser.add_argument("--stamp", choices=("wall", "sim"), default="wall",
                        help="header stamps: wall clock (default) or simulated time")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="stop after S wall seconds (default: until Ctrl-C)")
    priority = parser.add_mutually_exclusive_group()
    priority.add_argument("--normal-priority", dest="idle_priority", action="store_false",
                          default=False,
                          help="normal CPU priority (the default): a flood of ROS messages on "
                               "the adapter's own receive threads cannot starve its "
                               "publishing, and the server's tick, at real-time priority, "
                               "is above it anyway")
    priority.add_argument("--idle-priority", dest="idle_priority", action="store_true",
                          help="run the adapter's work at idle CPU priority (SCHED_IDLE): it "
                               "uses only CPU time nothing else wants, and on a busy machine "
                               "(or under a flood of ROS messages) it may not run at all")


def run(args: argparse.Namespace) -> int:
    """Run the adapter; errors in the flags exit 2, no server exits 3."""
    from simserver.errors import CliError
    from simserver.ros2.adapter import Ros2Options, run_ros2
    from simserver.ros2.wire import Ros2WireError

    topics = {}
    for item in args.topic:
        option, sep, name = item.partition("=")
        if not sep or not name:
            raise CliError(f"--topic: {item!r} is not NAME=ROSNAME", exit_code=2)
        topics[option] = name
    domain_id = args.domain_id
    if domain_id is None:
        env = os.environ.get("ROS_DOMAIN_ID", "").strip()
        try:
            domain_id = int(env) if env else 0
        except ValueError:
            raise CliError(f"ROS_DOMAIN_ID: {env!r} is not an integer", exit_code=2) from None
    connect = args.connect or ([] if args.zenoh_config else ["tcp/127.0.0.1:7447"])
    options = Ros2Options(
        connect=connect, zenoh_config=args.zenoh_config, ros_router=args.ros_router,
        prefix=args.prefix,
        vehicle_id=args.vehicle_id, domain_id=domain_id, namespace=args.namespace,
        node_name=args.node_name, rate_hz=args.rate, command_timeout_s=args.command_timeout,
        topics=topics, odom_frame=args.odom_frame, base_frame=args.base_frame,
        stamp=args.stamp, duration_s=args.duration, idle_priority=args.idle_priority,
        cars=args.cars)
    try:
        stats = run_ros2(options)
    except Ros2WireError as exc:
        raise CliError(str(exc), exit_code=2) from exc
    except TimeoutError as exc:
        raise CliError(f"no server answered: {exc}", exit_code=3) from exc
    print(f"ros2: {stats.states_received} states, {stats.messages_published} messages out, "
          f"{stats.ros_commands} ROS commands in ({stats.ros_commands_rejected} rejected, "
          f"{stats.ros_commands_superseded} superseded unread), {stats.commands_sent} "
          f"commands sent; {stats.periods} periods ({stats.periods_missed} deadlines missed); "
          f"CPU priority {stats.cpu_priority}", flush=True)
    return 0


SERVE_SETTINGS: dict[str, tuple[str, type]] = {
    "router": ("--ros-router", str),
    "domain_id": ("--domain-id", int),
    "namespace": ("--namespace", str),
    "node_name": ("--node-name", str),
    "rate_hz": ("--rate", float),
    "command_timeout_s": ("--command-timeout", float),
    "stamp": ("--stamp", str),
}
"""The keys of a server config's ``ros2:`` section and the ``simserver ros2`` flag of each
(plus ``topics: {option: name}`` and ``normal_priority: bool``)."""


def adapter_command(endpoint: str, prefix: str, vehicle_id: str,
                    settings: dict | None = None, source: str = "ros2",
                    several_cars: bool = False) -> list[str]:
    """The command line with which ``serve`` starts the adapter beside itself.

    Parameters
    ----------
    endpoint : str
        The server's own zenoh endpoint (as for the viewer: a loopback form of its first
        listen endpoint).
    prefix, vehicle_id : str
        The server's keys.
    settings : dict, optional
        The server config's ``ros2:`` section (keys of :data:`SERVE_SETTINGS`, ``topics``
        and ``normal_priority``); values are checked again by the adapter itself.
    source : str
        Where ``settings`` came from, for the error message (``"server.yaml: ros2"``).
    several_cars : bool
        The server serves several cars (``cars:`` with more than one): ``--cars all``,
        each car under its own namespace (docs/ros2.md, "Several cars"). A server of one
        car keeps the single car's names.

    Raises
    ------
    ValueError
        Naming ``source`` and the key, for an unknown key or a value of the wrong type.
    """
    import sys

    args = [sys.executable, "-m", "simserver", "ros2", "--connect", endpoint,
            "--prefix", prefix, "--vehicle-id", vehicle_id]
    if several_cars:
        args += ["--cars", "all"]
    for key, value in (settings or {}).items():
        if key == "topics":
            if not isinstance(value, dict):
                raise ValueError(f"{source}.topics: expected a mapping option: ROS name")
            for option, name in value.items():
                if not isinstance(name, str):
                    raise ValueError(f"{source}.topics.{option}: expected a ROS name, "
                                     f"got {name!r}")
                args += ["--topic", f"{option}={name}"]
        elif key == "normal_priority":
            if not isinstance(value, bool):
                raise ValueError(f"{source}.normal_priority: expected true or false")
            args.append("--normal-priority" if value else "--idle-priority")
        elif key in SERVE_SETTINGS:
            flag, kind = SERVE_SETTINGS[key]
            if isinstance(value, bool) or not isinstance(value, (kind, int) if kind is float
                                                          else kind):
                raise ValueError(f"{source}.{key}: expected a {kind.__name__}, got {value!r}")
            args += [flag, str(value)]
        else:
            raise ValueError(f"{source}: unknown key {key!r} (known: "
                             f"{', '.join([*SERVE_SETTINGS, 'topics', 'normal_priority'])})")
    return args


OPTION_OF_SETTING = {"router": "ros_router"}
"""Settings whose :class:`simserver.ros2.adapter.Ros2Options` field has another name."""


def serve_settings(value: Any, flag: bool | None = None,
                   source: str = "ros2") -> dict[str, Any] | None:
    """The adapter settings of a server config's ``ros2:`` value; None when it is off.

    Parameters
    ----------
    value : None, bool or dict
        The config's value: ``off``/``false``/absent (no adapter), ``on``/``true`` (the
        adapter with its defaults) or a mapping of settings (keys of
        :data:`SERVE_SETTINGS`, ``topics`` and ``normal_priority``).
    flag : bool, optional
        ``serve --ros2`` (True: start it, with the config's settings if it has any) or
        ``--no-ros2`` (False); None lets the config decide.
    source : str
        Where ``value`` came from, for the error message (``"server.yaml: ros2"``).

    Raises
    ------
    ValueError
        Naming ``source`` and the key: an unknown key, a value of the wrong type, or one
        the adapter would refuse (a domain id out of range, a bad namespace, ...).
    """
    from simserver.ros2.adapter import Ros2Options
    from simserver.ros2.wire import Ros2WireError

    if value is None or value is False:
        settings = None
    elif value is True:
        settings = {}
    elif isinstance(value, dict):
        settings = dict(value)
    else:
        raise ValueError(f"{source}: expected off, on or a mapping of the adapter's settings "
                         f"({', '.join([*SERVE_SETTINGS, 'topics', 'normal_priority'])}), "
                         f"got {value!r}")
    if flag is not None:
        settings = (settings if settings is not None else {}) if flag else None
    if settings is None:
        return None
    adapter_command("tcp/127.0.0.1:7447", "simserver", "car0", settings, source)  # keys, types
    options = {OPTION_OF_SETTING.get(k, k): v for k, v in settings.items()
               if k != "normal_priority"}
    try:
        Ros2Options(**options).check()
    except Ros2WireError as exc:
        raise ValueError(f"{source}: {exc}") from None
    return settings
