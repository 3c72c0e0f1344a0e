"""Real-time priority from RealtimeKit, for a server run by an ordinary user (issue 35).

Desktop Linux lets unprivileged programs (PipeWire, JACK clients) run threads at a
real-time priority through RealtimeKit, a system D-Bus service
(``org.freedesktop.RealtimeKit1``, Debian's ``rtkit``): the daemon, which holds
CAP_SYS_NICE, sets ``SCHED_RR`` (with ``SCHED_RESET_ON_FORK``) on a thread of the caller
when its policy allows (polkit's ``org.freedesktop.RealtimeKit1.acquire-real-time``:
an active local session by default). Its conditions, all checked by the daemon:

- the priority is at most its ``MaxRealtimePriority`` (20 by default);
- the process has set ``RLIMIT_RTTIME`` (hard limit) to at most its ``RTTimeUSecMax``
  (200 ms by default): a real-time thread that runs that long without blocking is killed
  by the kernel. The tick thread sleeps in every tick (``realtime.Pacer``), so it never
  comes near;
- a few threads and requests per user (25 threads, 25 requests in 20 s).

The D-Bus client is ``jeepney`` (pure Python, blocking I/O): one connection, two
property reads and one method call, from the tick thread before its clock starts
(``realtime.RealtimeScheduler.apply``), never in the tick.
"""

from __future__ import annotations

import os
import resource
from dataclasses import dataclass

BUS_NAME = "org.freedesktop.RealtimeKit1"
OBJECT_PATH = "/org/freedesktop/RealtimeKit1"
INTERFACE = "org.freedesktop.RealtimeKit1"
CALL_TIMEOUT_S = 2.0
"""A D-Bus call waits at most this long (a daemon that does not answer is no grant)."""


class RtkitError(Exception):
    """RealtimeKit did not grant a priority; the message says why (no system bus, no
    daemon, refused by its policy or its limits)."""


@dataclass(frozen=True)
class Grant:
    """What RealtimeKit granted: ``SCHED_RR`` at ``priority`` for thread ``tid``."""

    tid: int
    priority: int
    rttime_usec: int


def _bus_address() -> str:
    return os.environ.get("DBUS_SYSTEM_BUS_ADDRESS", "") or \
        "unix:path=/var/run/dbus/system_bus_socket"


def _connect():  # noqa: ANN202 - jeepney's connection type
    try:
        from jeepney.io.blocking import open_dbus_connection
    except ImportError as exc:  # pragma: no cover - declared in pyproject
        raise RtkitError(f"no D-Bus client ({exc})") from None
    try:
        return open_dbus_connection(bus="SYSTEM")
    except (OSError, RuntimeError, ValueError) as exc:
        why = getattr(exc, "strerror", None) or str(exc)
        raise RtkitError(f"no system D-Bus at {_bus_address()} ({why})") from None


def _call(conn, msg):  # noqa: ANN001, ANN202
    from jeepney import DBusErrorResponse
    from jeepney.wrappers import unwrap_msg

    try:
        return unwrap_msg(conn.send_and_get_reply(msg, timeout=CALL_TIMEOUT_S))
    except DBusErrorResponse as exc:
        detail = " ".join(str(a) for a in exc.data) if exc.data else ""
        raise RtkitError(f"{exc.name}{': ' + detail if detail else ''}") from None
    except TimeoutError:
        raise RtkitError(f"no answer from {BUS_NAME} within {CALL_TIMEOUT_S:g} s") \
            from None


def _property(conn, name: str) -> int:  # noqa: ANN001
    from jeepney import DBusAddress, Properties

    addr = DBusAddress(OBJECT_PATH, bus_name=BUS_NAME, interface=INTERFACE)
    (_, value), = _call(conn, Properties(addr).get(name))
    return int(value)


def limits() -> tuple[int, int]:
    """RealtimeKit's ``(MaxRealtimePriority, RTTimeUSecMax)``.

    Raises
    ------
    RtkitError
        No system bus, or no RealtimeKit on it.
    """
    conn = _connect()
    try:
        return _property(conn, "MaxRealtimePriority"), _property(conn, "RTTimeUSecMax")
    finally:
        conn.close()


def make_thread_realtime(tid: int, priority: int, pid: int | None = None) -> Grant:
    """Ask RealtimeKit for ``SCHED_RR`` at ``priority`` (capped at its maximum) for
    thread ``tid`` of process ``pid`` (default this one).

    Sets this process's ``RLIMIT_RTTIME`` to RealtimeKit's ``RTTimeUSecMax`` first (soft
    and hard: the daemon requires the hard limit), unless it is lower already.

    Raises
    ------
    RtkitError
        Not granted; the message names the reason RealtimeKit or the bus gave.
    """
    from jeepney import DBusAddress, new_method_call

    conn = _connect()
    try:
        max_priority, rttime_max = _property(conn, "MaxRealtimePriority"), \
            _property(conn, "RTTimeUSecMax")
        soft, hard = resource.getrlimit(resource.RLIMIT_RTTIME)
        if hard == resource.RLIM_INFINITY or hard > rttime_max:
            try:
                resource.setrlimit(resource.RLIMIT_RTTIME, (rttime_max, rttime_max))
            except (OSError, ValueError) as exc:
                raise RtkitError(f"RLIMIT_RTTIME cannot be set to {rttime_max} us "
                                 f"({exc})") from None
            hard = rttime_max
        priority = max(1, min(int(priority), max_priority))
        addr = DBusAddress(OBJECT_PATH, bus_name=BUS_NAME, interface=INTERFACE)
        _call(conn, new_method_call(addr, "MakeThreadRealtimeWithPID", "ttu",
                                    (os.getpid() if pid is None else pid, tid, priority)))
        return Grant(tid=tid, priority=priority, rttime_usec=int(hard))
    finally:
        conn.close()
