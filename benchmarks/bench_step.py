"""Cost of one fixed 1 ms vehicle step, per tire model, and the headless real-time factor.

Run from the repository root::

    python -m benchmarks.bench_step [--seconds S] [--repeats R]
    python -m benchmarks.bench_step --world-sizes 1,4,16,64     # cost per car-step
    python -m benchmarks.bench_step --ab ../main --rounds 7      # A/B against a tree

For each vehicle (paper_sedan: brush tires; mf_hatchback: four MF 6.1 tires) the compiled
``simulate`` loop runs a driving cycle (accelerate, steer, brake to rest, hold) of S
simulated seconds R times after compilation; each repeat gives ns per step. Reported: the
median and the 10th/90th percentiles over the repeats, and the real-time factor of the
median (simulated time / wall time). Target (issue 3): under 5 us per step with four MF
6.1 tires, i.e. 200 x real time or more.

``--world-sizes``: worlds of that many independent cars (``simserver.sim.simulation.World``,
one compiled step for all, issue 29), each car the brush car with its own throttle, 20 m
apart; the cost per car-step (CPU time / cars / steps) of each size against the world of
one, in one run, recording every 1000th step; and the contact stage alone (issue 30) per
car, the cars apart (its broad phase) and in a row bumper to bumper (every neighbour in
contact).

``--ab TREE``: this tree's step cost against another tree's (e.g. a worktree of main), in
interleaved rounds (A B A B ...: each round one fresh process per tree, so the machine's
weather spreads over both), timed by the process's CPU time; per vehicle the median over
rounds of each tree's median and the median of the per-round ratios.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from simserver.adapters.config import load_vehicle
from simserver.core import layout as L
from simserver.sim.scene import INITIAL_RANGES, Scene
from simserver.sim.simulation import Simulation

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


def bench_world(path: Path, n_cars: int, seconds: float, repeats: int,
                clock: Callable[[], int] = time.process_time_ns) -> np.ndarray:
    """ns per car-step of a world of ``n_cars`` brush cars for each repeat (the process's
    CPU time by default), each car with its own throttle (0.4 .. 0.8) on the driving
    cycle, the cars side by side 20 m apart (they never touch: the contact stage costs
    its broad phase, ``contact_stage_cost``)."""
    import dataclasses

    from simserver.sim.simulation import World

    initial = dict.fromkeys(INITIAL_RANGES, 0.0) | {"u_mps": 5.0}
    road = {"grade_pct": 3.0, "cross_slope_pct": 2.0, "friction_scale": 1.0}
    scene = Scene(path=path, vehicle=load_vehicle(path), road=road, initial=initial)
    sims = [Simulation(dataclasses.replace(scene, initial=initial | {"y_m": 20.0 * c}), DT_S,
                       car_id=f"car{c}") for c in range(n_cars)]
    world: World = sims[0].world
    for sim in sims[1:]:
        sim.move_to(world)
    n = int(seconds / DT_S)
    inputs = np.repeat(driving_cycle(n)[:, None, :], n_cars, axis=1)
    inputs[:, :, L.IN_THROTTLE] *= np.linspace(0.4, 0.8, n_cars)[None, :] / 0.6
    every = 1000
    rows = -(-n // every)
    states = np.zeros((rows, n_cars, L.N_STATE))
    outputs = np.zeros((rows, n_cars, L.N_OUT))
    world.run(inputs[:10], states, outputs, every)  # compile
    costs = np.empty(repeats)
    for k in range(repeats):
        for sim in sims:
            sim.reset(None)
        t0 = clock()
        world.run(inputs, states, outputs, every)
        costs[k] = (clock() - t0) / (n * n_cars)
        assert np.isfinite(world.data.x).all()
    return costs


def contact_stage_cost(n_cars: int, touching: bool, steps: int = 20000,
                       repeats: int = 5) -> float:
    """ns per call of the world's contact stage alone (``core.world.contacts``) for
    ``n_cars`` brush cars at rest: in a row 20 m apart (the broad phase only), or
    ``touching``: bumper to bumper 1 cm deep in a row (every neighbouring pair in
    contact). The median over repeats, the process's CPU time."""
    import dataclasses

    import numba as nb

    from simserver.core.world import contacts

    @nb.njit
    def loop(world, data, n):  # noqa: ANN001, ANN202
        for _ in range(n):
            contacts(world, data)

    path = VEHICLES["simple (paper_sedan)"]
    initial = dict.fromkeys(INITIAL_RANGES, 0.0)
    scene = Scene(path=path, vehicle=load_vehicle(path), road={"grade_pct": 0.0,
                  "cross_slope_pct": 0.0, "friction_scale": 1.0}, initial=initial)
    pitch = 4.6 - 0.01 if touching else 20.0  # the reference car's box is 4.6 m long
    sims = [Simulation(dataclasses.replace(scene, initial=initial | {"x_m": pitch * c}),
                       DT_S, car_id=f"car{c}") for c in range(n_cars)]
    world = sims[0].world
    for sim in sims[1:]:
        sim.move_to(world)
    loop(world.model, world.data, 1)  # compile
    costs = []
    for _ in range(repeats):
        t0 = time.process_time_ns()
        loop(world.model, world.data, steps)
        costs.append((time.process_time_ns() - t0) / steps)
    assert int(world.data.contacts.car[:, 0].sum()) == (n_cars if touching else 0)
    return float(np.median(costs))


