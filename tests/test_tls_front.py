"""The accept-filtering TLS front (``simserver.adapters.tls_front``) on its own.

A real front (its loop in a thread of this process) before a real loopback TCP backend
that records what reaches it and echoes it back; real sockets from real source
addresses (127.0.0.1, 127.0.0.2: Linux routes all of 127/8 to loopback). The front with
zenoh's TLS listener behind it, and real authenticated clients, is
``tests/test_security.py``'s.
"""

from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest

from simserver.adapters.tls_front import (
    FrontError,
    FrontLimits,
    FrontSupervisor,
    TlsFront,
    bind_listener,
    hello_prefix_ok,
    plan_fronts,
)
from simserver.testing import wait_until

pytestmark = pytest.mark.timeout(60)

# The start of a real ClientHello record: handshake (0x16), TLS 1.0 record version (as
# TLS 1.3 clients write it, RFC 8446 section 5.1), length (512), handshake type 1.
CLIENT_HELLO_START = bytes([0x16, 0x03, 0x01, 0x02, 0x00, 0x01])
# A whole first record of that shape, 32 bytes long: the front passes a client on only
# once it holds its whole ClientHello record.
CLIENT_HELLO = bytes([0x16, 0x03, 0x01, 0x00, 0x20, 0x01]) + bytes(range(31))


class Backend:
    """A loopback TCP server standing in for zenoh: it records every connection and
    echoes what it receives; ``reply_first`` is sent on accept (a ServerHello, say);
    ``silent``: it reads and never answers (zenoh busy with other handshakes)."""

    def __init__(self, reply_first: bytes = b"", silent: bool = False,
                 port: int = 0) -> None:
        self.silent = silent
        self.sock = bind_listener("127.0.0.1", port)
        self.port = self.sock.getsockname()[1]
        self.reply_first = reply_first
        self.connections = 0
        self.received: list[bytes] = []
        self._stop = False
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        self.sock.settimeout(0.1)
        while not self._stop:
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            self.connections += 1
            threading.Thread(target=self._echo, args=(conn,), daemon=True).start()

    def _echo(self, conn: socket.socket) -> None:
        got = bytearray()
        with conn:
            if self.reply_first:
                conn.sendall(self.reply_first)
            while True:
                try:
                    data = conn.recv(1 << 16)
                except OSError:
                    break
                if not data:
                    break
                got += data
                if not self.silent:
                    conn.sendall(data)
        self.received.append(bytes(got))

    def close(self) -> None:
        self._stop = True
        self.sock.close()


@contextmanager
def front(limits: FrontLimits | None = None, reply_first: bytes = b"",
          silent: bool = False) -> Iterator[tuple[TlsFront, int, Backend]]:
    limits = limits or FrontLimits()
    backend = Backend(reply_first, silent)
    listener = bind_listener("127.0.0.1", 0)
    tf = TlsFront(listener, ("127.0.0.1", backend.port), limits)
    thread = threading.Thread(target=tf.run, daemon=True)
    thread.start()
    try:
        yield tf, listener.getsockname()[1], backend
    finally:
        tf.stop()
        thread.join(5)
        listener.close()
        backend.close()


def connect(port: int, source: str = "127.0.0.1") -> socket.socket:
    sock = socket.socket()
    sock.bind((source, 0))
    sock.connect(("127.0.0.1", port))
    sock.settimeout(5.0)
    return sock


def closed_by_front(sock: socket.socket) -> bool:
    """The front closed the connection (a FIN, or a reset when bytes were left unread)."""
    try:
        return sock.recv(10) == b""
    except ConnectionResetError:
        return True


def recv_exactly(sock: socket.socket, n: int) -> bytes:
    data = bytearray()
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        assert chunk, f"closed after {len(data)} of {n} bytes"
        data += chunk
    return bytes(data)


def test_hello_prefix_check():
    assert hello_prefix_ok(CLIENT_HELLO_START) is True
    assert hello_prefix_ok(CLIENT_HELLO) is True
    assert hello_prefix_ok(bytes([0x16, 0x03, 0x03, 0x00, 0x40, 0x01])) is True  # TLS 1.2
    assert hello_prefix_ok(b"") is None and hello_prefix_ok(b"\x16\x03") is None
    assert hello_prefix_ok(b"GET / HTTP/1.1\r\n") is False
    assert hello_prefix_ok(b"\x16\x03\x01\x02\x00\x02") is False  # a ServerHello
    assert hello_prefix_ok(b"\x16\x02") is False  # SSL 2 record version
    assert hello_prefix_ok(b"\x17") is False  # application data first


