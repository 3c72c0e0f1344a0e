"""An accept-filtering front for zenoh's TLS listener (issue 14; docs/security.md section 5).

Why: zenoh 1.10's TLS listener drives its handshakes from one accept loop and sleeps
100 ms after every failed one (``TLS_ACCEPT_THROTTLE_TIME``, a compile-time constant).
A plain TCP connect-and-close is such a failure, so 500 of them (no byte sent) held every
new session off for about 50 s, the authenticated driver's included. Nothing in zenoh's
configuration changes that.

What: the public TLS port is this front, a small process of its own (never in the tick
process: its work costs the 1 kHz loop nothing, not even the GIL). It accepts TCP
connections and connects one through to zenoh's real TLS listener, on a loopback-only
port, only once the client has sent its whole first TLS record, a ClientHello (record
type 0x16, version 3.x, handshake type 1, at most 2^14 bytes), within
``hello_timeout_s``. Connections that close, stay silent, send anything else or only part
of their ClientHello (issue 34's slowloris: 11 of 249 bytes, which used to be forwarded
and then failed in zenoh) never reach zenoh, so they cannot trigger its throttle. The
front does not terminate TLS: the bytes pass unchanged both ways, so server
certificates, client certificates (mutual TLS) and zenoh's own authentication work as
without it.

zenoh's listener behind the front is reachable by the front alone (issue 34): ``serve``
sets a random TCP MD5 key on zenoh's listening socket (:func:`protect_own_listener`), and
the front signs its connections to zenoh with it (``backend_key``); the kernel drops every
unsigned SYN. docs/security.md section 5.1 says why not a Unix socket.

Bounds, so a flood cannot exhaust the front either:

- ``max_pending_per_source``: connections of one source address that are *pending*
  (accepted, and either not yet past the hello check or forwarded but still in their TLS
  handshake); more are closed at accept.
- ``max_pending``: the same over all sources. At it, the oldest hello-stage connection
  of the source holding the most pending ones is closed for a newcomer whose source holds
  at least two fewer (issue 34: 300 partial hellos from 50 addresses refused the driver).
- ``max_handshakes_per_source``: forwarded connections of one source whose handshake is
  not done yet; a further whole ClientHello of it waits in the front (``queued``) until
  one is done, at most ``hello_timeout_s``.
- ``handshake_timeout_s``: a forwarded connection whose TLS handshake is not done by then
  is closed. "Done" is read off the traffic without decrypting it: the server has
  answered the ClientHello and the client has then sent its second flight (its Finished,
  in every TLS version). A client that sends a ClientHello and then stalls or sends
  garbage still reaches zenoh (and costs its accept loop one 100 ms sleep when its
  handshake fails); the per-source pending cap bounds how many one source holds at once.
- ``failure_backoff_s``: a forwarded connection that ends before its handshake is done
  (a failed handshake, which cost zenoh 100 ms) bars its source from new connections for
  this long, doubling with each further failure up to ``failure_backoff_max_s``, and
  until a handshake of it completes it may have only one pending connection at a time.
  So one source cannot keep zenoh's accept loop asleep with ClientHellos followed by
  garbage or a close: after its first failures (up to ``max_pending_per_source`` at
  once), at most one per backoff period, 100 ms each. A connection zenoh never answered
  that waited ``UNANSWERED_GRACE_S`` is zenoh's delay, not a failure of its source.

Every refusal is counted and the counters are logged at most once every
``log_every_s`` seconds, when they changed.

Forwarding is a single-threaded ``epoll`` loop, one 256 KiB buffer,
``recv_into`` then ``send`` on non-blocking sockets with ``TCP_NODELAY`` on both sides,
and back-pressure (a side whose peer cannot take more is not read until it can).

Run by ``simserver serve`` (``tls_front: auto``: one front per ``tls/`` listen endpoint,
supervised and restarted if it dies; the server holds the public listening socket and
hands it to the front, so connections queue in the kernel during a restart), or by hand
in front of any zenoh TLS listener (a router): ``simserver tls-front``.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import select
import signal
import socket
import struct
import time
from collections import defaultdict, deque
from dataclasses import asdict, dataclass, field

log = logging.getLogger("simserver.tls_front")

TLS_RECORD_HANDSHAKE = 0x16
"""TLS record content type of a handshake message (RFC 8446 section 5.1, RFC 5246 6.2.1)."""
TLS_HANDSHAKE_CLIENT_HELLO = 0x01
"""Handshake message type of a ClientHello (RFC 8446 section 4, RFC 5246 7.4)."""
HELLO_PREFIX_BYTES = 6
"""Bytes checked: record type, version (2), length (2), handshake type."""
TLS_RECORD_HEADER_BYTES = 5
"""Record type, version (2), length (2) (RFC 8446 section 5.1)."""
TLS_MAX_RECORD_BYTES = 1 << 14
"""Largest plaintext record body (RFC 8446 section 5.1: MUST NOT exceed 2^14 bytes). The
front waits for the whole first record (the ClientHello) before zenoh sees a byte."""
TCP_MD5SIG_EXT = 32
"""``setsockopt`` option of ``linux/tcp.h``: a TCP MD5 signature key (RFC 2385) for the
peers of an address prefix."""
TCP_MD5SIG_FLAG_PREFIX = 0x1
BACKEND_KEY_BYTES = 32
"""The secret of the front's connections to zenoh (TCP_MD5SIG_MAXKEYLEN is 80)."""
UNANSWERED_GRACE_S = 1.0
"""A forwarded connection that zenoh had not answered after this long and that then ended
is zenoh's delay, not its source's failure: it does not bar the source (issue 34)."""
FORWARD_BUFFER_BYTES = 256 * 1024
"""One receive buffer for every connection (the loop is single-threaded)."""
LISTEN_BACKLOG = 4096


