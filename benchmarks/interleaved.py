"""Server configurations compared in interleaved rounds, beside the VM's own stall floor.

Shared by the benchmarks that compare the server's tick lateness across modes
(``benchmarks.bench_viewer``: the live viewer off, to a file, to a stalled viewer;
``benchmarks.bench_ros2``: the ROS 2 adapter off and on).

This VM stalls on its own: ``benchmarks.bench_clock``, the bare pacer with an empty loop,
is 0.3 % late in one minute and 5 % in another. One long run per mode compares two
stretches of that weather rather than the modes (``python -m benchmarks`` once gave the
adapter "off" 3.11 ms p99 against "on" 427 us, because the "off" rounds hit stalls). So:

- every mode runs once a round, in the same order (A B A B ...), over many short rounds,
  so slow drifts and stalls spread over all modes;
- each mode's figure is the median over rounds of its per-round p99 (itself the median of
  the server's 4096-tick windows): a stalled round moves it little; the per-round values
  and the paired ratio (the median over rounds of mode / first mode in the same round) are
  quoted beside it;
- after each round the bare pacer runs as the server's tick thread is scheduled
  (``bench_clock --realtime auto``, its own process): the ``clock floor`` row, the
  lateness this VM gave with no server at all in the same minutes, computed the same way.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Callable

import numpy as np

from simserver.testing import REPO

CLOCK_FLOOR = "clock floor"
"""The summary's key (and the printed mode name) of the bare pacer's rounds."""


def clock_floor(seconds: float) -> dict:
    """One ``benchmarks.bench_clock`` run of ``seconds`` in a process of its own, the pacer
    scheduled as the server's tick thread (SCHED_FIFO if permitted, ``/dev/cpu_dma_latency``
    held at the server's :data:`simserver.server.realtime.DEFAULT_CPU_LATENCY_US` if permitted), in
    the format of ``benchmarks.bench_server.run``'s lateness figures."""
    from simserver.server.realtime import DEFAULT_CPU_LATENCY_US

    latency = []
    if os.access("/dev/cpu_dma_latency", os.W_OK):
        latency = ["--cpu-latency-us", str(DEFAULT_CPU_LATENCY_US)]
    proc = subprocess.run([sys.executable, "-m", "benchmarks.bench_clock", "--seconds",
                           f"{seconds:g}", "--realtime", "auto", "--json", *latency], cwd=REPO,
                          capture_output=True, text=True, timeout=seconds + 120, check=True)
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    return {"lateness_p50_us": r["lateness_p50_us"],
            "lateness_p99_us": r["lateness_p99_windows_median_us"],
            "late_fraction": r["late_over_1ms"] / max(r["ticks"], 1),
            "cpu_percent": r["cpu_percent"], "scheduling": r["scheduling"]}


def compare_modes(modes: dict[str, Callable[[], dict]], rounds: int, what: str,
                  floor_seconds: float = 5.0) -> dict[str, dict]:
    """Run every mode once a round, interleaved over ``rounds`` rounds, and the clock
    floor (``floor_seconds``, 0 for none) after each round; return and print per mode the
    median over rounds of its tick lateness p50/p99 and late-tick fraction, its p99 over
    the first mode's, the paired per-round ratio and the per-round values. The floor is
    the entry ``CLOCK_FLOOR`` (with the same keys)."""
    results: dict[str, list[dict]] = {m: [] for m in modes}
    if floor_seconds > 0:
        results[CLOCK_FLOOR] = []
    for i in range(rounds):
        for name, one_run in modes.items():
            results[name].append(one_run())
        if floor_seconds > 0:
            results[CLOCK_FLOOR].append(clock_floor(floor_seconds))
        print(f"{what}: round {i + 1} of {rounds}: p99 "
              + ", ".join(f"{name} {rs[-1]['lateness_p99_us']:.0f} us"
                          for name, rs in results.items()), flush=True)
    base_rounds = np.array([r["lateness_p99_us"] for r in next(iter(results.values()))])
    base = float(np.median(base_rounds))
    summary: dict[str, dict] = {}
    for name, rs in results.items():
        rounds_p99 = np.array([r["lateness_p99_us"] for r in rs])
        p50 = float(np.median([r["lateness_p50_us"] for r in rs]))
        p99 = float(np.median(rounds_p99))
        late_rounds = [r["late_fraction"] for r in rs]
        late = float(np.median(late_rounds))
        paired = float(np.median(rounds_p99 / np.maximum(base_rounds, 1e-3)))
        cpu = float(np.median([r["cpu_percent"] for r in rs]))
        summary[name] = {"p50_us": p50, "p99_us": p99, "late_fraction": late,
                         "p99_vs_off": p99 / base, "p99_paired_vs_off": paired,
                         "p99_rounds_us": rounds_p99.tolist(),
                         "late_fraction_rounds": late_rounds,
                         "server_cpu_percent": cpu}
        label = "pacer" if name == CLOCK_FLOOR else "server"
        print(f"{what} {name:14s}: lateness p50 {p50:6.1f} us, p99 {p99:7.1f} us "
              f"({p99 / base:5.2f} x off, paired by round {paired:5.2f} x), ticks > 1 ms "
              f"late {100 * late:.2f} %; p99 by round "
              f"{', '.join(f'{x:.0f}' for x in rounds_p99)} us; {label} CPU {cpu:.0f} %")
    return summary