def test_plan_replaces_only_tls_endpoints_by_loopback_backends():
    plans, zenoh_listen = plan_fronts(["tls/192.0.2.10:7447?iface=eth0#x=1",
                                       "tcp/127.0.0.1:7448", "tls/[::]:7449"])
    assert [(p.host, p.port, p.suffix) for p in plans] == [
        ("192.0.2.10", 7447, "?iface=eth0#x=1"), ("::", 7449, "")]
    assert zenoh_listen[1] == "tcp/127.0.0.1:7448"
    assert zenoh_listen[0] == f"tls/127.0.0.1:{plans[0].backend_port}?iface=eth0#x=1"
    assert zenoh_listen[2] == f"tls/127.0.0.1:{plans[1].backend_port}"
    with pytest.raises(ValueError, match="HOST:PORT"):
        plan_fronts(["tls/nohost"])


def test_closed_silent_and_non_tls_connections_never_reach_the_backend():
    limits = FrontLimits(hello_timeout_s=0.3, max_pending_per_source=64)
    with front(limits) as (tf, port, backend):
        for _ in range(200):  # the connect-and-close, no byte sent
            connect(port).close()
        silent = [connect(port) for _ in range(5)]
        for payload in (b"GET / HTTP/1.0\r\n\r\n", b"\x16\x03\x01\x02\x00\x02", b"\x16\x03"):
            sock = connect(port)
            sock.sendall(payload)
            if payload != b"\x16\x03":  # refused at once; a partial prefix waits
                assert closed_by_front(sock)
            sock.close()
        c = tf.counters
        wait_until(lambda: c.dropped_closed + c.dropped_silent + c.dropped_not_tls,
                   lambda n: n == 208, timeout_s=10, what="every connection dropped")
        for sock in silent:
            assert closed_by_front(sock)  # after hello_timeout_s
            sock.close()
        assert (c.dropped_closed, c.dropped_silent, c.dropped_not_tls) == (200, 5, 3)
        assert backend.connections == 0 and c.forwarded == 0
        assert c.pending == 0 or not tf.pending


def test_forwarding_is_byte_exact_both_ways_with_half_close():
    with front() as (tf, port, backend):
        sock = connect(port)
        big = os.urandom(3 * 1024 * 1024)  # larger than every buffer on the way
        payload = CLIENT_HELLO_START + big

        def send_all() -> None:
            sock.sendall(payload)
            sock.shutdown(socket.SHUT_WR)  # the half-close reaches the backend

        sender = threading.Thread(target=send_all)
        sender.start()
        echoed = recv_exactly(sock, len(payload))
        sender.join(10)
        assert echoed == payload
        assert sock.recv(10) == b""  # the backend's close came through as well
        sock.close()
        wait_until(lambda: backend.received, timeout_s=5, what="the backend's record")
        assert backend.received == [payload] and backend.connections == 1
        wait_until(lambda: tf.counters.open_forwarded, lambda n: n == 0, timeout_s=5,
                   what="the forwarded connection closed")
        assert tf.counters.forwarded == 1


def test_pending_caps_per_source_and_in_total():
    """Per source: a connection over the cap is reset. In total: at the cap, a source
    holding fewer pending connections gets in at the expense of the oldest hello-stage
    connection of the source holding the most (issue 34), and is reset only when no
    source holds two more than it."""
    limits = FrontLimits(hello_timeout_s=5.0, max_pending_per_source=4, max_pending=6)
    with front(limits) as (tf, port, backend):
        held = []
        for k in range(1, 5):  # one by one: the first is the oldest
            held.append(connect(port, "127.0.0.2"))
            wait_until(lambda: len(tf.pending), lambda n, k=k: n == k,
                       timeout_s=5, what="127.0.0.2's connections pending")
        extra = connect(port, "127.0.0.2")  # a fifth from the same source: reset
        with pytest.raises(ConnectionResetError):
            extra.sendall(CLIENT_HELLO)
            extra.recv(10)
        extra.close()
        # another source still gets in, up to the total cap
        other = [connect(port, "127.0.0.3") for _ in range(2)]
        wait_until(lambda: len(tf.pending), lambda n: n == 6, timeout_s=5,
                   what="6 pending in total")
        # at the cap, 127.0.0.4 (none pending) takes the place of 127.0.0.2's oldest
        newcomer = connect(port, "127.0.0.4")
        assert closed_by_front(held[0])
        assert tf.counters.evicted_for_fairness == 1
        newcomer.sendall(CLIENT_HELLO)
        assert recv_exactly(newcomer, len(CLIENT_HELLO)) == CLIENT_HELLO  # forwarded
        # 3 + 2 + 1 pending: a third from 127.0.0.3 would make it as many as 127.0.0.2,
        # so nobody is evicted for it and it is reset
        over = connect(port, "127.0.0.3")
        with pytest.raises(ConnectionResetError):
            over.sendall(CLIENT_HELLO)
            over.recv(10)
        over.close()
        assert tf.counters.refused_source_cap == 1 and tf.counters.refused_total_cap == 1
        assert tf.counters.evicted_for_fairness == 1
        # one of 127.0.0.3's sends its hello: forwarded, the echo comes back
        other[0].sendall(CLIENT_HELLO)
        assert recv_exactly(other[0], len(CLIENT_HELLO)) == CLIENT_HELLO
        for sock in held + other + [newcomer]:
            sock.close()


