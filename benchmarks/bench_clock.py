"""The bare 1 kHz wall-clock pacer: how late do ticks start when the loop does nothing?

Run from the repository root::

    python -m benchmarks.bench_clock [--seconds 10] [--period-us 1000] [--spin-us 200]
        [--realtime off|auto] [--cpu-latency-us N] [--save FILE] [--json]
    python -m benchmarks.bench_clock --compare 8 --seconds 5

Runs :class:`simserver.server.realtime.Pacer` for the given wall time with an empty loop body and
prints, over every tick: start lateness p50 / p99 / max, the number and share of ticks
more than 1 ms late, overruns and skipped ticks, the achieved period, the drift of the
deadline sequence from wall time, and the process CPU use. This is the floor under the
server's own figures (issue 4 targets: lateness p99 under 100 us, under 1 % of ticks more
than 1 ms late; this VM alone stalls 0.3-0.7 % of periods, as this benchmark shows).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys

import numpy as np

from simserver.server.realtime import (
    CpuMeter,
    Pacer,
    RealtimeScheduler,
    RealtimeSettings,
    hold_cpu_latency,
)

WINDOW_TICKS = 4096
"""The server's statistics window (``diagnostics``' ``window_ticks``)."""
WINDOW_EVERY = 200
"""Ticks between two windows: the server's diagnostics at 5 Hz (``diag_hz``)."""


def windowed_p99_median(lateness_us: np.ndarray) -> float:
    """The median over sliding ``WINDOW_TICKS``-tick windows, one every ``WINDOW_EVERY``
    ticks, of each window's lateness p99: the figure ``benchmarks.bench_server`` quotes
    from the server's diagnostics, computed the same way from every tick of this run."""
    if lateness_us.size <= WINDOW_TICKS:
        return float(np.percentile(lateness_us, 99))
    windows = np.lib.stride_tricks.sliding_window_view(lateness_us, WINDOW_TICKS)
    return float(np.median(np.percentile(windows[::WINDOW_EVERY], 99, axis=1)))


def run(seconds: float, period_us: float, spin_us: float, max_catchup: int,
        save: str | None = None) -> dict:
    """Run the pacer for ``seconds`` of wall time; return the figures as a dict (with
    ``save``, every tick's start time goes to that file)."""
    period_ns = round(period_us * 1000)
    n_ticks = int(round(seconds * 1e9 / period_ns))
    pacer = Pacer(
        period_ns,
        spin_ns=round(spin_us * 1000),
        max_catchup_ticks=max_catchup,
        late_threshold_ns=1_000_000,
        window=n_ticks + 1,  # keep every tick
    )
    cpu = CpuMeter()
    starts = np.zeros(n_ticks, dtype=np.int64) if save else None
    pacer.start()
    wait = pacer.wait
    if starts is None:
        for _ in range(n_ticks):
            wait()
    else:
        i = 0
        try:  # a peer is ended by SIGINT: it saves what it has
            for i in range(n_ticks):
                starts[i] = wait() + pacer.deadline_ns
            i = n_ticks
        except KeyboardInterrupt:
            pass
        np.save(save, starts[:i])
    end_ns = pacer.clock()
    cpu_percent = cpu.percent()
    s = pacer.stats()
    lat_us = pacer.lateness_window() / 1000.0
    # Simulated time (one period per tick) against wall time, from the first tick's start
    # to the last one's: the difference is the last tick's lateness minus the first's,
    # plus skipped periods. With absolute deadlines it does not grow with the run length.
    first_start_ns = pacer.t0_ns + int(round(lat_us[0] * 1000))
    last_start_ns = pacer.deadline_ns + pacer.lateness_ns
    sim_span_ns = (pacer.ticks - 1) * period_ns
    drift_us = (last_start_ns - first_start_ns - sim_span_ns) / 1000.0
    return {
        "lateness_p99_windows_median_us": windowed_p99_median(lat_us),
        "seconds": seconds,
        "period_us": period_us,
        "spin_us": spin_us,
        "ticks": s.ticks,
        "lateness_p50_us": s.lateness_p50_us,
        "lateness_p99_us": s.lateness_p99_us,
        "lateness_p999_us": float(np.percentile(lat_us, 99.9)),
        "lateness_max_us": s.lateness_max_us,
        "late_over_1ms": s.late_ticks,
        "late_over_1ms_percent": 100.0 * s.late_ticks / max(s.ticks, 1),
        "late_over_100us": int(np.sum(lat_us > 100.0)),
        "overruns": s.overruns,
        "skipped_ticks": s.skipped_ticks,
        "period_p50_us": s.period_p50_us,
        "period_p99_us": s.period_p99_us,
        "period_min_us": s.period_min_us,
        "period_max_us": s.period_max_us,
        "period_mean_us": s.period_mean_us,
        "drift_us": drift_us,
        "last_lateness_us": float(lat_us[-1]),
        "wall_s": (end_ns - pacer.t0_ns) / 1e9,
        "cpu_percent": cpu_percent,
    }


COMPARED = {"spin 200 us": ["--spin-us", "200"], "spin 500 us": ["--spin-us", "500"],
            "spin 200 us, cpu_dma_latency 0": ["--spin-us", "200", "--cpu-latency-us", "0"]}
