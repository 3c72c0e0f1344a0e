"""simserver.adapters.zenoh_io on real zenoh sessions over loopback (no mocks).

Every session listens or connects on an explicit ``tcp/127.0.0.1:PORT`` with a free port,
with multicast scouting off (make_zenoh_config's default).
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import zenoh

from simserver.adapters.zenoh_io import (
    DEFAULT_BLOCK_WAIT_BEFORE_CLOSE_US,
    LINK_SNDBUF_BYTES,
    MISMATCHED_LINK_QUEUE_BATCHES,
    SocketBacklog,
    ZenohConfigError,
    ZenohEndpoint,
    ZenohOpenError,
    config_warnings,
    make_zenoh_config,
)
from simserver.testing import free_port, wait_until
from simserver.wire import protocol as P

REPO = Path(__file__).resolve().parents[1]
TIMEOUT_S = 5.0


def loopback(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def eventually(cond: Callable[[], object], timeout_s: float = TIMEOUT_S, what: str = ""):
    """Poll ``cond`` until it returns a truthy value; fail after ``timeout_s``."""
    return wait_until(cond, bool, timeout_s=timeout_s, what=what or str(cond))


def server(port: int, vehicle: str = "car0", **kw) -> ZenohEndpoint:
    return ZenohEndpoint(make_zenoh_config(listen=loopback(port)), vehicle=vehicle, **kw)


def client(*ports: int, vehicle: str = "car0", mode: str = "peer") -> ZenohEndpoint:
    cfg = make_zenoh_config(listen=[], connect=[loopback(p) for p in ports], mode=mode)
    ep = ZenohEndpoint(cfg, vehicle=vehicle)
    eventually(lambda: ep.session.info.peers_zid() or ep.session.info.routers_zid(),
               what="the client to connect")
    return ep


@contextmanager
def pair(vehicle: str = "car0") -> Iterator[tuple[ZenohEndpoint, ZenohEndpoint]]:
    port = free_port()
    with server(port, vehicle) as srv, client(port, vehicle=vehicle) as cli:
        yield srv, cli


LAST_PROBE = P.encode_command(seq=0xFFFFFFFF)
"""A command no test sends otherwise: what arrives up to it was in flight before it."""


def sync_commands(inbox, publisher) -> None:
    """Publish probes until the subscription has propagated, then empty the inbox up to
    a last probe (one publisher's samples arrive in order)."""
    eventually(lambda: publisher.put(P.encode_command(seq=0)) or inbox.wait_newest(0.01),
               what="the command subscription")
    publisher.put(LAST_PROBE)
    eventually(lambda: LAST_PROBE in inbox.drain_newest(), what="the last probe")


def flushed(sender: ZenohEndpoint, key: str, inbox) -> list[bytes]:
    """Everything ``inbox`` (a subscriber on ``key``) receives up to a probe that
    ``sender`` publishes on ``key`` as commands and states go (REAL_TIME, express): what
    ``sender`` sent there before has arrived by then, so what else came is all that will."""
    pub = sender.session.declare_publisher(key, priority=zenoh.Priority.REAL_TIME,
                                           express=True,
                                           congestion_control=zenoh.CongestionControl.BLOCK)
    got: list[bytes] = []
    try:
        eventually(lambda: pub.put(LAST_PROBE) or got.extend(inbox.drain_newest())
                   or LAST_PROBE in got, what=f"a probe on {key}")
    finally:
        pub.undeclare()
    return [g for g in got if g != LAST_PROBE]


# ============================================================================ config


def _json(cfg: zenoh.Config, key: str):
    return json.loads(cfg.get_json(key))


def test_default_config_is_loopback_only():
    cfg = make_zenoh_config()
    assert _json(cfg, "mode") == "peer"
    assert _json(cfg, "listen/endpoints") == ["tcp/127.0.0.1:7447"]
    assert _json(cfg, "connect/endpoints") == []
    assert _json(cfg, "scouting/multicast/enabled") is False
    assert _json(cfg, "transport/shared_memory/enabled") is False
    block = _json(cfg, "transport/link/tx/queue/congestion_control/block")
    assert block["wait_before_close"] == DEFAULT_BLOCK_WAIT_BEFORE_CLOSE_US
    assert _json(cfg, "transport/unicast/lowlatency") is True
    assert _json(cfg, "transport/unicast/qos/enabled") is False
    # a peer on zenoh's normal transport gets one queue of this many batches (issue 13)
    assert _json(cfg, "transport/link/tx/queue/size/data") == MISMATCHED_LINK_QUEUE_BATCHES
    # room for SocketBacklog to close a link that falls behind before a put waits on it
    assert _json(cfg, "transport/link/tcp/so_sndbuf") == LINK_SNDBUF_BYTES
    assert LINK_SNDBUF_BYTES > SocketBacklog.WEDGE_MAX_BYTES
    assert config_warnings(cfg) == []
    # zenoh's own defaults are what config_warnings warns about.
    assert len(config_warnings(zenoh.Config())) == 3
    client_cfg = make_zenoh_config(connect="tcp/127.0.0.1:7447", mode="client")
    assert _json(client_cfg, "listen/endpoints") == []
    assert _json(client_cfg, "connect/endpoints") == ["tcp/127.0.0.1:7447"]


def _fill(sock: socket.socket, nbytes: int) -> None:
    """Write ``nbytes`` more into a non-blocking socket whose reader does not read."""
    chunk = bytes(1 << 16)
    left = nbytes
    while left > 0:
        left -= sock.send(chunk[:left])


def _unsent(sock: socket.socket) -> int:
    import fcntl
    import termios

    buf = bytearray(4)
    fcntl.ioctl(sock.fileno(), termios.TIOCOUTQ, buf)
    return int.from_bytes(buf, "little", signed=True)


def test_a_link_seconds_behind_is_closed_though_its_reader_reads_now_and_then():
    """Issue 35 item 2: a subscriber's reader starved on a busy machine reads a little now
    and then, so its unsent bytes go down and the one-second rule never fires, while they
    grow towards the size at which the server's puts wait on its socket. At
    ``WEDGE_MAX_BYTES`` the link is closed whether or not they went down; below it, a
    reader that reads keeps its link."""
    with socket.create_server(("127.0.0.1", 0)) as listener:
        reader = socket.socket()
        reader.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 16)
        reader.connect(listener.getsockname())
        link, _ = listener.accept()  # the server's side of a subscriber's link
        with reader, link:
            link.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, LINK_SNDBUF_BYTES)
            link.setblocking(False)
            watch = SocketBacklog(close_wedged=True)
            t = 1000.0
            _fill(link, SocketBacklog.WEDGE_MAX_BYTES // 2)
            watch.largest(t)

            def read_a_little() -> None:  # enough to open the reader's window again
                before = _unsent(link)

                def take() -> int:
                    reader.recv(1 << 14)
                    return _unsent(link)

                wait_until(take, lambda n: n < before, what="the unsent bytes going down",
                           interval_s=0.001)

            for _ in range(4):  # the reader takes a little, then falls behind again
                read_a_little()
                t += 0.5
                watch.largest(t)
            assert watch.closed == [], "a link below the cap whose reader reads was closed"
            _fill(link, SocketBacklog.WEDGE_MAX_BYTES)
            read_a_little()  # it went down just before the look: still seconds behind
            t += 0.01
            watch.largest(t)
            assert len(watch.closed) == 1 and "seconds behind" in watch.closed[0]
            reader.setblocking(True)
            reader.settimeout(10.0)
            with pytest.raises(OSError):  # the link's end: reset, or its end after the data
                while reader.recv(1 << 20):
                    pass
                raise ConnectionResetError("the link ended")


def test_config_file_used_as_is_and_overridden_only_when_asked(tmp_path):
    path = tmp_path / "router.json5"
    path.write_text(textwrap.dedent("""\
        {
          // a user config: comments and trailing commas are JSON5
          mode: "router",
          listen: { endpoints: ["tcp/127.0.0.1:17999"] },
          scouting: { multicast: { enabled: false } },
        }
        """))
    cfg = make_zenoh_config(config_file=path)
    assert _json(cfg, "mode") == "router"
    assert _json(cfg, "listen/endpoints") == ["tcp/127.0.0.1:17999"]
    cfg = make_zenoh_config(config_file=path, listen=["tcp/127.0.0.1:18000"], mode="peer")
    assert _json(cfg, "listen/endpoints") == ["tcp/127.0.0.1:18000"]
    assert _json(cfg, "mode") == "peer"


@pytest.mark.parametrize(
    ("text", "suffix", "needle"),
    [
        ("{ mode: 'peer', ", ".json5", "not a valid zenoh config"),
        ("{ mode: 'sideways' }", ".json5", "sideways"),
        ("{ no_such_section: 1 }", ".json5", "no_such_section"),
        ("{}", ".txt", "not a valid zenoh config"),
    ],
)
def test_bad_config_file_names_the_file(tmp_path, text, suffix, needle):
    path = tmp_path / f"bad{suffix}"
    path.write_text(text)
    with pytest.raises(ZenohConfigError, match=needle) as err:
        make_zenoh_config(config_file=path)
    assert str(path) in str(err.value)
    assert ".rs:" not in str(err.value)  # no Rust source locations in user-facing errors


def test_missing_config_file_and_bad_values():
    with pytest.raises(ZenohConfigError, match="nowhere.json5.*not found"):
        make_zenoh_config(config_file="/nowhere.json5")
    with pytest.raises(ZenohConfigError, match="listen.*'127.0.0.1:7447'"):
        make_zenoh_config(listen="127.0.0.1:7447")
    with pytest.raises(ZenohConfigError, match="mode"):
        make_zenoh_config(mode="boss")


def test_port_in_use_is_a_clear_error():
    port = free_port()
    with server(port):
        with pytest.raises(ZenohOpenError, match=f"127.0.0.1:{port}.*in use") as err:
            server(port)
        assert ".rs:" not in str(err.value)
    with pytest.raises(P.ProtocolError, match="vehicle"):
        ZenohEndpoint(make_zenoh_config(listen=[]), vehicle="car/1")


def test_all_keys_are_valid_concrete_zenoh_key_expressions():
    for prefix, vehicle in (("simserver", "car0"), ("lab-1/sim.v2", "Cockpit_3")):
        k = P.vehicle_keys(prefix, vehicle)
        for key in (k.cmd, k.state, k.diag, k.alive, *k.ctl.values()):
            assert str(zenoh.KeyExpr(key)) == key
        assert zenoh.KeyExpr(k.ctl_wildcard).intersects(zenoh.KeyExpr(k.ctl["reset"]))


# ============================================================================ pub/sub


def test_command_published_is_drained_in_order_and_newest_last():
    with pair() as (srv, cli):
        inbox = srv.declare_command_inbox(capacity=32)
        pub = cli.declare_command_publisher()
        sync_commands(inbox, pub)
        assert inbox.drain_newest() == []  # nothing pending: returns at once, empty
        sent = [P.encode_command(0.01 * i, 0.5, seq=i) for i in range(1, 11)]
        for payload in sent:
            pub.put(payload)
        got: list[bytes] = []
        eventually(lambda: got.extend(inbox.drain_newest()) or len(got) >= 10,
                   what="10 commands")
        assert got == sent
        assert P.decode_command(got[-1]).seq == 10
        assert inbox.drain_newest() == []


def test_ring_keeps_only_the_newest():
    with pair() as (srv, cli):
        inbox = srv.declare_command_inbox(capacity=4)
        pub = cli.declare_command_publisher()
        sync_commands(inbox, pub)
        for i in range(1, 51):
            pub.put(P.encode_command(seq=i))
        drains: list[list[int]] = []

        def drain_slowly():
            time.sleep(0.2)  # the subject: a slow reader, so the burst overflows the ring
            drains.append([P.decode_command(g).seq for g in inbox.drain_newest()])
            return drains[-1] and drains[-1][-1] == 50

        eventually(drain_slowly, what="the newest command")
        assert all(len(d) <= 4 and d == sorted(d) for d in drains)
        assert sum(map(len, drains)) < 50  # older commands were dropped, newest kept


def test_state_and_diagnostics_reach_a_client():
    with pair() as (srv, cli):
        state_pub = srv.declare_state_publisher()
        diag_pub = srv.declare_diag_publisher()
        states = cli.declare_state_inbox()
        diags = cli.declare_diag_inbox()
        rec = P.new_state_record()
        rec["tick"] = 42
        rec["fz_n"] = [4000.0, 4100.0, 3900.0, 3800.0]
        diag = P.encode_diagnostics(**{f.name: 0 for f in P.DIAGNOSTICS_FIELDS
                                       if f.name not in ("version", "reserved")})

        def exchange():
            state_pub.put(rec.tobytes())
            diag_pub.put(diag)
            return states.wait_newest(0.01) and diags.wait_newest(0.01)

        eventually(exchange, what="state and diagnostics")
        state_pub.put(rec.tobytes())
        got = P.decode_state(eventually(lambda: states.wait_newest(0.1)))
        assert got["tick"] == 42 and got["fz_n"].tolist() == [4000.0, 4100.0, 3900.0, 3800.0]


def test_the_servers_publications_never_block_and_the_decimated_key_gets_every_tenth():
    """Issue 13: nothing the server's loop puts may wait for a reader that stopped (a
    viewer at SCHED_IDLE, a frozen process): the state, its 100 Hz key and the diagnostics
    are DROP (the diagnostics were BLOCK). Issue 19: the ``state/100hz`` key carries one
    of every ten states at 1 kHz."""
    with pair() as (srv, cli):
        pub = srv.declare_vehicle_publisher(states_per_s=1000.0)
        for p in (pub.state, pub.decimated, pub.diagnostics):
            assert p.congestion_control == zenoh.CongestionControl.DROP, p.key_expr
        assert str(pub.decimated.key_expr) == srv.keys.state_decimated
        assert pub.decimate_every == 1000 // P.STATE_DECIMATED_HZ
        slow = cli.declare_state_inbox(capacity=1024, decimated=True)
        full = cli.declare_state_inbox(capacity=1024)
        rec = P.new_state_record()

        def publish(n: int) -> None:
            for _ in range(n):
                rec["tick"] += 1
                pub.publish_state(rec.tobytes())
                time.sleep(0.001)  # the server's pace: a burst would meet DROP's limit

        eventually(lambda: publish(10) or slow.wait_newest(0.05),
                   what="a first decimated state")
        full.drain_newest()
        first = int(rec["tick"])
        publish(200)
        got = []
        eventually(lambda: got.extend(int(P.decode_state(b)["tick"])
                                      for b in slow.drain_newest()) or len(got) >= 15,
                   what="15 decimated states")
        full_ticks = [int(P.decode_state(b)["tick"]) for b in full.drain_newest()]
        assert len(full_ticks) > 150  # the 1 kHz key still carries every state
        # every tenth state of those published since: ticks ten apart (one lost to DROP on
        # a loaded machine would show as a gap of 20, still a multiple of ten)
        assert all(t > first for t in got)
        gaps = {b - a for a, b in zip(got, got[1:], strict=False)}
        assert 10 in gaps and all(g % 10 == 0 for g in gaps), got


@pytest.mark.parametrize("ours", ["listens", "connects"])
def test_low_latency_default_talks_to_a_peer_with_zenohs_defaults(ours):
    """The default's low-latency transport falls back for a peer that does not have it
    (zenoh's own defaults: QoS on, low latency off), whichever side opens the link."""
    port = free_port()
    plain = zenoh.Config()
    plain.insert_json5("scouting/multicast/enabled", "false")
    plain.insert_json5("transport/shared_memory/enabled", "false")
    if ours == "listens":
        first = make_zenoh_config(listen=[loopback(port)])
        plain.insert_json5("connect/endpoints", json.dumps([loopback(port)]))
        plain.insert_json5("listen/endpoints", "[]")
        second = plain
    else:
        plain.insert_json5("listen/endpoints", json.dumps([loopback(port)]))
        first, second = plain, make_zenoh_config(listen=[], connect=[loopback(port)])
    with ZenohEndpoint(first, prefix="simserver", vehicle="car0") as srv, \
            ZenohEndpoint(second, prefix="simserver", vehicle="car0") as cli:
        inbox = srv.declare_command_inbox()
        pub = cli.declare_command_publisher()

        def exchange():
            pub.put(P.encode_command(throttle=0.5, seq=7))
            return inbox.wait_newest(0.01)

        got = eventually(exchange, what="a command across the mixed link")
        assert P.decode_command(got).throttle == 0.5


# ============================================================================ controls


@contextmanager
def control_server(srv: ZenohEndpoint, handle: Callable[[str, dict], dict]):
    """Serve controls from a thread, as the server loop would (poll, reply)."""
    inbox = srv.declare_control_inbox()
    seen: list[tuple[str, dict]] = []
    stop = threading.Event()

    def loop():
        while not stop.is_set():
            for req in inbox.poll():
                seen.append((req.name, req.args))
                req.reply_ok(**handle(req.name, req.args))
            stop.wait(0.001)  # a server loop's period

    thread = threading.Thread(target=loop, daemon=True)
    thread.start()
    try:
        yield inbox, seen
    finally:
        stop.set()
        thread.join(5)


def test_queryable_replies_and_rejects_bad_requests():
    with pair() as (srv, cli):
        with control_server(srv, lambda name, args: {"echo": args, "tick": 7}) as (inbox, seen):
            reply = eventually(lambda: _try_request(cli, "step", {"n": 5}), what="a reply")
            assert reply == {"ok": True, "echo": {"n": 5}, "tick": 7}
            assert cli.request("get_config")["ok"] is True
            assert cli.request("reset", {"pose": {"x_m": 1, "y_m": 2, "yaw_rad": 0.1}})["echo"] \
                == {"pose": {"x_m": 1.0, "y_m": 2.0, "yaw_rad": 0.1}}
            n_seen = len(seen)
            # Bad arguments: answered with an error naming the field; the handler never runs.
            bad = cli.request("step", payload=b'{"n": 0}')
            assert bad["ok"] is False and bad["field"] == "n" and "n:" in bad["error"]
            bad = cli.request("set_road", payload=b'{"grade_pct": NaN}')
            assert bad["ok"] is False and bad["field"] == "request"
            bad = cli.request("reset", payload=b'{"pose": {"x_m": 1}}')
            assert bad["field"] == "pose.y_m"
            # Unknown control and wildcard queries get a zenoh error reply with the same JSON,
            # and so do keys below ctl that are no control (issue 14: they got no reply
            # at all, and a client waited out its timeout)
            base = cli.keys.base
            for key in (f"{base}/ctl/explode", f"{base}/ctl/*", cli.keys.ctl_wildcard,
                        f"{base}/ctl", f"{base}/ctl/reset/extra"):
                replies = list(cli.session.get(key, timeout=2.0))
                assert len(replies) == 1 and replies[0].err is not None
                body = P.decode_reply(replies[0].err.payload.to_bytes())
                assert body["ok"] is False and body["field"] == "control"
            assert len(seen) == n_seen
            assert inbox.rejected == 8
            # Invalid args are refused locally before anything is sent.
            with pytest.raises(P.ProtocolError, match="^n:"):
                cli.request("step", {"n": -1})


def _try_request(cli: ZenohEndpoint, name: str, args: dict) -> dict | None:
    try:
        return cli.request(name, args, timeout_s=0.5)
    except TimeoutError:
        return None


def test_request_without_server_times_out():
    with pair() as (_srv, cli):
        with pytest.raises(TimeoutError, match="no reply"):
            cli.request("pause", timeout_s=0.3)


def test_a_queryable_that_does_not_answer_in_time_is_a_timeout():
    """A server too busy to answer: zenoh's own error reply ("Timeout") is a TimeoutError,
    not a malformed reply (it was "reply: is not UTF-8 JSON" under load)."""
    with pair() as (srv, cli):
        inbox = srv.declare_control_inbox()  # declared, never polled
        querier = cli.session.declare_querier(cli.keys.ctl["pause"])
        eventually(lambda: querier.matching_status.matching, what="the queryable known")
        querier.undeclare()
        with pytest.raises(TimeoutError, match="a queryable matched"):
            cli.request("pause", timeout_s=0.3)
        assert inbox.received == 1


def test_closing_the_publisher_logs_no_hand_off(caplog):
    """``close`` turns the caller's inline puts off to stop ``state-tx``: the thread must
    not log that as states handed to it (a server's stop logged a hand-off "because a put
    took 0 us")."""
    with pair() as (srv, _cli):
        pub = srv.declare_vehicle_publisher(states_per_s=1000.0, sender_thread=True,
                                            inline_while_cheap=True)
        pub.WATCH_S = 0.0  # the thread looks at the mode on every wake-up, the last one too
        pub.publish_state(bytes(64))
        assert pub.mode() == "inline"
        with caplog.at_level("DEBUG", logger="simserver.server"):
            pub.close()
        assert not [r for r in caplog.records if "handed to this thread" in r.getMessage()]


def test_reply_twice_is_an_error():
    with pair() as (srv, cli):
        inbox = srv.declare_control_inbox()
        querier = cli.session.declare_querier(cli.keys.ctl["pause"])
        eventually(lambda: querier.matching_status.matching, what="the queryable known")
        querier.undeclare()
        result: dict = {}
        thread = threading.Thread(
            target=lambda: result.update(cli.request("pause", timeout_s=3.0)), daemon=True
        )
        thread.start()
        req = eventually(lambda: inbox.poll(), what="the query")[0]
        req.reply_ok(paused=True)
        with pytest.raises(RuntimeError, match="already answered"):
            req.reply_ok()
        thread.join(5)
        assert result == {"ok": True, "paused": True}


# ============================================================================ liveliness


def test_liveliness_token_appears_and_disappears():
    port = free_port()
    srv = server(port)
    try:
        with client(port) as cli:
            watch = cli.declare_alive_watch()
            assert cli.alive_tokens(timeout_s=0.5) == []
            srv.declare_alive_token()
            events: list[tuple[str, bool]] = []
            eventually(lambda: events.extend(watch.poll()) or events, what="token PUT")
            assert events == [("simserver/car0/alive", True)]
            assert cli.alive_tokens() == ["simserver/car0/alive"]
            srv.close()
            assert srv.closed
            eventually(lambda: events.extend(watch.poll()) or len(events) == 2,
                       what="token DELETE")
            assert events[-1] == ("simserver/car0/alive", False)
            assert cli.alive_tokens(timeout_s=0.5) == []
    finally:
        srv.close()
        srv.close()  # idempotent


# ============================================================================ isolation


def test_two_vehicle_ids_do_not_see_each_other_peer_to_peer():
    p0, p1 = free_port(), free_port()
    with server(p0, "car0") as s0, server(p1, "car1") as s1, \
            client(p0, p1, vehicle="car1") as c1:
        in0, in1 = s0.declare_command_inbox(), s1.declare_command_inbox()
        ctl0 = s0.declare_control_inbox()
        s0.declare_alive_token()
        s1.declare_alive_token()
        pub = c1.declare_command_publisher()
        sync_commands(in1, pub)
        for i in range(1, 21):
            pub.put(P.encode_command(seq=i))
        got1: list[bytes] = []
        eventually(lambda: got1.extend(in1.drain_newest()) or len(got1) >= 20, what="car1")
        assert flushed(c1, s0.keys.cmd, in0) == []  # nothing of car1's reached car0
        # car1 has no control server: car0's queryable does not answer for it.
        with pytest.raises(TimeoutError):
            c1.request("pause", timeout_s=0.3)
        assert ctl0.poll() == [] and ctl0.received == 0
        # A monitor sees both tokens with a wildcard.
        alive = eventually(lambda: sorted(c1.alive_tokens("simserver/*/alive")) if
                           len(c1.alive_tokens("simserver/*/alive")) == 2 else None,
                           what="both tokens")
        assert alive == ["simserver/car0/alive", "simserver/car1/alive"]


def test_isolation_through_a_router():
    """Servers and a client joined by a zenoh router (a Python session in router mode)."""
    rp = free_port()
    router_cfg = make_zenoh_config(listen=loopback(rp), mode="router")
    with zenoh.open(router_cfg), \
            ZenohEndpoint(make_zenoh_config(connect=loopback(rp), mode="client"),
                          vehicle="car0") as s0, \
            ZenohEndpoint(make_zenoh_config(connect=loopback(rp), mode="client"),
                          vehicle="car1") as s1, \
            client(rp, vehicle="car0", mode="client") as c0:
        in0, in1 = s0.declare_command_inbox(), s1.declare_command_inbox()
        state1 = s1.declare_state_publisher()
        states0 = c0.declare_state_inbox()
        pub = c0.declare_command_publisher()
        sync_commands(in0, pub)
        for i in range(1, 11):
            pub.put(P.encode_command(seq=i))
            state1.put(P.new_state_record().tobytes())  # car1's state: not car0's
        got: list[bytes] = []
        eventually(lambda: got.extend(in0.drain_newest()) or len(got) >= 10, what="car0")
        assert flushed(c0, s1.keys.cmd, in1) == []  # car0's commands did not reach car1
        assert flushed(s1, c0.keys.state, states0) == []  # nor car1's state car0's client


# ============================================================================ process exit


def test_process_exits_promptly_without_close():
    """Platform note: Python callbacks keep a process alive; channel handlers must not."""
    port = free_port()
    code = textwrap.dedent(f"""
        from simserver.adapters.zenoh_io import ZenohEndpoint, make_zenoh_config
        ep = ZenohEndpoint(make_zenoh_config(listen="tcp/127.0.0.1:{port}"))
        ep.declare_command_inbox(); ep.declare_control_inbox(); ep.declare_alive_token()
        ep.declare_state_publisher(); ep.declare_state_inbox(); ep.declare_alive_watch()
        print("declared", flush=True)
        # no close(): the interpreter must still exit
    """)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, timeout=30)
    assert res.returncode == 0, res.stderr
    assert "declared" in res.stdout
