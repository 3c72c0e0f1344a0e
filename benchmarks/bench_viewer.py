"""Tick timing with the live Rerun view on and off (issue 5: within 10 % of off).

Run from the repository root::

    python -m benchmarks.bench_viewer [--seconds 60] [--rounds 2]

Runs ``benchmarks.bench_server`` with the server's viewer ``off``, saving to an ``.rrd``
file, and streaming to a viewer address that accepts nothing (a socket that listens but
never accepts or answers: the viewer process stalls and buffers; the physics process must
not notice), interleaved over ``--rounds`` rounds so
that slow drifts of this shared machine's load hit every mode alike. Quotes the median
over rounds of each mode's tick lateness p50/p99 and its late-tick fraction, and the p99
ratio to ``off``.
"""

from __future__ import annotations

import argparse
import socket
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.bench_server import run


def stalled_viewer() -> tuple[socket.socket, str]:
    """A loopback socket that listens but never accepts: a viewer that accepts nothing."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen(1)
    return sock, f"rerun+http://127.0.0.1:{sock.getsockname()[1]}/proxy"


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args(argv)
    tmp_dir = tempfile.TemporaryDirectory(prefix="simserver_viewer_bench_")
    tmp = Path(tmp_dir.name)
    stalled, url = stalled_viewer()
    modes = {"off": "off", "file": f"save:{tmp / 'live.rrd'}", "stalled viewer": f"connect:{url}"}
    results: dict[str, list[dict]] = {m: [] for m in modes}
    for _ in range(args.rounds):
        for name, viewer in modes.items():
            results[name].append(run(args.seconds, 200.0, viewer))
    stalled.close()
    tmp_dir.cleanup()
    summary = {}
    base = np.median([r["lateness_p99_us"] for r in results["off"]])
    for name, rs in results.items():
        p50 = float(np.median([r["lateness_p50_us"] for r in rs]))
        p99 = float(np.median([r["lateness_p99_us"] for r in rs]))
        late = float(np.median([r["late_fraction"] for r in rs]))
        summary[name] = {"p50_us": p50, "p99_us": p99, "late_fraction": late,
                         "p99_vs_off": p99 / base}
        print(f"viewer {name:12s}: lateness p50 {p50:6.1f} us, p99 {p99:7.1f} us "
              f"({p99 / base:5.2f} x off), ticks > 1 ms late {100 * late:.2f} %")
    return summary


if __name__ == "__main__":
    main()