def test_a_handshake_that_fails_bars_its_source_for_a_doubling_backoff():
    """A ClientHello, then the client gives up before its second flight: a failed
    handshake (zenoh would sleep 100 ms); the source is barred for failure_backoff_s, then
    twice that; another source is not; a completed handshake clears the count."""
    limits = FrontLimits(failure_backoff_s=0.5, failure_backoff_max_s=30.0)
    server_hello = b"\x16\x03\x03\x00\x10" + bytes(16)
    with front(limits, reply_first=server_hello) as (tf, port, backend):
        def fail_once(source: str) -> None:
            sock = connect(port, source)
            sock.sendall(CLIENT_HELLO)
            assert recv_exactly(sock, len(server_hello)) == server_hello
            sock.close()  # no second flight: the handshake failed

        fail_once("127.0.0.2")
        wait_until(lambda: tf.counters.handshakes_failed, lambda n: n == 1, timeout_s=5,
                   what="the failure counted")
        t_fail = time.monotonic()
        barred = connect(port, "127.0.0.2")
        with pytest.raises(ConnectionResetError):
            barred.sendall(CLIENT_HELLO)
            barred.recv(10)
        barred.close()
        assert tf.counters.refused_backoff == 1
        fail_once("127.0.0.3")  # another source is not barred by 127.0.0.2's failure
        # after the backoff, 127.0.0.2 may try again; a second failure doubles it
        wait_until(time.monotonic, lambda t: t > t_fail + 0.6, timeout_s=5,
                   what="the first backoff over")
        fail_once("127.0.0.2")
        wait_until(lambda: tf.counters.handshakes_failed, lambda n: n == 3, timeout_s=5,
                   what="the second failure counted")
        assert tf.barred_until["127.0.0.2"] - time.monotonic() > 0.6  # 1.0 s now
        assert tf.failures["127.0.0.2"] == 2
        # on probation after it: one pending connection of 127.0.0.2 at a time
        barred_until = tf.barred_until["127.0.0.2"]
        wait_until(time.monotonic, lambda t: t > barred_until, timeout_s=5,
                   what="the second backoff over")
        first = connect(port, "127.0.0.2")
        wait_until(lambda: len(tf.pending), lambda n: n == 1, timeout_s=5,
                   what="127.0.0.2's connection pending")
        second = connect(port, "127.0.0.2")
        assert closed_by_front(second)
        assert tf.counters.refused_backoff == 2
        first.close()
        second.close()
        # a handshake that completes (server spoke, then the client's second flight)
        # clears the source's failures
        barred_until = tf.barred_until["127.0.0.3"]
        wait_until(time.monotonic, lambda t: t > barred_until, timeout_s=5,
                   what="127.0.0.3's backoff over")
        sock = connect(port, "127.0.0.3")
        sock.sendall(CLIENT_HELLO)
        echoed = recv_exactly(sock, len(server_hello) + len(CLIENT_HELLO))
        assert echoed[:len(server_hello)] == server_hello
        sock.sendall(b"\x14\x03\x03\x00\x01\x01")  # the client's second flight
        wait_until(lambda: tf.failures.get("127.0.0.3"), lambda n: n is None, timeout_s=5,
                   what="127.0.0.3's failures cleared")
        sock.close()


