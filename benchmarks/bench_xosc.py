"""Headless speed of the shipped OpenSCENARIO files (issue 31 acceptance: >= 100 x real
time headless for the three-car crest scenario).

Run from the repository root::

    python -m benchmarks.bench_xosc [--repeats R] [--duration S] [FILE.xosc ...]

Each file (default: every shipped ``configs/openscenario/**/*.xosc``) is played headless
with ``simserver.sim.xosc_run.play`` once to compile and warm up, then R times (default 3)
for at most S simulated seconds (default 30; a stop trigger may end it sooner). Reported,
median over the repeats:

- ``loop``: simulated seconds over the wall time of the run loop (``XoscRun.wall_time_s``:
  the storyboard and the compiled physics between its evaluations), the figure the
  acceptance asks for;
- ``cpu``: the same over the process's CPU time of the loop (less sensitive to the other
  engineers' load on the shared machine);
- ``physics``: the share of the loop's wall time spent in ``simulate_driven`` (the
  storyboard's cost is the rest);
- ``play``: simulated seconds over the whole ``play`` call (reading the file, building the
  OpenDRIVE terrain and the cars, then the loop).

Figures measured on the shared 2-core VM are in docs/openscenario.md (section "Speed").
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from simserver.testing import REPO

SHIPPED = sorted(p for p in (REPO / "configs" / "openscenario").rglob("*.xosc")
                 if "Catalogs" not in p.parts)  # catalogs are no scenarios


def measure(path: Path, duration_s: float) -> dict[str, float]:
    from simserver.sim.xosc_run import play

    t0 = time.perf_counter()
    run = play(path, duration_s=duration_s)
    whole = time.perf_counter() - t0
    physics = getattr(run, "physics_wall_s", float("nan"))
    cpu = getattr(run, "cpu_time_s", float("nan"))
    return {"sim_s": run.end_time_s, "loop": run.end_time_s / run.wall_time_s,
            "cpu": run.end_time_s / cpu, "physics": physics / run.wall_time_s,
            "play": run.end_time_s / whole}


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="*", type=Path, default=SHIPPED)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--duration", type=float, default=30.0)
    args = ap.parse_args(argv)
    out = {}
    for path in args.files:
        measure(path, min(args.duration, 1.0))  # compile and warm
        runs = [measure(path, args.duration) for _ in range(args.repeats)]
        med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
        out[path.name] = med
        print(f"{path.name:28s} {med['sim_s']:5.1f} s simulated: loop {med['loop']:6.1f} x "
              f"real time (min {min(r['loop'] for r in runs):.1f}), cpu {med['cpu']:6.1f} x, "
              f"physics {100 * med['physics']:4.0f} % of the loop, play {med['play']:6.1f} x",
              flush=True)
    return out


if __name__ == "__main__":
    main()
