"""The live server's timing: tick lateness, overruns, drift, and command-to-state latency.

Run from the repository root::

    python -m benchmarks.bench_server [--seconds 60] [--cmd-hz 200] [--hogs 2]

Starts ``simserver serve`` as a subprocess (state published every tick) on a free
loopback port; this process is the client: it publishes driver commands at ``--cmd-hz``
(a slow steer and throttle sweep, so the car drives) with ``sender_time_ns`` from the
shared monotonic clock, and times the first published state whose ``last_cmd_seq``
reflects each command (the server echoes the sender's timestamp). Each command goes out
at a random instant within its slot (uniform over one tick), as a driver's clock,
independent of the server's, would: a sender at a fixed period on the same clock keeps a
fixed phase to the server's ticks, and its latency would measure that one phase (any
value from the transport time to a tick more) instead of the distribution. States are
time-stamped on arrival in a zenoh callback, so the client's own polling does not add to
the figure. Tick lateness comes from the server's diagnostics (windows of 4096 ticks:
the median of the windows' p50 and p99 are quoted) and from its final statistics at
SIGTERM (maximum and late ticks over the whole run). Drift: simulated time (ticks x
1 ms) against the wall time between the first and last state received.

``--floor-seconds S`` (default 10) runs the bare pacer (``benchmarks.bench_clock``, the
VM's clock floor) S seconds just before and just after the server in the same command,
beside the same hogs: the server's figures are compared with what this VM gave an empty
loop in the same minutes.

``--hogs N`` starts N CPU-bound processes at normal priority for the whole run (a busy
machine). The server uses its default real-time scheduling (``--realtime auto``; pass
``--realtime off`` to compare) and so does this client, for its own zenoh threads and the
thread that sends commands (``--client-realtime off`` to leave it at normal priority): a
client starved by the hogs would time its own scheduling delay, not the server's.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from collections import deque
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import zenoh

from simserver.testing import Client, ServerProcess, wait_until
from simserver.wire import protocol as proto

TICK_S = 1e-3
"""The server's default period: a command's send instant is uniform over one of these."""


HOG = "while True: pass"


@contextmanager
def cpu_hogs(n: int):
    """``n`` CPU-bound processes at normal priority while the block runs."""
    hogs = [subprocess.Popen([sys.executable, "-c", HOG]) for _ in range(n)]
    try:
        yield hogs
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()


def run(seconds: float, cmd_hz: float, viewer: str = "off", hogs: int = 0,
        realtime: str = "auto", client_realtime: str = "auto",
        config: Path | None = None, ready: Callable[[], bool] | None = None,
        floor_seconds: float = 0.0) -> dict:
    """One server run of ``seconds`` with the live viewer ``viewer`` (a ``--viewer`` value),
    ``hogs`` CPU-bound processes beside it, the server's ``--realtime`` mode and this
    client's, and the server config ``config`` (default ``configs/server/default.yaml``).
    With ``ready``, the measured ``seconds`` start once it returns True (a process the
    server starts, such as the ROS 2 adapter, is then running; at most 120 s).

    With ``floor_seconds``, the bare pacer (:func:`benchmarks.interleaved.clock_floor`,
    scheduled as the server's tick thread, beside the same hogs) runs that long just
    before and just after the server: the VM's own lateness in the same minutes, under
    ``"clock_floor"`` (its late fraction and p99 over both runs, each run's too)."""
    from benchmarks.interleaved import clock_floor

    with cpu_hogs(hogs):
        before = clock_floor(floor_seconds) if floor_seconds > 0 else None
        r = _run(seconds, cmd_hz, viewer, realtime, client_realtime, config, ready)
        after = clock_floor(floor_seconds) if floor_seconds > 0 else None
    r |= {"hogs": hogs, "realtime": realtime, "client_realtime": client_realtime,
          "loadavg_1min": os.getloadavg()[0]}
    if before is not None:
        r["clock_floor"] = {
            "seconds": 2 * floor_seconds, "before": before, "after": after,
            "late_fraction": (before["late_fraction"] + after["late_fraction"]) / 2,
            "lateness_p99_us": max(before["lateness_p99_us"], after["lateness_p99_us"])}
    return r


def _run(seconds: float, cmd_hz: float, viewer: str, realtime: str,
         client_realtime: str, config: Path | None,
         ready: Callable[[], bool] | None = None) -> dict:
    # INFO: the publisher's hand-offs to its state-tx thread and back are logged, and quoted
    server = ServerProcess(scene=None, log_level="INFO", viewer=viewer, config=config,
                           extra_args=["--realtime", realtime])
    startup_s = server.ready_s
    try:
        return _measure(server, startup_s, seconds, cmd_hz, client_realtime, ready)
    finally:
        server.stop()  # also when the measurement failed: no server left behind


def _measure(server: ServerProcess, startup_s: float, seconds: float, cmd_hz: float,
             client_realtime: str, ready: Callable[[], bool] | None) -> dict:
    from simserver.server.realtime import RealtimeScheduler, RealtimeSettings

    # the server holds /dev/cpu_dma_latency itself (where permitted): the client leaves it
    client_rt = RealtimeScheduler(RealtimeSettings(mode=client_realtime, priority=40,
                                                   cpu_latency_us=None))
    latencies_us: list[float] = []
    delivery_ns: list[int] = []  # a state's arrival minus tick x period (+ a constant)
    diags: list[np.ndarray] = []
    first_state = last_state = None
    with Client(server, state_capacity=0) as client:
        ep, pub = client.ep, client.pub
        arrivals: deque[tuple[int, bytes]] = deque()

        def on_state(sample) -> None:  # zenoh's thread: stamp first, decode later
            arrivals.append((time.monotonic_ns(), sample.payload.to_bytes()))

        # indirect=False: stamped in zenoh's receiving thread (real-time with the client's
        # scheduling), not in a Python thread of zenoh's at normal priority that CPU hogs
        # would delay (that was this benchmark's own latency, not the server's)
        states = ep.session.declare_subscriber(
            ep.keys.state, zenoh.handlers.Callback(on_state, indirect=False))
        client_rt.apply()  # this thread and the client's zenoh threads
        if ready is not None:
            wait_until(ready, timeout_s=120.0, what="the server's companion process",
                       interval_s=0.05)
            arrivals.clear()
            client.diag.drain_newest()  # the windows of the wait are not measured
        diag = client.diag
        sent: dict[int, int] = {}
        seq = 0
        period_ns = int(TICK_S * 1e9)
        promote_at = time.monotonic() + 1.0
        period = 1.0 / cmd_hz
        rng = np.random.default_rng(7)
        t_slot = time.monotonic()
        t_end = t_slot + seconds
        t_next = t_slot + rng.uniform(0.0, TICK_S)
        while time.monotonic() < t_end:
            now = time.monotonic()
            if now >= t_next:
                seq += 1
                phase = now % 20.0
                t_ns = time.monotonic_ns()
                sent[seq] = t_ns
                pub.put(proto.encode_command(steer=0.2 * np.sin(phase / 3.0),
                                             throttle=0.3 if phase < 10 else 0.0,
                                             brake=0.0 if phase < 10 else 0.4,
                                             seq=seq, sender_time_ns=t_ns))
                t_slot += period
                t_next = t_slot + rng.uniform(0.0, TICK_S)
            while arrivals:
                t_rx, payload = arrivals.popleft()
                st = proto.decode_state(payload)
                if first_state is None:
                    first_state = (t_rx, int(st["tick"]))
                last_state = (t_rx, int(st["tick"]))
                delivery_ns.append(t_rx - int(st["tick"]) * period_ns)
                s = int(st["last_cmd_seq"])
                if s in sent:  # the first state reflecting command s
                    latencies_us.append((t_rx - sent.pop(s)) / 1e3)
            for payload in diag.drain_newest():
                diags.append(proto.decode_diagnostics(payload))
            time.sleep(0.0005)
            if now >= promote_at:  # once a second (it lists the threads, holding the GIL
                promote_at = now + 1.0  # that zenoh's thread needs to stamp an arrival)
                client_rt.promote_new_threads()
        states.undeclare()  # a callback subscriber would otherwise hold the exit
    server.stop()
    final = server.final_stats()
    lat = np.array(latencies_us)
    # the tick's own lateness, its work up to the publication, the put and the transport
    # (relative to the fastest state of the run: the deadlines' origin is not on the wire)
    delivery = np.array(delivery_ns, dtype=np.int64)
    delivery = (delivery - delivery.min()) / 1e3
    windows = [d for d in diags if int(d["window_ticks"]) >= 4096] or diags[-1:]
    if not windows:
        raise RuntimeError("no diagnostics received: run for a few seconds at least")
    wall_s = (last_state[0] - first_state[0]) / 1e9
    sim_s = (last_state[1] - first_state[1]) * 1e-3
    return {
        "seconds": seconds, "startup_s": startup_s,
        "ticks": final["ticks"],
        "lateness_p50_us": float(np.median([w["lateness_p50_us"] for w in windows])),
        "lateness_p99_us": float(np.median([w["lateness_p99_us"] for w in windows])),
        "lateness_p99_worst_window_us": float(max(w["lateness_p99_us"] for w in windows)),
        "lateness_max_us": final["lateness_max_us"],
        "late_ticks": final["late_ticks"], "late_fraction": final["late_ticks"] / final["ticks"],
        "overruns": final["overruns"], "skipped_ticks": final["skipped_ticks"],
        "drift_ms": 1e3 * (wall_s - sim_s), "wall_s": wall_s,
        "cpu_percent": float(np.median([d["cpu_percent"] for d in diags])),
        "commands": seq, "commands_acknowledged": int(lat.size),
        "latency_p50_us": float(np.percentile(lat, 50)),
        "latency_p99_us": float(np.percentile(lat, 99)),
        "latency_max_us": float(lat.max()),
        "state_delay_p50_us": float(np.percentile(delivery, 50)),
        "state_delay_p99_us": float(np.percentile(delivery, 99)),
        "cmd_rejected": final["cmd_rejected"], "cmd_stale": final["cmd_stale"],
        # states the tick put itself (not handed to the server's state-tx thread)
        "states_inline_fraction": final.get("publish_inline_puts", 0) / max(final["ticks"], 1),
        "publish_handoffs": final.get("publish_handoffs", 0),
        "publish_mode_lines": [line.split("state-tx: ", 1)[1].strip()
                               for line in server.output if "state-tx: states" in line],
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--cmd-hz", type=float, default=200.0)
    parser.add_argument("--viewer", default="off", help="the server's --viewer (default off)")
    parser.add_argument("--hogs", type=int, default=0,
                        help="CPU-bound processes at normal priority during the run")
    parser.add_argument("--realtime", default="auto", choices=("auto", "off"),
                        help="the server's --realtime (default auto)")
    parser.add_argument("--client-realtime", default="auto", choices=("auto", "off"),
                        help="real-time scheduling of this client (default auto)")
    parser.add_argument("--floor-seconds", type=float, default=10.0,
                        help="the bare pacer (the VM's clock floor) this long before and "
                        "after the server, beside the same hogs (0: none)")
    args = parser.parse_args(argv)
    r = run(args.seconds, args.cmd_hz, args.viewer, args.hogs, args.realtime,
            args.client_realtime, floor_seconds=args.floor_seconds)
    print(f"server run {r['seconds']:.0f} s (viewer {args.viewer}, {args.hogs} CPU hogs, "
          f"server realtime {args.realtime}, client realtime {args.client_realtime}, "
          f"load average {r['loadavg_1min']:.2f}), {r['ticks']} ticks, state every tick; "
          f"ready {r['startup_s']:.1f} s after launch")
    print(f"tick lateness: p50 {r['lateness_p50_us']:.1f} us, p99 {r['lateness_p99_us']:.1f} us"
          f" (worst 4096-tick window {r['lateness_p99_worst_window_us']:.0f} us), "
          f"max {r['lateness_max_us'] / 1e3:.2f} ms")
    print(f"ticks > 1 ms late: {r['late_ticks']} ({100 * r['late_fraction']:.2f} %), "
          f"overruns {r['overruns']}, skipped {r['skipped_ticks']}")
    print(f"drift of simulated from wall time over {r['wall_s']:.1f} s: {r['drift_ms']:+.2f} ms")
    print(f"command-to-state latency over {r['commands_acknowledged']} of {r['commands']} "
          f"commands: p50 {r['latency_p50_us']:.0f} us, p99 {r['latency_p99_us']:.0f} us, "
          f"max {r['latency_max_us'] / 1e3:.2f} ms")
    print(f"a state's arrival after its tick's deadline, beyond the run's fastest: p50 "
          f"{r['state_delay_p50_us']:.0f} us, p99 {r['state_delay_p99_us']:.0f} us")
    print(f"states put in the tick: {100 * r['states_inline_fraction']:.1f} % (the rest by "
          f"its state-tx thread; {r['publish_handoffs']} hand-offs to it)")
    for line in r["publish_mode_lines"]:
        print(f"  server: {line}")
    print(f"server CPU {r['cpu_percent']:.0f} % of a core; commands rejected "
          f"{r['cmd_rejected']}, stale {r['cmd_stale']}")
    floor = r.get("clock_floor")
    if floor:
        print(f"clock floor (the bare pacer as the tick thread, {floor['seconds'] / 2:g} s "
              f"before and after, same hogs): ticks > 1 ms late "
              f"{100 * floor['before']['late_fraction']:.2f} % / "
              f"{100 * floor['after']['late_fraction']:.2f} %, lateness p99 "
              f"{floor['before']['lateness_p99_us']:.0f} / "
              f"{floor['after']['lateness_p99_us']:.0f} us")
    return r


if __name__ == "__main__":
    main()
