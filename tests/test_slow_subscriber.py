"""Issue 35 item 2: a subscriber that stops reading costs only its own states.

A server, :data:`SUBSCRIBERS` state subscribers, clients joining and leaving, one
subscriber that never reads (``roles slowsub``: the project's client config, a FIFO of
one that fills and blocks zenoh's receiver, so the server's socket to it fills), and a
normal subscriber in this process, once with the project's client config and once with
zenoh's defaults. Once the slow subscriber's link is wedged (full: its unsent bytes, seen
in ``/proc/net/tcp``, past :data:`FULL_BYTES` and no longer moving) or closed by the
server, the normal subscriber must receive the states of the next :data:`TICKS` ticks:
nearly all of them, counted by tick number.

On the server's default transport (zenoh's low-latency one) a put writes to each
subscriber's socket in turn, so once the slow link is full every put waits on it and the
others' states stop (before the fix, 2 runs: the link filled within 11 s; once it was
full the normal subscriber got 1 of the next 3000 ticks' states in one run, the server's
sender queue dropping the rest, and all of them in the other, the link never closed).
The server now closes a link whose unsent bytes stay backed up for a second
(``zenoh_io.SocketBacklog``: wedged links), long before it is full, and says so in its
log. The same runs against zenoh's normal transport with QoS on
(``benchmarks.bench_cmd_latency.server_zenoh_config``: a transmit queue per link).
"""

from __future__ import annotations

import json

import pytest
import zenoh

from benchmarks.bench_cmd_latency import server_process
from simserver.testing import RoleProcess, client_config, process_sockets, wait_until
from simserver.wire import protocol as proto

pytestmark = pytest.mark.timeout(300)

SUBSCRIBERS = 20
"""Other state subscribers beside (``roles multisub``, as the issue's 20 viewers)."""
CHURN_PER_S = 10
"""Sessions a second joining and leaving a second later (``roles churn``)."""
TICKS = 3000
"""Ticks over which the normal subscriber's states are counted (3 s of states)."""
MIN_SHARE = 0.9
"""States of those ticks it must get: DROP may lose a few on a loaded loopback
(docs/protocol.md: up to 0.5 % of a 1 kHz stream), a stalled stream loses most."""
FULL_BYTES = 1_000_000
"""Unsent bytes on the server's socket to the slow subscriber from which, once they stop
moving, its link counts as full (loopback here: 3.9 MB at most, growing 360 kB/s while
the reader is stopped; a subscriber that keeps up leaves none)."""
TCP_CLOSE_WAIT = 8
"""``/proc/net/tcp``'s state of the slow subscriber's socket once the server closed the
link (its own receiver is stuck: it never closes its side)."""
STILL_POLLS = 3
"""Polls (0.2 s apart) with the same unsent bytes that show the link full."""


def _zenoh_defaults(endpoint: str) -> zenoh.Config:
    cfg = zenoh.Config()  # zenoh's defaults, only kept on this machine
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("listen/endpoints", "[]")
    cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
    return cfg


def _links(port: int, peer_pid: int) -> tuple[list[int], list[int]]:
    """The server's side of its TCP links to process ``peer_pid`` (from local ``port``):
    the send queues of the established ones; and the TCP states of that process's side
    (``/proc/net/tcp``: 1 established, 8 closed by the server and not yet by it)."""
    peer_ports = {s.local_port for s in process_sockets(peer_pid)}
    queues, states = [], []
    for name in ("tcp", "tcp6"):
        with open(f"/proc/net/{name}", encoding="ascii") as fh:
            next(fh)
            for line in fh:
                parts = line.split()
                local_port = int(parts[1].rsplit(":", 1)[1], 16)
                remote_port = int(parts[2].rsplit(":", 1)[1], 16)
                state = int(parts[3], 16)
                if local_port == port and remote_port in peer_ports and state == 1:
                    queues.append(int(parts[4].split(":")[0], 16))
                elif local_port in peer_ports and remote_port == port:
                    states.append(state)
    return queues, states


