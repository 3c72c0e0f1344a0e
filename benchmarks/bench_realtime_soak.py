"""Real-time soak of the live server (``simserver.testing.realtime_soak``), from the shell.

Run from the repository root::

    python -m benchmarks.bench_realtime_soak --seconds 600 [--rate 1000] [--join-every 3]
                                             [--json FILE]

A driver at ``--rate`` (1 kHz), a recorder and, every ``--join-every`` seconds, a joining
client (every third one killed with SIGKILL), each its own process, against
``simserver serve`` on a free loopback port; see ``simserver/testing/realtime_soak.py``
for what is measured. Exit code 0 when no command was lost and the server ran to the
end and exited cleanly.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from simserver.testing.realtime_soak import format_report, run_realtime_soak


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="wall seconds (default 60)")
    parser.add_argument("--rate", type=float, default=1000.0, help="driver command rate")
    parser.add_argument("--join-every", type=float, default=3.0,
                        help="a client joins every this many seconds (0: none)")
    parser.add_argument("--json", type=Path, default=None, help="write the figures here")
    args = parser.parse_args(argv)
    rep = run_realtime_soak(args.seconds, args.rate, args.join_every)
    print(format_report(rep))
    if args.json is not None:
        args.json.write_text(json.dumps(rep.as_dict(), indent=2) + "\n", encoding="utf-8")
    ok = rep.commands_lost == 0 and rep.server_alive_at_end and rep.server_exit_code == 0
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