@dataclass(frozen=True)
class FrontLimits:
    """The front's bounds (docs/security.md section 5 explains each)."""

    hello_timeout_s: float = 2.0
    handshake_timeout_s: float = 10.0
    max_pending_per_source: int = 8
    max_pending: int = 256
    max_handshakes_per_source: int = 1
    failure_backoff_s: float = 1.0
    failure_backoff_max_s: float = 30.0
    log_every_s: float = 10.0

    def __post_init__(self) -> None:
        for name in ("hello_timeout_s", "handshake_timeout_s", "failure_backoff_s",
                     "failure_backoff_max_s", "log_every_s"):
            value = getattr(self, name)
            if not 0.0 < value <= 3600.0:
                raise ValueError(f"tls front: {name} must be in (0, 3600] s, got {value}")
        for name in ("max_pending_per_source", "max_pending", "max_handshakes_per_source"):
            value = getattr(self, name)
            if not 1 <= value <= 100_000:
                raise ValueError(f"tls front: {name} must be in 1-100000, got {value}")


@dataclass
class FrontCounters:
    """What the front did; the ``dropped_*`` and ``refused_*`` never reached zenoh."""

    accepted: int = 0
    forwarded: int = 0
    dropped_closed: int = 0  # closed (or reset) before sending anything
    dropped_silent: int = 0  # sent nothing within hello_timeout_s
    dropped_partial_hello: int = 0  # began a ClientHello, not whole within hello_timeout_s
    dropped_not_tls: int = 0  # first bytes are not a TLS ClientHello
    dropped_queued: int = 0  # a whole ClientHello that waited hello_timeout_s behind its
    # source's max_handshakes_per_source handshakes in zenoh
    refused_source_cap: int = 0  # max_pending_per_source reached at accept
    refused_total_cap: int = 0  # max_pending reached at accept, no fair eviction possible
    evicted_for_fairness: int = 0  # a hello-stage connection of the source holding the
    # most pending ones, closed at max_pending so that a source holding fewer gets in
    refused_backoff: int = 0  # the source's last forwarded handshake failed: barred a while
    handshakes_failed: int = 0  # forwarded, ended before the TLS handshake was done
    handshakes_unanswered: int = 0  # of those, zenoh never answered the ClientHello and
    # the connection had waited UNANSWERED_GRACE_S: zenoh's delay, the source not barred
    handshake_timeouts: int = 0  # forwarded, TLS handshake not done in time: closed
    backend_unreachable: int = 0  # zenoh's listener refused the forwarded connection
    open_forwarded: int = 0  # forwarded connections open now
    pending: int = 0  # pending connections now


def hello_prefix_ok(data: bytes) -> bool | None:
    """Whether ``data`` starts like a TLS ClientHello: True, False, or None (too short to
    tell yet, and no byte so far contradicts it)."""
    checks = ((0, lambda b: b == TLS_RECORD_HANDSHAKE),
              (1, lambda b: b == 0x03),            # TLS 1.x / SSL 3 record version major
              (2, lambda b: b <= 0x04),            # minor: 0 (SSL 3) .. 4 (TLS 1.3)
              (5, lambda b: b == TLS_HANDSHAKE_CLIENT_HELLO))
    for index, ok in checks:
        if index >= len(data):
            return None
        if not ok(data[index]):
            return False
    return True


def hello_record_bytes(data: bytes | bytearray) -> int:
    """The length of the TLS record ``data`` starts with, its 5-byte header included
    (``data`` holds the header at least)."""
    return TLS_RECORD_HEADER_BYTES + int.from_bytes(data[3:5], "big")


def parse_host_port(text: str) -> tuple[str, int]:
    """``HOST:PORT`` or ``[V6]:PORT`` (the address part of a zenoh endpoint)."""
    host, colon, port = text.rpartition(":")
    if not colon or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"expected HOST:PORT with a port in 0-65535, got {text!r}")
    return host.strip("[]"), int(port)


