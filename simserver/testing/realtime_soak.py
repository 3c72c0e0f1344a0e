"""Real-time soak of the live server: a driver, a recorder and joiners for a wall duration.

Starts ``simserver serve`` (no viewer) on a free loopback port and, each in its own
process (``simserver.testing.roles``), as a lab would run them:

- a **driver** commanding at ``rate_hz`` (1 kHz) on absolute deadlines: a plausible
  stop-and-go cycle (throttle with a slow weave, brake to a stop, hold), ``seq`` from 1;
- a **recorder**: subscribes to the state and the diagnostics and appends every state
  payload to a file, checking the tick numbers for gaps;
- **joiners**: every ``join_every_s`` seconds a client connects, subscribes to the state,
  asks ``get_config`` and leaves after 1-4 s; every third one is killed with SIGKILL
  instead of leaving cleanly.

At the end the driver stops first (it reports how many commands it sent), then the
server's diagnostics are read (``cmd_received``: every command sent while the server was
up must have arrived, since no other process commands), then the server gets SIGTERM and
prints its final statistics. Reported: missed deadlines (late ticks, overruns, skipped
deadlines, lateness), lost and stale commands, states lost by the recorder, and the
server's memory (``VmRSS`` sampled once a second from ``/proc/PID/status``, and
``VmHWM``, the peak).

``benchmarks/bench_realtime_soak.py`` is its command line; ``tests/test_faults.py`` runs
a short one.
"""

from __future__ import annotations

import math
import random
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from simserver.testing import Client, RoleProcess, ServerProcess
from simserver.testing.roles import percentile
from simserver.wire import protocol as proto


