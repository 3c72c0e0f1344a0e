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
property reads, then one method call per thread: the tick thread's from itself before
its clock starts (``realtime.RealtimeScheduler.apply``), the other threads' from a
thread of their own as they start, never in the tick.
"""

from __future__ import annotations

import os
import resource

BUS_NAME = "org.freedesktop.RealtimeKit1"
OBJECT_PATH = "/org/freedesktop/RealtimeKit1"
INTERFACE = "org.freedesktop.RealtimeKit1"
CALL_TIMEOUT_S = 2.0
"""A D-Bus call waits at most this long (a daemon that does not answer is no grant)."""


class RtkitError(Exception):
    """RealtimeKit did not grant a priority; the message says why (no system bus, no
    daemon, refused by its policy or its limits)."""


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


class RealtimeKit:
    """A connection to RealtimeKit on the system bus, its limits read once.

    Raises
    ------
    RtkitError
        No system bus, or no RealtimeKit on it.
    """

    def __init__(self) -> None:
        self.conn = _connect()
        try:
            self.max_priority = _property(self.conn, "MaxRealtimePriority")
            self.rttime_usec_max = _property(self.conn, "RTTimeUSecMax")
        except BaseException:
            self.conn.close()
            raise

    def limit_rttime(self, soft_share: float = 1.0) -> tuple[int, int]:
        """Set this process's ``RLIMIT_RTTIME`` hard limit to ``RTTimeUSecMax`` (unless
        lower already) and its soft one to ``soft_share`` of it; ``(soft, hard)`` in us.

        Raises
        ------
        RtkitError
            The limit cannot be set.
        """
        _, hard = resource.getrlimit(resource.RLIMIT_RTTIME)
        if hard == resource.RLIM_INFINITY or hard > self.rttime_usec_max:
            hard = self.rttime_usec_max
        soft = max(1, int(hard * soft_share))
        try:
            resource.setrlimit(resource.RLIMIT_RTTIME, (soft, hard))
        except (OSError, ValueError) as exc:
            raise RtkitError(f"RLIMIT_RTTIME cannot be set to {hard} us ({exc})") from None
        return soft, int(hard)

    def make_thread_realtime(self, tid: int, priority: int, pid: int | None = None) -> int:
        """``SCHED_RR`` at ``priority`` (capped at ``max_priority``) for thread ``tid``
        of process ``pid`` (default this one); the priority granted. Call
        :meth:`limit_rttime` first (RealtimeKit refuses otherwise).

        Raises
        ------
        RtkitError
            Not granted; the message names the reason RealtimeKit or the bus gave.
        """
        from jeepney import DBusAddress, new_method_call

        priority = max(1, min(int(priority), self.max_priority))
        addr = DBusAddress(OBJECT_PATH, bus_name=BUS_NAME, interface=INTERFACE)
        _call(self.conn, new_method_call(addr, "MakeThreadRealtimeWithPID", "ttu",
                                         (os.getpid() if pid is None else pid, tid,
                                          priority)))
        return priority

    def close(self) -> None:
        self.conn.close()


def limits() -> tuple[int, int]:
    """RealtimeKit's ``(MaxRealtimePriority, RTTimeUSecMax)``.

    Raises
    ------
    RtkitError
        No system bus, or no RealtimeKit on it.
    """
    kit = RealtimeKit()
    kit.close()
    return kit.max_priority, kit.rttime_usec_max
