"""Issue 13: a client publishing its commands with zenoh's default congestion control
(DROP) lost its whole command stream for the rest of the session in 6 of 35 sessions
(``cmd_received`` frozen for 2-25 s while the session still got states). This runs many
short DROP sessions against one server beside CPU-bound processes and checks, in every
session, that the server keeps applying the client's commands: the state's
``last_cmd_seq`` follows the newest ``seq`` sent.

What these runs established (2026-12-01/02, load average 7-20): the cause is a zenoh 1.x
defect on a link where the two ends' transports differ. The server's default config asks
for zenoh's low-latency transport (QoS off); a client with zenoh's defaults asks for
neither, so their link gets zenoh's normal transport with QoS off: one transmit queue on
each end. When a DROP message finds no free batch there, zenoh marks the queue congested
under ``Priority::DEFAULT``, while a returned batch clears the mark of queue 0: the mark
stays, and every later DROP message on that link is dropped at once for the rest of the
session (zenoh-transport's ``pipeline.rs``). The server's states (DROP, express: a whole
batch each, 50 us wait) found zenoh's default 2 batches taken in 2 of 10 sessions beside
two CPU hogs and that client never got another state (1 and 424 states of 2000; with
BLOCK on the client it looked the same, since the test reads the lag from the states).
The server now gives such a link 16 batches (``MISMATCHED_LINK_QUEUE_BATCHES``): 0 of 20.
The case ``zenoh-defaults-client-mismatched`` failed before that change."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest
import zenoh

from simserver.testing import Client, ServerProcess, loopback_endpoint
from simserver.wire import protocol as proto
from tests.conftest import slow_enabled

pytestmark = pytest.mark.timeout(600)

SESSIONS = 12
"""DROP sessions per case: the mismatched case's always (before the fix it lost its stream
in 2 of 10 sessions; 12 sessions catch a 20 % loss rate 93 % of the time), every case's in
the long form (``-m slow`` or ``SIMSERVER_SLOW=1``)."""
MATCHED_SESSIONS_SHORT = 6
"""DROP sessions of the two matched-transport cases in the default suite (they never lost
a stream: the same check on half the sessions, 74 % for a 20 % loss rate; 24 s less)."""
SECONDS = 2.0
HOGS = 2


def zenoh_defaults(endpoint: str) -> zenoh.Config:
    """A client as a new user writes one: zenoh's defaults (QoS on, the normal transport,
    multicast scouting off only to stay on this machine) connecting to ``endpoint``."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", f'["{endpoint}"]')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return cfg


SERVER_DEFAULTS = ('{{ mode: "peer", listen: {{ endpoints: ["{endpoint}"] }}, '
                   'scouting: {{ multicast: {{ enabled: false }} }}, '
                   'transport: {{ shared_memory: {{ enabled: false }} }} }}\n')
"""A server config file with zenoh's default transport (multicast and shared memory off
only to keep to this machine)."""


def _session(server: ServerProcess, defaults: bool) -> dict:
    """One DROP session at 1 kHz for SECONDS: the longest time the server's
    ``last_cmd_seq`` lagged the newest seq sent by more than 50 commands."""
    with Client(server) as client:
        if defaults:  # the whole session as zenoh's defaults make it, publisher included
            client.ep.session.close()
            client.ep.session = zenoh.open(zenoh_defaults(server.endpoint))
            client.states = client.ep.declare_state_inbox()
            pub = client.ep.session.declare_publisher(client.ep.keys.cmd)
        else:
            pub = client.ep.session.declare_publisher(
                client.ep.keys.cmd, congestion_control=zenoh.CongestionControl.DROP,
                priority=zenoh.Priority.REAL_TIME, express=True)
        client.wait_state()
        seq = 0
        lag_since = None
        worst_lag_s = 0.0
        t_end = time.monotonic() + SECONDS
        next_t = time.monotonic()
        while time.monotonic() < t_end:
            seq += 1
            pub.put(proto.encode_command(seq=seq, throttle=0.1, gear=proto.Gear.D))
            next_t += 0.001
            st = client.poll()
            now = time.monotonic()
            if st is not None and seq - int(st["last_cmd_seq"]) > 50:
                lag_since = lag_since or now
                worst_lag_s = max(worst_lag_s, now - lag_since)
            else:
                lag_since = None
            time.sleep(max(0.0, next_t - time.monotonic()))  # the command stream's pace
        pub.undeclare()
    return {"sent": seq, "worst_lag_s": worst_lag_s}


