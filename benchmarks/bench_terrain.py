"""Step cost on a height map against the plane, in the same run (issue 15: at most 1.3 x).

Run from the repository root::

    python -m benchmarks.bench_terrain [--seconds S] [--repeats R]

The paper sedan drives ``bench_step``'s cycle (accelerate and steer, brake to rest, hold)
on four terrains: the plane kind (3 % grade, 2 % cross-slope), the same plane as a height
map, the generated hills (``configs/roads/hills.npz``) and the OpenDRIVE crest-curve road
(``configs/scenes/crest_curve_paper_sedan.yaml``, from the crest). The repeats alternate
between the terrains so that they share the machine's state; reported: median ns per step
and its ratio to the plane's.
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import time
from pathlib import Path

import numpy as np

from benchmarks.bench_step import DT_S, driving_cycle
from simserver.core import layout as L
from simserver.core.terrain import heightmap_terrain
from simserver.sim.scene import load_scene
from simserver.sim.simulation import Simulation

REPO = Path(__file__).resolve().parents[1]
GRADE_PCT, CROSS_PCT = 3.0, 2.0


def simulations(only: str | None = None) -> dict[str, Simulation]:
    """The four terrains' simulations (or only the one named ``only``)."""
    flat = load_scene(REPO / "configs/scenes/flat_paper_sedan.yaml")
    start = {**flat.initial, "u_mps": 5.0}
    road = {"grade_pct": GRADE_PCT, "cross_slope_pct": CROSS_PCT, "friction_scale": 1.0}
    xs = np.arange(-500.0, 500.5, 1.0)
    xx, yy = np.meshgrid(xs, xs)
    plane_map = heightmap_terrain(GRADE_PCT / 100 * xx + CROSS_PCT / 100 * yy, 1.0, 1.0,
                                  -500.0, -500.0)

    def hills() -> Simulation:
        scene = load_scene(REPO / "configs/scenes/hills_paper_sedan.yaml")
        return Simulation(dataclasses.replace(
            scene, initial={**scene.initial, "x_m": 0.0, "u_mps": 5.0}), DT_S)

    def crest() -> Simulation:
        scene = load_scene(REPO / "configs/scenes/crest_curve_paper_sedan.yaml")
        return Simulation(dataclasses.replace(
            scene, initial={**scene.initial, "u_mps": 5.0}), DT_S)

    makers = {
        "plane": lambda: Simulation(
            dataclasses.replace(flat, road=road, initial=start), DT_S),
        "plane as height map": lambda: Simulation(
            dataclasses.replace(flat, terrain=plane_map, initial=start), DT_S),
        "hills height map": hills,
        "OpenDRIVE crest-curve": crest,
    }
    return {name: make() for name, make in makers.items() if only in (None, name)}


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="simulated s per repeat")
    parser.add_argument("--repeats", type=int, default=11)
    args = parser.parse_args(argv)
    print(f"machine: {platform.processor() or platform.machine()}, {platform.python_version()}")
    sims = simulations()
    n = int(args.seconds / DT_S)
    inputs = driving_cycle(n)
    states = np.zeros((n, L.N_STATE))
    outputs = np.zeros((n, L.N_OUT))
    for sim in sims.values():
        sim.run(inputs[:10], states[:10], outputs[:10])  # compile
    costs = {name: np.empty(args.repeats) for name in sims}
    for k in range(args.repeats):
        for name, sim in sims.items():
            sim.reset(None)
            t0 = time.perf_counter_ns()
            sim.run(inputs, states, outputs)
            costs[name][k] = (time.perf_counter_ns() - t0) / n
            assert np.isfinite(sim.x).all(), name
    plane = float(np.median(costs["plane"]))
    rows = []
    for name, c in costs.items():
        med = float(np.median(c))
        rows.append({"terrain": name, "ns_per_step_median": med, "ratio_to_plane": med / plane})
        print(f"{name:22s} {med:8.0f} ns/step  {med / plane:5.2f} x plane")
    return rows


if __name__ == "__main__":
    main()