def bind_listener(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host:port`` (port 0: any free one)."""
    infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    family, stype, proto_num, _, addr = infos[0]
    sock = socket.socket(family, stype, proto_num)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(addr)
        sock.listen(LISTEN_BACKLOG)
    except OSError:
        sock.close()
        raise
    return sock


# ============================================================================ the backend's key


def set_md5_key(sock: socket.socket, key: bytes, network: str = "0.0.0.0",
                prefix_len: int = 0) -> None:
    """Sign (and require signed) every TCP segment between ``sock`` and the IPv4 peers of
    ``network/prefix_len`` with ``key`` (TCP MD5 signature, RFC 2385; Linux since 2.6.20,
    prefixes since 4.13).

    On a listening socket the kernel then drops every SYN from those peers that does not
    carry a valid signature, before any ``accept``: a process without the key cannot even
    open a connection (it sees a connect timeout). The connections it accepts inherit the
    key. Raises ``OSError`` where the kernel lacks ``CONFIG_TCP_MD5SIG``.
    """
    # struct tcp_md5sig: sockaddr_storage (128), flags, prefixlen, keylen, ifindex, key[80]
    addr = struct.pack("=H2s4s", socket.AF_INET, b"", socket.inet_aton(network))
    option = (addr.ljust(128, b"\0")
              + struct.pack("=BBHi", TCP_MD5SIG_FLAG_PREFIX, prefix_len, len(key), 0)
              + key.ljust(80, b"\0"))
    sock.setsockopt(socket.IPPROTO_TCP, TCP_MD5SIG_EXT, option)


def own_listening_fds(host: str, port: int) -> list[int]:
    """File descriptors of this process's TCP sockets listening on IPv4 ``host:port``
    (zenoh's own listener: it binds it itself and hands it to nobody)."""
    want = f"{socket.inet_aton(host)[::-1].hex().upper()}:{port:04X}"
    inodes = set()
    with open("/proc/self/net/tcp", encoding="ascii") as table:
        next(table)
        for line in table:
            fields = line.split()
            if fields[1] == want and fields[3] == "0A":  # 0A: TCP_LISTEN
                inodes.add(f"socket:[{fields[9]}]")
    fds = []
    for name in os.listdir("/proc/self/fd"):
        try:
            if os.readlink(f"/proc/self/fd/{name}") in inodes:
                fds.append(int(name))
        except OSError:
            continue  # closed meanwhile
    return fds


def protect_own_listener(host: str, port: int, key: bytes) -> int:
    """Require ``key`` of every connection to this process's listener on ``host:port``
    (zenoh's TLS listener behind a front); returns how many listening sockets got it.

    Raises
    ------
    OSError
        No such listener, or the kernel refuses TCP MD5 signatures.
    """
    fds = own_listening_fds(host, port)
    if not fds:
        raise OSError(errno.ENOENT, f"no listening socket of this process on {host}:{port}")
    for fd in fds:
        with socket.socket(fileno=os.dup(fd)) as dup:  # closing the dup leaves zenoh's
            set_md5_key(dup, key)
    return len(fds)


# ============================================================================ endpoints


@dataclass
class FrontPlan:
    """One fronted zenoh TLS endpoint: the public one and zenoh's loopback one."""

    public: str  # as configured, e.g. tls/192.0.2.10:7447?x=y#z
    host: str
    port: int
    backend_port: int
    suffix: str = ""  # the endpoint's ?metadata / #config, kept on zenoh's endpoint
    listener: socket.socket | None = field(default=None, repr=False)

    @property
    def backend(self) -> str:
        """zenoh's own endpoint: loopback only, the public endpoint's TLS settings."""
        return f"tls/127.0.0.1:{self.backend_port}{self.suffix}"

    @property
    def public_bound(self) -> str:
        """The public endpoint with the port really bound (port 0 resolved)."""
        port = self.listener.getsockname()[1] if self.listener is not None else self.port
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"tls/{host}:{port}{self.suffix}"


def plan_fronts(listen: list[str]) -> tuple[list[FrontPlan], list[str]]:
    """The ``tls/`` endpoints of ``listen`` to front, each with a loopback port for zenoh,
    and the listen list zenoh gets (each fronted endpoint replaced by its backend)."""
    plans, zenoh_listen = [], []
    for endpoint in listen:
        if not endpoint.startswith("tls/"):
            zenoh_listen.append(endpoint)
            continue
        rest = endpoint[len("tls/"):]
        cut = min((i for i in (rest.find("?"), rest.find("#")) if i >= 0), default=len(rest))
        host, port = parse_host_port(rest[:cut])
        plan = FrontPlan(public=endpoint, host=host, port=port,
                         backend_port=_free_loopback_port(), suffix=rest[cut:])
        plans.append(plan)
        zenoh_listen.append(plan.backend)
    return plans, zenoh_listen


def _free_loopback_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# ============================================================================ the loop


READ = select.EPOLLIN
WRITE = select.EPOLLOUT


class _Poller:
    """``select.epoll`` with each file descriptor's data and interest kept beside it (the
    ``selectors`` module does the same at several times the cost per event)."""

    def __init__(self) -> None:
        self.epoll = select.epoll()
        self.data: dict[int, object] = {}
        self.events: dict[int, int] = {}

    def set(self, sock: socket.socket, events: int, data: object) -> None:
        """Watch ``sock`` for ``events`` (0: not at all)."""
        fd = sock.fileno()
        now = self.events.get(fd, 0)
        if events == now:
            return
        if events == 0:
            self.epoll.unregister(fd)
            del self.events[fd], self.data[fd]
            return
        if now == 0:
            self.epoll.register(fd, events)
        else:
            self.epoll.modify(fd, events)
        self.events[fd] = events
        self.data[fd] = data

    def forget(self, sock: socket.socket) -> None:
        """Stop watching ``sock`` (before it is closed)."""
        fd = sock.fileno()
        if fd >= 0 and fd in self.events:
            self.set(sock, 0, None)


class _Conn:
    """One client connection: hello stage, then forwarding to zenoh."""

    __slots__ = ("client", "backend", "source", "t_accept", "t_forward", "t_queued", "hello",
                 "stage", "pending", "handshaking", "server_spoke", "to_client", "to_backend",
                 "eof_client", "eof_backend", "shut_client", "shut_backend")

    def __init__(self, client: socket.socket, source: str, now: float) -> None:
        self.client = client
        self.backend: socket.socket | None = None
        self.source = source
        self.t_accept = now
        self.t_forward = 0.0  # when the connection to zenoh began
        self.t_queued = 0.0  # when it began to wait for its source's handshake in zenoh
        self.hello = bytearray()
        self.stage = "hello"  # hello -> [queued ->] connecting -> forward -> closed
        self.pending = True
        self.handshaking = False  # connecting, or forwarded with its handshake not done
        self.server_spoke = False
        self.to_client = bytearray()  # bytes waiting to be sent to the client
        self.to_backend = bytearray()
        self.eof_client = self.eof_backend = False
        self.shut_client = self.shut_backend = False


class TlsFront:
    """The accept-filtering front: ``run()`` until SIGTERM/SIGINT or the parent dies.

    Parameters
    ----------
    listener : socket.socket
        The public listening socket (bound and listening).
    backend : tuple of (str, int)
        zenoh's TLS listener, on loopback.
    limits : FrontLimits
    parent_pid : int, optional
        Exit when this process is no longer the parent (``simserver serve`` died).
    backend_key : bytes, optional
        The TCP MD5 key zenoh's listener requires (``FrontSupervisor`` sets it there): every
        connection to zenoh is signed with it.
    """

    def __init__(self, listener: socket.socket, backend: tuple[str, int],
                 limits: FrontLimits = FrontLimits(), parent_pid: int | None = None,
                 backend_key: bytes | None = None) -> None:
        self.listener = listener
        self.backend = backend
        self.backend_key = backend_key
        self.limits = limits
        self.parent_pid = parent_pid
        self.counters = FrontCounters()
        self.poller = _Poller()
        self.buffer = bytearray(FORWARD_BUFFER_BYTES)
        self.view = memoryview(self.buffer)
        self.pending_by_source: dict[str, set[_Conn]] = defaultdict(set)
        self.pending: set[_Conn] = set()
        self.handshaking: dict[str, int] = {}  # source -> its handshakes in zenoh now
        self.queued: dict[str, deque[_Conn]] = {}  # source -> whole hellos waiting
        self.failures: dict[str, int] = {}  # source -> failed handshakes in a row
        self.barred_until: dict[str, float] = {}  # source -> end of its backoff
        self.running = False
        self._logged = asdict(self.counters)
        self._t_log = 0.0

    # ------------------------------------------------------------------ run
    def stop(self, *_: object) -> None:
        self.running = False

    def run(self) -> FrontCounters:
        self.listener.setblocking(False)
        poller = self.poller
        poller.set(self.listener, READ, None)
        listen_fd = self.listener.fileno()
        data = poller.data
        self.running = True
        t_parent = t_expire = time.monotonic()
        while self.running:
            try:
                ready = poller.epoll.poll(self._select_timeout())
            except InterruptedError:
                ready = ()
            for fd, mask in ready:
                if fd == listen_fd:
                    self._accept()
                    continue
                item = data.get(fd)
                if item is not None:  # (None: closed by an earlier event of this batch)
                    self._event(item[0], item[1], mask)
            now = time.monotonic()
            if now - t_expire >= 0.05:
                t_expire = now
                self._expire(now)
            if now - t_parent >= 1.0:
                t_parent = now
                if self.parent_pid is not None and os.getppid() != self.parent_pid:
                    log.warning("tls front: the server (pid %d) is gone; exiting",
                                self.parent_pid)
                    break
            if now - self._t_log >= self.limits.log_every_s:
                self._log_counters(now)
        self._log_counters(time.monotonic(), force=True)
        poller.epoll.close()
        return self.counters

    def _select_timeout(self) -> float:
        if not self.pending:
            return 1.0
        return 0.05  # deadlines are checked at least this often while any is pending

    # ------------------------------------------------------------------ accept
    def _accept(self) -> None:
        lim, c = self.limits, self.counters
        for _ in range(256):  # a burst: take what is queued, then serve the others
            try:
                sock, addr = self.listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # EMFILE and the like: the kernel keeps the backlog
                log.warning("tls front: accept failed: %s", exc)
                return
            c.accepted += 1
            source = addr[0]
            if source in self.barred_until:
                if time.monotonic() < self.barred_until[source]:
                    c.refused_backoff += 1
                    _abort(sock)
                    continue
                del self.barred_until[source]
            if source in self.failures and source in self.pending_by_source:
                # on probation after a failed handshake: one pending connection at a time,
                # so a backoff's end lets one more failure through, not a cap's worth
                self._reap(source)
                if source in self.pending_by_source:
                    c.refused_backoff += 1
                    _abort(sock)
                    continue
            if len(self.pending_by_source.get(source, ())) >= lim.max_pending_per_source:
                self._reap(source)  # connections that ended meanwhile free their slots
                if len(self.pending_by_source.get(source, ())) >= \
                        lim.max_pending_per_source:
                    c.refused_source_cap += 1
                    _abort(sock)
                    continue
            if len(self.pending) >= lim.max_pending and not self._evict_for(source):
                c.refused_total_cap += 1
                _abort(sock)
                continue
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn = _Conn(sock, source, time.monotonic())
            self.pending.add(conn)
            self.pending_by_source[source].add(conn)
            self.poller.set(sock, READ, (conn, "client"))
            self._event(conn, "client", READ)  # a burst's connect-and-
            # close ends here at once, and a ClientHello already queued goes on

    def _evict_for(self, source: str) -> bool:
        """At ``max_pending``: make room for a connection of ``source`` by closing the
        oldest hello-stage connection of the source that holds the most pending ones, if
        that source holds at least two more than ``source`` (issue 34: 300 partial
        ClientHellos held from 50 other addresses filled the cap and refused the driver
        on every try). A hello-stage connection has not reached zenoh, so closing it costs
        zenoh nothing; the flood's sources share the cap among themselves, and a source
        with few pending connections (the driver's) always gets a slot while some source
        holds several. Returns whether a connection was closed."""
        mine = len(self.pending_by_source.get(source, ()))
        victim = None
        for conns in sorted(self.pending_by_source.values(), key=len, reverse=True):
            if len(conns) < mine + 2:
                break
            hello = [k for k in conns if k.stage in ("hello", "queued")]
            if hello:  # (forwarded ones are in zenoh's handshake: closing one costs it)
                victim = min(hello, key=lambda k: k.t_accept)
                break
        if victim is None:
            return False
        self.counters.evicted_for_fairness += 1
        self._close(victim)
        return True

    def _reap(self, source: str) -> None:
        """Read the hello-stage connections of ``source`` now: those closed meanwhile
        (a connect-and-close burst queues faster than events are served) are dropped."""
        for conn in [k for k in self.pending_by_source[source] if k.stage == "hello"]:
            self._event(conn, "client", READ)

    def _release(self, conn: _Conn) -> None:
        """The connection is no longer pending (handshake done, or closed)."""
        if conn.pending:
            conn.pending = False
            self.pending.discard(conn)
            mine = self.pending_by_source[conn.source]
            mine.discard(conn)
            if not mine:
                del self.pending_by_source[conn.source]

    # ------------------------------------------------------------------ events
    def _event(self, conn: _Conn, side: str, mask: int) -> None:
        try:
            if conn.stage == "hello":
                self._read_hello(conn)
            elif conn.stage == "connecting":
                self._connected(conn)
            elif conn.stage == "forward":
                if mask & WRITE:
                    self._flush(conn, side)
                if mask & ~WRITE and conn.stage == "forward":  # readable, hang-up, error
                    self._pump(conn, side)
        except OSError:
            self._close(conn)

    def _read_hello(self, conn: _Conn) -> None:
        """Read the client's first TLS record, the ClientHello, whole: zenoh sees nothing
        of a client that has not sent it all within ``hello_timeout_s`` (issue 34: with
        only its first 6 bytes checked, 300 partial ClientHellos of 11 of 249 bytes were
        forwarded, each held one of zenoh's handshakes until it failed, and each failure
        then put zenoh's accept loop to sleep for 100 ms)."""
        if conn.stage != "hello":
            return
        hello = conn.hello
        need = (hello_record_bytes(hello) if len(hello) >= TLS_RECORD_HEADER_BYTES
                else TLS_RECORD_HEADER_BYTES)
        try:
            data = conn.client.recv(need - len(hello))
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            if hello:  # a partial ClientHello, then the end: not a TLS client
                self.counters.dropped_not_tls += 1
            else:
                self.counters.dropped_closed += 1
            self._close(conn)
            return
        hello += data
        verdict = hello_prefix_ok(hello)
        if verdict is None and len(hello) < HELLO_PREFIX_BYTES:
            return
        if verdict is False or not 0 < hello_record_bytes(hello) - TLS_RECORD_HEADER_BYTES \
                <= TLS_MAX_RECORD_BYTES:
            self.counters.dropped_not_tls += 1
            self._close(conn)
        elif len(hello) < hello_record_bytes(hello):
            return  # more of the record to come (or the hello timeout)
        elif time.monotonic() - conn.t_accept > self.limits.hello_timeout_s:
            # whole, but late (the loop was busy): the deadline holds all the same
            self.counters.dropped_partial_hello += 1
            self._close(conn)
        else:
            self._forward_or_queue(conn)

    def _forward_or_queue(self, conn: _Conn) -> None:
        """Forward a whole ClientHello, or let it wait while its source has
        ``max_handshakes_per_source`` handshakes in zenoh already. Every forwarded
        handshake that fails costs zenoh's accept loop 100 ms, so this bounds what one
        source's ClientHellos followed by a stall cost zenoh at once (8 per source
        before: 50 sources stalling 6 each kept the driver out 13.9 s after the attack)."""
        source = conn.source
        if self.handshaking.get(source, 0) >= self.limits.max_handshakes_per_source:
            conn.stage = "queued"
            conn.t_queued = time.monotonic()
            self.poller.set(conn.client, 0, None)  # its next bytes wait in the kernel
            self.queued.setdefault(source, deque()).append(conn)
        else:
            self._connect_backend(conn)

    def _handshake_over(self, conn: _Conn) -> None:
        """``conn``'s handshake in zenoh is done or ended: its source's next waiting
        ClientHello goes on (or is refused if the source is barred now)."""
        if not conn.handshaking:
            return
        conn.handshaking = False
        source = conn.source
        left = self.handshaking[source] - 1
        if left:
            self.handshaking[source] = left
        else:
            del self.handshaking[source]
        waiting = self.queued.get(source)
        while waiting and self.handshaking.get(source, 0) < \
                self.limits.max_handshakes_per_source:
            nxt = waiting[0]  # (closing it takes it off the queue)
            if time.monotonic() < self.barred_until.get(source, 0.0):
                self.counters.refused_backoff += 1
                self._close(nxt)
            elif not _still_open(nxt.client):  # gave up waiting: zenoh need not know
                self.counters.dropped_closed += 1
                self._close(nxt)
            else:
                waiting.popleft()
                if not waiting:
                    del self.queued[source]
                self._connect_backend(nxt)

    def _connect_backend(self, conn: _Conn) -> None:
        backend = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        backend.setblocking(False)
        backend.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        if self.backend_key is not None:
            set_md5_key(backend, self.backend_key, self.backend[0], 32)
        conn.backend = backend
        conn.to_backend += conn.hello
        conn.stage = "connecting"
        conn.t_forward = time.monotonic()
        conn.handshaking = True
        self.handshaking[conn.source] = self.handshaking.get(conn.source, 0) + 1
        self.poller.set(conn.client, 0, None)  # not read until zenoh's side is connected
        err = backend.connect_ex(self.backend)
        if err in (0, errno.EINPROGRESS):
            self.poller.set(backend, WRITE, (conn, "backend"))
        else:
            self.counters.backend_unreachable += 1
            self._close(conn)

    def _connected(self, conn: _Conn) -> None:
        err = conn.backend.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
        if err != 0:
            self.counters.backend_unreachable += 1
            self._close(conn)
            return
        conn.stage = "forward"
        self.counters.forwarded += 1
        self.counters.open_forwarded += 1
        self.poller.set(conn.client, READ, (conn, "client"))
        self._flush(conn, "backend")  # the ClientHello bytes read so far

    def _interest(self, conn: _Conn, side: str) -> None:
        """Read a side while its peer's outgoing buffer is empty; write while its own
        outgoing buffer holds bytes."""
        if side == "client":
            sock, out, peer_out, eof = conn.client, conn.to_client, conn.to_backend, \
                conn.eof_client
        else:
            sock, out, peer_out, eof = conn.backend, conn.to_backend, conn.to_client, \
                conn.eof_backend
        self.poller.set(sock, (READ if not eof and not peer_out else 0)
                        | (WRITE if out else 0), (conn, side))

    def _pump(self, conn: _Conn, side: str) -> None:
        """Bytes readable on ``side``: pass them to the other side."""
        src = conn.client if side == "client" else conn.backend
        try:
            n = src.recv_into(self.buffer)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            n = 0
        if n == 0:
            if side == "client":
                conn.eof_client = True
            else:
                conn.eof_backend = True
        else:
            if side == "backend":
                conn.server_spoke = True
            elif conn.server_spoke and conn.pending:
                self._release(conn)  # the client's second flight: the handshake is done
                self.failures.pop(conn.source, None)
                self._handshake_over(conn)
            out = conn.to_backend if side == "client" else conn.to_client
            dst = conn.backend if side == "client" else conn.client
            if out:
                out += self.view[:n]
            else:
                try:
                    sent = dst.send(self.view[:n])
                except (BlockingIOError, InterruptedError):
                    sent = 0
                if sent == n:
                    return  # the usual case: all passed on, nothing else changes
                out += self.view[sent:n]
        self._after_io(conn)

    def _flush(self, conn: _Conn, side: str) -> None:
        """``side`` writable: send what waits for it."""
        out = conn.to_client if side == "client" else conn.to_backend
        sock = conn.client if side == "client" else conn.backend
        if out:
            try:
                sent = sock.send(out)
            except (BlockingIOError, InterruptedError):
                sent = 0
            del out[:sent]
        self._after_io(conn)

    def _after_io(self, conn: _Conn) -> None:
        """Half-closes once a side's EOF is passed on; closes when both are; updates the
        event interests."""
        if conn.eof_client and not conn.to_backend and not conn.shut_backend:
            conn.shut_backend = True
            _shutdown_write(conn.backend)
        if conn.eof_backend and not conn.to_client and not conn.shut_client:
            conn.shut_client = True
            _shutdown_write(conn.client)
        if (conn.shut_client and conn.shut_backend) or \
                (conn.eof_backend and conn.pending and not conn.to_client):
            # both ends passed on, or zenoh ended a handshake (its alert passed on)
            self._close(conn)
            return
        self._interest(conn, "client")
        self._interest(conn, "backend")

    # ------------------------------------------------------------------ deadlines
    def _expire(self, now: float) -> None:
        lim = self.limits
        if len(self.barred_until) > 4 * lim.max_pending:  # forget ended backoffs
            for source in [s for s, t in self.barred_until.items() if t <= now]:
                del self.barred_until[source]
        if len(self.failures) > 64 * lim.max_pending:
            self.failures.clear()  # bounded memory; a source's next failure starts at 1 s
        for conn in list(self.pending):
            if conn.stage == "hello":
                if now - conn.t_accept > lim.hello_timeout_s:
                    self._read_hello(conn)  # what arrived meanwhile: a close, say
                    if conn.stage == "hello":  # not whole in time: never forwarded
                        if conn.hello:
                            self.counters.dropped_partial_hello += 1
                        else:
                            self.counters.dropped_silent += 1
                        self._close(conn)
            elif conn.stage == "queued":
                if now - conn.t_queued > lim.hello_timeout_s:
                    self.counters.dropped_queued += 1
                    self._close(conn)
            elif conn.stage == "connecting":
                if now - conn.t_forward > lim.hello_timeout_s:
                    self.counters.backend_unreachable += 1
                    self._close(conn)
            elif now - conn.t_forward > lim.handshake_timeout_s:
                self.counters.handshake_timeouts += 1
                self._close(conn)

    def _close(self, conn: _Conn) -> None:
        if conn.stage == "closed":
            return
        waiting = self.queued.get(conn.source)
        if conn.stage == "queued" and waiting and conn in waiting:
            waiting.remove(conn)
            if not waiting:
                del self.queued[conn.source]
        if conn.stage == "forward":
            self.counters.open_forwarded -= 1
            if conn.pending:  # the handshake failed (in zenoh, or the client gave up)
                self.counters.handshakes_failed += 1
                if not conn.server_spoke and \
                        time.monotonic() - conn.t_forward >= UNANSWERED_GRACE_S:
                    # zenoh never answered a client that waited for it: zenoh was busy
                    # (its queue, its 100 ms sleeps), the client is not to blame; barring
                    # it would let a driver's own retries lengthen its lock-out (issue 34)
                    self.counters.handshakes_unanswered += 1
                    n = 0
                else:
                    n = self.failures.get(conn.source, 0) + 1
            else:
                n = 0
            if n:
                self.failures[conn.source] = n
                lim = self.limits
                self.barred_until[conn.source] = time.monotonic() + min(
                    lim.failure_backoff_s * 2.0 ** min(n - 1, 30), lim.failure_backoff_max_s)
        conn.stage = "closed"
        self._release(conn)
        for sock in (conn.client, conn.backend):
            if sock is None:
                continue
            self.poller.forget(sock)
            sock.close()
        self._handshake_over(conn)  # after the backoff above: a barred source's next waits

    # ------------------------------------------------------------------ log
    def _log_counters(self, now: float, force: bool = False) -> None:
        """One line when the counters changed, at most once every ``log_every_s``."""
        self._t_log = now
        c = self.counters
        c.pending = len(self.pending)
        current = asdict(c)
        if current == self._logged and not force:
            return
        self._logged = current
        dropped = (c.dropped_closed + c.dropped_silent + c.dropped_not_tls
                   + c.refused_source_cap + c.refused_total_cap + c.refused_backoff)
        log.log(logging.WARNING if dropped and not force else logging.INFO,
                "tls front: %d kept from zenoh so far; counters %s", dropped,
                json.dumps(current))


def _abort(sock: socket.socket) -> None:
    """Close at once with a reset: no TIME_WAIT kept for a refused connection."""
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
    except OSError:
        pass
    sock.close()


def _still_open(sock: socket.socket) -> bool:
    """Whether the client has not closed (or reset) its end; reads nothing."""
    try:
        return sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) != b""
    except (BlockingIOError, InterruptedError):
        return True
    except OSError:
        return False


def _shutdown_write(sock: socket.socket) -> None:
    try:
        sock.shutdown(socket.SHUT_WR)
    except OSError:
        pass


# ============================================================================ process


def front_command(plan: FrontPlan, fd: int, limits: FrontLimits, parent_pid: int,
                  python: str, key_fd: int | None = None) -> list[str]:
    """The command line of a front process serving ``plan`` on the inherited socket
    ``fd`` (``simserver tls-front --listen-fd``), reading zenoh's key from the inherited
    pipe ``key_fd`` (never from its command line, which every local user can read)."""
    key = ["--backend-key-fd", str(key_fd)] if key_fd is not None else []
    return [python, "-m", "simserver", "tls-front", "--listen-fd", str(fd),
            "--backend", f"127.0.0.1:{plan.backend_port}", "--parent-pid", str(parent_pid),
            *key, *limit_args(limits)]


def limit_args(limits: FrontLimits) -> list[str]:
    """``FrontLimits`` as ``simserver tls-front`` options."""
    args = []
    for name, value in asdict(limits).items():
        args += [f"--{name.replace('_', '-')}", str(value)]
    return args


def serve(listener: socket.socket, backend: tuple[str, int], limits: FrontLimits,
          parent_pid: int | None = None, backend_key: bytes | None = None) -> FrontCounters:
    """Run a front in this process until SIGTERM/SIGINT (``simserver tls-front``)."""
    front = TlsFront(listener, backend, limits, parent_pid, backend_key)
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, front.stop)
    host, port = listener.getsockname()[:2]
    print(f"tls-front: ready on {host}:{port} -> {backend[0]}:{backend[1]}", flush=True)
    return front.run()


