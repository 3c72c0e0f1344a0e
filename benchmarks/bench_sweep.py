"""Runs per minute of the relaxation-length study: ``simserver sweep`` on Dask with 1 and 2
workers against a loop of ``simserver run-scenario`` processes (issue 18).

Run from the repository root::

    python -m benchmarks.bench_sweep [--loop-runs 4] [--rounds 3] [--study FILE] [--json FILE]

- sweep, N workers: ``run_sweep`` of the study (default configs/sweeps/
  relaxation_study_dense.yaml, 29 x 25 = 725 runs; the issue asks for 200 or more) on a
  fresh embedded LocalCluster of N worker processes, each in a fresh Python process of its
  own (so neither sweep finds what the other one imported or loaded), timed from the call
  to its return: the cluster's start (workers up, kernels warmed), the runs, the last
  table written, and the cluster's close. Plots excluded. Also the steady rate: runs over
  the time between the workers being up and warm and the last result in.
  CPU: process CPU time per run over that steady part, summed over the workers, and of
  the sweep's own process (the client, and the LocalCluster's scheduler and nannies): on
  two cores that process's CPU is taken from the second worker.
- process loop: ``simserver run-scenario CASE --out DIR`` (history, summary and plots,
  as a user runs it today) on the study's first cases, each written out as a resolved
  scenario file; runs per minute = 60 / mean wall time per process.
- the machine's own ceiling, no Dask, in the same rounds: the study's runs by the workers'
  own ``run_batch`` in 1 and then 2 plain processes forked warm from one parent and
  started together (case i to process i mod 2), and a pure-compute numba loop (no memory
  traffic) 1 vs 2 processes: what any engine could reach on this machine. CPU per run
  alone, with both cores running runs, and beside the compute loop on the other core.

Targets (issue 18): sweep >= 20 x the loop; 2 workers >= 1.7 x 1 worker on this 2-core
machine. Each of the R rounds (``--rounds``, 3 by default; about 90 s each on a quiet
machine) runs the plain processes, the compute loop and the two sweeps, 1 then 2 of each;
the medians over the rounds are reported, and each ratio also paired by round. The
machine's load average is printed with the figures: other work on the same cores shows in
them.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
STUDY = REPO / "configs" / "sweeps" / "relaxation_study_dense.yaml"


def sweep_rate(study: Path, workers: int, out: Path) -> dict:
    """One timed sweep in this process (``--one-sweep``)."""
    t_import = time.perf_counter()
    from simserver.sweep.engine import run_sweep
    from simserver.sweep.spec import load_sweep

    import_s = time.perf_counter() - t_import

    sweep = load_sweep(study)
    outcome = run_sweep(sweep, out, workers=workers, quiet=True)
    assert outcome.failed == 0 and outcome.ran == len(sweep.cases)
    steady_s = outcome.wall_time_s - outcome.ready_s - outcome.close_s
    return {"workers": outcome.workers, "runs": outcome.ran,
            "wall_time_s": outcome.wall_time_s,
            "runs_per_min": 60.0 * outcome.ran / outcome.wall_time_s,
            "cluster_ready_s": outcome.ready_s, "cluster_close_s": outcome.close_s,
            "sweep_imports_s": import_s,
            "steady_runs_per_min": 60.0 * outcome.ran / steady_s,
            "client_cpu_ms_per_run": 1e3 * outcome.client_cpu_s / outcome.ran,
            "worker_cpu_ms_per_run": 1e3 * outcome.worker_cpu_s / outcome.ran}


def fresh_sweep_rate(study: Path, workers: int, out: Path) -> dict:
    """``sweep_rate`` in a new Python process; its result is the last line it prints."""
    proc = subprocess.run([sys.executable, "-m", "benchmarks.bench_sweep", "--study",
                           str(study), "--one-sweep", str(workers), "--out", str(out)],
                          cwd=REPO, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"the {workers}-worker sweep failed:\n{proc.stdout}{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


COMPUTE_ITERATIONS = 2_000_000  # one unit of the pure-compute peer: a few ms
COMPUTE_UNITS = 600  # the peer's work, split between the processes
PLAIN_WARM_RUNS = 4  # runs each plain process makes before the clock (buffers, caches)


@functools.cache
def spin_kernel() -> Any:
    """A numba loop with no memory traffic: two dependent chains of floating-point work in
    registers (a logistic map and a square root), the machine's compute alone. Compiled
    once, in the parent before it forks."""
    import numba

    @numba.njit(cache=False)
    def spin(iterations: int, seed: float) -> float:
        x, y = seed, 0.25
        for _ in range(iterations):
            x = 3.9 * x * (1.0 - x)
            y = math.sqrt(y + x)
        return x + y

    spin(10, 0.5)
    return spin


def _plain_work(kind: str, share: Any, metrics: tuple) -> int:
    """A plain process's share: the runs (-> how many are ok), the compute units, or
    (``spin``) compute units until the event ``share`` is set."""
    if kind == "runs":
        from simserver.sweep.worker import run_batch

        return sum(r["status"] == "ok" for r in run_batch(share, metrics, None))
    spin = spin_kernel()
    if kind == "spin":
        done = 0
        while not share.is_set():
            spin(COMPUTE_ITERATIONS, 0.3)
            done += 1
        return done
    for _ in range(share):
        spin(COMPUTE_ITERATIONS, 0.3)
    return share


def _plain_child(kind: str, share: Any, warm: Any, metrics: tuple, barrier: Any,
                 conn: Any) -> None:
    """One plain process (no Dask): warm, wait for the others, then its share of the work;
    sends back its start, end, the CPU seconds of its work and how much was done."""
    _plain_work("compute" if kind == "spin" else kind, warm, metrics)
    barrier.wait()
    t0, c0 = time.perf_counter(), time.thread_time()
    done = _plain_work(kind, share, metrics)
    c1, t1 = time.thread_time(), time.perf_counter()
    conn.send((t0, t1, c1 - c0, done))
    conn.close()


def plain_rate(study: Path, kind: str, procs: int) -> dict:
    """The machine's own ceiling in this process (``--one-plain``): the work split between
    ``procs`` plain processes forked from here, started together. ``runs``: the study's
    runs by the sweep workers' own ``run_batch`` (case i to process i mod procs, so the
    shares are alike); ``compute``: ``COMPUTE_UNITS`` units of the pure-compute loop;
    ``beside``: half the study's runs in one process while another one runs the compute
    loop until they are done (is a run slowed by any busy core, or by another run?)."""
    import multiprocessing as mp

    from simserver.sweep.spec import load_sweep
    from simserver.sweep.worker import warm_up

    sweep = load_sweep(study)
    ctx = mp.get_context("fork")
    spin_kernel()
    warm_runs = sweep.cases[-PLAIN_WARM_RUNS:]
    if kind in ("runs", "beside"):
        warm_up(sweep.cases[0].resolved, sweep.cases[0].base)
    stop = ctx.Event()
    if kind == "runs":
        total = len(sweep.cases)
        specs = [("runs", sweep.cases[i::procs], warm_runs) for i in range(procs)]
    elif kind == "compute":
        total = COMPUTE_UNITS
        specs = [("compute", len(range(i, total, procs)), 2) for i in range(procs)]
    else:
        procs, work = 2, sweep.cases[::2]
        total = len(work)
        specs = [("runs", work, warm_runs), ("spin", stop, 2)]
    barrier = ctx.Barrier(procs)
    pipes, children = [], []
    for child_kind, share, warm in specs:
        recv, send = ctx.Pipe(duplex=False)
        child = ctx.Process(target=_plain_child,
                            args=(child_kind, share, warm, sweep.metrics, barrier, send))
        child.start()
        send.close()
        pipes.append(recv)
        children.append(child)
    results = [pipes[0].recv()]
    stop.set()
    results += [p.recv() for p in pipes[1:]]
    for child in children:
        child.join()
        if child.exitcode != 0:
            raise RuntimeError(f"a plain {kind} process exited with {child.exitcode}")
    if kind == "beside":  # the spinning process is not the work
        results = results[:1]
    done = sum(r[3] for r in results)
    if done != total:
        raise RuntimeError(f"plain {kind}: {done} of {total} ok")
    wall = max(r[1] for r in results) - min(r[0] for r in results)
    return {"kind": kind, "procs": procs, "count": total, "wall_time_s": wall,
            "per_min": 60.0 * total / wall,
            "cpu_ms_per_item": 1e3 * sum(r[2] for r in results) / total}


def fresh_plain_rate(study: Path, kind: str, procs: int) -> dict:
    """``plain_rate`` in a new Python process."""
    proc = subprocess.run([sys.executable, "-m", "benchmarks.bench_sweep", "--study",
                           str(study), "--one-plain", kind, str(procs)],
                          cwd=REPO, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"the plain {kind} x {procs} failed:\n{proc.stdout}{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def loop_rate(study: Path, n: int, tmp: Path) -> dict:
    import yaml

    from simserver.sweep.spec import load_sweep

    sweep = load_sweep(study)
    walls = []
    for case in sweep.cases[:n]:
        path = tmp / f"case_{case.index}.yaml"
        path.write_text(yaml.safe_dump(case.resolved))
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "simserver", "run-scenario", str(path), "--out",
                        str(tmp / f"out_{case.index}"), "--quiet"], cwd=REPO, check=True,
                       stdout=subprocess.DEVNULL)
        walls.append(time.perf_counter() - t0)
    mean = sum(walls) / len(walls)
    return {"runs": n, "wall_time_s_each": walls, "runs_per_min": 60.0 / mean}


def median_of(rounds: list[dict]) -> dict:
    """Each figure's median over the rounds (the rounds themselves are kept)."""
    keys = [k for k, v in rounds[0].items() if isinstance(v, (int, float))]
    return {**{k: statistics.median(r[k] for r in rounds) for k in keys}, "rounds": rounds}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--loop-runs", type=int, default=4)
    parser.add_argument("--rounds", type=int, default=3,
                        help="alternate the 1- and 2-process measurements this many times "
                             "(medians)")
    parser.add_argument("--study", type=Path, default=STUDY)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--one-sweep", type=int, default=None, metavar="WORKERS",
                        help=argparse.SUPPRESS)
    parser.add_argument("--one-plain", nargs=2, default=None, metavar=("KIND", "PROCS"),
                        help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    study = args.study.resolve()
    if args.one_sweep is not None:
        print(json.dumps(sweep_rate(study, args.one_sweep, args.out)))
        return 0
    if args.one_plain is not None:
        print(json.dumps(plain_rate(study, args.one_plain[0], int(args.one_plain[1]))))
        return 0
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        loop = loop_rate(study, args.loop_runs, tmp)
        rounds: dict[int, list[dict]] = {1: [], 2: []}
        plain: dict[tuple[str, int], list[dict]] = {}
        # each round: the same study's runs by plain processes, the compute peer, then
        # Dask, 1 then 2 processes each, so a round's figures share the machine's state
        for i in range(args.rounds):
            for kind, procs in (("runs", 1), ("runs", 2), ("beside", 2), ("compute", 1),
                                ("compute", 2)):
                plain.setdefault((kind, procs), []).append(fresh_plain_rate(study, kind, procs))
            for workers in (1, 2):
                rounds[workers].append(fresh_sweep_rate(study, workers, tmp / f"w{workers}_{i}"))
        one, two = median_of(rounds[1]), median_of(rounds[2])
    load_after = os.getloadavg()

    def paired(a: list[dict], b: list[dict], key: str) -> float:
        """The median over rounds of each round's b / a."""
        return statistics.median(y[key] / x[key] for x, y in zip(a, b, strict=True))

    ceiling = {kind: {"1": median_of(plain[(kind, 1)]), "2": median_of(plain[(kind, 2)]),
                      "x_2_over_1": paired(plain[(kind, 1)], plain[(kind, 2)], "per_min"),
                      "cpu_2_over_1": paired(plain[(kind, 1)], plain[(kind, 2)],
                                             "cpu_ms_per_item")}
               for kind in ("runs", "compute")}
    ceiling["runs"]["beside"] = median_of(plain[("beside", 2)])
    ceiling["runs"]["cpu_beside_over_1"] = paired(plain[("runs", 1)], plain[("beside", 2)],
                                                  "cpu_ms_per_item")
    res = {"study": str(study.relative_to(REPO)) if study.is_relative_to(REPO) else str(study),
           "loop": loop, "sweep_1": one, "sweep_2": two, "ceiling": ceiling,
           "x_loop_1": one["runs_per_min"] / loop["runs_per_min"],
           "x_loop_2": two["runs_per_min"] / loop["runs_per_min"],
           "x_2_over_1": two["runs_per_min"] / one["runs_per_min"],
           "x_2_over_1_steady": two["steady_runs_per_min"] / one["steady_runs_per_min"],
           "x_2_over_1_paired": paired(rounds[1], rounds[2], "runs_per_min"),
           "x_2_over_1_steady_paired": paired(rounds[1], rounds[2], "steady_runs_per_min"),
           "loadavg_before": load_before, "loadavg_after": load_after, "cpus": os.cpu_count()}
    print(f"study: {res['study']} ({one['runs']:.0f} runs); median of {args.rounds} round(s), "
          f"each sweep in a fresh process")
    print(f"run-scenario loop: {loop['runs_per_min']:.1f} runs/min "
          f"({loop['runs']} processes, {sum(loop['wall_time_s_each']) / loop['runs']:.2f} s each)")
    for r, x in ((one, res["x_loop_1"]), (two, res["x_loop_2"])):
        print(f"sweep, {r['workers']:.0f} worker(s): {r['runs_per_min']:.0f} runs/min "
              f"({r['runs']:.0f} runs in {r['wall_time_s']:.1f} s, cluster start "
              f"{r['cluster_ready_s']:.2f} s and close {r['cluster_close_s']:.2f} s included), "
              f"{x:.0f} x the loop (target >= 20 x); {r['steady_runs_per_min']:.0f} runs/min "
              f"steady (warm workers up to the last result); CPU per run "
              f"{r['worker_cpu_ms_per_run']:.1f} ms in the workers, "
              f"{r['client_cpu_ms_per_run']:.1f} ms in the sweep's process (client, scheduler)")
    print(f"not in the figures: the sweep process's own imports (distributed, simserver), "
          f"{one['sweep_imports_s']:.2f} s and {two['sweep_imports_s']:.2f} s, paid before the "
          f"sweep starts as by `simserver sweep`; the forked workers inherit them")
    runs, comp = ceiling["runs"], ceiling["compute"]
    print("the machine's own ceiling, no Dask (1 then 2 plain processes forked warm and "
          "started together, the work split between them):")
    print(f"  the study's runs by the workers' run_batch: {runs['1']['per_min']:.0f} -> "
          f"{runs['2']['per_min']:.0f} runs/min, {runs['x_2_over_1']:.2f} x; CPU per run "
          f"{runs['1']['cpu_ms_per_item']:.1f} ms alone, {runs['2']['cpu_ms_per_item']:.1f} ms "
          f"with both cores busy ({runs['cpu_2_over_1']:.2f} x), "
          f"{runs['beside']['cpu_ms_per_item']:.1f} ms beside the compute loop "
          f"({runs['cpu_beside_over_1']:.2f} x)")
    print(f"  pure compute (numba loop, no memory traffic): {comp['1']['per_min']:.0f} -> "
          f"{comp['2']['per_min']:.0f} units/min, {comp['x_2_over_1']:.2f} x; CPU per unit "
          f"{comp['1']['cpu_ms_per_item']:.1f} ms alone, {comp['2']['cpu_ms_per_item']:.1f} ms "
          f"with both cores busy ({comp['cpu_2_over_1']:.2f} x)")
    print(f"2 workers / 1 worker: {res['x_2_over_1']:.2f} x overall (start and close included), "
          f"{res['x_2_over_1_steady']:.2f} x steady (target >= 1.7 x); paired by round "
          f"{res['x_2_over_1_paired']:.2f} x and {res['x_2_over_1_steady_paired']:.2f} x; "
          f"the plain processes' ceiling {runs['x_2_over_1']:.2f} x, pure compute "
          f"{comp['x_2_over_1']:.2f} x; Dask's 2 workers steady at "
          f"{100 * two['steady_runs_per_min'] / runs['2']['per_min']:.0f} % of 2 plain "
          f"processes")
    print(f"load average before {load_before[0]:.2f}, after {load_after[0]:.2f} "
          f"({os.cpu_count()} cores)")
    if args.json:
        args.json.write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
