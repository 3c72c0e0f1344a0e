"""The ROS 2 adapter under floods (issue 34, item 5), with real processes on loopback.

``simserver serve`` starts the adapter as it does for a user (its ROS node a client of a
zenoh router standing in for ``rmw_zenohd``); this test's ROS node counts the odometry;
a flooder process of its own publishes one command topic as fast as it can, with payloads
built by rosbags (``benchmarks/ros2_flood.py``): valid ``AckermannDriveStamped`` commands,
then ``cmd_vel`` payloads that do not decode as a ``Twist``. Each flood window lies
between two windows without a flood of the same run, and is compared with them.

Before the fix (checkout 362909f, this machine shared with seven other engineers'
builds): odometry 4 % (Ackermann) and 44 % (malformed) of the rate without a flood, 1 639
output lines in the 4 s of the malformed flood; ``python -m benchmarks.bench_ros2 --floods``
prints the figures.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import pytest

from benchmarks.ros2_flood import FloodRun, bracketing_baselines, format_run, measure_floods
from simserver.ros2.adapter import REJECT_LOG_INTERVAL_S

WINDOW_S = 3.0
MIN_ODOMETRY_SHARE = 0.90
"""Issue 34's acceptance: the odometry under a flood at least 90 % of its rate without."""
VM_STALL_SHARE = 0.007
"""This VM makes about half a per cent of a bare 1 kHz pacer's ticks late by itself (the
ROS 2 rows' clock floor in docs/performance.md: 0.53 % more than 1 ms late): the late
ticks a flood window may have beyond the windows around it without one."""


@pytest.fixture(scope="module")
def run() -> Iterator[FloodRun]:
    result = measure_floods(WINDOW_S, domain=44)
    print("\n" + format_run(result))
    yield result


@pytest.mark.parametrize("kind", ["ackermann", "malformed"])
def test_a_flood_holds_the_odometry_rate(run: FloodRun, kind: str) -> None:
    flood = run.by_label(kind)
    before, after = bracketing_baselines(run, kind)
    assert flood.sent > 10_000 * WINDOW_S, "the flooder did not flood"
    reference = 0.5 * (before.odometry_per_s + after.odometry_per_s)
    assert flood.odometry_per_s >= MIN_ODOMETRY_SHARE * reference, format_run(run)


def test_a_valid_flood_still_drives(run: FloodRun) -> None:
    """The Ackermann flood reached the adapter: it drove the car (one command a period)."""
    flood = run.by_label("ackermann")
    assert flood.commands >= 0.5 * 100 * WINDOW_S, format_run(run)


@pytest.mark.parametrize("kind", ["ackermann", "malformed"])
def test_a_flood_does_not_make_the_servers_ticks_late(run: FloodRun, kind: str) -> None:
    flood = run.by_label(kind)
    before, after = bracketing_baselines(run, kind)
    allowed = max(before.late_ticks, after.late_ticks) + math.ceil(VM_STALL_SHARE * flood.ticks)
    assert flood.late_ticks <= allowed, format_run(run)


def test_a_malformed_flood_is_logged_at_a_bounded_rate_with_counts(run: FloodRun) -> None:
    flood = run.by_label("malformed")
    decode = [line for line in flood.lines if "cannot decode a geometry_msgs/msg/Twist" in line]
    assert decode, "the malformed flood never reached the adapter"
    # one line a second at most, plus the server's own (a watchdog transition or two)
    assert flood.log_lines <= math.ceil(flood.seconds / REJECT_LOG_INTERVAL_S) + 3, \
        "".join(flood.lines[:20])
    counted = [line for line in decode if "more since the last report" in line]
    assert counted, "no line gave the count of the bad messages in between"
    suppressed = max(int(line.rsplit("(", 1)[1].split()[0]) for line in counted)
    assert suppressed >= 100, counted
