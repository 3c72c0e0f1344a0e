"""Real-time scheduling of the live server (issue 13): the policy of its threads read from
the kernel (``os.sched_getscheduler`` on each thread id of ``/proc/PID/task``), the
fallback when the OS refuses a real-time policy, and ``--realtime off``."""

from __future__ import annotations

import os
import shutil
import sys

import pytest

from simserver.server.realtime import (
    RealtimeScheduler,
    RealtimeSettings,
    open_files,
    parse_cpus,
    process_threads,
    thread_policy,
)
from simserver.testing import Client, ServerProcess, free_port, serve_args, wait_until

pytestmark = [pytest.mark.timeout(300),
              pytest.mark.skipif(sys.platform != "linux", reason="Linux scheduling")]


def _fifo_permitted() -> bool:
    try:
        before = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        os.sched_setscheduler(0, before[0], before[1])
        return True
    except OSError:
        return False


def policies(server: ServerProcess) -> dict[str, list[tuple[str, int]]]:
    """Thread name -> the (policy, priority) of each thread of that name."""
    out: dict[str, list[tuple[str, int]]] = {}
    for tid, name in process_threads(server.pid).items():
        try:
            out.setdefault(name, []).append(thread_policy(tid))
        except OSError:
            continue  # ended meanwhile
    return out


CPU_LATENCY = "/dev/cpu_dma_latency"


def zenoh_threads_promoted(server: ServerProcess) -> dict[str, list[tuple[str, int]]]:
    """Wait (a client connected) until zenoh's rx threads are promoted; the policies."""
    return wait_until(lambda: policies(server),
                      lambda p: any(n.startswith("rx-") for n in p) and all(
                          pol == ("SCHED_FIFO", 49) for n, v in p.items()
                          if n.startswith(("rx-", "tx-")) for pol in v),
                      timeout_s=10, what="zenoh's rx/tx threads at SCHED_FIFO 49")


@pytest.mark.skipif(not _fifo_permitted(), reason="this test process may not use SCHED_FIFO")
def test_the_tick_thread_and_zenohs_threads_run_sched_fifo():
    with ServerProcess() as server, Client(server) as client:
        client.drive_until(lambda s: s["tick"] > 10, throttle=0.1)
        pol = zenoh_threads_promoted(server)
        # the main thread (named after the process) ticks: SCHED_FIFO at the priority
        assert thread_policy(server.pid) == ("SCHED_FIFO", 50)
        # zenoh's runtimes are promoted; the load worker (a child) is not
        assert all(v == [("SCHED_FIFO", 49)] for n, v in pol.items()
                   if n.startswith(("acc-", "app-", "net-")))
        for child in server.children():
            assert thread_policy(child) == ("SCHED_OTHER", 0)
        line = server.wait_for_line("real-time scheduling:")
        assert "SCHED_FIFO priority 50 for the tick thread" in line
        assert "SCHED_FIFO priority 49 for zenoh's threads (every thread started from " \
               "now on)" in line
        assert "warning" not in line
        if os.access(CPU_LATENCY, os.W_OK):  # held open by the server, said in the line
            assert "/dev/cpu_dma_latency held at 0 us" in line
            assert CPU_LATENCY in open_files(server.pid).values()


@pytest.mark.skipif(not _fifo_permitted(), reason="this test process may not use SCHED_FIFO")
def test_priority_and_cpus_are_configurable():
    with ServerProcess(extra_args=["--rt-priority", "20", "--rt-cpus", "0"]) as server:
        assert thread_policy(server.pid) == ("SCHED_FIFO", 20)
        assert os.sched_getaffinity(server.pid) == {0}
        assert "CPUs 0" in server.wait_for_line("real-time scheduling:")


def test_realtime_off_leaves_every_thread_alone():
    with ServerProcess(extra_args=["--realtime", "off"]) as server, Client(server) as client:
        client.drive_until(lambda s: s["tick"] > 10, throttle=0.1)
        assert all(pol == ("SCHED_OTHER", 0) for v in policies(server).values() for pol in v)
        assert "real-time scheduling: off" in server.wait_for_line("real-time scheduling:")
        assert CPU_LATENCY not in open_files(server.pid).values()


@pytest.mark.skipif(shutil.which("setpriv") is None or shutil.which("prlimit") is None
                    or os.geteuid() != 0, reason="needs root, setpriv and prlimit")
def test_without_permission_it_warns_and_falls_back_and_still_serves():
    """No CAP_SYS_NICE and an rtprio limit of 0: SCHED_FIFO and a negative nice are both
    refused; the server says so, names what to grant, and serves at normal priority."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    argv = ["setpriv", "--inh-caps=-all", "--bounding-set=-sys_nice",
            "prlimit", "--rtprio=0", "--nice=0", "--",
            *serve_args(listen=[endpoint])]
    with ServerProcess(argv=argv, listen=[endpoint]) as server, Client(server) as client:
        client.drive_until(lambda s: s["tick"] > 10, throttle=0.1)
        line = server.wait_for_line("real-time scheduling:")
        assert "WARNING" in line and "SCHED_FIFO refused" in line
        assert "CAP_SYS_NICE" in line and "ulimit -r 99" in line and "--realtime off" in line
        assert "nice -10 refused too" in line
        assert all(pol == ("SCHED_OTHER", 0) for v in policies(server).values() for pol in v)


def test_settings_are_validated():
    with pytest.raises(ValueError, match="expected one of auto, off"):
        RealtimeSettings(mode="on")
    with pytest.raises(ValueError, match="expected 2-99"):
        RealtimeSettings(priority=1)
    assert parse_cpus("0-2,5") == (0, 1, 2, 5)
    with pytest.raises(ValueError, match="not a CPU list"):
        parse_cpus("x")
    sched = RealtimeScheduler(RealtimeSettings(mode="off"))
    assert sched.apply() == "real-time scheduling: off (--realtime off)"
    assert sched.promote_new_threads() == 0
