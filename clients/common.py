"""What the three clients share: connection flags, the start-up check, exit codes, pacing.

Every client connects as a zenoh peer that listens nowhere and connects to the server's
endpoint (default ``tcp/127.0.0.1:7447``, the server's embedded default), with multicast
scouting and shared memory off (:func:`simserver.adapters.zenoh_io.make_zenoh_config`),
or uses a standard zenoh config file (``--zenoh-config``) for routers and other hosts.

At start-up :func:`connect` asks whether a server is there: the vehicle's liveliness
token (``{prefix}/{vehicle}/alive``) and a ``get_config`` control, retried for
``--wait`` seconds. When nothing answers, the client prints one clear sentence and exits
with :data:`EXIT_NO_SERVER`.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from types import FrameType
from typing import Any, TextIO

import numpy as np

from simserver.adapters.validate import short_repr
from simserver.adapters.zenoh_io import (
    ZenohConfigError,
    ZenohEndpoint,
    ZenohOpenError,
    make_zenoh_config,
)
from simserver.wire import protocol as proto

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"
"""The server's embedded default endpoint (loopback only)."""

DEFAULT_WAIT_S = 2.0
"""How long the start-up check waits for a server before giving up."""

EXIT_OK = 0
"""Normal end (quit key, Ctrl-C, end of the maneuver, SIGTERM)."""
EXIT_FAILED = 1
"""The run started but failed (the server went away, a file could not be written)."""
EXIT_USAGE = 2
"""Bad command line, profile or scenario file: the message names the file and the key."""
EXIT_NO_SERVER = 3
"""No server answered at start-up."""


class ClientError(Exception):
    """An error to report in one line and exit with ``code`` (no traceback).

    Parameters
    ----------
    message : str
        The sentence printed after the program name.
    code : int
        Process exit code (:data:`EXIT_USAGE`, :data:`EXIT_NO_SERVER`, ...).
    """

    def __init__(self, message: str, code: int = EXIT_USAGE) -> None:
        super().__init__(message)
        self.code = code


COMMAND_RATE_RANGE_HZ = (10.0, 1000.0)
"""The command rates a sending client accepts (``--rate``)."""


def add_rate_arg(parser: argparse.ArgumentParser, default_hz: float) -> None:
    """Add ``--rate HZ``, the command rate (checked by :func:`check_rate`)."""
    lo, hi = COMMAND_RATE_RANGE_HZ
    parser.add_argument("--rate", metavar="HZ", type=float, default=default_hz,
                        help=f"command rate (default {default_hz:g} Hz; {lo:g} to {hi:g})")


def check_rate(rate_hz: float) -> None:
    """Raise :class:`ClientError` unless ``rate_hz`` is within ``COMMAND_RATE_RANGE_HZ``."""
    lo, hi = COMMAND_RATE_RANGE_HZ
    if not lo <= rate_hz <= hi:
        raise ClientError(f"--rate {rate_hz:g}: expected {lo:g} to {hi:g} Hz")


def add_connection_args(parser: argparse.ArgumentParser) -> None:
    """Add ``--connect``, ``--zenoh-config``, ``--prefix``, ``--vehicle-id``, ``--wait``.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The client's parser.
    """
    group = parser.add_argument_group("connection")
    group.add_argument(
        "--connect", metavar="ENDPOINT", action="append", default=None,
        help=f"zenoh endpoint of the server or a router (repeatable; default {DEFAULT_CONNECT})",
    )
    group.add_argument(
        "--zenoh-config", metavar="FILE", default=None,
        help="a standard zenoh JSON5/YAML config file (routers, TLS, access control); "
        "--connect overrides its endpoints",
    )
    group.add_argument("--prefix", default=proto.DEFAULT_PREFIX,
                       help=f"key-expression prefix (default {proto.DEFAULT_PREFIX})")
    group.add_argument("--vehicle-id", default=proto.DEFAULT_VEHICLE,
                       help=f"vehicle id (default {proto.DEFAULT_VEHICLE})")
    group.add_argument(
        "--wait", metavar="S", type=float, default=DEFAULT_WAIT_S,
        help=f"seconds to wait for the server at start-up (default {DEFAULT_WAIT_S:g})",
    )


