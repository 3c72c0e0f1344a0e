"""Zenoh transport for the server and its clients.

- :func:`make_zenoh_config`: the safe default (a peer listening on ``tcp/127.0.0.1:7447``
  only, multicast scouting off, shared memory off) or any zenoh JSON5/YAML config file.
- :class:`ZenohEndpoint`: one zenoh session bound to one vehicle's keys
  (:func:`simserver.wire.protocol.vehicle_keys`), with the few entities the server and the
  clients declare. Every receiver uses a channel handler polled with ``try_recv()``:
  nothing here blocks a real-time loop, and no Python callback keeps a process alive
  (a process with a callback subscriber does not exit until its session is closed).

Facts this relies on (measured on the development machine, see ``docs/protocol.md``
sections 1 and 5): zenoh's defaults join UDP multicast 224.0.0.224:7446 and listen on every
interface; shared memory (on for payloads of 3 KiB and more) gave 13-110 ms spikes;
congestion control DROP lost up to 0.5 % of a 1 kHz stream on loopback while BLOCK lost
none.

For the server this module is the adapter of the loop's ports
(:class:`simserver.server.loop.SlotPorts`): :class:`Inbox` is its command inbox,
:class:`ControlInbox` its control inbox and :class:`VehiclePublisher` its publisher.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import re
import select
import socket
import termios
import threading
import time
from collections import deque
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import zenoh

from simserver.server.realtime import open_files
from simserver.wire.protocol import (
    COMMAND_RING_SLOTS,
    DEFAULT_PREFIX,
    DEFAULT_VEHICLE,
    ENCODING_COLLISION,
    ENCODING_COMMAND,
    ENCODING_CONTROL,
    ENCODING_DIAGNOSTICS,
    ENCODING_STATE,
    ENCODING_STORYBOARD,
    ENCODING_WORLD,
    STATE_DECIMATED_HZ,
    WORLD_CONTROL_SPECS,
    ProtocolError,
    VehicleKeys,
    decode_reply,
    encode_control,
    reply_error,
    reply_ok,
    validate_control,
    vehicle_keys,
    world_keys,
)

log = logging.getLogger("simserver.server")

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
"""The embedded default: a peer on loopback only."""

DEFAULT_BLOCK_WAIT_BEFORE_CLOSE_US = 100_000
"""Congestion control BLOCK waits at most this long for a full link before closing it.

Zenoh's own default is 5 s: a client that stops reading would stall ``put()`` in the
1 kHz loop for that long. 100 ms bounds the damage (about 100 ticks, then caught up) and
drops the wedged peer's link instead.
"""

STATE_DROP_WAIT_US = 50
"""A DROP publication waits at most this long for a full link before dropping for it.

The server's state publisher uses DROP (issue 13): with BLOCK a subscriber that stopped
reading stalled the 1 kHz loop 100 ms (:data:`DEFAULT_BLOCK_WAIT_BEFORE_CLOSE_US`) each
time its socket buffers filled; zenoh's own DROP wait is 1 ms, a whole tick.
"""

MISMATCHED_LINK_QUEUE_BATCHES = 16
"""Batches in the transmit queue of a link that falls back to zenoh's normal transport.

