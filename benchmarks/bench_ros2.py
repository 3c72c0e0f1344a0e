"""Tick timing with the ROS 2 adapter on and off (issue 19: p99 within 10 % of off); with
``--floods``, the adapter under floods of ROS commands (issue 34).

Run from the repository root::

    python -m benchmarks.bench_ros2 [--seconds 12] [--rounds 8] [--floor-seconds 5]
    python -m benchmarks.bench_ros2 --floods [--seconds 4]

``--floods`` (:mod:`benchmarks.ros2_flood`) runs the server and its adapter twice, at the
adapter's default (normal) CPU priority and at idle priority (``normal_priority: false``,
the default before issue 34), and in each a window without a flood, a flood of valid
Ackermann commands from a process of its own, a window without, a flood of malformed
Twists, a window without: the odometry a ROS node receives (as a share of the windows
around each flood), the server's late ticks and the lines printed. At 362909f (before
issue 34's fix: every sample in a ring of 10 decoded, one line logged per bad message,
idle priority) a run of 4 s windows printed odometry 4 % and 44 % of the rate without a
flood and 1 639 lines during the malformed one.

Measured as the viewer's cost is (``benchmarks.bench_viewer``), with the same helper
(``benchmarks.interleaved.compare_modes``): ``benchmarks.bench_server`` runs the server
with its ``ros2:`` setting ``off`` and ``on``, interleaved (off, on, off, on ...) over
``--rounds`` short rounds, and after each round the bare pacer (``bench_clock``, scheduled
as the server's tick thread) measures this VM's own stall floor in the same minutes. The
figure per mode is the median over rounds of its per-round p99, quoted with the per-round
values, the paired per-round ratio and the floor: one "off" round caught in a VM stall
(5 % of ticks late with nothing running) no longer decides the comparison.

The two server configs differ in that key alone. With it on, ``serve`` starts the adapter
as it does for a user (its own process, normal CPU priority, 100 Hz); its ROS node joins a
zenoh router standing in for ``rmw_zenohd``, and a ROS node of this process subscribes to
every topic of the domain, so the adapter's four topics really travel (their message rate
is quoted). The benchmark's own client drives the car; the adapter, with no ROS command,
only publishes. The adapter's rounds are timed once it publishes (it takes seconds to
start, 20 s and more on a busy machine). This process, which hosts the router, stays at
normal priority (``bench_server``'s ``client_realtime="off"``): with its threads
real-time, the adapter never got through to the router here. The tick lateness, which is
what is compared, is the server's own.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import zenoh

from benchmarks.bench_server import run
from benchmarks.interleaved import compare_modes
from simserver.adapters.zenoh_io import make_zenoh_config
from simserver.testing import CONFIGS, loopback_endpoint

DOMAIN = 42
"""The ROS domain of the benchmark's adapter (apart from any other on this machine)."""


def server_config(folder: Path, name: str, ros2: str) -> Path:
    """A server config like the default one, with ``ros2: <ros2>`` (a YAML value)."""
    path = folder / f"{name}.yaml"
    path.write_text(f"scene: {CONFIGS / 'scenes' / 'flat_paper_sedan.yaml'}\n"
                    f"ros2: {ros2}\n", encoding="utf-8")
    return path


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=12.0,
                        help="measured seconds of one mode in one round (default 12)")
    parser.add_argument("--rounds", type=int, default=8)
    parser.add_argument("--floor-seconds", type=float, default=5.0,
                        help="the bare pacer's run after each round (0: none)")
    parser.add_argument("--idle-priority", action="store_true",
                        help="the adapter at idle CPU priority (the default before issue 34; "
                        "on a busy machine its loop may then never run, and it publishes "
                        "nothing)")
    parser.add_argument("--floods", action="store_true",
                        help="instead: the adapter under floods of ROS commands (issue 34)")
    args = parser.parse_args(argv)
    if args.floods:
        return floods(args.seconds if "--seconds" in (argv or sys.argv) else 4.0)
    router_endpoint = loopback_endpoint()
    router = zenoh.open(make_zenoh_config(listen=[router_endpoint], mode="router"))
    ros_node = zenoh.open(make_zenoh_config(listen=["tcp/127.0.0.1:0"],
                                            connect=[router_endpoint], mode="peer"))
    received = [0]

    def count(_sample: zenoh.Sample) -> None:
        received[0] += 1

    sub = ros_node.declare_subscriber(f"{DOMAIN}/**", count)
    rates: list[float] = []
    try:  # a failed round must not leave the callback subscriber holding the exit
        with tempfile.TemporaryDirectory(prefix="simserver_ros2_bench_") as tmp:
            off = server_config(Path(tmp), "off", "off")
            normal = ", normal_priority: false" if args.idle_priority else ""
            on = server_config(Path(tmp), "on", f"{{router: '{router_endpoint}', "
                                                    f"domain_id: {DOMAIN}{normal}}}")

            def with_adapter() -> dict:
                # measured once the adapter publishes: its start (imports, sessions) takes
                # seconds, 20 s and more on a busy machine, and would otherwise be all a short
                # run saw of it
                start = [received[0]]

                def publishing() -> bool:
                    if received[0] - start[0] >= 40:  # every topic a few times
                        start[0] = received[0]
                        return True
                    return False

                result = run(args.seconds, 200.0, config=on, ready=publishing,
                             client_realtime="off")
                rates.append((received[0] - start[0]) / args.seconds)
                return result

            summary = compare_modes({"off": lambda: run(args.seconds, 200.0, config=off,
                                                        client_realtime="off"),
                                     "on": with_adapter}, args.rounds, "ROS 2 adapter",
                                    floor_seconds=args.floor_seconds)
    finally:
        sub.undeclare()
        ros_node.close()
        router.close()
    summary["on"]["ros_messages_per_s"] = float(np.median(rates))
    print(f"ROS messages received from the adapter: {np.median(rates):.0f} per second "
          "of the run (median over rounds; four topics at 100 Hz)")
    if not np.median(rates):
        print("warning: the adapter published nothing, so 'on' measured an idle adapter: "
              "at idle priority on a busy machine its loop does not run (drop --idle-priority)")
    return summary


def floods(seconds: float) -> dict:
    """The adapter under floods at its default and at idle priority; the windows' figures."""
    from benchmarks.ros2_flood import (
        format_run,
        measure_floods,
        median_odometry_share,
        odometry_share,
    )

    out = {}
    for name, settings in (("normal priority (default)", ""),
                           ("idle priority", ", normal_priority: false")):
        run = measure_floods(seconds, settings=settings, repeats=2)
        medians = ", ".join(f"{kind} {100 * median_odometry_share(run, kind):.1f} %"
                            for kind in ("ackermann", "malformed"))
        print(f"ROS 2 adapter under floods, {name}, {seconds:g} s windows:\n"
              f"{format_run(run)}\nodometry under a flood, median share of the windows "
              f"around: {medians}", flush=True)
        out[name] = {w.label: {"odometry_per_s": w.odometry_per_s, "late_ticks": w.late_ticks,
                               "ticks": w.ticks, "output_lines": w.log_lines,
                               "flood_per_s": w.sent / w.seconds,
                               **({"odometry_share": odometry_share(run, w.label)}
                                  if w.sent else {})}
                     for w in run.windows}
    return out


if __name__ == "__main__":
    main()