def endpoints_text(args: argparse.Namespace) -> str:
    """The endpoints a client connects to, for messages."""
    if args.connect:
        return ", ".join(args.connect)
    if args.zenoh_config:
        return f"the endpoints of {args.zenoh_config}"
    return DEFAULT_CONNECT


@dataclass
class Connection:
    """An open endpoint and what the server said about itself.

    Attributes
    ----------
    ep : ZenohEndpoint
        The session, bound to the vehicle's keys.
    config : dict
        The ``config`` member of the server's ``get_config`` reply (server, vehicle,
        scene, road, keys).
    where : str
        ``"{prefix}/{vehicle} at {endpoints}"``, for messages.
    """

    ep: ZenohEndpoint
    config: dict[str, Any]
    where: str

    def close(self) -> None:
        """Close the session (idempotent)."""
        self.ep.close()


def connect(args: argparse.Namespace, prog: str) -> Connection:
    """Open the session and check that the vehicle's server answers.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed flags of :func:`add_connection_args`.
    prog : str
        Program name for messages.

    Returns
    -------
    Connection

    Raises
    ------
    ClientError
        :data:`EXIT_USAGE` for a bad prefix, vehicle id or zenoh config;
        :data:`EXIT_NO_SERVER` when neither the liveliness token nor ``get_config``
        answers within ``args.wait`` seconds.
    """
    try:
        keys = proto.vehicle_keys(args.prefix, args.vehicle_id)
    except proto.ProtocolError as exc:
        raise ClientError(f"bad --prefix/--vehicle-id: {exc}") from None
    connect_to = args.connect
    if connect_to is None and args.zenoh_config is None:
        connect_to = [DEFAULT_CONNECT]
    try:
        cfg = make_zenoh_config(listen=[] if args.zenoh_config is None else None,
                                connect=connect_to, config_file=args.zenoh_config)
        ep = ZenohEndpoint(cfg, prefix=keys.prefix, vehicle=keys.vehicle)
    except ZenohConfigError as exc:
        raise ClientError(f"zenoh configuration: {exc}") from None
    except ZenohOpenError as exc:
        raise ClientError(f"{exc} ({endpoints_text(args)})", EXIT_NO_SERVER) from None
    where = f"{keys.base} at {endpoints_text(args)}"
    deadline = time.monotonic() + max(0.0, args.wait)
    last_error = "no liveliness token"
    while True:
        try:
            if ep.alive_tokens(timeout_s=0.5):
                reply = ep.request("get_config", timeout_s=max(0.5, min(2.0, args.wait)))
                if reply.get("ok"):
                    if reply.get("protocol_version") != proto.PROTOCOL_VERSION:
                        ep.close()
                        raise ClientError(
                            f"the server on {where} speaks protocol version "
                            f"{short_repr(reply.get('protocol_version'))}, this "
                            f"client {proto.PROTOCOL_VERSION}", EXIT_NO_SERVER)
                    config = check_server_config(reply.get("config"))
                    return Connection(ep=ep, config=config, where=where)
                last_error = f"get_config failed: {short_repr(reply.get('error'))}"
        except TimeoutError:
            last_error = "get_config timed out"
        except proto.ProtocolError as exc:
            last_error = f"bad get_config reply: {exc}"
        if time.monotonic() >= deadline:
            break
        time.sleep(0.2)
    ep.close()
    raise ClientError(
        f"no simserver answers for {where} ({last_error} after {args.wait:g} s). "
        f"Start one with 'simserver serve', or check --connect, --prefix and --vehicle-id.",
        EXIT_NO_SERVER,
    )


