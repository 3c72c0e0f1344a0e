"""The ROS 2 adapter under floods (issue 34, item 5), with real processes on loopback.

``simserver serve`` starts the adapter as it does for a user (its ROS node a client of a
zenoh router standing in for ``rmw_zenohd``); this test's ROS node counts the odometry;
a flooder process of its own publishes one command topic at 25 kHz, with payloads built
by rosbags (``benchmarks/ros2_flood.py``): valid ``AckermannDriveStamped`` commands,
then ``cmd_vel`` payloads that do not decode as a ``Twist``. Each flood window lies
between two windows without a flood of the same run, and is compared with them.

Before the fix (this file run against checkout 362909f, this machine shared with seven
other engineers' builds, 1.5 s windows): median odometry 26 % (Ackermann) and 63 %
(malformed) of the windows around, 3 203-3 506 lines printed in each malformed window; 7
of 9 tests failed (the late-tick ones passed: the server's ticks did not go late under
either flood here, before or after). After: 99-100 % and 98-110 %, 1-2 lines a window.
``python -m benchmarks.bench_ros2 --floods`` prints the figures of floods as fast as a
process can, at the adapter's default and at idle priority.
"""

from __future__ import annotations

import logging
import math
import re
import statistics
import sys
from collections.abc import Iterator

import pytest
import zenoh

from benchmarks.ros2_flood import (
    ACKERMANN,
    MALFORMED,
    FloodRun,
    ackermann_payload,
    bracketing_baselines,
    floods_of,
    format_run,
    measure_floods,
    median_odometry_share,
    typestore,
)
from simserver.adapters.zenoh_io import make_zenoh_config
from simserver.ros2.adapter import REJECT_LOG_INTERVAL_S
from simserver.testing import wait_until

WINDOW_S = 1.5
REPEATS = 3
FLOOD_HZ = 25_000.0
"""Above the issue's "about 20 kHz". As fast as a process can (up to 140 kHz here) is the
benchmark's (``bench_ros2 --floods``): in a test on this shared 2-core machine the
flooder's own core then decides the figure as much as the adapter does."""
MIN_ODOMETRY_SHARE = 0.90
"""Issue 34's acceptance: the odometry under a flood at least 90 % of its rate without."""
VM_STALL_SHARE = 0.007
"""This VM makes about half a per cent of a bare 1 kHz pacer's ticks late by itself (the
ROS 2 rows' clock floor in docs/performance.md: 0.53 % more than 1 ms late): the late
ticks a flood window may have beyond the windows around it without one."""


@pytest.fixture(scope="module")
def run() -> Iterator[FloodRun]:
    result = measure_floods(WINDOW_S, domain=44, rate_hz=FLOOD_HZ, repeats=REPEATS)
    print("\n" + format_run(result))
    yield result


@pytest.mark.parametrize("kind", ["ackermann", "malformed"])
def test_a_flood_holds_the_odometry_rate(run: FloodRun, kind: str) -> None:
    """The median over the flood's windows of its odometry rate over that of the windows
    around it (this machine is shared: one window may fall in a burst of other work)."""
    for flood in floods_of(run, kind):
        # it flooded (a starved flooder may fall short of its rate; a ROS publisher sends
        # at 10-100 Hz)
        assert flood.sent >= 5_000 * WINDOW_S, "the flooder did not flood"
    assert median_odometry_share(run, kind) >= MIN_ODOMETRY_SHARE, format_run(run)


def test_a_valid_flood_still_drives(run: FloodRun) -> None:
    """The Ackermann flood reached the adapter: it drove the car (one command a period)."""
    for flood in floods_of(run, "ackermann"):
        assert flood.commands >= 0.5 * 100 * WINDOW_S, format_run(run)


@pytest.mark.parametrize("kind", ["ackermann", "malformed"])
def test_a_flood_does_not_make_the_servers_ticks_late(run: FloodRun, kind: str) -> None:
    """Each flood window's late ticks beyond those of the windows around it and the VM's
    own stalls; the median over the flood's windows decides, as for the odometry rate: a
    burst of other work during one window (CI: 21 late of 1600 in one window, 0 in the
    baselines) does not, while a flood that makes the ticks late does so in every window."""
    excess = []
    for flood in floods_of(run, kind):
        before, after = bracketing_baselines(run, flood.label)
        allowed = max(before.late_ticks, after.late_ticks) + \
            math.ceil(VM_STALL_SHARE * flood.ticks)
        excess.append(flood.late_ticks - allowed)
    assert len(excess) == REPEATS and statistics.median(excess) <= 0, format_run(run)