class FrontError(RuntimeError):
    """A public TLS endpoint cannot be fronted (its address cannot be bound)."""


class FrontSupervisor:
    """The fronts of ``simserver serve``: one process per fronted ``tls/`` endpoint.

    The server binds each public socket itself (a port in use fails at start, naming the
    endpoint) and hands it to its front; a watcher thread per front restarts a front that
    dies (at most once a second), so the public port never closes while the server runs:
    during a restart, connections wait in the kernel's accept queue.

    zenoh's listeners behind the fronts are reachable by the fronts alone (issue 34: a
    burst of 500 plain connect-and-close on zenoh's loopback port, visible to any local
    process, kept the driver out for 59 s). ``start()``, called in the process that
    opened the zenoh session once it listens, puts a random TCP MD5 key
    (:func:`set_md5_key`) on zenoh's listening sockets; the kernel then drops every SYN
    that is not signed with it, so no connection without the key ever reaches zenoh's
    accept loop. Each front gets the key through an inherited pipe and signs its
    connections to zenoh with it.

    Parameters
    ----------
    listen : list of str
        The server's effective listen endpoints.
    limits : FrontLimits
    """

    RESTART_INTERVAL_S = 1.0

    def __init__(self, listen: list[str], limits: FrontLimits = FrontLimits()) -> None:
        import sys
        import threading

        self.limits = limits
        self.plans, self.zenoh_listen = plan_fronts(listen)
        self.public_listen = list(listen)
        self.procs: list = [None] * len(self.plans)
        self.restarts = 0
        self.running = True
        self._priority: int | None = None
        self._lock = threading.Lock()
        self._python = sys.executable
        self._threading = threading
        self.key: bytes | None = os.urandom(BACKEND_KEY_BYTES)
        try:
            for plan in self.plans:
                try:
                    plan.listener = bind_listener(plan.host, plan.port)
                except OSError as exc:
                    raise FrontError(f"listen endpoint {plan.public}: cannot bind "
                                     f"{plan.host}:{plan.port} ({exc.strerror or exc})") \
                        from None
            self.public_listen = [next((p.public_bound for p in self.plans
                                        if p.public == ep), ep) for ep in listen]
        except BaseException:
            self.stop()
            raise

    def start(self) -> None:
        """Lock zenoh's listeners (this process's, listening by now) to the key, then
        start the fronts. Until then clients wait in the public sockets' accept queues.

        Where the kernel refuses TCP MD5 keys (no ``CONFIG_TCP_MD5SIG``), the fronts run
        without one and an error says that zenoh's loopback port is open to local
        processes."""
        try:
            for plan in self.plans:
                protect_own_listener("127.0.0.1", plan.backend_port, self.key)
        except OSError as exc:
            log.error("tls front: zenoh's loopback listener cannot be locked to the front "
                      "(%s): any local process can reach it and hold new sessions off "
                      "(docs/security.md section 5.1)", exc.strerror or exc)
            for plan in self.plans:  # the sockets already keyed: undone with an empty key
                for fd in own_listening_fds("127.0.0.1", plan.backend_port):
                    with socket.socket(fileno=os.dup(fd)) as dup, \
                            contextlib.suppress(OSError):
                        set_md5_key(dup, b"")
            self.key = None
        try:
            for i in range(len(self.plans)):
                self._spawn(i)
                self._threading.Thread(target=self._watch, args=(i,),
                                       name=f"tls-front-{i}", daemon=True).start()
        except BaseException:
            self.stop()
            raise

    def _spawn(self, i: int) -> None:
        import subprocess

        plan = self.plans[i]
        fd = plan.listener.fileno()
        key_fd = None
        if self.key is not None:  # a pipe holds the key until the front reads it
            key_fd, write_fd = os.pipe()
            os.write(write_fd, self.key)
            os.close(write_fd)
        try:
            proc = subprocess.Popen(
                front_command(plan, fd, self.limits, os.getpid(), self._python, key_fd),
                pass_fds=(fd,) if key_fd is None else (fd, key_fd))
        finally:
            if key_fd is not None:
                os.close(key_fd)
        self.procs[i] = proc
        log.info("tls front (pid %d): %s -> zenoh on %s", proc.pid, plan.public_bound,
                 plan.backend)
        if self._priority is not None:
            self._promote(proc.pid)

    def _watch(self, i: int) -> None:
        while True:
            proc = self.procs[i]
            code = proc.wait()
            t_died = time.monotonic()
            with self._lock:
                if not self.running:
                    return
                self.restarts += 1
                log.error("tls front (pid %d) for %s ended with exit code %d; restarting "
                          "it (the public port stays open meanwhile)", proc.pid,
                          self.plans[i].public_bound, code)
            time.sleep(max(0.0, self.RESTART_INTERVAL_S - (time.monotonic() - t_died)))
            with self._lock:  # (a crash loop is paced by the interval above)
                if not self.running:
                    return
                self._spawn(i)

    def set_priority(self, priority: int) -> None:
        """Give every front (and each restarted one) SCHED_FIFO at ``priority``, as the
        server's zenoh threads: the front is on the path of every command and state."""
        with self._lock:
            self._priority = priority
            for proc in self.procs:
                if proc is not None:
                    self._promote(proc.pid)

    def _promote(self, pid: int) -> None:
        try:
            os.sched_setscheduler(pid, os.SCHED_FIFO, os.sched_param(self._priority))
        except (OSError, AttributeError) as exc:
            log.warning("tls front (pid %d): SCHED_FIFO refused (%s); normal priority",
                        pid, exc)

    def pids(self) -> list[int]:
        """The fronts' process ids (tests, diagnostics)."""
        return [p.pid for p in self.procs if p is not None]

    def stop(self) -> None:
        """Terminate the fronts and close the public sockets."""
        import subprocess

        with self._lock:
            self.running = False
        for proc in self.procs:
            if proc is None:
                continue
            proc.terminate()
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for plan in self.plans:
            if plan.listener is not None:
                plan.listener.close()