def test_a_stalled_handshake_is_closed_after_handshake_timeout_s():
    limits = FrontLimits(handshake_timeout_s=0.5)
    with front(limits) as (tf, port, backend):
        sock = connect(port, "127.0.0.2")
        sock.sendall(CLIENT_HELLO)  # and then nothing (the backend says nothing)
        assert recv_exactly(sock, len(CLIENT_HELLO)) == CLIENT_HELLO  # echoed: forwarded
        t0 = time.monotonic()
        assert sock.recv(10) == b""
        assert 0.3 < time.monotonic() - t0 < 5.0
        assert tf.counters.handshake_timeouts == 1
        sock.close()


def test_a_public_port_in_use_fails_at_start_naming_the_endpoint():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        endpoint = f"tls/127.0.0.1:{taken.getsockname()[1]}"
        with pytest.raises(FrontError, match=f"listen endpoint {endpoint}: cannot bind"):
            FrontSupervisor([endpoint])


def test_bad_limits_are_refused_naming_them():
    with pytest.raises(ValueError, match="max_pending_per_source"):
        FrontLimits(max_pending_per_source=0)
    with pytest.raises(ValueError, match="hello_timeout_s"):
        FrontLimits(hello_timeout_s=float("nan"))


def test_a_partial_client_hello_is_dropped_at_the_hello_timeout_never_forwarded():
    """Issue 34: 11 bytes of a 249-byte ClientHello passed the old 6-byte check and were
    forwarded; zenoh then held each in a handshake until it failed (a 100 ms sleep of its
    accept loop each). The front now waits for the whole first record: a partial one is
    dropped at the hello timeout, a whole one sent in pieces is forwarded."""
    limits = FrontLimits(hello_timeout_s=0.5)
    record = bytes([0x16, 0x03, 0x01, 0x00, 0xF4, 0x01]) + bytes(range(243))  # 249 bytes
    with front(limits) as (tf, port, backend):
        partial = connect(port, "127.0.0.2")
        partial.sendall(record[:11])
        t0 = time.monotonic()
        assert closed_by_front(partial)
        assert 0.4 < time.monotonic() - t0 < 5.0
        partial.close()
        assert tf.counters.dropped_partial_hello == 1
        assert backend.connections == 0 and tf.counters.forwarded == 0
        whole = connect(port, "127.0.0.2")
        cuts = [0, 3, 11, 100, len(record)]
        for a, b in zip(cuts, cuts[1:], strict=False):  # pieces, each read on its own
            whole.sendall(record[a:b])
            if b < len(record):
                wait_until(lambda: [len(k.hello) for k in list(tf.pending)],
                           lambda n, b=b: n == [b], timeout_s=5, what=f"{b} bytes read")
        assert recv_exactly(whole, len(record)) == record  # forwarded whole, echoed
        whole.close()
        assert tf.counters.forwarded == 1 and backend.connections == 1
        # a record announcing more than 2^14 bytes is not TLS
        huge = connect(port, "127.0.0.3")
        huge.sendall(bytes([0x16, 0x03, 0x01, 0x40, 0x01, 0x01]))
        assert closed_by_front(huge)
        huge.close()
        assert tf.counters.dropped_not_tls == 1


def test_a_client_left_unanswered_by_zenoh_is_not_barred():
    """Issue 34: a driver whose ClientHello waited in zenoh's busy accept loop and who gave
    up was counted as a failed handshake, and its retries were barred for a doubling
    backoff. A forwarded connection that zenoh never answered and that waited at least
    UNANSWERED_GRACE_S is not held against its source; one that ends sooner still is
    (a ClientHello then a close: zenoh's 100 ms sleep)."""
    with front(FrontLimits(failure_backoff_s=5.0), silent=True) as (tf, port, backend):
        waited = connect(port, "127.0.0.2")
        waited.sendall(CLIENT_HELLO)
        wait_until(lambda: backend.connections, lambda n: n == 1, timeout_s=5,
                   what="forwarded")
        t_forwarded = time.monotonic()
        wait_until(time.monotonic, lambda t: t > t_forwarded + 1.2, timeout_s=5,
                   what="a wait longer than the grace")
        waited.close()  # the driver gives up on an unanswered handshake
        wait_until(lambda: tf.counters.handshakes_failed, lambda n: n == 1, timeout_s=5,
                   what="the handshake ended")
        assert tf.counters.handshakes_unanswered == 1
        assert "127.0.0.2" not in tf.failures
        retry = connect(port, "127.0.0.2")  # its retry is forwarded at once
        retry.sendall(CLIENT_HELLO)
        wait_until(lambda: backend.connections, lambda n: n == 2, timeout_s=5,
                   what="the retry forwarded")
        assert tf.counters.refused_backoff == 0
        retry.close()  # gave up at once, zenoh silent: a failure of 127.0.0.2's
        wait_until(lambda: tf.counters.handshakes_failed, lambda n: n == 2, timeout_s=5,
                   what="the quick close counted")
        assert tf.failures["127.0.0.2"] == 1 and tf.counters.handshakes_unanswered == 1