def _port(server) -> int:
    return int(server.endpoint.rsplit(":", 1)[1])


class _SlowLink:
    """Polled: ``"closed"`` once the slow subscriber's link is gone, ``"full"`` once its
    unsent bytes passed :data:`FULL_BYTES` and stayed the same :data:`STILL_POLLS` polls,
    else ``""``."""

    def __init__(self, port: int, pid: int) -> None:
        self.port, self.pid = port, pid
        self.seen = False
        self.history: list[int] = []

    def __call__(self) -> str:
        queues, states = _links(self.port, self.pid)
        if states:
            self.seen = True
        if (self.seen and not queues) or TCP_CLOSE_WAIT in states:
            return "closed"
        if not queues:
            return ""
        self.history.append(max(queues))
        last = self.history[-STILL_POLLS:]
        if len(last) == STILL_POLLS and last[0] > FULL_BYTES and len(set(last)) == 1:
            return "full"
        return ""


@pytest.mark.parametrize("transport,kind", [
    ("default", "project"),
    ("default", "zenoh_defaults"),
    ("normal", "project"),
    ("normal", "zenoh_defaults"),
])
def test_a_slow_subscriber_does_not_stop_the_others_states(transport, kind, tmp_path):
    with server_process(transport, str(tmp_path)) as server:
        conn = server.client_args()
        # the load first: many viewers, one that never reads, clients joining
        roles = [RoleProcess("multisub", [*conn, "--sessions", str(SUBSCRIBERS)]),
                 RoleProcess("churn", [*conn, "--rate", str(CHURN_PER_S), "--life", "1.0"])]
        slow = RoleProcess("slowsub", [*conn, "--capacity", "1"])
        roles.append(slow)
        cfg = (client_config(server.endpoint) if kind == "project"
               else _zenoh_defaults(server.endpoint))
        keys = proto.vehicle_keys("simserver", server.vehicle_id)
        counts: dict[str, int] = {}
        try:
            slow_link = _SlowLink(_port(server), slow.pid)
            # its link seen up (it said READY; on a busy machine the socket may show a
            # moment later), before the server may close it
            wait_until(lambda: slow_link() == "closed" or slow_link.seen, timeout_s=30.0,
                       what="the slow subscriber's link to the server")
            with zenoh.open(cfg) as session:
                sub = session.declare_subscriber(keys.state,
                                                 zenoh.handlers.RingChannel(1 << 16))
                ticks: list[int] = []

                def newest() -> int:
                    while (sample := sub.try_recv()) is not None:
                        ticks.append(int(proto.decode_state(
                            sample.payload.to_bytes())["tick"]))
                    return ticks[-1] if ticks else -1

                def count(phase: str) -> None:
                    wait_until(newest, lambda t: t >= 0, timeout_s=30.0,
                               what=f"a state ({phase})")
                    first = newest() + 1
                    # a stream that stopped never reaches the last tick: the timeout says so
                    wait_until(newest, lambda t: t >= first + TICKS - 1, timeout_s=60.0,
                               what=f"the states of {TICKS} ticks ({phase})")
                    counts[phase] = len({t for t in ticks if first <= t < first + TICKS})

                # joined just after the slow subscriber (its link is filling)
                count("joined beside it")
                wedged = wait_until(slow_link, timeout_s=90.0, interval_s=0.2,
                                    what="the slow subscriber's link to fill or be closed")
                ticks.clear()
                count(f"its link {wedged}")
                sub.undeclare()
        finally:
            for role in roles:
                role.stop()
    print(f"{transport}/{kind}: states of {TICKS} ticks received: {counts}; the slow "
          f"link's unsent bytes, last polls: {slow_link.history[-3:]}")
    for phase, got in counts.items():
        assert got >= MIN_SHARE * TICKS, (
            f"{kind}: {got} of the {TICKS} ticks' states arrived ({phase})")
    assert wedged == "closed" and "state-watch: link from" in server.text(), (
        f"the server did not close the slow subscriber's wedged link ({wedged})")
