"""Timed loop of CommonRoad's multi-body vehicle model ("MB") integrated with classic RK4.

Run by :mod:`benchmarks.bench_commonroad` inside the benchmark's own virtual environment,
where ``commonroad-vehicle-models`` is installed (it is not a dependency of simserver)::

    .bench-venv/commonroad/bin/python benchmarks/commonroad_env/mb_loop.py --steps 2000

Each repeat integrates ``--steps`` steps of ``--dt`` seconds from the model's own initial
state (``init_mb``, 15 m/s) with the vehicle-2 parameter set (``parameters_vehicle2``),
under a steering-rate and acceleration input that changes over the run, and reports the
wall time and the process CPU time per step (on a shared machine the CPU time is the fairer
figure: it leaves out the time other processes held the core). The right-hand side is
CommonRoad's ``vehicle_dynamics_mb`` as shipped (pure Python); the RK4 step, four
evaluations, is written here, for the state in one of two forms (``--state``):

- ``array``: a numpy array, the stage sums numpy expressions; every ``x[i]`` the model
  reads is then a numpy scalar. This is how a numpy RK4 or scipy's integrators
  (``odeint``, ``solve_ivp``) call the model; its cost matches issue 16's figure for
  the peer (227 us a step).
- ``list``: a list of Python floats, the stage sums list comprehensions: the fastest way
  to call the model from Python (about 2.7 x faster here).

Prints one JSON object: ``us_per_step`` and ``cpu_us_per_step`` (one figure per repeat),
the state form, the package version and a final-state check.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from importlib.metadata import version

import numpy as np  # in the benchmark's environment (requirements.txt), for --state array


def rk4_step_list(f, x: list[float], u: list[float], p: object, h: float) -> list[float]:  # noqa: ANN001
    """One classic fourth-order Runge-Kutta step of ``dx/dt = f(x, u, p)``, ``x`` a list."""
    k1 = f(x, u, p)
    k2 = f([xi + 0.5 * h * ki for xi, ki in zip(x, k1, strict=True)], u, p)
    k3 = f([xi + 0.5 * h * ki for xi, ki in zip(x, k2, strict=True)], u, p)
    k4 = f([xi + h * ki for xi, ki in zip(x, k3, strict=True)], u, p)
    return [xi + h / 6.0 * (a + 2.0 * b + 2.0 * c + d)
            for xi, a, b, c, d in zip(x, k1, k2, k3, k4, strict=True)]


def rk4_step_array(f, x, u: list[float], p: object, h: float):  # noqa: ANN001, ANN201
    """The same step with ``x`` a numpy array (the model's list result made an array)."""
    k1 = np.asarray(f(x, u, p))
    k2 = np.asarray(f(x + 0.5 * h * k1, u, p))
    k3 = np.asarray(f(x + 0.5 * h * k2, u, p))
    k4 = np.asarray(f(x + h * k3, u, p))
    return x + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


STATE_FORMS = {"array": rk4_step_array, "list": rk4_step_list}


def main() -> None:
    from vehiclemodels.init_mb import init_mb
    from vehiclemodels.parameters_vehicle2 import parameters_vehicle2
    from vehiclemodels.vehicle_dynamics_mb import vehicle_dynamics_mb

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dt", type=float, default=0.001, help="step (s)")
    parser.add_argument("--steps", type=int, default=2000, help="steps per repeat")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--state", choices=sorted(STATE_FORMS), default="list",
                        help="the state's form (see the module docstring)")
    args = parser.parse_args()
    rk4_step = STATE_FORMS[args.state]
    start_state = np.array if args.state == "array" else list

    p = parameters_vehicle2()
    # x, y, steering angle, speed, yaw, yaw rate, slip angle at the centre of mass
    x0 = init_mb([0.0, 0.0, 0.0, 15.0, 0.0, 0.0, 0.0], p)
    n = args.steps
    # steering rate (rad/s) and acceleration (m/s^2): a weave while accelerating, then braking
    inputs = [[0.15 * math.cos(2.0 * math.pi * 0.5 * k * args.dt),
               1.0 if k < n // 2 else -2.0] for k in range(n)]
    per_step, cpu_per_step = [], []
    x = x0
    for _ in range(args.repeats):
        x = start_state(x0)
        t0 = time.perf_counter_ns()
        c0 = time.process_time_ns()
        for k in range(n):
            x = rk4_step(vehicle_dynamics_mb, x, inputs[k], p, args.dt)
        cpu_per_step.append((time.process_time_ns() - c0) / n / 1e3)
        per_step.append((time.perf_counter_ns() - t0) / n / 1e3)
    finite = all(math.isfinite(float(v)) for v in x)
    package = f"commonroad-vehicle-models {version('commonroad-vehicle-models')}"
    print(json.dumps({"us_per_step": per_step, "cpu_us_per_step": cpu_per_step, "steps": n,
                      "dt_s": args.dt, "state": args.state, "package": package,
                      "final_speed_mps": float(x[3]),
                      "finite": finite}))


if __name__ == "__main__":
    main()
