"""Real time without root through RealtimeKit (issue 35 item 1).

An ordinary user may not set SCHED_FIFO; on a desktop, RealtimeKit (Debian's ``rtkit``,
``org.freedesktop.RealtimeKit1`` on the system D-Bus) grants a real-time priority to a
thread of such a user's process. The server asks it when SCHED_FIFO is refused.

Real parts: a system bus (``dbus-daemon`` with Debian's system policy), ``polkitd`` with
the project's rule (``configs/rtkit/50-simserver-realtime.rules``) and Debian's
``rtkit-daemon``, started by ``simserver.testing.rtkit_bus``; the server runs as an
unprivileged system user (``setpriv``: its own uid and groups, no capabilities, rtprio
limit 0), and the tick thread's policy is read from the kernel
(``/proc/PID/task/TID/sched`` and ``sched_getscheduler``).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest

from simserver.server.realtime import process_threads, thread_policy
from simserver.testing import (
    Client,
    ServerProcess,
    free_port,
    process_argv,
    rtkit_bus,
    serve_args,
    wait_until,
)

pytestmark = [pytest.mark.timeout(600),
              pytest.mark.skipif(rtkit_bus.missing() is not None,
                                 reason=str(rtkit_bus.missing()))]


COLD_READY_S = 480.0
"""The user's server loads the kernels copied from this tree's cache; a kernel not in it
yet (this tree's cache cold, or partly) is compiled there, minutes on a loaded machine."""


@pytest.fixture(scope="module")
def user_env():
    """The unprivileged user and its environment (its own kernel cache and HOME)."""
    user = rtkit_bus.unprivileged_user()
    home = Path(tempfile.mkdtemp(prefix="simserver-rt-home-", dir="/tmp"))
    os.chown(home, user.pw_uid, user.pw_gid)
    cache = rtkit_bus.user_kernel_cache(home / "numba", user)
    env = dict(os.environ, PYTHONUNBUFFERED="1", HOME=str(home), NUMBA_CACHE_DIR=str(cache))
    env.pop("DBUS_SYSTEM_BUS_ADDRESS", None)
    try:
        yield user, env
    finally:
        shutil.rmtree(home, ignore_errors=True)


def policies(server: ServerProcess) -> dict[str, list[tuple[str, int]]]:
    """Thread name -> the (policy, priority) of each thread of that name."""
    out: dict[str, list[tuple[str, int]]] = {}
    for tid, name in process_threads(server.pid).items():
        try:
            out.setdefault(name, []).append(thread_policy(tid))
        except OSError:
            continue  # ended meanwhile
    return out


def sched_field(pid: int, tid: int, name: str) -> int:
    """A field of ``/proc/PID/task/TID/sched`` (the kernel's own view of the thread)."""
    with open(f"/proc/{pid}/task/{tid}/sched", encoding="ascii") as fh:
        for line in fh:
            key, _, value = line.partition(":")
            if key.strip() == name:
                return int(value.split()[0])
    raise AssertionError(f"no {name} in /proc/{pid}/task/{tid}/sched")


def test_an_unprivileged_servers_tick_thread_gets_sched_rr_from_realtimekit(user_env):
    user, env = user_env
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with rtkit_bus.RtkitBus() as bus:
        argv = rtkit_bus.as_user(user, serve_args(listen=[endpoint]))
        with ServerProcess(argv=argv, listen=[endpoint], env=dict(env, **bus.env()),
                           ready_timeout_s=COLD_READY_S) as server, Client(server) as client:
            assert "serve" in process_argv(server.pid)
            assert os.stat(f"/proc/{server.pid}").st_uid == user.pw_uid
            client.drive_until(lambda s: s["tick"] > 10, throttle=0.1)
            line = server.wait_for_line("real-time scheduling:")
            assert "SCHED_FIFO refused" in line, line
            assert "RealtimeKit granted SCHED_RR priority 20 for the tick thread" in line, line
            assert "warning" not in line, line
            # the main thread ticks: SCHED_RR (2) at 20, from the kernel, as RealtimeKit
            # set it (with SCHED_RESET_ON_FORK: the children are not real-time)
            assert thread_policy(server.pid) == ("SCHED_RR", 20)
            assert sched_field(server.pid, server.pid, "policy") == 2
            assert sched_field(server.pid, server.pid, "prio") == 99 - 20
            for child in server.children():
                assert thread_policy(child) == ("SCHED_OTHER", 0)
            # zenoh's threads (and the server's other threads) one lower, asked of
            # RealtimeKit by a thread of the server's own
            pol = wait_until(lambda: policies(server),
                             lambda p: any(n.startswith("rx-") for n in p) and all(
                                 v == ("SCHED_RR", 19) for n, vs in p.items()
                                 if n.startswith(("rx-", "tx-")) for v in vs),
                             timeout_s=20, what="zenoh's rx/tx threads at SCHED_RR 19")
            assert sum(v == ("SCHED_RR", 19) for vs in pol.values() for v in vs) >= 4, pol
            line = server.wait_for_line("real-time scheduling:")
            assert "SCHED_RR priority 19 from RealtimeKit for zenoh's threads" in line, line
            # RealtimeKit's condition, and the soft limit under it
            with open(f"/proc/{server.pid}/limits", encoding="ascii") as fh:
                rttime = next(ln for ln in fh if ln.startswith("Max realtime timeout"))
            assert rttime.split()[3:5] == ["100000", "200000"], rttime
        assert "Successfully made thread" in bus.rtkit.text()


def test_without_realtimekit_the_warning_states_the_expected_lateness(user_env):
    user, env = user_env
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    argv = rtkit_bus.as_user(user, serve_args(listen=[endpoint]))
    no_bus = dict(env, DBUS_SYSTEM_BUS_ADDRESS="unix:path=/nonexistent/system_bus_socket")
    with ServerProcess(argv=argv, listen=[endpoint], env=no_bus,
                       ready_timeout_s=COLD_READY_S) as server:
        line = server.wait_for_line("real-time scheduling:")
        assert "WARNING" in line and "SCHED_FIFO refused" in line, line
        assert "RealtimeKit granted nothing (no system D-Bus at " \
               "unix:path=/nonexistent/system_bus_socket" in line, line
        assert "1.9 % of ticks were more than 1 ms late" in line, line
        assert "up to 46 % of the deadlines" in line, line
        assert thread_policy(server.pid) == ("SCHED_OTHER", 0)
