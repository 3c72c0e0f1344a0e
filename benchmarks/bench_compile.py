"""Cold compile of the physics: every entry point ``Simulation.warm_up`` compiles, timed one
by one from an empty numba cache, then the same from the warm cache.

    python -m benchmarks.bench_compile                 # 1 cold + 1 warm run, default scene
    python -m benchmarks.bench_compile --cold 3 --warm 3   # medians of 3
    python -m benchmarks.bench_compile --scene configs/scenes/flat_mf_hatchback.yaml

Each run is a fresh Python process (``NUMBA_CACHE_DIR`` a new empty temporary directory for
a cold run, the last cold run's directory for a warm one; Python's own bytecode is already
compiled). Per entry point it reports the wall time and the process's CPU time: on a loaded
machine the CPU time is the steadier figure (the compile is single-threaded), the wall time
is what a user waits. ``import`` is the import of the simulation modules (the tire kernels
compiled with explicit signatures compile there), ``Simulation()`` the model built from the
scene, ``tire_forces`` the kernel of ``simserver tire-curves`` (not in the server's
warm-up). The figures are medians over the runs.

The server's whole start-up (zenoh included) is ``python -m benchmarks --only startup``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_SCENE = ROOT / "configs" / "scenes" / "flat_paper_sedan.yaml"


def _child(scene_path: str) -> None:
    """One measured run (in a fresh process): print one JSON line of (name, wall, cpu)."""
    rows: list[tuple[str, float, float]] = []
    wall, cpu = time.perf_counter(), time.process_time()

    def mark(name: str) -> None:
        nonlocal wall, cpu
        w, c = time.perf_counter(), time.process_time()
        rows.append((name, w - wall, c - cpu))
        wall, cpu = w, c

    import numpy as np

    from simserver.core import tire_layout as TL
    from simserver.core.tire import tire_forces
    from simserver.sim.scene import load_scene
    from simserver.sim.simulation import Simulation
    from simserver.tires.registry import tire_kernels

    mark("import")
    sim = Simulation(load_scene(scene_path), 0.001)
    mark("Simulation()")
    for name, call in sim.warm_up_calls():
        call()
        mark(name)
    out = np.zeros(TL.N_TIRE_OUT)
    tire_forces(tire_kernels(), sim.tp[0], 0.01, 0.01, 0.0, 4000.0, 1.0, 20.0, out)
    mark("tire_forces")
    print(json.dumps(rows))


def _run(cache_dir: Path, scene: Path) -> list[tuple[str, float, float]]:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir)}
    proc = subprocess.run([sys.executable, "-m", "benchmarks.bench_compile", "--child",
                           str(scene)], env=env, capture_output=True, text=True, check=False,
                          cwd=ROOT)
    if proc.returncode != 0:
        raise RuntimeError(f"bench_compile child failed:\n{proc.stderr[-4000:]}")
    return [tuple(r) for r in json.loads(proc.stdout.strip().splitlines()[-1])]


def measure(cold: int, warm: int, scene: Path, log: bool = True) -> dict[str, dict]:
    """``cold`` runs from empty caches, then ``warm`` runs from the last one's cache:
    ``{"cold": {name: {"wall_s", "cpu_s"}}, "warm": ...}`` (medians; ``total`` included)."""
    dirs = [Path(tempfile.mkdtemp(prefix="simserver_numba_")) for _ in range(cold)]
    runs: dict[str, list] = {"cold": [], "warm": []}
    try:
        for d in dirs:
            runs["cold"].append(_run(d, scene))
            if log:
                print(f"cold run: {sum(r[1] for r in runs['cold'][-1]):.1f} s wall", flush=True)
        for _ in range(warm):
            runs["warm"].append(_run(dirs[-1], scene))
            if log:
                print(f"warm run: {sum(r[1] for r in runs['warm'][-1]):.2f} s wall", flush=True)
    finally:
        for d in dirs:
            shutil.rmtree(d, ignore_errors=True)
    result: dict[str, dict] = {}
    for kind, kind_runs in runs.items():
        if not kind_runs:
            continue
        names = [r[0] for r in kind_runs[0]]
        table = {}
        for i, name in enumerate(names):
            table[name] = {"wall_s": statistics.median(run[i][1] for run in kind_runs),
                           "cpu_s": statistics.median(run[i][2] for run in kind_runs)}
        table["total"] = {"wall_s": statistics.median(sum(r[1] for r in run) for run in kind_runs),
                          "cpu_s": statistics.median(sum(r[2] for r in run) for run in kind_runs)}
        result[kind] = table
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cold", type=int, default=1, help="runs from an empty cache (default 1)")
    ap.add_argument("--warm", type=int, default=1, help="runs from the warm cache (default 1)")
    ap.add_argument("--scene", type=Path, default=DEFAULT_SCENE)
    ap.add_argument("--json", type=Path, help="also write the figures here")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        _child(args.child)
        return 0
    result = measure(args.cold, args.warm, args.scene.resolve())
    kinds = list(result)
    print(f"\n{'entry point':22s}" + "".join(f"{k + ' wall':>12s}{k + ' cpu':>12s}" for k in kinds))
    for name in result[kinds[0]]:
        print(f"{name:22s}" + "".join(f"{result[k][name]['wall_s']:11.2f}s"
                                       f"{result[k][name]['cpu_s']:11.2f}s" for k in kinds))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
