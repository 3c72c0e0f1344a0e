"""Cost of the built-in driver per car-step against the car step (issue 30 item 2).

Run from the repository root::

    python -m benchmarks.bench_driver [--cars 1,8,32] [--seconds S] [--repeats R]

A world of N brush cars (paper_sedan) on the flat, every car driven by the built-in driver
(``simserver.core.driver``) along one straight path, 30 m apart at 15 m/s (each sees the
car ahead: the IDM's gap term, every car projected onto the path). Per world size, timed
by the process's CPU time after compilation, R repeats of S simulated seconds each of:

- ``step``: ``core.world.simulate`` with the inputs fixed (the car step alone);
- ``drive``: ``core.driver.drive`` alone, called once a step on the same states;
- ``closed loop``: ``core.driver.simulate_driven`` (drive, then the world step).

Reported: ns per car-step (median, 10th and 90th percentile over the repeats), the
driver's cost against the car step's, and the closed loop's against the open loop's.

On the shared 2-core VM (7 other engineers at work), 2026-12-07,
``python -m benchmarks.bench_driver --cars 1,8,32 --seconds 2 --repeats 5``::

      1 car:  step 903 ns, drive 291 ns (0.32 x), closed loop 1211 ns (1.34 x)
      8 cars: step 915 ns, drive 149 ns (0.16 x), closed loop 1113 ns (1.22 x)
     32 cars: step 917 ns, drive 141 ns (0.15 x), closed loop 1116 ns (1.22 x)

The driver costs 0.15 of the brush car's step per car in a world of several cars (its
fixed part, the call and the loops, spreads over them; the projections of every car on
the one path and the scan for the car ahead grow with the cars but stay small at 32).
"""

from __future__ import annotations

import argparse
import time

import numba as nb
import numpy as np

from simserver.adapters.config import load_vehicle
from simserver.adapters.driver_config import DriverSpec, build_drivers
from simserver.core import driver as D
from simserver.core import layout as L
from simserver.core.contact import N_CAR_CONTACT_OUT
from simserver.core.world import WorldData, WorldModel
from simserver.core.world import simulate as world_simulate
from simserver.sim.scene import INITIAL_RANGES, Scene
from simserver.sim.simulation import Simulation, World
from simserver.testing import REPO

VEHICLE = REPO / "configs" / "vehicles" / "paper_sedan" / "vehicle.yaml"
DT_S = 0.001
SPACING_M = 30.0
SPEED_MPS = 15.0


@nb.njit(cache=True, _nrt=False)
def drive_only(world: WorldModel, data: WorldData, drv: D.Drivers, n: int) -> None:
    """``drive`` ``n`` times on the same states (the driver's cost alone)."""
    for _ in range(n):
        D.drive(world, data, drv)


def make_world(n_cars: int) -> tuple[World, D.Drivers]:
    """N driven brush cars on the flat along x, 30 m apart, at 15 m/s, settled."""
    vehicle = load_vehicle(VEHICLE, {})
    params = np.zeros(D.N_DRIVER_PARAM)
    for p in D.DRIVER_PARAMS:
        if not p.derived:
            params[p.slot] = np.nan if isinstance(p.default, str) else p.default
    params[D.DP_IDM_V0_MPS] = 20.0
    path = np.array([[-100.0, 0.0], [n_cars * SPACING_M + 10_000.0, 0.0]])
    world: World | None = None
    specs: dict[str, DriverSpec] = {}
    for c in range(n_cars):
        initial = dict.fromkeys(INITIAL_RANGES, 0.0) | {"x_m": c * SPACING_M,
                                                        "u_mps": SPEED_MPS, "relaxed": 1.0}
        scene = Scene(path=VEHICLE, vehicle=vehicle, road={"grade_pct": 0.0,
                      "cross_slope_pct": 0.0, "friction_scale": 1.0}, initial=initial)
        sim = Simulation(scene, DT_S, car_id=f"car{c}")
        sim.inputs[L.IN_GEAR] = L.GEAR_D
        sim.reset(None)
        if world is None:
            world = sim.world
        else:
            sim.move_to(world)
        specs[f"car{c}"] = DriverSpec(params=params.copy(), path_xy=path, speed_profile=[],
                                      stop_s_m=np.inf, go_t_s=np.inf)
    return world, build_drivers(world, specs)


def _copy(data: WorldData) -> WorldData:
    return WorldData(data.x.copy(), data.inputs.copy(), data.out.copy(),
                     type(data.ws)(*(a.copy() for a in data.ws)),
                     type(data.contacts)(*(a.copy() for a in data.contacts)))


def measure(n_cars: int, seconds: float, repeats: int) -> dict[str, np.ndarray]:
    world, drivers = make_world(n_cars)
    steps = int(round(seconds / DT_S))
    every = 1000
    rows = -(-steps // every)
    states = np.zeros((rows, n_cars, L.N_STATE))
    outputs = np.zeros((rows, n_cars, L.N_OUT))
    applied = np.zeros((rows, n_cars, L.N_INPUT))
    dstates = np.zeros((rows, n_cars, D.N_DRIVER_STATE))
    contact_rows = np.zeros((rows, n_cars, N_CAR_CONTACT_OUT))
    start = _copy(world.data)
    # one closed-loop second first: the inputs the open loop repeats are a driver's
    data = _copy(start)
    warm = np.zeros((1000, n_cars, L.N_INPUT))
    D.simulate_driven(world.model, data, drivers, warm, states[:1], outputs[:1], applied[:1],
                      dstates[:1], 1000)
    inputs = np.repeat(data.inputs[None], steps, axis=0)
    d0 = drivers.state.copy()
    p0 = drivers.proj.copy()
    times: dict[str, list[float]] = {"step": [], "drive": [], "closed loop": []}
    for r in range(repeats + 1):  # the first round compiles or loads
        runs = (("step", lambda d: world_simulate(world.model, d, inputs, states, outputs,
                                                  every, contact_rows)),
                ("drive", lambda d: drive_only(world.model, d, drivers, steps)),
                ("closed loop", lambda d: D.simulate_driven(world.model, d, drivers, inputs,
                                                            states, outputs, applied,
                                                            dstates, every)))
        for name, call in runs:
            d = _copy(data)
            drivers.state[:] = d0
            drivers.proj[:] = p0
            t0 = time.process_time()
            call(d)
            dt = time.process_time() - t0
            if r > 0:
                times[name].append(1e9 * dt / (steps * n_cars))
    return {k: np.array(v) for k, v in times.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cars", default="1,8,32")
    parser.add_argument("--seconds", type=float, default=2.0)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    print("ns per car-step (CPU time): median [p10, p90] over repeats")
    for n in (int(v) for v in args.cars.split(",")):
        t = measure(n, args.seconds, args.repeats)
        med = {k: float(np.median(v)) for k, v in t.items()}
        cells = "  ".join(f"{k} {med[k]:7.0f} [{np.percentile(v, 10):.0f}, "
                          f"{np.percentile(v, 90):.0f}]" for k, v in t.items())
        print(f"{n:3d} cars: {cells}  driver/step {med['drive'] / med['step']:.2f}  "
              f"closed loop/step {med['closed loop'] / med['step']:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