A peer without the low-latency transport (zenoh's defaults) gets a normal-transport link
with QoS off (this side has it off), so one queue, sized by ``queue/size/data`` (zenoh's
default 2, at most 16). Zenoh 1.x (zenoh-transport's ``pipeline.rs``) marks a
one-queue pipeline congested under the bit of ``Priority::DEFAULT`` when a DROP message
finds no free batch, but a returned batch clears the bit of queue index 0
(``Priority::Control``): the mark is never cleared, and every later DROP message on that
link is dropped at once, for the rest of the session (issue 13's "DROP publishers lose
their stream"). An express state takes a whole batch, so with 2 batches and the 50 us
:data:`STATE_DROP_WAIT_US` a TX task held off for 2 ms was enough; 16 batches absorb a
16 ms hold. Links on the low-latency transport have no queue and ignore this."""

LINK_SNDBUF_BYTES = 4 << 20
"""The TCP send buffer asked for each link (``transport/link/tcp/so_sndbuf``; the kernel
doubles it, capped by ``net.core.wmem_max``).

On the low-latency transport a state put writes every subscriber's socket in turn from
one thread, and a write to a full socket waits (issue 35 item 2). With the kernel's
autotuned buffer a link blocked at 0.35-0.8 MB unsent: on a busy machine (load 23) the
readers of 20 subscribers in one process fell behind for a second at a time, each such
link held the sender, the sender's queue dropped 13 000-19 000 states in 20 s for every
subscriber and the driver saw 0.5-1.5 s without a state. A 4 MiB buffer leaves
:class:`SocketBacklog` the time to close a link that falls behind
(:data:`SocketBacklog.WEDGE_MAX_BYTES`) before any put waits on it; memory is taken only
for bytes unsent."""

_RUST_LOCATION = re.compile(r"\s+at /\S+\.rs:\d+\.?")


class ZenohConfigError(ValueError):
    """A zenoh configuration that cannot be built; the message names the file or key."""


class ZenohOpenError(RuntimeError):
    """The zenoh session could not be opened (for example the listen port is in use)."""


def _clean(exc: BaseException) -> str:
    return _RUST_LOCATION.sub("", str(exc)).strip()


def _endpoints(what: str, value: str | Sequence[str]) -> list[str]:
    items = [value] if isinstance(value, str) else list(value)
    for ep in items:
        if not isinstance(ep, str) or "/" not in ep:
            raise ZenohConfigError(
                f"{what}: endpoint {ep!r} is not of the form <protocol>/<address> "
                "(e.g. tcp/127.0.0.1:7447)"
            )
    return items


def _insert(cfg: zenoh.Config, key: str, value: Any, origin: str) -> None:
    try:
        cfg.insert_json5(key, json.dumps(value))
    except zenoh.ZError as exc:
        raise ZenohConfigError(f"{origin}: {key} = {value!r}: {_clean(exc)}") from None


def make_zenoh_config(
    listen: str | Sequence[str] | None = None,
    connect: str | Sequence[str] | None = None,
    config_file: str | Path | None = None,
    mode: str | None = None,
) -> zenoh.Config:
    """Build the zenoh configuration of a server or client.

    Parameters
    ----------
    listen : str or sequence of str, optional
        Endpoints to listen on. Without ``config_file``, defaults to
        ``["tcp/127.0.0.1:7447"]`` for a peer or router and ``[]`` for a client.
    connect : str or sequence of str, optional
        Endpoints to connect to (default none).
    config_file : str or Path, optional
        A zenoh configuration file (``.json5``, ``.json`` or ``.yaml``), used as is:
        routers, other hosts, TLS, access control. Its scouting and shared-memory
        settings are respected; ``listen``, ``connect`` and ``mode`` override it only
        when given.
    mode : {"peer", "client", "router"}, optional
        Default ``"peer"`` without a file.

    Returns
    -------
    zenoh.Config
        Without a file: ``mode``, the endpoints above, multicast scouting off, shared
        memory off, zenoh's low-latency transport (QoS off), the BLOCK wait bounded to
        :data:`DEFAULT_BLOCK_WAIT_BEFORE_CLOSE_US`, the DROP wait to
        :data:`STATE_DROP_WAIT_US`, :data:`MISMATCHED_LINK_QUEUE_BATCHES` transmit
        batches for a peer on zenoh's normal transport, and TCP send buffers of
        :data:`LINK_SNDBUF_BYTES`.

    Raises
    ------
    ZenohConfigError
        Naming the file when it is missing or does not parse, or the key of a bad value.
    """
    if config_file is not None:
        path = Path(config_file)
        if not path.is_file():
            raise ZenohConfigError(f"{path}: zenoh config file not found")
        try:
            cfg = zenoh.Config.from_file(str(path))
        except zenoh.ZError as exc:
            raise ZenohConfigError(f"{path}: not a valid zenoh config: {_clean(exc)}") from None
        origin = str(path)
        if mode is not None:
            _insert(cfg, "mode", mode, origin)
        if listen is not None:
            _insert(cfg, "listen/endpoints", _endpoints("listen", listen), origin)
        if connect is not None:
            _insert(cfg, "connect/endpoints", _endpoints("connect", connect), origin)
        return cfg

    mode = mode or "peer"
    if listen is None:
        listen = [] if mode == "client" else [DEFAULT_LISTEN]
    origin = "zenoh config"
    cfg = zenoh.Config()
    _insert(cfg, "mode", mode, origin)
    _insert(cfg, "listen/endpoints", _endpoints("listen", listen), origin)
    _insert(cfg, "connect/endpoints", _endpoints("connect", connect or []), origin)
    _insert(cfg, "scouting/multicast/enabled", False, origin)
    _insert(cfg, "transport/shared_memory/enabled", False, origin)
    # Zenoh's low-latency transport writes to the link from the publishing thread instead
    # of waking a TX task: one hop on loopback here went from 202 to 131 us (p50; 1800
    # commands). It excludes QoS (priorities), which a link that carries one car's
    # traffic does not need. Peers with zenoh's defaults still connect: the transport
    # falls back to the normal one for that link.
    _insert(cfg, "transport/unicast/qos/enabled", False, origin)
    _insert(cfg, "transport/unicast/lowlatency", True, origin)
    _insert(cfg, "transport/link/tx/queue/size/data", MISMATCHED_LINK_QUEUE_BATCHES, origin)
    _insert(
        cfg,
        "transport/link/tx/queue/congestion_control/block/wait_before_close",
        DEFAULT_BLOCK_WAIT_BEFORE_CLOSE_US,
        origin,
    )
    _insert(cfg, "transport/link/tx/queue/congestion_control/drop/wait_before_drop",
            STATE_DROP_WAIT_US, origin)
    _insert(cfg, "transport/link/tcp/so_sndbuf", LINK_SNDBUF_BYTES, origin)
    return cfg


def effective_endpoints(zcfg: zenoh.Config, key: str = "listen/endpoints") -> list[str]:
    """The endpoints a zenoh config really has (a list, or per mode for routers/peers)."""
    value = json.loads(zcfg.get_json(key))
    if isinstance(value, dict):
        mode = json.loads(zcfg.get_json("mode")) or "peer"
        value = value.get(mode, [])
    return [str(v) for v in value or []]


def config_warnings(cfg: zenoh.Config) -> list[str]:
    """Settings of a (user-given) config that ``docs/protocol.md`` advises against.

    Returns
    -------
    list of str
        One sentence per concern (multicast scouting on, shared memory on, listening on
        every interface); empty when none.
    """
    out = []
    multicast = json.loads(cfg.get_json("scouting/multicast/enabled"))
    if multicast is None or multicast:
        out.append("multicast scouting is on (joins UDP 224.0.0.224:7446)")
    if json.loads(cfg.get_json("transport/shared_memory/enabled")):
        out.append("shared memory is on (13-110 ms latency spikes measured on this platform)")
    listen = json.loads(cfg.get_json("listen/endpoints"))
    eps = listen if isinstance(listen, list) else [e for v in listen.values() for e in v or []]
    if any("0.0.0.0" in e or "[::]" in e for e in eps):
        out.append(f"listening on every interface: {eps}")
    return out


class Inbox:
    """A subscriber on a ring channel, drained without blocking.

    The channel keeps the newest ``capacity`` samples; older ones are dropped by zenoh
    when a tick's worth of input exceeds it (the newest always survive).
    """

    def __init__(self, session: zenoh.Session, key: str, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.key = key
        self.capacity = capacity
        self.received = 0
        self._sub = session.declare_subscriber(key, zenoh.handlers.RingChannel(capacity))

    def drain_newest(self) -> list[bytes]:
        """All payloads received since the last call, oldest first (never blocks).

        At most ``capacity`` items; ``received`` counts them.
        """
        out: list[bytes] = []
        try_recv = self._sub.try_recv
        sample = try_recv()
        while sample is not None:
            out.append(sample.payload.to_bytes())
            sample = try_recv()
        self.received += len(out)
        return out

    def wait_newest(self, timeout_s: float, poll_s: float = 0.0005) -> bytes | None:
        """Block up to ``timeout_s`` for input and return the newest payload (clients only)."""
        deadline = time.monotonic() + timeout_s
        while True:
            got = self.drain_newest()
            if got:
                return got[-1]
            if time.monotonic() >= deadline:
                return None
            time.sleep(poll_s)

    def close(self) -> None:
        """Undeclare the subscriber (idempotent)."""
        if self._sub is not None:
            try:
                self._sub.undeclare()
            except zenoh.ZError:
                pass  # already gone with its session
            self._sub = None


class ControlRequest:
    """One control request; answer it exactly once with a ``reply*`` method.

    ``args`` are the validated arguments, or None when its inbox leaves validation to the
    server (``validate=False``); ``payload`` is the raw JSON body either way.
    """

    __slots__ = ("name", "args", "payload", "key", "_query")

    def __init__(self, name: str, args: dict | None, key: str, query: zenoh.Query,
                 payload: bytes = b"") -> None:
        self.name = name
        self.args = args
        self.payload = payload
        self.key = key
        self._query = query

    def reply(self, body: bytes) -> None:
        """Send a JSON reply body and finalise the query."""
        query, self._query = self._query, None
        if query is None:
            raise RuntimeError(f"control {self.name!r} was already answered")
        try:  # zenoh 1.x takes no congestion control per reply (the argument is
            # deprecated and ignored): a reply goes out as zenoh's queries do
            query.reply(self.key, body, encoding=zenoh.Encoding(ENCODING_CONTROL))
        finally:
            query.drop()

    def reply_ok(self, **data: Any) -> None:
        """Reply ``{"ok": true, ...data}``."""
        self.reply(reply_ok(**data))

    def reply_error(self, error: str | ProtocolError, field: str | None = None) -> None:
        """Reply ``{"ok": false, "error": ..., "field": ...}``."""
        self.reply(reply_error(error, field))


class ControlInbox:
    """One queryable on ``{prefix}/{vehicle}/ctl/*`` serving every control, fairly.

    Requests are queued per client (the client's session id, which
    :meth:`ZenohEndpoint.request` attaches; requests without one share a queue), each
    queue bounded to ``per_client``: a request beyond it is answered at once with a busy
    error and counted in ``busy``, so a client flooding the server cannot push out
    another's requests, and none goes unanswered. The queueing runs in zenoh's receive
    thread (a short Python callback); :meth:`poll` (the tick) takes the queues in turn.

    :meth:`poll` answers malformed requests itself (unknown control, wildcard key, and
    with ``validate`` bad arguments: an error reply naming the field) and returns the
    others. The server passes ``validate=False``: its control table validates.
    """

    def __init__(self, session: zenoh.Session, keys: VehicleKeys, per_client: int = 16,
                 validate: bool = True, max_clients: int = 256) -> None:
        if per_client < 1:
            raise ValueError(f"per_client must be >= 1, got {per_client}")
        self.keys = keys
        self.validate = validate
        self.per_client = per_client
        self.max_clients = max_clients
        self.received = 0
        self.rejected = 0
        self.busy = 0
        self._queues: dict[bytes, deque] = {}
        self._turn: deque[bytes] = deque()  # clients with something queued, in turn
        # indirect=False: the callback runs in zenoh's receiving thread (the server makes it
        # real-time), not in a Python thread of its own, which would hold the GIL at
        # normal priority and keep the interpreter from exiting (platform note)
        self._q = session.declare_queryable(
            keys.ctl_wildcard, zenoh.handlers.Callback(self._on_query, indirect=False),
            complete=True)

    def _on_query(self, query: zenoh.Query) -> None:
        """zenoh's thread: queue the request, or answer busy when its client's queue is full."""
        self.received += 1
        client = query.attachment.to_bytes() if query.attachment is not None else b""
        queue = self._queues.get(client)
        if queue is None:
            if len(self._queues) >= self.max_clients:
                client, queue = b"", self._queues.setdefault(b"", deque())
            else:
                queue = self._queues[client] = deque()
        if len(queue) >= self.per_client:
            self.busy += 1
            try:
                query.reply_err(reply_error(
                    f"busy: {len(queue)} requests of this client are waiting; ask again "
                    "after their replies", "control"))
            except zenoh.ZError:
                pass  # the client is gone
            finally:
                query.drop()
            return
        if not queue:
            self._turn.append(client)
        queue.append(query)

    def poll(self, limit: int = 1 << 30) -> list[ControlRequest]:
        """Valid requests received since the last call, at most ``limit``, one client at a
        time in turn (never blocks; usually empty)."""
        out: list[ControlRequest] = []
        turn = self._turn
        while turn and len(out) < limit:
            client = turn.popleft()
            queue = self._queues.get(client)
            if not queue:
                continue
            request = self._accept(queue.popleft())
            if queue:
                turn.append(client)  # its next request after the other clients'
            if request is not None:
                out.append(request)
        return out

    def _accept(self, query: zenoh.Query) -> ControlRequest | None:
        key = str(query.key_expr)
        name = self.keys.control_name(key)
        payload = query.payload.to_bytes() if query.payload is not None else b""
        try:
            if name is None:
                raise ProtocolError(
                    "control", f"{key!r} is not one control key of {self.keys.base}"
                )
            args = validate_control(name, payload) if self.validate else None
        except Exception as exc:  # ProtocolError, or a validator bug: never escapes
            if not isinstance(exc, ProtocolError):
                exc = ProtocolError("request", f"could not be validated ({type(exc).__name__})")
            self.rejected += 1
            try:
                if name is None:
                    query.reply_err(reply_error(exc))
                else:
                    query.reply(key, reply_error(exc),
                                encoding=zenoh.Encoding(ENCODING_CONTROL))
            finally:
                query.drop()
            return None
        return ControlRequest(name, args, key, query, payload)

    def close(self) -> None:
        """Undeclare the queryable (idempotent); queued requests are dropped unanswered."""
        if self._q is not None:
            try:
                self._q.undeclare()
            except zenoh.ZError:
                pass
            self._q = None
        for queue in self._queues.values():
            while queue:
                queue.popleft().drop()


class VehiclePublisher:
    """A vehicle's state and diagnostics publishers: the server loop's publisher port.

    ``slow_publishes`` counts state publications that took longer than ``slow_ns``: the
    state publisher never waits for a subscriber (congestion control DROP, with
    :data:`STATE_DROP_WAIT_US`), so these are the ticks a congested link cost something.

    With ``decimated`` (the ``state/100hz`` publisher) every ``decimate_every``-th state is
    put there too (:data:`simserver.wire.protocol.STATE_DECIMATED_HZ`).

    With ``sender_thread`` the puts run in a sender thread (``state-tx``), not in the
    caller's: :meth:`publish_state` only queues the payload (a few microseconds). The
    vehicle publishers of one endpoint share that thread and one ``state-watch``
    (:class:`SenderThread`): a server of 32 cars ran 64 such threads, each woken every
    20 ms to scan the same sockets of the process and each wanting the GIL at real-time
    priority (issue 30: 40 000 wake-ups a second, 16 % of ticks late). On
    the low-latency transport zenoh writes a put to every subscriber's socket in the
    calling thread, about 8 us of CPU per subscriber (20 subscribers: 166 us p50, with
    waits on the links' locks up to 4 ms p99 on a busy machine, ``benchmarks.bench_load``'s
    tick trace), and a subscriber that reads slower than the states come blocks it for as
    long as its socket stays full (16 s measured: zenoh's low-latency transport has no
    congestion control); the put releases the GIL while it writes. The queue holds
    :data:`SENDER_QUEUE` publications: beyond, the oldest is dropped and counted in
    ``slow_publishes`` too (the sender is that far behind: a link stalled for as long).

    With ``inline_while_cheap`` as well, the caller puts the state itself while puts are
    cheap and hands them to ``state-tx`` only when they are not: the hand-off costs a
    wake-up of that thread and the GIL passed over, about 40 us of command-to-state
    latency p99 (``benchmarks.bench_server --hogs 2``). The rule (:meth:`mode`):

    - inline, two state puts within :data:`INLINE_SLOW_WITHIN` that took longer than
      :data:`INLINE_PUT_NS` (wall time: many subscribers, a lock held by a link; one alone
      may be the caller preempted) send the next ones to the thread;
    - so does a backlog: ``state-tx`` checks every :data:`WATCH_S` the unsent bytes of
      this process's sockets (``SIOCOUTQ``), and more than :data:`BACKLOG_BYTES` in one
      at two checks in a row (a subscriber whose socket fills up: the put that finds it
      full would block the caller) keeps the puts in the thread while it lasts;
    - queued, the thread times its own puts (CPU time); when at most a fifth
      (:data:`INLINE_AGAIN_COSTLY_SHARE`) of :data:`INLINE_AGAIN_PUTS` in a row took more
      than half :data:`INLINE_PUT_NS`, with no backlog, the caller puts inline again once
      nothing is queued. Going back to the thread within :data:`INLINE_STABLE_S` of that
      doubles the count judged next time (up to :data:`INLINE_AGAIN_MAX_PUTS`): a load
      that comes and goes settles in the thread instead of switching back and forth.

    The diagnostics always go through the thread (5 Hz; their latency does not matter).
    """

    SENDER_QUEUE = 256
    INLINE_PUT_NS = 250_000
    """An inline put slower than this is slow (a quarter period; a put to one subscriber
    on loopback takes 30-70 us on this VM, the receiver's side of the loopback included;
    20 subscribers 166 us CPU p50 and lock waits up to 4 ms)."""
    INLINE_SLOW_WITHIN = 100
    """Inline, a second slow put within this many puts hands off (one alone may be the
    caller preempted: on this VM a single put of 2.5-3.9 ms handed off 2 times in 30 s
    beside two CPU hogs, and a stall of the VM is no reason to)."""
    INLINE_AGAIN_PUTS = 2000
    """Puts in the thread judged together before going inline again (2 s at 1 kHz): at
    most :data:`INLINE_AGAIN_COSTLY_SHARE` of them above half :data:`INLINE_PUT_NS` by the
    thread's CPU time (its wall time counts the GIL passed back and the thread's own
    preemption), and no socket backlog meanwhile."""
    INLINE_AGAIN_COSTLY_SHARE = 0.2
    """The share of costly puts (above half :data:`INLINE_PUT_NS`) a window may hold and
    still go inline: the 80th percentile of a put's CPU time at most 125 us. A put to one
    subscriber here: p80 57-59 us, p95 87-95 us; 6 subscribers p80 94 us, 11 subscribers
    146 us, 20 subscribers 229 us (p50 196 us). The share was 5 % (the 95th percentile,
    which one subscriber's puts reach on this VM in a slow hour): in a CI run that took
    1.5 x its usual time, one subscriber's states stayed in the thread for over 60 s."""
    INLINE_AGAIN_MAX_PUTS = 64_000
    INLINE_STABLE_S = 10.0
    BACKLOG_BYTES = 16_384
    """Unsent bytes in one socket that count as a backlog (55 states of 296 bytes; a
    subscriber that keeps up leaves none on loopback)."""
    WATCH_S = 0.02
    """How often ``state-tx`` checks the sockets' backlog (and rescans them once a second)."""

    def __init__(self, state: zenoh.Publisher, diagnostics: zenoh.Publisher,
                 slow_ns: int = 250_000, decimated: zenoh.Publisher | None = None,
                 decimate_every: int = 1, sender_thread: bool = False,
                 inline_while_cheap: bool = False,
                 inline_again_puts: int = INLINE_AGAIN_PUTS,
                 sender: SenderThread | None = None) -> None:
        self.state = state
        self.diagnostics = diagnostics
        self.slow_ns = slow_ns
        self.slow_publishes = 0
        self.decimated = decimated
        self.decimate_every = max(1, decimate_every)
        self._states = 0
        self.dropped = 0  # by the sender thread's full queue (also in slow_publishes)
        self.handoffs = 0  # inline -> thread switches
        self.inline_puts = 0  # states put by the caller while a thread exists
        self._queue: deque[tuple[bool | zenoh.Publisher, bytes]] | None = None
        # queued, not yet put: enqueued - dropped (both the caller's) - sent (the thread's)
        self._enqueued = self._sent = 0
        self._sender: SenderThread | None = None
        self._own_sender = False  # made for this publisher alone (closed with it)
        self._closing = False
        self._inline = False  # the caller puts states itself (only with inline_while_cheap)
        self._inline_ok = False  # set by the thread: cheap long enough, go inline
        self._backlog = 0  # the largest socket backlog last seen by the watch (bytes)
        self._backlogged = False  # ... above BACKLOG_BYTES
        self._adaptive = sender_thread and inline_while_cheap
        self.inline_again_puts = inline_again_puts
        self._again_puts = inline_again_puts
        self._judged = self._costly = 0  # the thread's puts judged, and the costly ones
        self._inline_since = 0.0
        self._last_slow_ns = 0
        self._slow_at = -self.INLINE_SLOW_WITHIN - 1  # inline_puts at the last slow one
        self._logged_mode = "thread"
        if sender_thread:
            self._queue = deque()
            self._inline = self._adaptive  # nobody subscribes yet: puts are cheap
            self._logged_mode = self.mode()
            if sender is None:
                sender, self._own_sender = SenderThread(), True
            self._sender = sender
            sender.register(self)

    def mode(self) -> str:
        """``"inline"`` (the caller puts the states) or ``"thread"`` (``state-tx`` does)."""
        return "inline" if self._queue is None or self._inline else "thread"

    def _pending(self) -> int:
        """Publications queued and not put yet (read by the caller; the thread's count may
        be a moment old: then one more goes through the thread, in order)."""
        return self._enqueued - self.dropped - self._sent

    def publish_state(self, payload: bytes) -> None:
        """Put one VehicleState (and every ``decimate_every``-th on the decimated key)."""
        queue = self._queue
        if queue is None:
            self._put_state(payload)
            return
        if not self._inline and self._inline_ok and not self._pending():
            # nothing left in the thread (one producer: this caller): order is kept
            self._inline, self._inline_ok = True, False
            self._inline_since = time.monotonic()
        if self._inline and not self._backlogged:
            took = self._put_state(payload)
            self.inline_puts += 1
            if took > self.INLINE_PUT_NS:
                # one slow put may be this thread preempted (the VM stalls 1-25 ms at
                # random); a second one within INLINE_SLOW_WITHIN puts is the links
                if self.inline_puts - self._slow_at <= self.INLINE_SLOW_WITHIN:
                    self._to_thread(took)
                self._slow_at = self.inline_puts
            return
        if self._inline:
            self._to_thread(0)
        self._enqueue(True, payload)

    def _to_thread(self, took_ns: int) -> None:
        """From inline to the thread (from the caller)."""
        self._inline = False
        self._judged = self._costly = 0
        self._last_slow_ns = took_ns
        self.handoffs += 1
        if time.monotonic() - self._inline_since < self.INLINE_STABLE_S:
            self._again_puts = min(2 * self._again_puts,
                                   max(self.INLINE_AGAIN_MAX_PUTS, self.inline_again_puts))
        else:
            self._again_puts = self.inline_again_puts

    def publish_diagnostics(self, payload: bytes) -> None:
        """Put one Diagnostics."""
        if self._queue is not None:
            self._enqueue(False, payload)
        else:
            self.diagnostics.put(payload)

    def publish_on(self, publisher: zenoh.Publisher, payload: bytes) -> None:
        """Put ``payload`` on another publisher of the server's (a world event: a
        collision) through this vehicle's sender thread, in order with its states and
        diagnostics; put by the caller when there is no thread."""
        if self._queue is not None:
            self._enqueue(publisher, payload)
        else:
            publisher.put(payload)

    def _put_state(self, payload: bytes) -> int:
        """Put one state; how long it took (ns)."""
        t0 = time.perf_counter_ns()
        self.state.put(payload)
        self._states += 1
        if self.decimated is not None and self._states % self.decimate_every == 0:
            self.decimated.put(payload)
        took = time.perf_counter_ns() - t0
        if took > self.slow_ns:
            self.slow_publishes += 1
        return took

    def _enqueue(self, is_state: bool | zenoh.Publisher, payload: bytes) -> None:
        # is_state: True a state, False the diagnostics, else the publisher to put on
        queue = self._queue
        if len(queue) >= self.SENDER_QUEUE:
            try:
                queue.popleft()
                self.slow_publishes += 1
                self.dropped += 1
            except IndexError:  # the thread took it meanwhile
                pass
        queue.append((is_state, payload))
        self._enqueued += 1
        self._sender.wake()

    def _send_queued(self) -> None:
        """Put what is queued, in order (in the sender thread); judge the puts' cost."""
        queue = self._queue
        while True:
            try:
                is_state, payload = queue.popleft()
            except IndexError:
                break
            try:
                if is_state is True:
                    cpu0 = time.thread_time_ns()
                    self._put_state(payload)
                    took = time.thread_time_ns() - cpu0
                    self._judged += 1
                    if took > self.INLINE_PUT_NS // 2:
                        self._costly += 1
                elif is_state is False:
                    self.diagnostics.put(payload)
                else:
                    is_state.put(payload)
            except zenoh.ZError:
                pass  # undeclared meanwhile (the session closing)
            except Exception:  # never let the thread end: no state would go out again
                log.exception("state-tx: a publication failed")
            finally:
                self._sent += 1
        if self._adaptive and self._judged >= self._again_puts:
            if (not self._inline
                    and self._costly <= self.INLINE_AGAIN_COSTLY_SHARE * self._judged):
                self._inline_ok = True
            self._judged = self._costly = 0

    def _note_backlog(self, seen: int) -> None:
        """The watch's look at the sockets (in ``state-watch``): twice in a row above
        :data:`BACKLOG_BYTES` (a client's first burst passes) keeps the puts in the
        thread while it lasts; a change of mode logged."""
        self._backlogged = min(seen, self._backlog) > self.BACKLOG_BYTES
        self._backlog = seen
        if self._backlogged:
            self._judged = self._costly = 0
        mode = self.mode()
        if mode != self._logged_mode and not self._closing:  # not close() turning the
            self._logged_mode = mode                          # caller off
            self._log_mode(mode)

    @property
    def links_closed(self) -> int:
        """Links closed because their reader stopped reading (:class:`SocketBacklog`)."""
        sender = self._sender
        return 0 if sender is None else len(sender.links_closed())

    def _log_mode(self, mode: str) -> None:
        # DEBUG, not INFO: an idle server with no client switched a few times a minute
        # (132 INFO lines in 55 minutes, issue 32); the stop statistics count the
        # hand-offs (publish_handoffs)
        if mode == "thread":
            why = (f"a socket with {self._backlog} bytes unsent" if self._backlogged
                   else f"a put took {self._last_slow_ns / 1e3:.0f} us")
            log.debug("state-tx: states handed to this thread (%s: slow links or many "
                      "subscribers)", why)
        else:
            log.debug("state-tx: states put in the tick again (puts cheap over the last %d)",
                      self._again_puts)

    def close(self, timeout_s: float = 1.0) -> None:
        """Send what is queued (up to ``timeout_s``) and leave the sender thread
        (idempotent; a sender of its own is stopped); the publishers are undeclared with
        their session."""
        sender, self._sender = self._sender, None
        if sender is None:
            return
        self._closing = True
        self._inline = self._inline_ok = False
        sender.wake()
        t_end = time.monotonic() + timeout_s
        while self._pending() > 0 and sender.alive() and time.monotonic() < t_end:
            time.sleep(0.001)
        sender.unregister(self)
        if self._own_sender:
            sender.close()


class SenderThread:
    """The ``state-tx`` thread shared by the vehicle publishers of one endpoint (a
    server's cars), and, once a publisher that puts inline while cheap joins, the
    ``state-watch`` thread that looks at the process's sockets for all of them.

    One thread puts every car's queued publications, each car's in order: a wake-up
    drains every car's queue (a tick's states in one go), not one thread a car woken for
    each. The sockets are the process's, so one look at them (:class:`SocketBacklog`)
    serves every car; each car's publisher then judges its own mode
    (``VehiclePublisher._note_backlog``). A put that waits on a full socket would hold
    the other cars' queued states too; the watch closes such a wedged link within
    ``SocketBacklog.WEDGE_S``, long before a socket fills (docs/reliability.md).
    """

    WATCH_S = VehiclePublisher.WATCH_S

    def __init__(self) -> None:
        self._publishers: tuple[VehiclePublisher, ...] = ()  # replaced, never mutated
        self._lock = threading.Lock()
        self._wake = os.eventfd(0)
        self._stopping = False
        self._thread: threading.Thread | None = threading.Thread(
            target=self._send_loop, name="state-tx", daemon=True)
        self._thread.start()
        self._watch: SocketBacklog | None = None
        self._watcher: threading.Thread | None = None
        self._watch_stop = threading.Event()

    def register(self, pub: VehiclePublisher) -> None:
        with self._lock:
            self._publishers = (*self._publishers, pub)
            if pub._adaptive and self._watcher is None:
                # its own thread: a put that waits on a full socket holds state-tx, and
                # the watch is what unblocks it (SocketBacklog: wedged links)
                self._watch = SocketBacklog(close_wedged=True)
                self._watcher = threading.Thread(target=self._watch_loop,
                                                 name="state-watch", daemon=True)
                self._watcher.start()

    def unregister(self, pub: VehiclePublisher) -> None:
        with self._lock:
            self._publishers = tuple(p for p in self._publishers if p is not pub)

    def wake(self) -> None:
        os.eventfd_write(self._wake, 1)

    def alive(self) -> bool:
        thread = self._thread
        return thread is not None and thread.is_alive()

    def links_closed(self) -> list[str]:
        """What each link the watch closed was (``SocketBacklog.closed``)."""
        return [] if self._watch is None else self._watch.closed

    def _send_loop(self) -> None:
        """Put what every publisher queued, each in order; wait (GIL released)."""
        poller = select.poll()
        poller.register(self._wake, select.POLLIN)
        reported = last = 0
        while True:
            if poller.poll(-1):
                os.eventfd_read(self._wake)
            for pub in self._publishers:
                if pub._queue:
                    pub._send_queued()
            if self._stopping:
                return
            dropped = sum(p.dropped for p in self._publishers)
            now = time.monotonic()
            if dropped != reported and now - last > 1.0:
                reported, last = dropped, now  # not in the tick; 1/s
                log.warning("state-tx: %d publications dropped so far: the sender was %d "
                            "behind (a link or this thread stalled)", dropped,
                            VehiclePublisher.SENDER_QUEUE)

    def _watch_loop(self) -> None:
        """The ``state-watch`` thread: every :data:`WATCH_S` the sockets' backlog, told to
        every publisher (puts to the thread while one lasts), and the wedged links closed
        (:class:`SocketBacklog`). Not ``state-tx``: a put that finds a full socket holds
        that thread until the link is closed."""
        watch = self._watch
        while not self._watch_stop.wait(self.WATCH_S):
            seen = watch.largest(time.monotonic())
            for pub in self._publishers:
                if pub._adaptive:
                    pub._note_backlog(seen)

    def close(self) -> None:
        """Stop both threads after what is queued (idempotent)."""
        watcher, self._watcher = self._watcher, None
        if watcher is not None:
            self._watch_stop.set()
            watcher.join(timeout=1.0)
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stopping = True
            self.wake()
            thread.join(timeout=1.0)
            os.close(self._wake)


class SocketBacklog:
    """The largest count of unsent bytes (``SIOCOUTQ``) over this process's sockets; and,
    with ``close_wedged``, the links it closes because their reader stopped reading.

    The socket list (``/proc/self/fd``) is read again once a second; a descriptor closed
    or reused meanwhile is skipped (``ioctl`` fails on anything but a socket or tty).

    **Wedged links** (issue 35 item 2, docs/reliability.md "Command-to-state latency under
    many viewers"). On zenoh's low-latency transport a put writes to every subscriber's
    socket in turn from the putting thread, with no congestion control: once one
    subscriber's socket is full (a reader that stopped reading: on loopback its unsent
    bytes grow 360 kB/s to the 3.9 MB send buffer, 11 s, then every put waits on it) every
    other subscriber waits as long, and so do zenoh's own threads writing declarations to
    that link (10 joins a second: their replies too). So a link of a listener of this
    process (a client or peer that connected to it: its local port is one this process
    listens on) whose unsent bytes stay at or above :data:`WEDGE_MIN_BYTES` without once
    going down for :data:`WEDGE_S` is shut down (``shutdown(2)`` on the socket: zenoh's
    blocked write fails, its reader sees the end, and zenoh closes that session's
    transport as it does for a dead peer; the client may connect again). A reader that
    keeps up leaves no unsent bytes on loopback (the kernel takes them into its receive
    window whether or not the program reads), and on a network link the bytes in flight
    go down with every acknowledgement; only a reader slower than the stream, or stopped
    (its whole receive window unread, then a second more), keeps them from going down
    for a second. A second, not less: a client starved of the CPU for a moment (a
    viewer at ``SCHED_IDLE`` on a busy machine) keeps its link. A link whose reader reads
    now and then but falls ever further behind (a process starved on a busy machine: its
    unsent bytes go down a little, then grow again) is closed once they reach
    :data:`WEDGE_MAX_BYTES`, whether or not they went down: a reader seconds behind a live
    stream, closed before its socket is full (:data:`LINK_SNDBUF_BYTES`), so no put waits
    on it. Zenoh's normal transport closes
    a link its BLOCK messages wait on for ``block/wait_before_close`` the same way
    (:data:`DEFAULT_BLOCK_WAIT_BEFORE_CLOSE_US`).
    """

    RESCAN_S = 1.0
    WEDGE_MIN_BYTES = 16_384
    """Unsent bytes from which a link counts as backed up (55 states of 296 bytes: on
    loopback, past the reader's whole receive window)."""
    WEDGE_S = 1.0
    """How long a link's unsent bytes may stay backed up without going down before it is
    closed (a second of states, about 360 kB more on loopback: far from the 3.9 MB at
    which the puts would wait, 11 s after the reader stopped)."""

    WEDGE_MAX_BYTES = 1 << 20
    """Unsent bytes at which a link is closed at once (3.5 s of states of 296 bytes at
    1 kHz; on a network link far above the bytes in flight: 300 kB/s x 100 ms round trip
    is 30 kB). Below :data:`LINK_SNDBUF_BYTES`, so the puts never wait on it; the kernel's
    own autotuned buffer blocked writes at 0.35-0.8 MB here."""

    def __init__(self, close_wedged: bool = False) -> None:
        self._fds: list[int] = []
        self._links: dict[int, str] = {}  # fd -> its /proc target, for listener links
        self._scanned = -1e9
        self.close_wedged = close_wedged
        self._backed: dict[int, tuple[float, int]] = {}  # fd -> (backed up since, last)
        self.closed: list[str] = []  # what each closed link was (peer address, why)

    def _scan(self) -> None:
        try:
            files = open_files()
        except OSError:
            files = {}
        self._fds = [fd for fd, target in files.items() if target.startswith("socket:")]
        if self.close_wedged:
            self._links = self._listener_links(files)
            self._backed = {fd: v for fd, v in self._backed.items() if fd in self._links}

    def _listener_links(self, files: dict[int, str]) -> dict[int, str]:
        """The connected TCP sockets whose local port one of this process's listening
        sockets has: the links of clients and peers that connected to it."""
        listening: set[int] = set()
        conns: list[tuple[int, int]] = []
        for fd in self._fds:
            try:
                with socket.socket(fileno=os.dup(fd)) as sock:
                    if sock.type != socket.SOCK_STREAM or sock.family not in (
                            socket.AF_INET, socket.AF_INET6):
                        continue
                    port = sock.getsockname()[1]
                    if sock.getsockopt(socket.SOL_SOCKET, socket.SO_ACCEPTCONN):
                        listening.add(port)
                    else:
                        conns.append((fd, port))
            except OSError:
                continue  # closed meanwhile, or not a socket any more
        return {fd: files[fd] for fd, port in conns if port in listening}

    def largest(self, now: float) -> int:
        if now - self._scanned >= self.RESCAN_S:
            self._scanned = now
            self._scan()
        out = 0
        buf = bytearray(4)
        for fd in self._fds:
            try:
                fcntl.ioctl(fd, termios.TIOCOUTQ, buf)  # SIOCOUTQ on a socket
            except OSError:
                continue
            n = int.from_bytes(buf, "little", signed=True)
            if n > out:
                out = n
            if fd in self._links:
                self._judge(fd, n, now)
        return out

    def _judge(self, fd: int, unsent: int, now: float) -> None:
        """Track a link's backlog; shut it down once wedged (:data:`WEDGE_S`)."""
        if unsent < self.WEDGE_MIN_BYTES:
            self._backed.pop(fd, None)
            return
        since, last = self._backed.get(fd, (now, unsent))
        if unsent < last:
            since = now  # it went down: the reader reads
        self._backed[fd] = (since, unsent)
        if now - since >= self.WEDGE_S or unsent >= self.WEDGE_MAX_BYTES:
            self._shut(fd, unsent, now - since)

    def _shut(self, fd: int, unsent: int, for_s: float) -> None:
        target = self._links.pop(fd, None)
        self._backed.pop(fd, None)
        try:
            if os.readlink(f"/proc/self/fd/{fd}") != target:
                return  # closed and reused since the scan: not the link judged
            with socket.socket(fileno=os.dup(fd)) as sock:
                try:
                    host, port = sock.getpeername()[:2]
                    peer = f"{host}:{port}"
                except OSError:
                    peer = "?"
                sock.shutdown(socket.SHUT_RDWR)  # the link, not only this duplicate
        except OSError:
            return  # closed meanwhile
        why = (f"link from {peer} closed: {unsent} bytes unsent, " + (
            f"not going down for {1e3 * for_s:.0f} ms (a subscriber that stopped reading)"
            if unsent < self.WEDGE_MAX_BYTES else
            f"at least {self.WEDGE_MAX_BYTES} (a subscriber seconds behind the stream)"))
        self.closed.append(why)
        log.warning("state-watch: %s", why)


class AliveWatch:
    """Liveliness subscriber on a vehicle's (or a pattern's) token key."""

    def __init__(self, session: zenoh.Session, key: str, capacity: int = 64) -> None:
        self.key = key
        self._sub = session.liveliness().declare_subscriber(
            key, zenoh.handlers.FifoChannel(capacity), history=True
        )

    def poll(self) -> list[tuple[str, bool]]:
        """Changes since the last call: ``(token key, True if it appeared)``, oldest first."""
        out = []
        sample = self._sub.try_recv()
        while sample is not None:
            out.append((str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))
            sample = self._sub.try_recv()
        return out

    def close(self) -> None:
        """Undeclare the subscriber (idempotent)."""
        if self._sub is not None:
            try:
                self._sub.undeclare()
            except zenoh.ZError:
                pass
            self._sub = None


ZENOH_TIMEOUT_REPLY = b"Timeout"
"""The error reply zenoh itself gives a query whose matching queryable did not answer
within the query's timeout (zenoh 1.x), told apart from the server's JSON error replies."""


class ZenohEndpoint:
    """A zenoh session bound to one vehicle's keys, for the server and its clients.

    Parameters
    ----------
    config : zenoh.Config, optional
        Default :func:`make_zenoh_config` (loopback peer on port 7447).
    prefix, vehicle : str, optional
        Key prefix and vehicle id (validated).

    Raises
    ------
    simserver.wire.protocol.ProtocolError
        For an invalid prefix or vehicle id.
    ZenohOpenError
        When the session cannot be opened (a listen port in use, a bad endpoint).

    Notes
    -----
    Use it as a context manager or call :meth:`close`; every entity declared through it
    is undeclared, then the session closed. Only channel handlers are used, so a process
    exits even if it forgets to close.

    Examples
    --------
    Server side, per tick::

        for payload in inbox.drain_newest(): ...      # count, decode, keep newest valid
        state_pub.put(state_bytes)
        for req in controls.poll(): req.reply_ok(tick=tick)
    """

    def __init__(
        self,
        config: zenoh.Config | None = None,
        *,
        prefix: str = DEFAULT_PREFIX,
        vehicle: str = DEFAULT_VEHICLE,
    ) -> None:
        self.keys = vehicle_keys(prefix, vehicle)
        self._closeables: list[Any] = []
        config = config if config is not None else make_zenoh_config()
        self.config = config
        """The session's config (a diagnosis of an unreached server reads it)."""
        try:
            self.session = zenoh.open(config)
        except zenoh.ZError as exc:
            text = _clean(exc)
            if "Unable to connect" in text:  # zenoh says the same whatever the cause:
                # find what the server wants that this client lacks (issue 35)
                from simserver.adapters.zenoh_diagnose import explain

                why = explain(config)
                text += f" ({why})" if why else ""
            raise ZenohOpenError(f"cannot open the zenoh session: {text}") from None
        # sent with control requests: the server queues them per client (ControlInbox)
        self._client_id = str(self.session.zid()).encode()
        self._owns_session = True
        self._sender: SenderThread | None = None  # the vehicle publishers' (shared)

    def for_vehicle(self, vehicle: str) -> ZenohEndpoint:
        """An endpoint of another car's keys on this one's session (a process serving
        several cars, as the ROS 2 adapter of a multi-car server: one session, not one a
        car). Closing it undeclares its own entities only; the session stays this one's."""
        view = object.__new__(type(self))
        view.keys = vehicle_keys(self.keys.prefix, vehicle)
        view._closeables = []
        view.config = self.config
        view.session = self.session
        view._client_id = self._client_id
        view._owns_session = False
        view._sender = None
        return view

    # ---------------------------------------------------------------- lifecycle

    def __enter__(self) -> ZenohEndpoint:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        """True once :meth:`close` ran (or the session was closed)."""
        return self.session.is_closed()

    def close(self) -> None:
        """Undeclare every entity (newest first), then close the session. Idempotent."""
        while self._closeables:
            obj = self._closeables.pop()
            try:
                if hasattr(obj, "close"):
                    obj.close()
                else:
                    obj.undeclare()
            except zenoh.ZError:
                pass
        if self._owns_session and not self.session.is_closed():
            self.session.close()

    def _keep(self, obj: Any) -> Any:
        self._closeables.append(obj)
        return obj

    def _publisher(
        self, key: str, encoding: str, priority: zenoh.Priority, express: bool,
        congestion_control: zenoh.CongestionControl,
    ) -> zenoh.Publisher:
        return self._keep(
            self.session.declare_publisher(
                key,
                encoding=zenoh.Encoding(encoding),
                congestion_control=congestion_control,
                priority=priority,
                express=express,
            )
        )

    # ---------------------------------------------------------------- server side

    # ``keys`` (default this endpoint's) lets one session serve several vehicles.
    def declare_command_inbox(self, capacity: int = COMMAND_RING_SLOTS,
                              keys: VehicleKeys | None = None) -> Inbox:
        """Subscriber on ``cmd`` with a ring of ``capacity``; drain it every tick."""
        return self._keep(Inbox(self.session, (keys or self.keys).cmd, capacity))

    def declare_state_publisher(
        self, congestion_control: zenoh.CongestionControl = zenoh.CongestionControl.BLOCK,
        keys: VehicleKeys | None = None,
    ) -> zenoh.Publisher:
        """Publisher on ``state``: REAL_TIME priority, express, BLOCK (lossless)."""
        return self._publisher((keys or self.keys).state, ENCODING_STATE,
                               zenoh.Priority.REAL_TIME, True, congestion_control)

    def declare_diag_publisher(self, keys: VehicleKeys | None = None) -> zenoh.Publisher:
        """Publisher on ``diag``: DATA priority, batched, DROP.

        DROP as the state (was BLOCK): the server puts it from its loop thread, and a
        subscriber that stops reading (a viewer whose threads run at ``SCHED_IDLE`` on a
        busy machine, a frozen process) would otherwise hold that put up to
        :data:`DEFAULT_BLOCK_WAIT_BEFORE_CLOSE_US` once its link is full.
        """
        return self._publisher((keys or self.keys).diag, ENCODING_DIAGNOSTICS,
                               zenoh.Priority.DATA, False, zenoh.CongestionControl.DROP)

    def declare_vehicle_publisher(self, keys: VehicleKeys | None = None,
                                  states_per_s: float = 1000.0,
                                  sender_thread: bool = False,
                                  inline_while_cheap: bool = False) -> VehiclePublisher:
        """The server loop's publisher: ``state`` with congestion control DROP (a
        subscriber that stops reading loses states, the loop never waits for it: see
        :data:`STATE_DROP_WAIT_US`), the same every ``states_per_s / STATE_DECIMATED_HZ``-th
        state on ``state/100hz``, and ``diag`` as above; with ``sender_thread`` put from a
        thread of its own (:class:`VehiclePublisher`), closed before the publishers, and
        with ``inline_while_cheap`` too, states put by the caller while that is cheap."""
        keys = keys or self.keys
        # Not express: the low-latency transport ignores it (every message goes straight
        # to the socket), and on a link that falls back to zenoh's normal transport an
        # express message takes a whole transmit batch, so a transmit thread held off a
        # few ticks left no free batch and the link lost every later state (see
        # MISMATCHED_LINK_QUEUE_BATCHES); batched, a held-off thread finds the states of
        # 200 ticks in one batch. That queue sends a batch at once when idle.
        return self._keep(VehiclePublisher(
            self._publisher(keys.state, ENCODING_STATE, zenoh.Priority.REAL_TIME, False,
                            zenoh.CongestionControl.DROP),
            self.declare_diag_publisher(keys=keys),
            decimated=self._publisher(keys.state_decimated, ENCODING_STATE,
                                      zenoh.Priority.REAL_TIME, False,
                                      zenoh.CongestionControl.DROP),
            decimate_every=round(states_per_s / STATE_DECIMATED_HZ),
            sender_thread=sender_thread, inline_while_cheap=inline_while_cheap,
            sender=self._shared_sender() if sender_thread else None))

    def _shared_sender(self) -> SenderThread:
        """The sender thread of this endpoint's vehicle publishers (one for all its cars:
        :class:`SenderThread`), made with the first; closed after them (kept before them)."""
        if self._sender is None:
            self._sender = self._keep(SenderThread())
        return self._sender

    def declare_world_publisher(self, prefix: str | None = None) -> zenoh.Publisher:
        """Publisher on the world message ``{prefix}/world/state``: DATA priority,
        batched, DROP (the loop never waits for a reader, as for the diagnostics)."""
        key = world_keys(prefix or self.keys.prefix).state
        return self._publisher(key, ENCODING_WORLD, zenoh.Priority.DATA, False,
                               zenoh.CongestionControl.DROP)

    def declare_collision_publisher(self, prefix: str | None = None) -> zenoh.Publisher:
        """Publisher on ``{prefix}/world/collision`` (one message per contact event):
        DATA priority, batched, DROP (the loop never waits for a reader)."""
        key = world_keys(prefix or self.keys.prefix).collision
        return self._publisher(key, ENCODING_COLLISION, zenoh.Priority.DATA, False,
                               zenoh.CongestionControl.DROP)

    def declare_storyboard_publisher(self, prefix: str | None = None) -> zenoh.Publisher:
        """Publisher on ``{prefix}/world/storyboard`` (a served scenario's storyboard state
        changes, put by its worker thread, never the tick): DATA priority, BLOCK (each
        line is one state change of the trace: none is dropped)."""
        key = world_keys(prefix or self.keys.prefix).storyboard
        return self._publisher(key, ENCODING_STORYBOARD, zenoh.Priority.DATA, False,
                               zenoh.CongestionControl.BLOCK)

    def declare_control_inbox(self, per_client: int = 16, keys: VehicleKeys | None = None,
                              validate: bool = True) -> ControlInbox:
        """Queryable serving every ``ctl/*`` key, ``per_client`` requests queued per client
        at most; poll it every tick.

        With ``validate=False`` requests come with their raw payload only (``args`` None)
        for a caller that validates them itself (the server's control table).
        """
        return self._keep(ControlInbox(self.session, keys or self.keys, per_client, validate))

    def declare_alive_token(self, keys: VehicleKeys | None = None) -> zenoh.LivelinessToken:
        """Liveliness token on ``alive`` (gone when undeclared, closed, or the process dies)."""
        return self._keep(self.session.liveliness().declare_token((keys or self.keys).alive))

    # ---------------------------------------------------------------- client side

    def declare_command_publisher(
        self, congestion_control: zenoh.CongestionControl = zenoh.CongestionControl.BLOCK
    ) -> zenoh.Publisher:
        """Publisher on ``cmd``: REAL_TIME priority, express, BLOCK."""
        return self._publisher(self.keys.cmd, ENCODING_COMMAND, zenoh.Priority.REAL_TIME,
                               True, congestion_control)

    def declare_state_inbox(self, capacity: int = 1024, decimated: bool = False) -> Inbox:
        """Subscriber on ``state`` (or with ``decimated`` on ``state/100hz``) with a ring
        of ``capacity``."""
        key = self.keys.state_decimated if decimated else self.keys.state
        return self._keep(Inbox(self.session, key, capacity))

    def declare_inbox(self, key: str, capacity: int = 16) -> Inbox:
        """Subscriber on any key (``{prefix}/world/state``, ...) with a ring of ``capacity``."""
        return self._keep(Inbox(self.session, key, capacity))

    def declare_diag_inbox(self, capacity: int = 64) -> Inbox:
        """Subscriber on ``diag`` with a ring of ``capacity``."""
        return self._keep(Inbox(self.session, self.keys.diag, capacity))

    def declare_alive_watch(self, key: str | None = None) -> AliveWatch:
        """Liveliness subscriber on this vehicle's token (or ``key``, e.g. ``prefix/*/alive``)."""
        return self._keep(AliveWatch(self.session, key or self.keys.alive))

    def alive_tokens(self, key: str | None = None, timeout_s: float = 1.0) -> list[str]:
        """Keys of the liveliness tokens present now (this vehicle's, or matching ``key``)."""
        replies = self.session.liveliness().get(key or self.keys.alive, timeout=timeout_s)
        return [str(r.ok.key_expr) for r in replies if r.ok is not None]

    def request_world(self, name: str, args: dict[str, Any] | None = None, *,
                      payload: bytes | None = None, timeout_s: float = 10.0) -> dict[str, Any]:
        """A world control (``{prefix}/world/ctl/{name}``: ``add_car``, ``remove_car``,
        ``get_config``) of this endpoint's prefix, as :meth:`request`."""
        keys = world_keys(self.keys.prefix)
        body = payload if payload is not None else encode_control(name, args,
                                                                  WORLD_CONTROL_SPECS)
        return self._query(keys.control(name), body, timeout_s)

    def request(
        self,
        name: str,
        args: dict[str, Any] | None = None,
        *,
        payload: bytes | None = None,
        timeout_s: float = 2.0,
    ) -> dict[str, Any]:
        """Send a control request and return the decoded reply.

        Parameters
        ----------
        name : str
            Control name (``"reset"``, ``"step"``, ...).
        args : dict, optional
            Arguments, validated locally first (:func:`simserver.wire.protocol.encode_control`).
        payload : bytes, optional
            Raw request body sent as is, instead of ``args`` (for tests of bad input).
        timeout_s : float, optional
            Query timeout.

        Returns
        -------
        dict
            ``{"ok": True, ...}`` or ``{"ok": False, "error": ..., "field": ...}``.

        Raises
        ------
        ProtocolError
            When ``args`` are invalid (nothing is sent) or the reply is malformed.
        TimeoutError
            When no queryable answered within ``timeout_s``.
        """
        key = self.keys.control(name)
        body = payload if payload is not None else encode_control(name, args)
        return self._query(key, body, timeout_s)

    def _query(self, key: str, body: bytes, timeout_s: float) -> dict[str, Any]:
        """A control query on ``key`` and its decoded reply (:meth:`request`)."""
        replies = self.session.get(
            key, payload=body, encoding=zenoh.Encoding(ENCODING_CONTROL), timeout=timeout_s,
            attachment=self._client_id,
        )
        for reply in replies:
            if reply.ok is not None:
                return decode_reply(reply.ok.payload.to_bytes())
            body = reply.err.payload.to_bytes()
            if body == ZENOH_TIMEOUT_REPLY:
                # a queryable matched but did not answer in time: zenoh's own error reply
                raise TimeoutError(f"no reply on {key} within {timeout_s} s (a queryable "
                                   f"matched: the server is busy or stalled)")
            return decode_reply(body)  # the server's errors (an unknown control) come so
        raise TimeoutError(f"no reply on {key} within {timeout_s} s (is the server up?)")
