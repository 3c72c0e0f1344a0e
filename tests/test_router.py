"""``simserver router`` (issue 35 item 3): servers on several ports (machines) joined by
one zenoh router with the project's safe defaults, seen and driven from one client that
connects to the router alone.

Real ``simserver serve`` and ``simserver router`` subprocesses on loopback; the client
is a zenoh session of this process in client mode.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

from simserver.adapters.zenoh_io import Inbox, ZenohEndpoint, make_zenoh_config
from simserver.testing import (
    OutputProcess,
    ServerProcess,
    free_port,
    process_sockets,
    wait_until,
)
from simserver.wire import protocol as proto

pytestmark = pytest.mark.timeout(300)


def router_argv(*args: str) -> list[str]:
    return [sys.executable, "-m", "simserver", "router", *args]


def test_two_servers_joined_by_the_router_are_seen_and_driven_from_one_client():
    cars = ("car0", "car1")
    servers = {vid: ServerProcess(vehicle_id=vid) for vid in cars}  # two ports
    router_ep = f"tcp/127.0.0.1:{free_port()}"
    router = None
    try:
        connect = [a for s in servers.values() for a in ("--connect", s.endpoint)]
        router = OutputProcess(router_argv("--listen", router_ep, *connect), ready="ready:")
        assert router.wait_ready(60.0), router.text()
        line = router.wait_for_line("ready:")
        assert f"listening on {router_ep};" in line, line
        assert "multicast scouting off, gossip off" in line, line
        # the router listens on the given loopback endpoint only, and holds no UDP socket
        socks = process_sockets(router.pid)
        assert sorted((s.local_ip, s.local_port) for s in socks if s.listening) == \
            [("127.0.0.1", int(router_ep.rsplit(":", 1)[1]))]
        assert not [s for s in socks if s.proto.startswith("udp")]
        # one client session, connected to the router alone
        with ZenohEndpoint(make_zenoh_config(listen=[], connect=[router_ep], mode="client"),
                           prefix="simserver", vehicle="car0") as ep:
            tokens = wait_until(
                lambda: sorted(ep.alive_tokens("simserver/*/alive", timeout_s=0.5)),
                lambda t: all(f"simserver/{vid}/alive" in t for vid in cars),
                timeout_s=30.0, what="both servers' liveliness tokens through the router")
            assert set(tokens) >= {f"simserver/{vid}/alive" for vid in cars}
            keys = {vid: proto.vehicle_keys("simserver", vid) for vid in cars}
            inboxes = {vid: Inbox(ep.session, keys[vid].state, 1024) for vid in cars}
            pubs = {vid: ep.session.declare_publisher(keys[vid].cmd) for vid in cars}
            # car1 only: full throttle; car0 only: reverse. Each command reaches its own
            # server only, and each server's state comes back through the router.
            drive = {"car0": dict(throttle=0.6, gear=proto.Gear.R),
                     "car1": dict(throttle=0.6, gear=proto.Gear.D)}
            newest: dict[str, np.void] = {}
            seq = [0]

            def step() -> dict[str, np.void]:
                seq[0] += 1
                for vid in cars:
                    pubs[vid].put(proto.encode_command(seq=seq[0], **drive[vid]))
                    payloads = inboxes[vid].drain_newest()
                    if payloads:
                        newest[vid] = proto.decode_state(payloads[-1])
                return newest

            wait_until(step, lambda n: len(n) == 2 and n["car1"]["u_mps"] > 1.0
                       and n["car0"]["u_mps"] < -0.5, timeout_s=30.0, interval_s=0.005,
                       what="car1 forward and car0 in reverse, driven through the router")
            assert newest["car1"]["gear"] == proto.Gear.D
            assert newest["car0"]["gear"] == proto.Gear.R
            for p in pubs.values():
                p.undeclare()
            for inbox in inboxes.values():
                inbox.close()
        for server in servers.values():
            assert server.alive(), server.text()
    finally:
        if router is not None:
            code = router.stop(timeout_s=30.0)
        for server in servers.values():
            server.stop()
    assert code == 0, router.text()
    assert "Traceback" not in router.text(), router.text()
    assert "simserver router: stopped" in router.text()


def test_a_port_in_use_is_a_one_line_error_naming_it():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with OutputProcess(router_argv("--listen", endpoint), ready="ready:") as first:
        assert first.wait_ready(60.0), first.text()
        second = OutputProcess(router_argv("--listen", endpoint))
        assert second.wait(timeout_s=60.0) == 2, second.text()
    text = second.text()
    assert "Traceback" not in text, text
    (error,) = [ln for ln in text.splitlines() if ln.startswith("error:")]
    assert endpoint in error, error
