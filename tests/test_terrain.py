"""Terrain kinds (docs/model.md section 11): the height map's surface, its files, and the car
on it: the plane as a height map rests like the plane kind, the sharp bump lifts a wheel,
coasting between hills only loses energy."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from simserver.adapters.terrain_files import load_terrain
from simserver.adapters.validate import ConfigError
from simserver.core import layout as L
from simserver.core.chassis import wheel_inertia
from simserver.core.params import (
    VP_CG_HEIGHT_M,
    VP_GRAVITY_MPS2,
    VP_MASS_KG,
    VP_PITCH_INERTIA_KGM2,
    VP_ROLL_INERTIA_KGM2,
    VP_SPRUNG_MASS_KG,
    VP_YAW_INERTIA_KGM2,
)
from simserver.core.road import road_axes
from simserver.core.terrain import TERRAIN_HEIGHTMAP, heightmap_terrain, surface_at
from simserver.sim.scene import load_scene
from simserver.sim.simulation import Simulation

REPO = Path(__file__).resolve().parents[1]
FLAT_SCENE = REPO / "configs" / "scenes" / "flat_paper_sedan.yaml"
HILLS_SCENE = REPO / "configs" / "scenes" / "hills_paper_sedan.yaml"
DT_S = 0.001


def run(sim: Simulation, n_steps: int, gear: int) -> tuple[np.ndarray, np.ndarray]:
    """``n_steps`` steps in gear ``gear`` with no pedal: start states and outputs."""
    inputs = np.zeros((n_steps, L.N_INPUT))
    inputs[:, L.IN_GEAR] = gear
    states = np.zeros((n_steps, L.N_STATE))
    outputs = np.zeros((n_steps, L.N_OUT))
    sim.run(inputs, states, outputs, 1)
    return states, outputs


def cg_height(sim: Simulation, x: np.ndarray) -> float:
    """World height of the CG at state ``x`` (on the reference plane stored in ``x``)."""
    axes = road_axes(x[L.REF_GRADE_PCT], x[L.REF_CROSS_SLOPE_PCT])
    lift = sim.vp[VP_CG_HEIGHT_M] + x[L.HEAVE_M]
    return float(x[L.REF_HEIGHT_M] + x[L.X_M] * axes[0, 2] + x[L.Y_M] * axes[1, 2]
                 + lift * axes[2, 2])


# ---------------------------------------------------------------- the surface
def test_catmull_rom_reproduces_a_plane_and_is_c1_on_the_hills():
    xs = np.arange(-5.0, 5.5, 0.5)
    xx, yy = np.meshgrid(xs, xs)
    plane = heightmap_terrain(0.1 * xx - 0.03 * yy + 2.0, 0.5, 0.5, -5.0, -5.0)
    for px, py in ((0.13, -1.7), (3.3, 2.9), (-4.0, 0.26)):
        h, gx, gy, mu = surface_at(plane, px, py)
        assert h == pytest.approx(0.1 * px - 0.03 * py + 2.0, abs=1e-12)
        assert (gx, gy, mu) == (pytest.approx(0.1), pytest.approx(-0.03), 1.0)
    hills = load_terrain(HILLS_SCENE, {"kind": "heightmap", "file": "../roads/hills.npz",
                                       "cell_m": 0.25, "origin_m": [-10.0, -6.0]})
    # across cell boundaries (every 0.25 m) the gradient moves by what the slope's own
    # variation explains, no jump: sample 1 mm apart through the bump's flank and the hill
    for x0, y0 in ((199.75, 1.0), (50.0, 0.0), (200.0, 0.1)):
        for axis in (0, 1):
            p0 = [x0, y0]
            p1 = [x0, y0]
            p0[axis] -= 0.0005
            p1[axis] += 0.0005
            g0 = np.array(surface_at(hills, *p0)[1:3])
            g1 = np.array(surface_at(hills, *p1)[1:3])
            assert np.max(np.abs(g1 - g0)) < 0.01


def test_png_heightmap_with_height_scale(tmp_path):
    from PIL import Image

    values = (np.arange(12 * 9).reshape(9, 12) * 600).astype(np.uint16)
    Image.fromarray(values).save(tmp_path / "h.png")
    terrain = load_terrain(tmp_path / "scene.yaml", {
        "kind": "heightmap", "file": "h.png", "cell_m": 2.0, "height_scale_m": 10.0,
        "height_offset_m": -1.0})
    assert terrain.kind == TERRAIN_HEIGHTMAP
    np.testing.assert_allclose(terrain.heights, -1.0 + values * (10.0 / 65535.0), rtol=0,
                               atol=1e-12)


@pytest.mark.parametrize("what", ["missing", "truncated", "nan", "png8", "no_heights"])
def test_bad_heightmap_files_are_named(tmp_path, what):
    grid = np.zeros((5, 6))
    name = "h.npz"
    if what == "truncated":
        np.savez(tmp_path / name, heights=grid)
        data = (tmp_path / name).read_bytes()
        (tmp_path / name).write_bytes(data[: len(data) // 2])
    elif what == "nan":
        grid[3, 2] = np.nan
        np.savez(tmp_path / name, heights=grid)
    elif what == "png8":
        from PIL import Image

        name = "h.png"
        Image.fromarray(np.zeros((4, 4), dtype=np.uint8)).save(tmp_path / name)
    elif what == "no_heights":
        np.savez(tmp_path / name, height=grid)
    raw = {"kind": "heightmap", "file": name, "cell_m": 1.0}
    if name.endswith(".png"):
        raw["height_scale_m"] = 1.0
    with pytest.raises(ConfigError) as err:
        load_terrain(tmp_path / "scene.yaml", raw)
    assert str(tmp_path / name) in str(err.value)
    if what == "nan":
        assert "row 3, column 2" in str(err.value)


def test_bad_terrain_keys_name_the_scene_and_key(tmp_path):
    scene = tmp_path / "scene.yaml"
    scene.write_text(
        f"vehicle: {REPO / 'configs/vehicles/paper_sedan/vehicle.yaml'}\n"
        "terrain: {kind: moon}\n")
    with pytest.raises(ConfigError, match=r"scene\.yaml: key 'terrain\.kind'.*moon"):
        load_scene(scene)
    scene.write_text(
        f"vehicle: {REPO / 'configs/vehicles/paper_sedan/vehicle.yaml'}\n"
        "terrain: {kind: heightmap, file: hills.npz}\n")
    with pytest.raises(ConfigError, match=r"scene\.yaml.*cell_m"):
        load_scene(scene)


# ---------------------------------------------------------------- the car on it
def test_plane_as_heightmap_rests_and_holds_like_the_plane():
    """A 10 % grade with a 5 % cross-slope, as the plane kind and as a height map: the
    same resting forces within 0.5 % of the wheel load, and both hold (in P)."""
    scene = load_scene(FLAT_SCENE)
    road = {"grade_pct": 10.0, "cross_slope_pct": 5.0, "friction_scale": 1.0}
    xs = np.arange(-40.0, 40.5, 1.0)
    xx, yy = np.meshgrid(xs, xs)
    terrain = heightmap_terrain(0.10 * xx + 0.05 * yy, 1.0, 1.0, -40.0, -40.0)
    plane = Simulation(dataclasses.replace(scene, road=road), DT_S)
    mapped = Simulation(dataclasses.replace(scene, terrain=terrain), DT_S)
    states_p, out_p = run(plane, 8000, L.GEAR_P)
    states_m, out_m = run(mapped, 8000, L.GEAR_P)
    fz = out_p[-1, L.O_FZ]
    for block in (L.O_FZ, L.O_FX, L.O_FY):
        assert np.all(np.abs(out_m[-1, block] - out_p[-1, block]) < 0.005 * fz), block
    assert np.all(states_m[-1, L.IN_CONTACT] == 1.0)
    # the same plane found under the car
    assert states_m[-1, L.REF_GRADE_PCT] == pytest.approx(10.0, abs=1e-9)
    assert states_m[-1, L.REF_CROSS_SLOPE_PCT] == pytest.approx(5.0, abs=1e-9)
    # holds: after settling (3 s) the car moves by less than a micrometre on both
    for states in (states_p, states_m):
        drift = np.hypot(states[-1, L.X_M] - states[3000, L.X_M],
                         states[-1, L.Y_M] - states[3000, L.Y_M])
        assert drift < 1e-6
    # and both settle to the same place
    assert states_m[-1, L.X_M] == pytest.approx(states_p[-1, L.X_M], abs=1e-3)
    assert states_m[-1, L.Y_M] == pytest.approx(states_p[-1, L.Y_M], abs=1e-3)


@pytest.mark.parametrize("world_yaw_rad", [0.0, 0.7, -2.5, np.pi])
def test_placed_heading_is_the_heading_seen_from_above(world_yaw_rad):
    """``initial.yaw_rad`` on a height map is the heading from world x (docs/model.md
    section 11): the placed car's world pose has that yaw, to rounding, on a plane tilted
    both ways (before the fix it was off by about grade x cross slope, 0.02 rad here)."""
    scene = load_scene(FLAT_SCENE)
    xs = np.arange(-40.0, 40.5, 1.0)
    xx, yy = np.meshgrid(xs, xs)
    terrain = heightmap_terrain(0.15 * xx - 0.12 * yy, 1.0, 1.0, -40.0, -40.0)
    sim = Simulation(dataclasses.replace(
        scene, terrain=terrain, initial={**scene.initial, "yaw_rad": world_yaw_rad}), DT_S)
    yaw = sim.update_pose()[L.POSE_YAW_RAD]
    assert np.angle(np.exp(1j * (yaw - world_yaw_rad))) == pytest.approx(0.0, abs=1e-12)


def test_plane_as_heightmap_drives_the_same_path_as_the_plane():
    """Accelerating, weaving and braking to rest for 10 s on a 3 % grade with a 2 %
    cross-slope, as the plane kind and as a height map (whose spline reproduces a plane
    exactly, so only rounding and the plane fit's re-expression differ): the same world
    pose at the end, 1 mm and 1e-5 rad over about 60 m (a start heading off by grade x
    cross slope, 6e-4 rad, ended 36 mm apart)."""
    scene = load_scene(FLAT_SCENE)
    start = {**scene.initial, "u_mps": 5.0}
    road = {"grade_pct": 3.0, "cross_slope_pct": 2.0, "friction_scale": 1.0}
    xs = np.arange(-200.0, 200.5, 1.0)
    xx, yy = np.meshgrid(xs, xs)
    terrain = heightmap_terrain(0.03 * xx + 0.02 * yy, 1.0, 1.0, -200.0, -200.0)
    n = 10000
    inputs = np.zeros((n, L.N_INPUT))
    inputs[:, L.IN_GEAR] = L.GEAR_D
    inputs[:4000, L.IN_THROTTLE] = 0.6
    inputs[:4000, L.IN_STEER] = 0.15 * np.sin(np.linspace(0, 6 * np.pi, 4000))
    inputs[4000:, L.IN_BRAKE] = 0.5
    poses = []
    for sim in (Simulation(dataclasses.replace(scene, road=road, initial=start), DT_S),
                Simulation(dataclasses.replace(scene, terrain=terrain, initial=start), DT_S)):
        sim.run(inputs, np.zeros((n, L.N_STATE)), np.zeros((n, L.N_OUT)), 1)
        poses.append(sim.update_pose().copy())
    plane, mapped = poses
    assert plane[L.POSE_X_M] > 50.0  # it did drive
    assert np.abs(mapped[:3] - plane[:3]).max() < 1e-3
    assert np.abs(mapped[3:] - plane[3:]).max() < 1e-5


def test_sharp_bump_lifts_a_wheel_and_the_car_lands():
    """At 15 m/s in neutral over the 10 cm bump under the left wheels: a left wheel
    leaves the ground (zero load and zero shear force), the car lands with every state
    finite and all four wheels on the ground."""
    scene = load_scene(HILLS_SCENE)
    scene = dataclasses.replace(scene, initial={**scene.initial, "x_m": 185.0, "u_mps": 15.0})
    sim = Simulation(scene, DT_S)
    states, out = run(sim, 3000, L.GEAR_N)
    airborne = out[:, L.O_FZ] == 0.0
    assert airborne[:, L.FL].any()
    assert not airborne[:, L.FR].any() and not airborne[:, L.RR].any()
    assert np.all(out[airborne[:, 0], L.O_FX0] == 0.0)
    assert np.all(out[airborne[:, 0], L.O_FY0] == 0.0)
    lifted_rows = np.nonzero(airborne[:-1, L.FL])[0]
    assert np.all(states[lifted_rows + 1, L.IN_CONTACT0 + L.FL] == 0.0)
    assert np.isfinite(states).all() and np.isfinite(out).all()
    assert np.all(states[-1, L.IN_CONTACT] == 1.0)
    assert states[-1, L.X_M] > 215.0  # it drove on


def test_coasting_between_hills_only_loses_energy():
    """From rest near the top of the 6 m hill, in neutral: down into the dip and up the
    8 m hill, back and forth; the CG never climbs back to its starting height and the
    mechanical energy never rises."""
    scene = load_scene(HILLS_SCENE)
    sim = Simulation(scene, DT_S)
    vp = sim.vp
    states, _ = run(sim, 40000, L.GEAR_N)
    rows = states[::20]
    mass = vp[VP_MASS_KG]
    g = vp[VP_GRAVITY_MPS2]
    heights = np.array([cg_height(sim, x) for x in rows])
    spin = sum(0.5 * wheel_inertia(vp, i) * rows[:, L.OMEGA0 + i] ** 2
               for i in range(L.N_WHEELS))
    energy = (0.5 * mass * (rows[:, L.U_MPS] ** 2 + rows[:, L.V_MPS] ** 2)
              + 0.5 * vp[VP_SPRUNG_MASS_KG] * rows[:, L.HEAVE_RATE_MPS] ** 2
              + 0.5 * vp[VP_ROLL_INERTIA_KGM2] * rows[:, L.ROLL_RATE_RADPS] ** 2
              + 0.5 * vp[VP_PITCH_INERTIA_KGM2] * rows[:, L.PITCH_RATE_RADPS] ** 2
              + 0.5 * vp[VP_YAW_INERTIA_KGM2] * rows[:, L.YAW_RATE_RADPS] ** 2
              + spin + mass * g * heights)
    assert np.ptp(heights) > 4.0  # it did roll down into the dip
    assert heights[1:].max() < heights[0]
    # energy only falls: never above its running minimum by more than the suspension's
    # stored energy (springs not counted above; a few joules)
    rise = energy - np.minimum.accumulate(energy)
    assert rise.max() < 30.0, rise.max()
    assert energy[-1] < energy[0] - 0.2 * mass * g * (heights[0] - heights.min())


CONSTANT_GRADE_XODR = """<OpenDRIVE><header/>
<road id="1" length="200" junction="-1"><planView>
<geometry s="0" x="-100" y="0" hdg="0" length="200"><line/></geometry></planView>
<elevationProfile><elevation s="0" a="-10" b="0.1" c="0" d="0"/></elevationProfile>
<lanes><laneSection s="0"><left><lane id="1" type="driving">
<width sOffset="0" a="10" b="0" c="0" d="0"/></lane></left>
<center><lane id="0" type="none"/></center><right><lane id="-1" type="driving">
<width sOffset="0" a="10" b="0" c="0" d="0"/></lane></right></laneSection></lanes>
</road></OpenDRIVE>
"""


def test_opendrive_road_of_constant_grade_rests_like_the_plane(tmp_path):
    """A straight OpenDRIVE road rising 10 % (rasterised at load): the same resting forces
    as the plane kind within 0.5 % of the wheel load, and it holds."""
    (tmp_path / "grade.xodr").write_text(CONSTANT_GRADE_XODR)
    terrain = load_terrain(tmp_path / "scene.yaml", {"kind": "opendrive",
                                                     "file": "grade.xodr", "cell_m": 0.5})
    scene = load_scene(FLAT_SCENE)
    road = {"grade_pct": 10.0, "cross_slope_pct": 0.0, "friction_scale": 1.0}
    plane = Simulation(dataclasses.replace(scene, road=road), DT_S)
    drive = Simulation(dataclasses.replace(scene, terrain=terrain), DT_S)
    _, out_p = run(plane, 6000, L.GEAR_P)
    states_d, out_d = run(drive, 6000, L.GEAR_P)
    fz = out_p[-1, L.O_FZ]
    for block in (L.O_FZ, L.O_FX, L.O_FY):
        assert np.all(np.abs(out_d[-1, block] - out_p[-1, block]) < 0.005 * fz), block
    assert states_d[-1, L.REF_GRADE_PCT] == pytest.approx(10.0, abs=1e-6)
    drift = np.hypot(states_d[-1, L.X_M] - states_d[3000, L.X_M],
                     states_d[-1, L.Y_M] - states_d[3000, L.Y_M])
    assert drift < 1e-6