def world_sizes(sizes: list[int], seconds: float, repeats: int) -> list[dict]:
    """The world-size table: ns per car-step per size, and against the world of one; the
    contact stage's share (``contact_stage_cost``, apart and touching) per car-step."""
    path = VEHICLES["simple (paper_sedan)"]
    rows = []
    base = None
    for size in sizes:
        med = float(np.median(bench_world(path, size, seconds, repeats)))
        base = med if base is None else base
        apart = contact_stage_cost(size, touching=False) / size
        touching = contact_stage_cost(size, touching=True) / size if size > 1 else apart
        rows.append({"cars": size, "ns_per_car_step_median": med, "vs_first": med / base,
                     "contact_ns_per_car_apart": apart,
                     "contact_ns_per_car_touching": touching})
        print(f"world of {size:3d} cars: {med / 1e3:6.2f} us per car-step "
              f"({med / base:.3f} x the world of {sizes[0]}); contact stage "
              f"{apart:6.1f} ns per car apart, {touching:6.1f} ns per car touching in a "
              f"row", flush=True)
    return rows


def ab(other: Path, rounds: int, seconds: float, repeats: int) -> dict[str, dict]:
    """This tree against ``other`` in interleaved rounds of fresh processes."""
    here = REPO
    per: dict[str, dict[str, list[float]]] = {}
    for _ in range(rounds):
        for label, tree in (("this", here), ("other", other)):
            env = {**os.environ, "PYTHONPATH": str(tree)}
            # bench_vehicle of that tree's own bench_step (older trees have no --json)
            # the process's CPU time: on a shared machine it leaves out the time others
            # held the core (the wall time of a loaded VM varied 4 x between rounds)
            code = ("import json, time, numpy as np\n"
                    "from benchmarks.bench_step import VEHICLES, bench_vehicle\n"
                    "print(json.dumps([{'tire_model': n, 'ns_per_step_median': float(np.median("
                    f"bench_vehicle(p, {seconds!r}, {repeats!r}, time.process_time_ns)))}}\n"
                    "    for n, p in VEHICLES.items()]))")
            out = subprocess.run([sys.executable, "-c", code], cwd=tree, env=env,
                                 capture_output=True, text=True, check=True)
            for row in json.loads(out.stdout.strip().splitlines()[-1]):
                per.setdefault(row["tire_model"], {}).setdefault(label, []).append(
                    row["ns_per_step_median"])
    summary = {}
    for name, runs in per.items():
        ratios = np.array(runs["this"]) / np.array(runs["other"])
        summary[name] = {"this_median_ns": float(np.median(runs["this"])),
                         "other_median_ns": float(np.median(runs["other"])),
                         "ratio_median": float(np.median(ratios)),
                         "ratios": [round(float(r), 3) for r in ratios]}
        print(f"{name:22s}: this {summary[name]['this_median_ns'] / 1e3:.3f} us, other "
              f"{summary[name]['other_median_ns'] / 1e3:.3f} us, ratio median "
              f"{summary[name]['ratio_median']:.3f} (rounds {summary[name]['ratios']})")
    return summary


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="simulated s per repeat")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--world-sizes", default="",
                        help="comma-separated car counts (e.g. 1,4,16,64): the world table")
    parser.add_argument("--ab", type=Path, help="compare against this tree, interleaved")
    parser.add_argument("--rounds", type=int, default=7, help="rounds of --ab")
    parser.add_argument("--json", action="store_true", help="last line: the rows as JSON")
    args = parser.parse_args(argv)
    if args.ab is not None:
        return [ab(args.ab.resolve(), args.rounds, args.seconds, args.repeats)]
    if args.world_sizes:
        return world_sizes([int(v) for v in args.world_sizes.split(",")], args.seconds,
                           args.repeats)
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
    if args.json:
        print(json.dumps(rows))
    return rows


if __name__ == "__main__":
    main()