@pytest.mark.parametrize(("defaults", "server_defaults"), [
    (False, False),
    (True, False),
    (True, True),
], ids=["project-config", "zenoh-defaults-client-mismatched", "zenoh-defaults-both"])
def test_drop_publishers_under_cpu_load_keep_their_command_stream(defaults, server_defaults,
                                                                  tmp_path, request):
    mismatched = defaults and not server_defaults
    sessions = SESSIONS if mismatched or slow_enabled(
        request.config.getoption("markexpr")) else MATCHED_SESSIONS_SHORT
    endpoint = loopback_endpoint()
    extra: list[str] = []
    if server_defaults:
        zcfg = tmp_path / "server_defaults.json5"
        zcfg.write_text(SERVER_DEFAULTS.format(endpoint=endpoint), encoding="utf-8")
        extra = ["--zenoh-config", str(zcfg)]
    with ServerProcess(listen=[endpoint] if not server_defaults else [],
                       extra_args=extra) as server:
        server.endpoint = endpoint
        # the hogs run from the server's ready line to the last session's end: every
        # session runs beside them as before, but the server's start and stop (seconds of
        # wall time each on a busy machine) no longer burn two cores in hogs (issue 33)
        hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
                for _ in range(HOGS)]
        try:
            results = [_session(server, defaults) for _ in range(sessions)]
        finally:
            for hog in hogs:
                hog.kill()
                hog.wait()
    lost = [r for r in results if r["worst_lag_s"] > 0.5]
    print(f"\n[DROP sessions] {sessions} x {SECONDS:.0f} s beside {HOGS} CPU hogs: "
          f"worst lags {[round(r['worst_lag_s'], 3) for r in results]} s")
    assert not lost, f"{len(lost)} of {sessions} sessions lost their command stream"


def _link(port: int, listen: bool, qos: bool) -> zenoh.Config:
    """A peer on zenoh's normal transport, QoS ``qos``, one transmit batch per queue and a
    1 us DROP wait: the smallest queue, so that a burst of express messages overflows it."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("listen/endpoints" if listen else "connect/endpoints",
                     f'["tcp/127.0.0.1:{port}"]')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("transport/unicast/qos/enabled", "true" if qos else "false")
    cfg.insert_json5("transport/link/tx/queue/size/data", "1")
    cfg.insert_json5("transport/link/tx/queue/congestion_control/drop/wait_before_drop", "1")
    return cfg


@pytest.mark.parametrize("qos", [False, True], ids=["one-queue", "qos-queues"])
def test_zenoh_drops_every_drop_message_after_one_congestion_of_a_one_queue_link(qos):
    """The zenoh defect behind the lost streams, alone: after a burst overflows the queue
    of a link with QoS off (one queue), a DROP publisher's later messages, sent one every
    2 ms with the link idle, never arrive; with QoS on (a queue per priority) they do.
    (The queue is marked congested under ``Priority::DEFAULT`` and a returned batch clears
    the mark of queue 0; zenoh-transport's ``pipeline.rs``.)

    If the one-queue case starts passing, zenoh has fixed the defect, and the server's
    MISMATCHED_LINK_QUEUE_BATCHES and states without express are no longer needed for it."""
    from simserver.testing import free_port, wait_until

    port = free_port()
    with zenoh.open(_link(port, True, qos)) as rx_session, \
            zenoh.open(_link(port, False, qos)) as tx_session:
        sub = rx_session.declare_subscriber("drop/test", zenoh.handlers.RingChannel(1 << 16))
        pub = tx_session.declare_publisher("drop/test", express=True,
                                           congestion_control=zenoh.CongestionControl.DROP)
        wait_until(lambda: pub.put(b"probe") or sub.try_recv(), timeout_s=10.0,
                   what="the subscription", interval_s=0.01)
        for _ in range(5000):  # the burst: 1 batch, 1 us wait: some must be dropped
            pub.put(b"x" * 200)
        time.sleep(0.2)  # the link drains and is idle again
        while sub.try_recv() is not None:
            pass
        for i in range(50):
            pub.put(b"after %d" % i)
            time.sleep(0.002)
        deadline = time.monotonic() + 1.0
        after = []
        while time.monotonic() < deadline and len(after) < 50:
            sample = sub.try_recv()
            if sample is None:
                time.sleep(0.005)
            else:
                after.append(sample.payload.to_bytes())
    if qos:  # the stream recovers (a busy machine may still drop a few of the 50)
        assert after, "with QoS on, none of 50 paced messages arrived"
    else:
        assert after == [], (
            f"{len(after)} of 50 paced messages arrived after the congestion: zenoh "
            "clears the one-queue link's congestion mark now (see the docstring)")
