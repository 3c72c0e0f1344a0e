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

With ``--by-function`` it also lists where a cold compile goes: the compile time of each
function and specialisation (numba's ``numba:compile`` events; exclusive: the time of the
callees it compiled meanwhile is theirs), wall and CPU, the largest first, and how much of
the whole was LLVM (``numba:llvm_lock`` events; the rest is numba's type inference and
lowering). ``inline="always"`` functions never appear: they are compiled inside their
callers; the step's stages and helpers that LLVM inlines (``core.layout.STEP_JIT_OPTIONS``,
``forceinline``) appear as functions of their own.

    python -m benchmarks.bench_compile --warm 0 --by-function 25

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


class CompileTimes:
    """Exclusive compile time per (function, signature) from numba's compile events, and
    the time spent in LLVM, while registered (``with CompileTimes() as times``)."""

    def __init__(self) -> None:
        self.by_function: dict[str, list[float]] = {}  # key -> [wall_s, cpu_s, count]
        self.llvm_wall_s = 0.0
        self._stack: list[list[float]] = []  # [wall0, cpu0, child_wall, child_cpu]
        self._llvm_t0 = 0.0

    def __enter__(self) -> CompileTimes:
        from numba.core import event

        times = self

        class _Compile(event.Listener):
            def on_start(self, ev: event.Event) -> None:
                times._stack.append([time.perf_counter(), time.process_time(), 0.0, 0.0])

            def on_end(self, ev: event.Event) -> None:
                w0, c0, child_w, child_c = times._stack.pop()
                wall, cpu = time.perf_counter() - w0, time.process_time() - c0
                if times._stack:
                    times._stack[-1][2] += wall
                    times._stack[-1][3] += cpu
                disp = ev.data["dispatcher"]
                key = (f"{disp.py_func.__module__}.{disp.py_func.__qualname__}"
                       f"{tuple(str(a) for a in ev.data['args'])}")
                row = times.by_function.setdefault(key, [0.0, 0.0, 0])
                row[0] += wall - child_w
                row[1] += cpu - child_c
                row[2] += 1

        class _Llvm(event.Listener):
            def on_start(self, ev: event.Event) -> None:
                times._llvm_t0 = time.perf_counter()

            def on_end(self, ev: event.Event) -> None:
                times.llvm_wall_s += time.perf_counter() - times._llvm_t0

        self._listeners = [("numba:compile", _Compile()), ("numba:llvm_lock", _Llvm())]
        for kind, listener in self._listeners:
            event.register(kind, listener)
        return self

    def __exit__(self, *exc: object) -> None:
        from numba.core import event

        for kind, listener in self._listeners:
            event.unregister(kind, listener)


def _child(scene_path: str) -> None:
    """One measured run (in a fresh process): print one JSON line of (name, wall, cpu)
    rows, the compile times by function and the LLVM time."""
    times = CompileTimes().__enter__()
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
    times.__exit__()
    print(json.dumps({"rows": rows, "by_function": times.by_function,
                      "llvm_wall_s": times.llvm_wall_s}))


def cache_env(cache_dir: Path) -> dict[str, str]:
    """This process's environment with every kernel cache setting pointed at
    ``cache_dir``: ``NUMBA_CACHE_DIR`` and the shared cache's ``SIMSERVER_CACHE_DIR``
    (``simserver.core``), which takes precedence for simserver's kernels."""
    from simserver.core import CACHE_DIR_ENV

    return {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir), CACHE_DIR_ENV: str(cache_dir)}


def _run(cache_dir: Path, scene: Path) -> dict:
    env = cache_env(cache_dir)
    proc = subprocess.run([sys.executable, "-m", "benchmarks.bench_compile", "--child",
                           str(scene)], env=env, capture_output=True, text=True, check=False,
                          cwd=ROOT)
    if proc.returncode != 0:
        raise RuntimeError(f"bench_compile child failed:\n{proc.stderr[-4000:]}")
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    result["rows"] = [tuple(r) for r in result["rows"]]
    return result


def measure(cold: int, warm: int, scene: Path, log: bool = True) -> dict[str, dict]:
    """``cold`` runs from empty caches, then ``warm`` runs from the last one's cache:
    ``{"cold": {name: {"wall_s", "cpu_s"}}, "warm": ...}`` (medians; ``total`` included)
    and ``"by_function"``: the cold runs' exclusive compile time per function and
    specialisation, ``{key: {"wall_s", "cpu_s"}}`` (medians), with ``"llvm_wall_s"``."""
    dirs = [Path(tempfile.mkdtemp(prefix="simserver_numba_")) for _ in range(cold)]
    runs: dict[str, list] = {"cold": [], "warm": []}
    try:
        for d in dirs:
            runs["cold"].append(_run(d, scene))
            if log:
                print(f"cold run: {sum(r[1] for r in runs['cold'][-1]['rows']):.1f} s wall",
                      flush=True)
        for _ in range(warm):
            runs["warm"].append(_run(dirs[-1], scene))
            if log:
                print(f"warm run: {sum(r[1] for r in runs['warm'][-1]['rows']):.2f} s wall",
                      flush=True)
    finally:
        for d in dirs:
            shutil.rmtree(d, ignore_errors=True)
    result: dict[str, dict] = {}
    if runs["cold"]:
        keys = set().union(*(r["by_function"] for r in runs["cold"]))
        result["by_function"] = {
            k: {"wall_s": statistics.median(r["by_function"].get(k, [0.0])[0]
                                            for r in runs["cold"]),
                "cpu_s": statistics.median(r["by_function"].get(k, [0.0, 0.0])[1]
                                           for r in runs["cold"])} for k in keys}
        result["llvm_wall_s"] = statistics.median(r["llvm_wall_s"] for r in runs["cold"])
    for kind, all_runs in runs.items():
        if not all_runs:
            continue
        kind_runs = [r["rows"] for r in all_runs]
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
    ap.add_argument("--by-function", type=int, default=0, metavar="N",
                    help="also list the N functions whose cold compile took longest")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        _child(args.child)
        return 0
    result = measure(args.cold, args.warm, args.scene.resolve())
    kinds = [k for k in ("cold", "warm") if k in result]
    print(f"\n{'entry point':22s}" + "".join(f"{k + ' wall':>12s}{k + ' cpu':>12s}" for k in kinds))
    for name in result[kinds[0]]:
        print(f"{name:22s}" + "".join(f"{result[k][name]['wall_s']:11.2f}s"
                                       f"{result[k][name]['cpu_s']:11.2f}s" for k in kinds))
    if args.by_function and "by_function" in result:
        funcs = sorted(result["by_function"].items(), key=lambda kv: -kv[1]["cpu_s"])
        total_cpu = sum(v["cpu_s"] for v in result["by_function"].values())
        total_wall = sum(v["wall_s"] for v in result["by_function"].values())
        print(f"\ncold compile by function (exclusive; {len(funcs)} specialisations, "
              f"{total_wall:.1f} s wall, {total_cpu:.1f} s CPU in all, of which LLVM "
              f"{result['llvm_wall_s']:.1f} s wall):")
        print(f"{'wall':>8s}{'cpu':>8s}{'share':>7s}  function (argument types)")
        for key, v in funcs[:args.by_function]:
            share = v["cpu_s"] / total_cpu if total_cpu else 0.0
            print(f"{v['wall_s']:7.2f}s{v['cpu_s']:7.2f}s{share:6.0%}  {key[:160]}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