def run_main(prog: str, body: Callable[[], int]) -> int:
    """Run a client's body, turning :class:`ClientError` into a message and an exit code.

    Parameters
    ----------
    prog : str
        Program name, printed before messages (``"simserver-driver: ..."``).
    body : callable
        Returns the exit code.

    Returns
    -------
    int
        The exit code.
    """
    try:
        return body()
    except ClientError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr, flush=True)
        return exc.code


def client_main(prog: str, build_parser: Callable[[], argparse.ArgumentParser],
                run: Callable[[argparse.Namespace], int], argv: Sequence[str] | None) -> int:
    """A client's entry point: parse ``argv`` (default ``sys.argv[1:]``) with the parser
    ``build_parser`` makes, then :func:`run_main` ``run(args)``; the exit code."""
    args = build_parser().parse_args(argv)
    return run_main(prog, lambda: run(args))


class StopFlag:
    """Set by SIGINT or SIGTERM; the clients' loops poll it and end cleanly.

    Use as a context manager: the previous handlers are restored on exit.
    """

    def __init__(self, signals: Sequence[int] = (signal.SIGINT, signal.SIGTERM)) -> None:
        self.signals = tuple(signals)
        self.stopped = False
        self.signal_name: str | None = None
        self._previous: dict[int, Any] = {}

    def _handle(self, signum: int, _frame: FrameType | None) -> None:
        self.stopped = True
        self.signal_name = signal.Signals(signum).name

    def __enter__(self) -> StopFlag:
        for s in self.signals:
            self._previous[s] = signal.signal(s, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        self._previous.clear()


class RatePacer:
    """A loop pacer on absolute deadlines ``t0 + k * period`` (no drift).

    Sleeps until the next deadline; when a wait comes back more than ``max_late``
    periods late (a stalled process), the missed deadlines are skipped and counted
    rather than run back to back.

    Parameters
    ----------
    rate_hz : float
        Loop rate.
    max_late : int, optional
        Late periods tolerated before skipping ahead.
    """

    def __init__(self, rate_hz: float, max_late: int = 5) -> None:
        if not rate_hz > 0:
            raise ValueError(f"rate must be positive, got {rate_hz}")
        self.period_s = 1.0 / rate_hz
        self.max_late = max_late
        self.t0 = time.monotonic()
        self.k = 0
        self.late = 0
        self.skipped = 0

    def start(self) -> float:
        """Restart the clock now; returns the start time (``time.monotonic()``)."""
        self.t0 = time.monotonic()
        self.k = 0
        return self.t0

    def wait(self, poll: Callable[[], None] | None = None, poll_s: float = 0.0005) -> float:
        """Sleep until the next deadline; returns the time since :meth:`start` (s).

        Parameters
        ----------
        poll : callable, optional
            Called about every ``poll_s`` while waiting (to take input as it arrives).
        poll_s : float, optional
            Poll interval.
        """
        self.k += 1
        deadline = self.t0 + self.k * self.period_s
        now = time.monotonic()
        while deadline > now:
            if poll is None:
                time.sleep(deadline - now)
            else:
                poll()
                time.sleep(min(poll_s, max(0.0, deadline - time.monotonic())))
            now = time.monotonic()
        late = now - deadline
        if late > self.period_s:
            self.late += 1
            if late > self.max_late * self.period_s:
                skip = int(late / self.period_s)
                self.k += skip
                self.skipped += skip
        return now - self.t0


class ServerPresence:
    """Follows the server's liveliness token; a loss counts only after a grace period.

    A zenoh link that is closed and re-opened (an overloaded machine, a router restart)
    drops the token and brings it back; a server that stopped does not come back.

    Parameters
    ----------
    ep : ZenohEndpoint
        The client's endpoint (its vehicle's ``alive`` key is watched).
    grace_s : float
        How long the token may be absent before :meth:`gone` says so.
    """

    def __init__(self, ep: ZenohEndpoint, grace_s: float = 3.0) -> None:
        self.watch = ep.declare_alive_watch()
        self.grace_s = grace_s
        self.present = True
        self.lost_at: float | None = None

    def gone(self) -> bool:
        """Poll the token's changes; True once it has been absent for ``grace_s``."""
        for _, present in self.watch.poll():
            self.present = present
            self.lost_at = None if present else time.monotonic()
        return self.lost_at is not None and time.monotonic() - self.lost_at > self.grace_s


# ------------------------------------------------------------------ what a client trusts
def _section(config: dict[str, Any], name: str) -> dict[str, Any]:
    value = config.get(name, {})
    if not isinstance(value, dict):
        raise proto.ProtocolError(f"config.{name}", "is not an object")
    return value


def _config_number(section: dict[str, Any], where: str, key: str, lo: float, hi: float,
                   integer: bool = False) -> None:
    if key not in section:
        return
    value = section[key]
    if isinstance(value, bool) or not isinstance(value, int | float) or \
            (integer and not isinstance(value, int)) or not math.isfinite(value) or \
            not lo <= value <= hi:
        raise proto.ProtocolError(f"config.{where}.{key}", f"expected a "
                                  f"{'whole ' if integer else ''}number in [{lo:g}, {hi:g}], "
                                  f"got {short_repr(value)}")


SERVER_CONFIG_TEXTS = (("server", "path"), ("vehicle", "name"), ("vehicle", "path"),
                       ("scene", "path"), ("scene", "terrain"))
"""Members of ``get_config``'s config a client shows or compares: strings when present."""


def check_server_config(config: Any) -> dict[str, Any]:
    """``get_config``'s ``config`` member, checked for what the clients read from it.

    Objects where sections are expected; ``server.period_s`` and ``server.state_every``
    within the server's own ranges; ``road`` numbers finite and within ``set_road``'s
    ranges (``protocol.CONTROL_SPECS``); names and paths strings. Members a client does
    not read are left as they are. Raises ``ProtocolError`` naming the member: a reply
    no server sends (on a network without access control anyone may answer).
    """
    if not isinstance(config, dict):
        raise proto.ProtocolError("config", "is not an object")
    server = _section(config, "server")
    _config_number(server, "server", "period_s", 1e-4, 0.1)
    _config_number(server, "server", "state_every", 1, 1000, integer=True)
    road = _section(config, "road")
    for arg in proto.CONTROL_SPECS["set_road"].args:
        _config_number(road, "road", arg.name, arg.lo, arg.hi)
    for name in ("vehicle", "scene", "keys"):
        _section(config, name)
    for name, key in SERVER_CONFIG_TEXTS:
        value = config.get(name, {}).get(key)
        if value is not None and (not isinstance(value, str) or len(value) > 4096):
            raise proto.ProtocolError(f"config.{name}.{key}", "expected a short text, got "
                                      f"{short_repr(value)}")
    return config


STATE_CONFIRM_PERIODS = 20
"""A new run of ticks (a reset, a load, a restarted server) is taken once the old one has
been silent for this many state periods (at least :data:`STATE_CONFIRM_MIN_S`)."""
STATE_CONFIRM_MIN_S = 0.1
STATE_TICK_SLACK = 1000
"""Ticks a state may run ahead of the wall clock since the last one (delivery jitter)."""
STATE_HELD_MAX = 4096
"""States of an unconfirmed new run held at most (the oldest beyond are dropped)."""
STATE_CANDIDATES_MAX = 8
"""Unconfirmed new runs followed at once (beyond: the one heard from longest ago is
dropped)."""
WARN_EVERY_S = 5.0


@dataclass
class StateFilter:
    """The VehicleStates a client takes: valid and in the server's order, counted otherwise.

    On a network without access control anyone may publish on the state key
    (``docs/security.md``). A state is **rejected** when it is malformed (size, version)
    or carries what no server publishes (:func:`simserver.wire.protocol.invalid_fields`:
    a non-finite value, a value outside its field's range, an undefined flag bit). It is
    **out of order** when its tick does not continue the run being followed: lower than
    the last (but a reset or load restarts the tick), or further ahead than the wall
    clock allows since the last state (plus :data:`STATE_TICK_SLACK`). A state that does
    not continue the run continues or starts a *candidate* run, held back; once the run
    has been silent for :data:`STATE_CONFIRM_PERIODS` state periods, the longest
    candidate that has continued replaces it (a reset, a load, a restarted server:
    ``restart`` in :meth:`take`'s result). A candidate that stops while the run goes on
    is dropped. Another publisher's states interleaved with the server's therefore never
    take over while the server publishes, and each is counted. States that continue the
    server's own run plausibly (finite, in range, the next ticks) cannot be told from the
    server's: only access control keeps them out (``docs/security.md``). Warnings: the
    first of each kind at once, then at most one every :data:`WARN_EVERY_S` with the
    counts.

    Parameters
    ----------
    period_s, state_every : float, int
        The server's tick period and state decimation (``get_config``).
    prog : str
        Program name for the warnings.
    out : file
        Where warnings go (None: nowhere, the counts only).
    """

    period_s: float = 0.001
    state_every: int = 1
    prog: str = "simserver-client"
    out: TextIO | None = sys.stderr
    rejected: int = 0
    out_of_order: int = 0
    last_tick: int | None = None
    last_recv_s: float = 0.0
    _candidates: list[list[tuple[bytes, int, float]]] = field(default_factory=list)
    _warned_s: float = -math.inf
    _warned_counts: tuple[int, int] = (0, 0)

    @property
    def confirm_s(self) -> float:
        return max(STATE_CONFIRM_MIN_S, STATE_CONFIRM_PERIODS * self.period_s * self.state_every)

    def _bound(self, last_tick: int, last_recv_s: float, recv_s: float) -> int:
        return last_tick + int(max(0.0, recv_s - last_recv_s) / self.period_s) + \
            STATE_TICK_SLACK + self.state_every

    def _continues(self, tick: int, recv_s: float) -> bool:
        return self.last_tick is not None and \
            self.last_tick <= tick <= self._bound(self.last_tick, self.last_recv_s, recv_s)

    def take(self, payloads: Sequence[bytes], recv_s: float
             ) -> list[tuple[bytes, int, str]]:
        """File the payloads received at ``recv_s`` (monotonic seconds), oldest first.

        Returns the states taken, in order: ``(payload, tick, kind)`` with ``kind``
        ``"next"`` (a later tick of the run), ``"repeat"`` (the same tick again: paused)
        or ``"restart"`` (the first state of a new run). Call it also with no payloads:
        a candidate run is confirmed with time.
        """
        out: list[tuple[bytes, int, str]] = []
        good = [p for p in payloads if len(p) == proto.STATE_SIZE]
        bad_size = len(payloads) - len(good)
        if bad_size:
            self._reject(bad_size, f"{bad_size} state(s) of the wrong size", recv_s)
        if good:
            raw = np.frombuffer(b"".join(good), dtype=np.uint8).reshape(len(good), -1)
            faults = proto.invalid_fields(raw, "state")
            ticks = raw[:, _TICK_OFFSET:_TICK_OFFSET + 8].copy().view("<u8").ravel()
            for payload, fault, tick in zip(good, faults.tolist(), ticks.tolist(),
                                            strict=True):
                if fault >= 0:
                    name = proto.STATE_FIELDS[fault].name
                    self._reject(1, f"a state with an invalid {name} (tick {tick})", recv_s)
                    continue
                self._file(payload, tick, recv_s, out)
        self._confirm(recv_s, out)
        self._maybe_report(recv_s)
        return out

    def _file(self, payload: bytes, tick: int, recv_s: float,
              out: list[tuple[bytes, int, str]]) -> None:
        if self.last_tick is None:  # the first state: the run to follow
            self.last_tick, self.last_recv_s = tick, recv_s
            out.append((payload, tick, "restart"))
            return
        if self._continues(tick, recv_s):
            kind = "repeat" if tick == self.last_tick else "next"
            self.last_tick, self.last_recv_s = tick, recv_s
            out.append((payload, tick, kind))
            return
        for run in self._candidates:  # a candidate run it continues
            _, cand_tick, cand_recv = run[-1]
            if cand_tick < tick <= self._bound(cand_tick, cand_recv, recv_s):
                run.append((payload, tick, recv_s))
                if len(run) > STATE_HELD_MAX:  # a run going on beside the server's
                    del run[0]
                    self._out_of_order(1, tick, recv_s)
                return
        self._candidates.append([(payload, tick, recv_s)])
        if len(self._candidates) > STATE_CANDIDATES_MAX:  # the one heard from longest ago
            oldest = min(self._candidates, key=lambda r: r[-1][2])
            self._candidates.remove(oldest)
            self._out_of_order(len(oldest), oldest[0][1], recv_s)

    def _confirm(self, recv_s: float, out: list[tuple[bytes, int, str]]) -> None:
        if not self._candidates:
            return
        silent = recv_s - self.last_recv_s >= self.confirm_s
        runs = [r for r in self._candidates if len(r) >= 2] if silent else []
        if runs:  # the old run ended: the longest candidate is the new one
            best = max(runs, key=len)
            for k, (payload, tick, _) in enumerate(best):
                out.append((payload, tick, "restart" if k == 0 else "next"))
            self.last_tick, self.last_recv_s = best[-1][1], best[-1][2]
            for run in self._candidates:
                if run is not best:
                    self._out_of_order(len(run), run[0][1], recv_s)
            self._candidates = []
            return
        for run in [r for r in self._candidates if recv_s - r[-1][2] >= self.confirm_s]:
            # a candidate that stopped while the run went on: not the server's
            self._candidates.remove(run)
            self._out_of_order(len(run), run[0][1], recv_s)

    def _out_of_order(self, n: int, tick: int, recv_s: float) -> None:
        self.out_of_order += n
        if self.out_of_order == n:
            self._warn(f"dropped {n} state(s) out of the server's order (tick {tick} while "
                       f"following tick {self.last_tick}): another publisher on the state "
                       "key?", recv_s)

    def _reject(self, n: int, what: str, recv_s: float) -> None:
        self.rejected += n
        if self.rejected == n:
            self._warn(f"dropped {what}: no server sends it; another publisher on the state "
                       "key?", recv_s)

    def _warn(self, text: str, recv_s: float) -> None:
        self._warned_s = recv_s
        self._warned_counts = (self.rejected, self.out_of_order)
        if self.out is not None:
            print(f"{self.prog}: warning: {text}", file=self.out, flush=True)

    def _maybe_report(self, recv_s: float) -> None:
        counts = (self.rejected, self.out_of_order)
        if counts != self._warned_counts and recv_s - self._warned_s >= WARN_EVERY_S:
            self._warn(self.summary(), recv_s)

    def summary(self) -> str:
        """The counts, for a warning or a final report."""
        return (f"{self.rejected} invalid and {self.out_of_order} out-of-order state(s) "
                "dropped so far")

    def newest(self, payloads: Sequence[bytes], recv_s: float) -> np.void | None:
        """:meth:`take` and decode the newest state taken (None if none was)."""
        taken = self.take(payloads, recv_s)
        return proto.decode_state(taken[-1][0]) if taken else None


def state_filter(conn: Connection, prog: str, out: TextIO | None = sys.stderr
                 ) -> StateFilter:
    """A :class:`StateFilter` with the server's period and state decimation."""
    server = conn.config.get("server", {})
    return StateFilter(period_s=float(server.get("period_s", 0.001)),
                       state_every=int(server.get("state_every", 1)), prog=prog, out=out)


_TICK_OFFSET = proto.STATE_DTYPE.fields["tick"][1]

GEAR_NAMES = tuple(g.name for g in proto.Gear)
"""Gear letters by code: ``("P", "R", "N", "D")``."""


def gear_name(code: int) -> str:
    """Letter of a gear code (``"?"`` for an unknown one)."""
    return GEAR_NAMES[code] if 0 <= code < len(GEAR_NAMES) else "?"
