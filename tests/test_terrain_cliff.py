"""A car meeting a real cliff or wall on a height map stays finite (issue 34 item 2).

A 10 m vertical step on a 0.25 m grid, met at 10 m/s in neutral, up (a wall) and down (a
drop). Before: the contact took the face as it was, so the load went to sqrt(1 + s^2)
times the suspension's force (s about 60 on the spline's face) and the damper's rate to
s x speed: 9.3 MN on the wall and 1.1 MN at the drop's edge, and the fitted reference
plane swung onto the cliff's foot (a 75 degree tilt in one step, pitch reaching 14 rad).
Now (docs/model.md section 11): a face steeper than ``chassis.WALL_SLOPE`` is ridden as
one of that slope, a corner compresses at most to its bump stop (the body's height), and
ground farther below a corner than that leaves the wheel hanging.

The bound on the load is the suspension's: along the contact normal, at most
sqrt(1 + WALL_SLOPE^2) times the corner's force, the static share plus the spring and
anti-roll bar at the bump stop plus the damper at a piston speed of at most twice the
fastest the coasting car can move (its speed on entry and the 10 m fall: energy).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from simserver.core import layout as L
from simserver.core.chassis import WALL_SLOPE, static_wheel_load
from simserver.core.params import (
    VP_ANTIROLL_FRONT_NPM,
    VP_ANTIROLL_REAR_NPM,
    VP_CG_HEIGHT_M,
    VP_DAMPER_FRONT_NSPM,
    VP_DAMPER_REAR_NSPM,
    VP_GRAVITY_MPS2,
    VP_SPRING_FRONT_NPM,
    VP_SPRING_REAR_NPM,
)
from simserver.core.terrain import heightmap_terrain
from simserver.sim.scene import load_scene
from simserver.sim.simulation import Simulation
from simserver.testing import CONFIGS, REPO
from tests.test_terrain_physics import run, world_cg

pytestmark = pytest.mark.timeout(600)

DT_S = 0.001
STEP_M = 10.0
SPEED_MPS = 10.0
CELL_M = 0.25


def load_bound(sim: Simulation, fall_m: float, speed_mps: float) -> float:
    """The largest wheel load (N) the suspension can put through a contact (module
    docstring)."""
    vp = sim.vp
    v_max = math.sqrt(speed_mps ** 2 + 2.0 * vp[VP_GRAVITY_MPS2] * fall_m)
    travel = vp[VP_CG_HEIGHT_M]
    worst = 0.0
    for i, (k_s, k_arb, c_s) in enumerate(
            ((vp[VP_SPRING_FRONT_NPM], vp[VP_ANTIROLL_FRONT_NPM], vp[VP_DAMPER_FRONT_NSPM]),) * 2
            + ((vp[VP_SPRING_REAR_NPM], vp[VP_ANTIROLL_REAR_NPM], vp[VP_DAMPER_REAR_NSPM]),) * 2):
        corner = (static_wheel_load(vp, sim.model.terrain.road, i) + (k_s + 2.0 * k_arb) * travel
                  + c_s * 2.0 * v_max)
        worst = max(worst, corner)
    return math.sqrt(1.0 + WALL_SLOPE ** 2) * worst


def coasting(n_steps: int, steer: float = 0.0) -> np.ndarray:
    inputs = np.zeros((n_steps, L.N_INPUT))
    inputs[:, L.IN_GEAR] = L.GEAR_N
    inputs[:, L.IN_STEER] = steer
    return inputs


@pytest.mark.parametrize("direction", ["up", "down"])
def test_a_10_m_step_stays_finite_with_wheel_loads_within_the_suspensions_bound(direction):
    sign = 1.0 if direction == "up" else -1.0
    xs = np.arange(-20.0, 60.0 + CELL_M / 2, CELL_M)
    ys = np.arange(-10.0, 10.0 + CELL_M / 2, CELL_M)
    xx, _ = np.meshgrid(xs, ys)
    face_x = 10.0
    terrain = heightmap_terrain(np.where(xx >= face_x, sign * STEP_M, 0.0), CELL_M, CELL_M,
                                -20.0, -10.0)
    base = load_scene(CONFIGS / "scenes" / "flat_paper_sedan.yaml")
    sim = Simulation(dataclasses.replace(base, terrain=terrain, initial={
        **base.initial, "x_m": 0.0, "y_m": 0.0, "yaw_rad": 0.0, "u_mps": SPEED_MPS}), DT_S)
    states, outputs = run(sim, coasting(3000))
    assert np.isfinite(states).all() and np.isfinite(outputs).all()
    fz = outputs[:, L.O_FZ]
    bound = load_bound(sim, STEP_M if direction == "down" else 0.0, SPEED_MPS)
    print(f"\n10 m step {direction}: largest wheel load {fz.max() / 1e3:.1f} kN "
          f"(bound {bound / 1e3:.1f} kN; before the fix 9.3 MN up, 1.1 MN down)")
    assert fz.max() <= bound
    cg = world_cg(sim, states)
    if direction == "down":
        airborne = (fz == 0.0).all(axis=1)
        assert airborne.sum() > 100  # all four wheels off the ground for a while
        assert cg[:, 2].min() < -STEP_M + 1.0  # and it fell to the foot
    else:
        # the wall stopped it: it never got onto the top, and rolls back from the face
        assert cg[:, 2].max() < 0.5 * STEP_M
        assert cg[-1, 0] < face_x and states[-1, L.U_MPS] < 0.0


def test_a_car_driven_off_the_road_of_tunnels_xodr_into_the_ground_stays_finite():
    """Issue 34: off a road of tunnels.xodr into the ground between the roads, the car saw
    0.7-3.2 MN within 6 ms and the run went non-finite. Here: off road 1's right-hand
    lanes at x = 114 m, heading south at 15 m/s across where the old fill had a 7.8 m
    cliff (y = -48.5 m, road 1's margin against rows filled from road 2); for 4 s
    everything stays finite and the loads within the suspension's bound for the heights
    the ground spans."""
    from simserver.adapters.terrain_files import terrain_from_spec

    road_file = REPO / "tests" / "data" / "tunnels.xodr"
    spec = {"kind": "opendrive", "file": str(road_file), "cell_m": 0.5, "margin_m": 20.0}
    terrain = terrain_from_spec(spec)
    scene = load_scene(CONFIGS / "scenes" / "crest_curve_paper_sedan.yaml")
    sim = Simulation(dataclasses.replace(scene, terrain=terrain, terrain_spec=spec, initial={
        **scene.initial, "x_m": 114.0, "y_m": -30.0, "yaw_rad": -math.pi / 2,
        "u_mps": 15.0}), DT_S)
    states, outputs = run(sim, coasting(4000))
    assert np.isfinite(states).all() and np.isfinite(outputs).all()
    cg = world_cg(sim, states)
    assert cg[:, 1].min() < -60.0  # it crossed y = -48.5 m
    heights = terrain.heights
    bound = load_bound(sim, float(heights.max() - heights.min()), 15.0)
    print(f"\ntunnels.xodr off the road: largest wheel load "
          f"{outputs[:, L.O_FZ].max() / 1e3:.1f} kN (bound {bound / 1e3:.1f} kN)")
    assert outputs[:, L.O_FZ].max() <= bound