def test_serves_fronts_lock_zenohs_listener_to_their_key():
    """``FrontSupervisor.start`` (as ``serve`` calls it once zenoh listens) keys this
    process's listener on the backend port: a plain connection to it times out, while a
    real front process (the key handed over in a pipe) passes a client through."""
    supervisor = FrontSupervisor(["tls/127.0.0.1:0"])
    (plan,) = supervisor.plans
    backend = Backend(port=plan.backend_port)  # stands in for zenoh's own listener
    try:
        supervisor.start()
        assert supervisor.key is not None
        with socket.socket() as plain:
            plain.settimeout(0.5)
            with pytest.raises(TimeoutError):
                plain.connect(("127.0.0.1", plan.backend_port))
        client = connect(plan.listener.getsockname()[1])
        client.settimeout(60.0)  # the front process starts meanwhile (seconds when loaded)
        client.sendall(CLIENT_HELLO)
        assert recv_exactly(client, len(CLIENT_HELLO)) == CLIENT_HELLO  # through the front
        client.close()
        assert backend.connections == 1
    finally:
        supervisor.stop()
        backend.close()


def test_without_a_listener_to_lock_the_fronts_run_keyless_and_say_so(caplog):
    supervisor = FrontSupervisor(["tls/127.0.0.1:0"])  # nothing listens behind it
    try:
        supervisor.start()
        assert supervisor.key is None and len(supervisor.pids()) == 1
        assert "cannot be locked to the front" in caplog.text
    finally:
        supervisor.stop()


def test_one_handshake_per_source_in_zenoh_the_next_whole_hello_waits():
    """Each forwarded handshake that fails costs zenoh's accept loop 100 ms, so a source
    has at most ``max_handshakes_per_source`` (1) in zenoh at once: its next whole
    ClientHello waits in the front until that one is done (then it goes on), and is
    dropped if it waits ``hello_timeout_s``. Another source is not held up."""
    server_hello = b"\x16\x03\x03\x00\x10" + bytes(16)
    limits = FrontLimits(hello_timeout_s=1.0)
    with front(limits, reply_first=server_hello) as (tf, port, backend):
        first = connect(port, "127.0.0.2")
        first.sendall(CLIENT_HELLO)
        assert recv_exactly(first, len(server_hello)) == server_hello  # in zenoh
        second = connect(port, "127.0.0.2")
        second.sendall(CLIENT_HELLO)
        wait_until(lambda: len(tf.queued.get("127.0.0.2", ())), lambda n: n == 1,
                   timeout_s=5, what="127.0.0.2's second hello waiting")
        other = connect(port, "127.0.0.3")  # another source goes straight on
        other.sendall(CLIENT_HELLO)
        assert recv_exactly(other, len(server_hello)) == server_hello
        assert backend.connections == 2
        first.sendall(b"\x14\x03\x03\x00\x01\x01")  # its second flight: handshake done
        assert recv_exactly(second, len(server_hello)) == server_hello  # went on
        assert backend.connections == 3
        # the second one's handshake is not done: a third waits, and is dropped in time
        third = connect(port, "127.0.0.2")
        third.sendall(CLIENT_HELLO)
        t0 = time.monotonic()
        assert closed_by_front(third)
        assert 0.5 < time.monotonic() - t0 < 5.0
        assert tf.counters.dropped_queued == 1 and backend.connections == 3
        # one that gives up while it waits is not forwarded when its turn comes
        fourth = connect(port, "127.0.0.2")
        fourth.sendall(CLIENT_HELLO)
        wait_until(lambda: len(tf.queued.get("127.0.0.2", ())), lambda n: n == 1,
                   timeout_s=5, what="the fourth waiting")
        fourth.close()
        closed_before = tf.counters.dropped_closed
        second.sendall(b"\x14\x03\x03\x00\x01\x01")  # the second's handshake done
        wait_until(lambda: tf.counters.dropped_closed, lambda n: n == closed_before + 1,
                   timeout_s=5, what="the fourth dropped at its turn")
        assert backend.connections == 3 and tf.counters.handshakes_failed == 0
        for sock in (first, second, third, other):
            sock.close()