"""The pacer's variants of ``--compare`` (issue 13: ``--hogs 0`` was worse than ``--hogs
2``, the idle vCPU waking late: does a longer spin or a polling idle keep the tick from
depending on that wake-up?)."""


def compare(rounds: int, seconds: float) -> dict:
    """The variants of :data:`COMPARED`, interleaved over ``rounds``; printed medians."""
    import subprocess

    out: dict[str, list[dict]] = {name: [] for name in COMPARED}
    for i in range(rounds):
        for name, extra in COMPARED.items():
            proc = subprocess.run(
                [sys.executable, "-m", "benchmarks.bench_clock", "--seconds", f"{seconds:g}",
                 "--realtime", "auto", "--json", *extra], capture_output=True, text=True,
                timeout=seconds + 120, check=True)
            out[name].append(json.loads(proc.stdout.strip().splitlines()[-1]))
        print(f"round {i + 1}: " + "; ".join(
            f"{name} {rs[-1]['late_over_1ms_percent']:.2f} % late, p99 "
            f"{rs[-1]['lateness_p99_windows_median_us']:.0f} us" for name, rs in out.items()),
            flush=True)
    for name, rs in out.items():
        late = np.median([r["late_over_1ms_percent"] for r in rs])
        print(f"{name:32s}: ticks > 1 ms late {late:.3f} % (median of {rounds} rounds), "
              "lateness p99 "
              f"{np.median([r['lateness_p99_windows_median_us'] for r in rs]):.0f} us, CPU "
              f"{np.median([r['cpu_percent'] for r in rs]):.0f} %")
    return out


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, run, print a table (and optionally JSON)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--period-us", type=float, default=1000.0)
    parser.add_argument("--spin-us", type=float, default=200.0,
                        help="sleep until this long before each deadline, then spin (0: sleep)")
    parser.add_argument("--max-catchup", type=int, default=100)
    parser.add_argument("--realtime", default="off", choices=("off", "auto"),
                        help="the pacer's thread scheduled as the server's tick thread is "
                        "(auto: SCHED_FIFO at its default priority, if permitted): the floor "
                        "under a real-time server's figures (default off)")
    parser.add_argument("--cpu-latency-us", type=int, default=None,
                        help="hold /dev/cpu_dma_latency at this many us while running (0: "
                        "the idle vCPU polls instead of halting, so its wake-up does not "
                        "wait for the hypervisor; needs root)")
    parser.add_argument("--compare", type=int, default=0, metavar="ROUNDS",
                        help="instead: the pacer as the tick thread with spin 200 us, spin "
                        "500 us, and spin 200 us with --cpu-latency-us 0, each --seconds "
                        "per round, in ROUNDS interleaved rounds (own processes); medians")
    parser.add_argument("--json", action="store_true", help="also print the figures as JSON")
    parser.add_argument("--save", metavar="FILE", default=None,
                        help="write every tick's start time (CLOCK_MONOTONIC ns, numpy .npy): "
                        "a peer of a server run, whose stalls are the VM's (benchmarks."
                        "bench_load compares them with the server's)")
    args = parser.parse_args(argv)
    if args.compare:
        compare(args.compare, args.seconds)
        return 0
    latency_fd = hold_cpu_latency(args.cpu_latency_us) \
        if args.cpu_latency_us is not None else None
    # the latency hold is this benchmark's variable: the scheduler leaves it alone
    scheduling = RealtimeScheduler(RealtimeSettings(mode=args.realtime,
                                                    cpu_latency_us=None)).apply()
    if latency_fd is not None:
        scheduling += f"; /dev/cpu_dma_latency held at {args.cpu_latency_us} us"
    r = run(args.seconds, args.period_us, args.spin_us, args.max_catchup, args.save)
    r["scheduling"] = scheduling
    print(f"pacer: {r['ticks']} ticks of {r['period_us']:g} us over {r['wall_s']:.2f} s "
          f"(spin {r['spin_us']:g} us), Python {platform.python_version()}, "
          f"{platform.machine()}; {r['scheduling']}")
    print(f"  lateness   p50 {r['lateness_p50_us']:8.1f} us   p99 {r['lateness_p99_us']:8.1f} us"
          f"   p99.9 {r['lateness_p999_us']:8.1f} us   max {r['lateness_max_us']:9.1f} us")
    print(f"  late > 1 ms  {r['late_over_1ms']} ticks ({r['late_over_1ms_percent']:.3f} %)"
          f"   late > 100 us  {r['late_over_100us']} ticks"
          f"   overruns {r['overruns']}   skipped {r['skipped_ticks']}")
    print(f"  period     p50 {r['period_p50_us']:8.1f} us   p99 {r['period_p99_us']:8.1f} us"
          f"   min {r['period_min_us']:7.1f} us   max {r['period_max_us']:9.1f} us"
          f"   mean {r['period_mean_us']:.4f} us")
    print(f"  wall minus simulated time at the last tick: {r['drift_us']:.3f} us "
          f"(last tick's lateness {r['last_lateness_us']:.1f} us; skipped periods add)")
    print(f"  CPU {r['cpu_percent']:.1f} % of one core")
    if args.json:
        print(json.dumps(r))
    return 0


if __name__ == "__main__":
    sys.exit(main())
