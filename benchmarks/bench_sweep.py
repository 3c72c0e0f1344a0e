"""Runs per minute of the relaxation-length study: ``simserver sweep`` on Dask with 1 and 2
workers against a loop of ``simserver run-scenario`` processes (issue 18).

Run from the repository root::

    python -m benchmarks.bench_sweep [--loop-runs 4] [--json FILE]

- sweep, N workers: ``run_sweep`` of configs/sweeps/relaxation_study.yaml (225 runs) on a
  fresh embedded LocalCluster of N worker processes, from the cluster's start (workers
  spawned, kernels warmed) to the last row of the table written; plots excluded. Also
  the steady rate: runs over the time after the workers were up and warm.
  CPU: process CPU time per run over that steady part, summed over the workers, and of
  this process (the client, and the LocalCluster's scheduler and nannies): on two cores
  this process's CPU is taken from the second worker.
- process loop: ``simserver run-scenario CASE --out DIR`` (history, summary and plots,
  as a user runs it today) on the study's first cases, each written out as a resolved
  scenario file; runs per minute = 60 / mean wall time per process.

Targets (issue 18): sweep >= 20 x the loop; 2 workers >= 1.7 x 1 worker on this 2-core
machine. The machine's load average is printed with the figures: other work on the same
cores shows in them.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

from simserver.sweep.engine import run_sweep
from simserver.sweep.spec import load_sweep

REPO = Path(__file__).resolve().parents[1]
STUDY = REPO / "configs" / "sweeps" / "relaxation_study.yaml"


def sweep_rate(workers: int, out: Path) -> dict:
    sweep = load_sweep(STUDY)
    outcome = run_sweep(sweep, out, workers=workers, quiet=True)
    assert outcome.failed == 0 and outcome.ran == len(sweep.cases)
    return {"workers": workers, "runs": outcome.ran, "wall_time_s": outcome.wall_time_s,
            "runs_per_min": 60.0 * outcome.ran / outcome.wall_time_s,
            "cluster_ready_s": outcome.ready_s,
            "steady_runs_per_min": 60.0 * outcome.ran / (outcome.wall_time_s - outcome.ready_s),
            "client_cpu_ms_per_run": 1e3 * outcome.client_cpu_s / outcome.ran,
            "worker_cpu_ms_per_run": 1e3 * outcome.worker_cpu_s / outcome.ran}


def loop_rate(n: int, tmp: Path) -> dict:
    sweep = load_sweep(STUDY)
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--loop-runs", type=int, default=4)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        loop = loop_rate(args.loop_runs, tmp)
        one = sweep_rate(1, tmp / "w1")
        two = sweep_rate(2, tmp / "w2")
    load_after = os.getloadavg()
    res = {"loop": loop, "sweep_1": one, "sweep_2": two,
           "x_loop_1": one["runs_per_min"] / loop["runs_per_min"],
           "x_loop_2": two["runs_per_min"] / loop["runs_per_min"],
           "x_2_over_1": two["runs_per_min"] / one["runs_per_min"],
           "loadavg_before": load_before, "loadavg_after": load_after, "cpus": os.cpu_count()}
    print(f"run-scenario loop: {loop['runs_per_min']:.1f} runs/min "
          f"({loop['runs']} processes, {sum(loop['wall_time_s_each']) / loop['runs']:.2f} s each)")
    for r, x in ((one, res["x_loop_1"]), (two, res["x_loop_2"])):
        print(f"sweep, {r['workers']} worker(s): {r['runs_per_min']:.0f} runs/min "
              f"({r['runs']} runs in {r['wall_time_s']:.1f} s, cluster start included), "
              f"{x:.0f} x the loop (target >= 20 x); {r['steady_runs_per_min']:.0f} runs/min "
              f"once the {r['workers']} warm worker(s) were up ({r['cluster_ready_s']:.1f} s); "
              f"CPU per run {r['worker_cpu_ms_per_run']:.1f} ms in the workers, "
              f"{r['client_cpu_ms_per_run']:.1f} ms in this process (client, scheduler)")
    steady = two["steady_runs_per_min"] / one["steady_runs_per_min"]
    res["x_2_over_1_steady"] = steady
    print(f"2 workers / 1 worker: {res['x_2_over_1']:.2f} x, {steady:.2f} x steady "
          f"(target >= 1.7 x)")
    print(f"load average before {load_before[0]:.2f}, after {load_after[0]:.2f} "
          f"({os.cpu_count()} cores)")
    if args.json:
        args.json.write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