@dataclass
class SoakReport:
    """Figures of one real-time soak."""

    seconds: float
    rate_hz: float
    commands_sent: int = 0
    commands_received: int = 0
    commands_lost: int = 0
    commands_rejected: int = 0
    commands_stale: int = 0
    watchdog_trips_while_driving: int = 0
    ticks: int = 0
    late_ticks: int = 0
    overruns: int = 0
    skipped_ticks: int = 0
    lateness_max_us: float = math.nan
    lateness_p99_us_worst_window: float = math.nan
    period_p99_us_median_window: float = math.nan
    states_published: int = 0
    recorder: dict[str, Any] = field(default_factory=dict)
    joiners: int = 0
    joiners_killed: int = 0
    joiners_config_ok: int = 0
    rss_start_kb: int = 0
    rss_end_kb: int = 0
    rss_growth_kb: int = 0
    rss_slope_kb_per_min: float = math.nan
    rss_samples: list[tuple[float, int]] = field(default_factory=list)
    vm_hwm_kb: int = 0
    server_alive_at_end: bool = False
    server_exit_code: int | None = None
    final_stats: dict[str, Any] | None = None

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready figures."""
        return {k: v for k, v in self.__dict__.items()}


def run_realtime_soak(seconds: float, rate_hz: float = 1000.0, join_every_s: float = 3.0,
                      workdir: Path | None = None, log: Any = print,
                      seed: int = 1) -> SoakReport:
    """Run the live server with a driver, a recorder and joiners for ``seconds`` (wall).

    Returns
    -------
    SoakReport
        See the module docstring. ``commands_lost`` = sent - received by the server.
    """
    import tempfile

    rng = random.Random(seed)
    own_tmp = None
    if workdir is None:
        own_tmp = tempfile.TemporaryDirectory(prefix="rt_soak_")
        workdir = Path(own_tmp.name)
    rep = SoakReport(seconds=seconds, rate_hz=rate_hz)
    server = ServerProcess(log_level="WARNING")
    roles: list[RoleProcess] = []
    joiners: list[tuple[RoleProcess, float, bool]] = []
    windows_p99: list[float] = []
    windows_period: list[float] = []
    try:
        conn = ["--connect", server.endpoint]
        with Client(server) as probe:
            recorder = RoleProcess("recorder", [*conn, "--out", str(workdir / "states.bin")])
            roles.append(recorder)
            driver = RoleProcess("driver", [*conn, "--rate", str(rate_hz)])
            roles.append(driver)
            probe.wait_state(lambda s: not s["flags"] & proto.StateFlag.WATCHDOG,
                             what="the driver's commands moving the car")
            trips0 = int(probe.diagnostics()["watchdog_trips"])
            rss: list[tuple[float, int]] = []
            t0 = time.monotonic()
            next_join = t0 + join_every_s
            next_sample = t0
            end = t0 + seconds
            while time.monotonic() < end:
                now = time.monotonic()
                if now >= next_sample:
                    rss.append((now - t0, server.memory_kb()["VmRSS"]))
                    next_sample += 1.0
                    for payload in probe.diag.drain_newest():
                        d = proto.decode_diagnostics(payload)
                        windows_p99.append(float(d["lateness_p99_us"]))
                        windows_period.append(float(d["period_p99_us"]))
                if join_every_s > 0 and now >= next_join:
                    rep.joiners += 1
                    kill = rep.joiners % 3 == 0
                    life = rng.uniform(1.0, 4.0)
                    # a killed joiner vanishes mid-session; the others leave by themselves
                    due = now + (0.6 * life if kill else life + 0.5)
                    joiners.append((RoleProcess("joiner", [*conn, "--seconds", f"{life:.2f}"],
                                                wait_ready_s=None), due, kill))
                    next_join += join_every_s
                for j in [j for j in joiners if now >= j[1]]:
                    proc, _, kill = j
                    if kill and proc.proc.poll() is None and not proc.wait_ready(0.0):
                        continue  # still starting: kill it once its session is up
                    joiners.remove(j)
                    if kill and proc.proc.poll() is None:
                        proc.kill()
                        rep.joiners_killed += 1
                    else:
                        res = proc.wait(10.0)
                        rep.joiners_config_ok += int(bool(res and res["config_ok"]))
                if not server.alive():
                    break
                probe.states.drain_newest()
                time.sleep(0.05)
            for proc, _, _ in joiners:
                proc.kill()
            joiners.clear()
            rss.append((time.monotonic() - t0, server.memory_kb()["VmRSS"]))
            rep.rss_samples = [(round(t, 1), kb) for t, kb in rss]
            rep.server_alive_at_end = server.alive()
            rep.recorder = recorder.stop() or {}  # its figures cover the driving only
            sent = driver.stop()
            # a diagnostics message published after the last command arrived (if none was
            # lost) and the watchdog took over from the stopped driver
            try:
                diag = probe.wait_diagnostics(
                    lambda d: int(d["cmd_received"]) >= int(sent["sent"] if sent else 0)
                    and int(d["watchdog_trips"]) > trips0, timeout_s=5.0,
                    what="every command sent counted, and the watchdog tripped")
            except TimeoutError:
                diag = probe.diagnostics()
            rep.commands_sent = int(sent["sent"]) if sent else -1
            rep.commands_received = int(diag["cmd_received"])
            rep.commands_lost = rep.commands_sent - rep.commands_received
            rep.commands_rejected = int(diag["cmd_rejected"])
            rep.commands_stale = int(diag["cmd_stale"])
            rep.watchdog_trips_while_driving = int(diag["watchdog_trips"]) - trips0 - 1
            mem = server.memory_kb()
            rep.vm_hwm_kb = mem["VmHWM"]
            start = next((kb for t, kb in rss if t >= min(2.0, seconds / 4)), rss[0][1])
            rep.rss_start_kb = start
            rep.rss_end_kb = rss[-1][1]
            rep.rss_growth_kb = rep.rss_end_kb - rep.rss_start_kb
            tail = [(t, kb) for t, kb in rss if t >= seconds / 4]
            if len(tail) >= 3:
                ts, kbs = np.array(tail, dtype=float).T
                rep.rss_slope_kb_per_min = round(float(np.polyfit(ts, kbs, 1)[0]) * 60.0, 1)
    finally:
        for proc, _, _ in joiners:
            proc.kill()
        for r in roles:
            r.stop()
        rep.server_exit_code = server.stop()
        if own_tmp is not None:
            own_tmp.cleanup()
    stats = server.final_stats() or {}
    rep.final_stats = stats
    rep.ticks = int(stats.get("steps_total", 0))
    rep.late_ticks = int(stats.get("late_ticks", -1))
    rep.overruns = int(stats.get("overruns", -1))
    rep.skipped_ticks = int(stats.get("skipped_ticks", -1))
    rep.lateness_max_us = float(stats.get("lateness_max_us", math.nan))
    rep.states_published = int(stats.get("state_published", 0))
    rep.lateness_p99_us_worst_window = round(max(windows_p99), 1) if windows_p99 else math.nan
    rep.period_p99_us_median_window = round(percentile(windows_period, 50), 1)
    return rep


def format_report(rep: SoakReport) -> str:
    """A human-readable summary."""
    r = rep.recorder or {}
    lines = [
        f"real-time soak: {rep.seconds:.0f} s wall, driver at {rep.rate_hz:.0f} Hz, "
        f"{rep.joiners} joiners ({rep.joiners_killed} killed -9)",
        f"  commands: sent {rep.commands_sent}, received {rep.commands_received}, lost "
        f"{rep.commands_lost}, rejected {rep.commands_rejected}, stale (superseded within a "
        f"tick) {rep.commands_stale}, watchdog trips while driving "
        f"{rep.watchdog_trips_while_driving}",
        f"  ticks: {rep.ticks}, late (> 1 ms) {rep.late_ticks} "
        f"({100.0 * rep.late_ticks / max(rep.ticks, 1):.3f} %), overruns {rep.overruns}, "
        f"skipped deadlines {rep.skipped_ticks}, max lateness {rep.lateness_max_us:.0f} us, "
        f"worst window p99 lateness {rep.lateness_p99_us_worst_window} us, "
        f"median window p99 period {rep.period_p99_us_median_window} us",
        f"  recorder: {r.get('states')} states of {rep.states_published} published, "
        f"{r.get('missing_ticks')} missing ticks in {r.get('gaps')} gaps, command age p50 "
        f"{r.get('cmd_age_p50_ms')} ms p99 {r.get('cmd_age_p99_ms')} ms max "
        f"{r.get('cmd_age_max_ms')} ms",
        f"  server memory: VmRSS {rep.rss_start_kb} -> {rep.rss_end_kb} kB "
        f"({rep.rss_growth_kb:+d} kB, slope {rep.rss_slope_kb_per_min} kB/min after the "
        f"first quarter), VmHWM {rep.vm_hwm_kb} kB",
        f"  server alive at the end: {rep.server_alive_at_end}, exit code "
        f"{rep.server_exit_code}",
    ]
    return "\n".join(lines)