def test_a_malformed_flood_is_logged_at_a_bounded_rate_with_counts(run: FloodRun) -> None:
    floods = floods_of(run, "malformed")
    lines = [line for flood in floods for line in flood.lines]
    decode = [line for line in lines if "cannot decode a geometry_msgs/msg/Twist" in line]
    assert decode, "the malformed flood never reached the adapter"
    for flood in floods:  # one line a second at most, plus the server's own (a watchdog
        # transition or two)
        assert flood.log_lines <= math.ceil(flood.seconds / REJECT_LOG_INTERVAL_S) + 3, \
            "".join(flood.lines[:20])
    counted = [line for line in decode if "more since the last report" in line]
    assert counted, "no line gave the count of the bad messages in between"
    suppressed = max(int(line.rsplit("(", 1)[1].split()[0]) for line in counted)
    assert suppressed >= 100, counted  # 4 a period decoded, 400 a second


# ---------------------------------------------------------------- the parts, in-process

@pytest.fixture
def session() -> Iterator[zenoh.Session]:
    """A zenoh session of its own (listening nowhere, no scouting): local delivery only."""
    with zenoh.open(make_zenoh_config(listen=[], mode="peer")) as s:
        yield s


def test_each_period_decodes_at_most_the_newest_samples_newest_first(session) -> None:
    """A flood costs a period at most COMMAND_RING_DEPTH decodes, and the newest valid
    command wins (with zenoh's local delivery, a put is in the ring when it returns)."""
    from simserver.ros2 import wire
    from simserver.ros2.adapter import COMMAND_RING_DEPTH, RosNode, _target_from_ackermann

    store = typestore()
    node = RosNode(session, 45, "/", "flood_test")
    sub = node.subscription("/ackermann_cmd", ACKERMANN, wire.QoS(depth=10))
    pub = session.declare_publisher(sub.key)
    try:
        # a flood of bad payloads, then a valid command: the valid one, one decode
        for _ in range(1000):
            pub.put(MALFORMED)
        pub.put(ackermann_payload(store, 5.0))
        target, refused = sub.newest(_target_from_ackermann)
        assert target is not None and target.speed_mps == 5.0 and refused == 0
        assert (sub.rejected, sub.superseded) == (0, COMMAND_RING_DEPTH - 1)
        # a valid command, then the flood: it fell out of the ring; only the ring decoded
        pub.put(ackermann_payload(store, 3.0))
        for _ in range(1000):
            pub.put(MALFORMED)
        assert sub.newest(_target_from_ackermann) == (None, 0)
        assert sub.rejected == COMMAND_RING_DEPTH
        # valid ones at any rate: the newest; NaN is refused and the next older one taken
        for speed in range(1000):
            pub.put(ackermann_payload(store, float(speed)))
        pub.put(ackermann_payload(store, math.nan))
        target, refused = sub.newest(_target_from_ackermann)
        assert target is not None and target.speed_mps == 999.0 and refused == 1
        assert sub.newest(_target_from_ackermann) == (None, 0)  # nothing new: nothing
    finally:
        pub.undeclare()
        node.close()


def test_a_child_that_keeps_dying_is_restarted_with_a_doubling_delay(
        caplog) -> None:
    from simserver.ros2 import supervisor as S

    caplog.set_level(logging.WARNING, logger="simserver.server")
    sup = S.AdapterSupervisor([sys.executable, "-c", "import sys; sys.exit(3)"], "the child")
    sup.start()
    try:
        waiting = wait_until(sup.status, lambda st: st["state"] == "restarting", timeout_s=10,
                             what="the supervisor waiting to restart")
        assert waiting["pid"] is None and waiting["last_exit_code"] == 3
        assert 0.0 <= waiting["restart_in_s"] <= S.MAX_DELAY_S
        wait_until(lambda: sup.restarts, lambda n: n >= 3, timeout_s=20,
                   what="three restarts")
    finally:
        sup.stop(lambda p: (p.terminate(), p.wait()))
    delays = [float(m.group(1)) for r in caplog.records
              if (m := re.search(r"ended with exit code 3 after .* restarting it in "
                                 r"([0-9.]+) s", r.getMessage()))]
    assert delays[:3] == [S.FIRST_DELAY_S, 2 * S.FIRST_DELAY_S, 4 * S.FIRST_DELAY_S]
    assert sup.status()["state"] == "stopped"


def test_a_healthy_run_resets_the_delay(monkeypatch, caplog) -> None:
    from simserver.ros2 import supervisor as S

    monkeypatch.setattr(S, "HEALTHY_RUN_S", 0.2)  # the child runs 0.4 s: healthy
    caplog.set_level(logging.WARNING, logger="simserver.server")
    sup = S.AdapterSupervisor([sys.executable, "-c", "import time; time.sleep(0.4)"],
                              "the child")
    sup.start()
    try:
        wait_until(lambda: sup.restarts, lambda n: n >= 2, timeout_s=20, what="two restarts")
    finally:
        sup.stop(lambda p: (p.terminate(), p.wait()))
    delays = [float(m.group(1)) for r in caplog.records
              if (m := re.search(r"restarting it in ([0-9.]+) s", r.getMessage()))]
    assert delays[:2] == [S.FIRST_DELAY_S, S.FIRST_DELAY_S]
