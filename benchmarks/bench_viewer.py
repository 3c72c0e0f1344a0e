"""Tick timing with the live Rerun view on and off (issue 5: within 10 % of off).

Run from the repository root::

    python -m benchmarks.bench_viewer [--seconds 60] [--rounds 2]

Runs ``benchmarks.bench_server`` with the server's viewer ``off``, saving to an ``.rrd``
file, and streaming to a viewer address that accepts nothing (a socket that listens but
never accepts or answers: the viewer process stalls and buffers; the physics process must
not notice), interleaved over ``--rounds`` rounds so
that slow drifts of this shared machine's load hit every mode alike, with this VM's own
stall floor (the bare pacer) after each round (``benchmarks.interleaved``). Quotes the
median over rounds of each mode's tick lateness p50/p99 and its late-tick fraction, and
the p99 ratio to ``off``.
"""

from __future__ import annotations

import argparse
import functools
import socket
import tempfile
from pathlib import Path

from benchmarks.bench_server import run
from benchmarks.interleaved import compare_modes


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
    parser.add_argument("--floor-seconds", type=float, default=5.0,
                        help="the bare pacer's run after each round (0: none)")
    args = parser.parse_args(argv)
    tmp_dir = tempfile.TemporaryDirectory(prefix="simserver_viewer_bench_")
    tmp = Path(tmp_dir.name)
    stalled, url = stalled_viewer()
    modes = {"off": "off", "file": f"save:{tmp / 'live.rrd'}", "stalled viewer": f"connect:{url}"}
    summary = compare_modes({name: functools.partial(run, args.seconds, 200.0, viewer)
                             for name, viewer in modes.items()}, args.rounds, "viewer",
                            floor_seconds=args.floor_seconds)
    stalled.close()
    tmp_dir.cleanup()
    return summary


if __name__ == "__main__":
    main()