# ============================================================================ command line


def add_arguments(parser: object) -> None:
    """The options of ``simserver tls-front``."""
    import argparse

    assert isinstance(parser, argparse.ArgumentParser)
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--listen", metavar="HOST:PORT",
                       help="the public address to accept TLS clients on")
    where.add_argument("--listen-fd", type=int, metavar="FD",
                       help="an inherited listening socket instead (simserver serve)")
    parser.add_argument("--backend", required=True, metavar="HOST:PORT",
                        help="zenoh's TLS listener (loopback)")
    parser.add_argument("--parent-pid", type=int, default=None, metavar="PID",
                        help="exit when this process is no longer the parent")
    parser.add_argument("--backend-key-fd", type=int, default=None, metavar="FD",
                        help="an inherited pipe holding the TCP MD5 key zenoh's listener "
                             "requires (simserver serve)")
    defaults = FrontLimits()
    for name, value in asdict(defaults).items():
        parser.add_argument(f"--{name.replace('_', '-')}", type=type(value), default=value,
                            metavar="N", help=f"default {value}")
    parser.add_argument("--log-level", default="INFO", help="logging level (default INFO)")


def main(args: object) -> int:
    """``simserver tls-front``: run one front until SIGTERM/SIGINT.

    Raises
    ------
    ValueError, OSError
        A bad option, or the address cannot be bound.
    """
    logging.basicConfig(level=str(args.log_level).upper(),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    limits = FrontLimits(**{name: getattr(args, name) for name in asdict(FrontLimits())})
    backend = parse_host_port(args.backend)
    key = None
    if args.backend_key_fd is not None:
        with os.fdopen(args.backend_key_fd, "rb") as pipe:
            key = pipe.read(80)
        if not key:
            raise ValueError("--backend-key-fd: no key in the pipe")
    if args.listen_fd is not None:
        listener = socket.socket(fileno=args.listen_fd)
    else:
        listener = bind_listener(*parse_host_port(args.listen))
    serve(listener, backend, limits, args.parent_pid, key)
    return 0
