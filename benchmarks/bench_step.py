"""Cost of one fixed 1 ms vehicle step, per tire model, and the headless real-time factor.

Run from the repository root::

    python -m benchmarks.bench_step [--seconds S] [--repeats R]

For each vehicle (paper_sedan: brush tires; mf_hatchback: four MF 6.1 tires) the compiled
``simulate`` loop runs a driving cycle (accelerate, steer, brake to rest, hold) of S
simulated seconds R times after compilation; each repeat gives ns per step. Reported: the
median and the 10th/90th percentiles over the repeats, and the real-time factor of the
median (simulated time / wall time). Target (issue 3): under 5 us per step with four MF
6.1 tires, i.e. 200 x real time or more.
"""

from __future__ import annotations

import argparse
import platform
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from simserver.adapters.config import load_vehicle
from simserver.core import layout as L
from simserver.scenario import INITIAL_RANGES, Scene
from simserver.simulation import Simulation

REPO = Path(__file__).resolve().parents[1]
VEHICLES = {
    "simple (paper_sedan)": REPO / "configs/vehicles/paper_sedan/vehicle.yaml",
    "mf61 (mf_hatchback)": REPO / "configs/vehicles/mf_hatchback/vehicle.yaml",
}
DT_S = 0.001


def driving_cycle(n: int) -> np.ndarray:
    """Inputs per step: 40 % accelerate and steer, then brake to rest and hold."""
    table = np.zeros((n, L.N_INPUT))
    table[:, L.IN_GEAR] = L.GEAR_D
    a = int(0.4 * n)
    table[:a, L.IN_THROTTLE] = 0.6
    table[:a, L.IN_STEER] = 0.15 * np.sin(np.linspace(0, 6 * np.pi, a))
    table[a:, L.IN_BRAKE] = 0.5
    return table


def bench_vehicle(path: Path, seconds: float, repeats: int,
                  clock: Callable[[], int] = time.perf_counter_ns) -> np.ndarray:
    """ns per step for each repeat, by ``clock`` (wall time; ``time.process_time_ns`` for
    the CPU time, which on a shared machine leaves out the time others held the core)."""
    initial = dict.fromkeys(INITIAL_RANGES, 0.0) | {"u_mps": 5.0}
    road = {"grade_pct": 3.0, "cross_slope_pct": 2.0, "friction_scale": 1.0}
    sim = Simulation(Scene(path=path, vehicle=load_vehicle(path), road=road, initial=initial),
                     DT_S)
    n = int(seconds / DT_S)
    inputs = driving_cycle(n)
    states = np.zeros((n, L.N_STATE))
    outputs = np.zeros((n, L.N_OUT))
    sim.run(inputs[:10], states, outputs)  # compile
    costs = np.empty(repeats)
    for k in range(repeats):
        sim.reset(None)
        t0 = clock()
        sim.run(inputs, states, outputs)
        costs[k] = (clock() - t0) / n
        assert np.isfinite(sim.x).all()
    return costs


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="simulated s per repeat")
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args(argv)
    print(f"machine: {platform.processor() or platform.machine()}, {platform.python_version()}")
    rows = []
    for name, path in VEHICLES.items():
        costs = bench_vehicle(path, args.seconds, args.repeats)
        p10, med, p90 = np.percentile(costs, [10, 50, 90])
        rtf = 1e9 * DT_S / med
        rows.append({"tire_model": name, "ns_per_step_median": med, "p10": p10, "p90": p90,
                     "real_time_factor": rtf})
        print(f"step cost {name:22s}: median {med / 1e3:6.2f} us (p10 {p10 / 1e3:.2f}, "
              f"p90 {p90 / 1e3:.2f}) -> {rtf:7.0f} x real time")
    return rows


if __name__ == "__main__":
    main()
