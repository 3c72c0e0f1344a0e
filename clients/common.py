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
import signal
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from types import FrameType
from typing import Any

from simserver import protocol as proto
from simserver.adapters.zenoh_io import (
    ZenohConfigError,
    ZenohEndpoint,
    ZenohOpenError,
    make_zenoh_config,
)

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
                            f"{reply.get('protocol_version')}, this client "
                            f"{proto.PROTOCOL_VERSION}", EXIT_NO_SERVER)
                    return Connection(ep=ep, config=reply.get("config") or {}, where=where)
                last_error = f"get_config failed: {reply.get('error')}"
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


GEAR_NAMES = tuple(g.name for g in proto.Gear)
"""Gear letters by code: ``("P", "R", "N", "D")``."""


def gear_name(code: int) -> str:
    """Letter of a gear code (``"?"`` for an unknown one)."""
    return GEAR_NAMES[code] if 0 <= code < len(GEAR_NAMES) else "?"
