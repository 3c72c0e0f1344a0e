"""The terrain in the Rerun scene (issue 15 item 4): real recordings read back with Rerun's
reader (``rerun.chunk.RrdReader``).

- headless (``log_result``, what ``run-scenario --rrd`` writes): a car rolling down the
  generated height map's hill is drawn on it: the ground mesh is there, static, with the
  grid's vertex count and bounds; the car's CG is the state's world pose and falls with
  the ground; the wheels stand on the surface under them;
- an OpenDRIVE road: its lanes lie on the rasterised surface, its road marks are drawn
  where and as the file says;
- live: the viewer's path (wire states -> ``rows_from_state`` on the plane fitted under
  the car -> ``SceneLogger``) draws the same car as the state's world pose, and the
  ``simserver view`` process against a server on the height map writes the terrain and
  the car on it.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

from simserver.adapters import rerun_scene as S
from simserver.adapters import rerun_terrain as T
from simserver.core import layout as L
from simserver.core.params import VP_CG_HEIGHT_M
from simserver.core.pose import world_pose
from simserver.core.road import road_axes
from simserver.core.terrain import surface_at

REPO = Path(__file__).resolve().parents[1]
VEHICLE = REPO / "configs" / "vehicles" / "paper_sedan" / "vehicle.yaml"
HILLS = REPO / "configs" / "roads" / "hills.npz"

HILL_SCENARIO = f"""\
name: rerun_terrain_hill_roll
vehicle: {VEHICLE.as_posix()}
terrain: {{kind: heightmap, file: {HILLS.as_posix()}, cell_m: 0.25, origin_m: [-10.0, -6.0]}}
initial: {{x_m: 55.0, y_m: 0.0, yaw_rad: 0.0, u_mps: 0.0}}
duration_s: 4.0
inputs:
  - {{t: 0.0, gear: N}}
"""


def read_rrd(path: Path) -> dict[str, dict]:
    """Every entity: its static columns and its temporal rows ``(sim_time ns, columns)``."""
    from rerun.chunk import RrdReader

    entities: dict[str, dict] = {}
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        entry = entities.setdefault(chunk.entity_path, {"static": {}, "rows": []})
        names = [n for n in batch.schema.names if n != "rerun.controls.RowId"]
        if chunk.is_static:
            entry["static"].update({n: batch.column(n).to_pylist() for n in names})
            continue
        times = batch.column("sim_time").cast("int64").to_pylist()
        cols = {n: batch.column(n).to_pylist() for n in names if n != "sim_time"}
        entry["rows"] += [(t, {n: c[k] for n, c in cols.items()}) for k, t in enumerate(times)]
    for entry in entities.values():
        entry["rows"].sort(key=lambda r: r[0])
    return entities


def quat_matrix(q) -> np.ndarray:
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def state_world_pose(x: np.ndarray, cg_height_m: float) -> np.ndarray:
    """The world pose of a state on a terrain (``Simulation.update_pose``: the states live
    on their reference plane, through (0, 0, REF_HEIGHT_M))."""
    pose = np.zeros(L.N_POSE)
    world_pose(x, road_axes(x[L.REF_GRADE_PCT], x[L.REF_CROSS_SLOPE_PCT]), cg_height_m, pose)
    pose[L.POSE_Z_M] += x[L.REF_HEIGHT_M]
    return pose


def drawn_cg_and_hubs(entities: dict, t_ns: int) -> tuple[np.ndarray, np.ndarray,
                                                           np.ndarray]:
    """World CG position, car-frame rotation and world hub positions drawn at ``t_ns``."""
    car = dict(entities["/world/car"]["rows"])[t_ns]
    body = dict(entities["/world/car/body"]["rows"])[t_ns]
    (car_t,), (car_q,) = car["Transform3D:translation"], car["Transform3D:quaternion"]
    (body_t,) = body["Transform3D:translation"]
    r_car = quat_matrix(car_q)
    cg = np.array(car_t) + r_car @ np.array(body_t)
    hubs = []
    for w in L.WHEEL_NAMES:
        (hub_t,) = dict(entities[f"/world/car/wheel_{w}"]["rows"])[t_ns][
            "Transform3D:translation"]
        hubs.append(np.array(car_t) + r_car @ np.array(hub_t))
    return cg, r_car, np.array(hubs)


@pytest.fixture(scope="module")
def hill_run(tmp_path_factory):
    """4 s of the paper's car rolling in neutral from near the top of the height map's
    6 m hill, logged by ``log_result`` (the ``run-scenario --rrd`` path)."""
    import rerun as rr

    from simserver.sim.scenario import load_scenario, run_scenario

    root = tmp_path_factory.mktemp("rerun_terrain")
    path = root / "hill.yaml"
    path.write_text(HILL_SCENARIO, encoding="utf-8")
    scenario = load_scenario(path)
    result = run_scenario(scenario)
    rrd = root / "hill.rrd"
    rec = rr.RecordingStream("simserver", recording_id="hill")
    rec.save(rrd)
    S.log_result(rec, result)
    rec.disconnect()
    return {"scenario": scenario, "result": result, "entities": read_rrd(rrd)}


def test_the_height_map_is_one_static_mesh_with_the_grid_s_vertices(hill_run):
    entities = hill_run["entities"]
    terrain = hill_run["scenario"].scene.terrain
    ground = entities["/" + T.GROUND]
    assert not ground["rows"], "the terrain is static: logged once per recording"
    (positions,) = ground["static"]["Mesh3D:vertex_positions"]
    positions = np.array(positions)
    ny, nx = terrain.heights.shape  # 49 x 961: below MAX_GROUND_VERTICES, every sample
    assert T.ground_stride(ny, nx) == 1 and positions.shape == (ny * nx, 3)
    np.testing.assert_allclose(positions[:, :2].min(axis=0), [-10.0, -6.0], atol=1e-4)
    np.testing.assert_allclose(positions[:, :2].max(axis=0), [230.0, 6.0], atol=1e-4)
    np.testing.assert_allclose(  # the mesh passes through the samples (float32 in the file)
        [positions[:, 2].min(), positions[:, 2].max()],
        np.array([terrain.heights.min(), terrain.heights.max()]) + T.GROUND_OFFSET_M,
        atol=1e-5)
    (triangles,) = ground["static"]["Mesh3D:triangle_indices"]
    assert len(triangles) == 2 * (ny - 1) * (nx - 1)
    # the plane kind's road is not drawn under a terrain
    assert "/" + S.ROAD_SURFACE not in entities and "/" + S.ROAD_GRID not in entities
    (note,) = entities["/" + S.SCENE_INFO]["static"]["TextDocument:text"]
    assert "Terrain: 961 x 49 height grid of 0.25 m cells" in str(note)


def test_the_car_is_drawn_at_its_world_pose_and_falls_with_the_ground(hill_run):
    """The drawn CG is the state's world pose (``Simulation.update_pose``) at every frame;
    the car rolls down the hill, so its height falls by metres, and it stays its CG
    height above the ground under it."""
    entities, result = hill_run["entities"], hill_run["result"]
    terrain = hill_run["scenario"].scene.terrain
    vp = hill_run["scenario"].scene.vehicle.vp
    h_cg = float(vp[VP_CG_HEIGHT_M])
    times = np.round(result.time_s * 1e9).astype(np.int64)
    rows = entities["/world/car"]["rows"]
    assert len(rows) == 201  # 4 s at 50 frames a second, and the last row
    heights, clearances = [], []
    for t_ns, _ in rows:
        (k,) = np.flatnonzero(times == t_ns)
        pose = state_world_pose(result.states[k], h_cg)
        cg, _, _ = drawn_cg_and_hubs(entities, t_ns)
        # float32 translations in the file: 1e-5 relative of 70 m
        np.testing.assert_allclose(cg, pose[:3], atol=1e-3)
        ground_z = surface_at(terrain, cg[0], cg[1])[0]
        heights.append(cg[2])
        clearances.append(cg[2] - ground_z)
    assert heights[0] - heights[-1] > 1.0  # it rolled down a metre and more
    # The CG is h_cg above the plane fitted under the wheels, along its normal: on the
    # hill's flank (grade up to 21 %) that puts it up to h_cg (1/cos - 1) + the plane's
    # miss of the curved surface (about 1 cm over the wheelbase) off h_cg vertically,
    # plus the body's heave and pitch on its springs (centimetres).
    np.testing.assert_allclose(clearances, h_cg, atol=0.06)


def test_the_wheels_stand_on_the_ground_under_them(hill_run):
    """Each hub is its rolling radius above the surface, along the plane's normal."""
    entities = hill_run["entities"]
    terrain = hill_run["scenario"].scene.terrain
    radius = S.CarGeometry.from_params(hill_run["scenario"].scene.vehicle.vp,
                                       hill_run["scenario"].scene.vehicle.tp).wheel_radius_m
    checked = 0
    for t_ns, _ in entities["/world/car"]["rows"][::10]:
        _, r_car, hubs = drawn_cg_and_hubs(entities, t_ns)
        normal = r_car[:, 2]
        for i in range(L.N_WHEELS):
            contact = hubs[i] - radius[i] * normal
            ground = surface_at(terrain, contact[0], contact[1])[0]
            # the gap is measured along the plane's normal at the contact point's foot on
            # the plane: on a 21 % grade that point is a few mm from the drawn one
            assert abs(contact[2] - ground) < 0.01, (t_ns, i, contact[2] - ground)
            checked += 1
    assert checked >= 80


def test_a_wheel_off_the_ground_hangs_and_a_loaded_one_stands_on_it():
    """Over a 1 m cliff at 8 m/s: while a front wheel carries load its hub is drawn on the
    ground under it; while it carries none with the ground far below, it hangs near the
    body (its spring at free length), not down on the ground."""
    import dataclasses

    from simserver.core.terrain import heightmap_terrain
    from simserver.sim.scene import load_scene
    from simserver.sim.simulation import Simulation

    scene = load_scene(REPO / "configs" / "scenes" / "flat_paper_sedan.yaml")
    x = np.arange(0.0, 60.01, 0.5)
    terrain = heightmap_terrain(np.tile(np.where(x < 20.0, 1.0, 0.0), (21, 1)), 0.5, 0.5,
                                0.0, -5.0)
    scene = dataclasses.replace(scene, terrain=terrain,
                                initial={**scene.initial, "x_m": 14.0, "u_mps": 8.0})
    n = 1200
    inputs = np.zeros((n, L.N_INPUT))
    inputs[:, L.IN_GEAR] = L.GEAR_N
    states, out = np.zeros((n, L.N_STATE)), np.zeros((n, L.N_OUT))
    Simulation(scene, 0.001).run(inputs, states, out, 1)
    assert np.isfinite(states).all() and states[-1, L.X_M] > 21.0  # over the edge
    geometry = S.CarGeometry.from_params(scene.vehicle.vp, scene.vehicle.tp)
    axes, heights = S.reference_planes(states)
    offsets = S.wheel_hub_offsets(states, out, axes, heights, terrain, scene.vehicle.vp,
                                  geometry)
    car_t, car_q = S.car_pose(states, axes, heights)
    radius = geometry.wheel_radius_m
    for i in range(L.N_FRONT_WHEELS):
        hub = np.column_stack([np.tile(geometry.wheel_xy_m[i], (n, 1)),
                               radius[i] + offsets[:, i]])
        rot = np.array([quat_matrix(q) for q in car_q])
        contact = car_t + np.einsum("nij,nj->ni", rot, hub) - radius[i] * rot[:, :, 2]
        above = contact[:, 2] - [surface_at(terrain, a, b)[0] for a, b in contact[:, :2]]
        loaded = out[:, L.O_FZ0 + i] > 0.0
        # on the ground while loaded (1 cm: the plane's gap is taken at the contact
        # point's foot on the plane, and the 1 m step is smoothed over a 0.5 m cell)
        assert np.all(np.abs(above[loaded]) < 0.01), i
        # unloaded past the edge: it hangs with the body, well above the ground below
        assert np.sum(~loaded & (above > 0.2)) > 50, i
        assert np.all(above[~loaded] > -0.01), i


# --------------------------------------------------------------------- OpenDRIVE
XODR = """\
<?xml version="1.0" standalone="yes"?>
<OpenDRIVE>
  <header revMajor="1" revMinor="6" name="test"/>
  <road name="r" length="120.0" id="7" junction="-1">
    <planView>
      <geometry s="0.0" x="5.0" y="-3.0" hdg="0.3" length="60.0"><line/></geometry>
      <geometry s="60.0" x="62.3215" y="14.7303" hdg="0.3" length="60.0">
        <arc curvature="0.01"/></geometry>
    </planView>
    <elevationProfile><elevation s="0.0" a="1.0" b="0.05" c="0.0" d="0.0"/></elevationProfile>
    <lateralProfile><superelevation s="0.0" a="0.0" b="0.001" c="0.0" d="0.0"/></lateralProfile>
    <lanes>
      <laneSection s="0.0">
        <left><lane id="1" type="driving" level="false">
          <width sOffset="0.0" a="3.5" b="0.0" c="0.0" d="0.0"/>
          <roadMark sOffset="0.0" type="solid" color="standard" width="0.12"/>
        </lane></left>
        <center><lane id="0" type="none" level="false">
          <roadMark sOffset="0.0" type="broken" color="yellow" width="0.15"/>
        </lane></center>
        <right>
          <lane id="-1" type="driving" level="false">
            <width sOffset="0.0" a="3.5" b="0.0" c="0.0" d="0.0"/>
            <roadMark sOffset="0.0" type="solid" color="standard" width="0.12"/>
            <roadMark sOffset="50.0" type="none"/>
          </lane>
          <lane id="-2" type="shoulder" level="false">
            <width sOffset="0.0" a="1.0" b="0.0" c="0.0" d="0.0"/>
          </lane>
        </right>
      </laneSection>
    </lanes>
  </road>
</OpenDRIVE>
"""


@pytest.fixture(scope="module")
def road_scene(tmp_path_factory):
    from simserver.sim.scene import load_scene

    root = tmp_path_factory.mktemp("xodr")
    (root / "road.xodr").write_text(XODR, encoding="utf-8")
    scene = root / "scene.yaml"
    scene.write_text(f"vehicle: {VEHICLE.as_posix()}\n"
                     "terrain: {kind: opendrive, file: road.xodr, cell_m: 0.5, margin_m: 5}\n",
                     encoding="utf-8")
    return load_scene(scene)


def test_opendrive_lanes_lie_on_the_rasterised_surface(road_scene):
    """The lane mesh's points are the surface the step drives on: within 1 cm of the
    height grid's interpolated surface (the raster's own error on a 0.5 m grid)."""
    from simserver.adapters.opendrive import load_opendrive

    lanes = T.lane_surfaces(load_opendrive(road_scene.terrain_spec["file"]))
    assert sorted((ln["id"], ln["type"]) for ln in lanes) == [
        (-2, "shoulder"), (-1, "driving"), (0, "center"), (1, "driving")]
    for lane in lanes:
        for points in (lane["inner"], lane["outer"]):
            z = np.array([surface_at(road_scene.terrain, x, y)[0] for x, y in points[:, :2]])
            np.testing.assert_allclose(points[:, 2], z, atol=0.01)
    # the left driving lane's outer border is 3.5 m to the left of the reference line
    left = next(ln for ln in lanes if ln["id"] == 1)
    start = left["outer"][0]
    np.testing.assert_allclose(start, [5.0 - 3.5 * np.sin(0.3), -3.0 + 3.5 * np.cos(0.3),
                                       1.0], atol=1e-9)


def test_opendrive_road_is_drawn_with_its_marks(road_scene, tmp_path):
    import rerun as rr

    path = tmp_path / "road.rrd"
    rec = rr.RecordingStream("simserver", recording_id="road")
    rec.save(path)
    text = T.log_terrain(rec, road_scene.terrain, road_scene.terrain_spec)
    rec.disconnect()
    entities = read_rrd(path)
    assert {"/" + p for p in T.TERRAIN_ENTITY_PATHS} <= set(entities)
    assert "OpenDRIVE 1 road(s), 3 lane pieces" in text
    (lane_vertices,) = entities["/" + T.LANES]["static"]["Mesh3D:vertex_positions"]
    assert len(lane_vertices) == 3 * 2 * 121  # 3 lanes, 2 borders, 120 m every 1 m
    marks = entities["/" + T.MARKS]["static"]
    (strips,) = marks["LineStrips3D:strips"]
    (radii,) = marks["LineStrips3D:radii"]
    lengths = [np.sum(np.linalg.norm(np.diff(np.array(s), axis=0), axis=1)) for s in strips]
    # solid left border: one strip of 120 m; the right one ends at s = 50 m (type none
    # from there); the yellow centre line broken: 3 m dashes every 9 m
    yellow = int.from_bytes(bytes([240, 200, 40, 255]), "big")
    (colors,) = marks["LineStrips3D:colors"]
    dashes = [ln for ln, c in zip(lengths, colors, strict=True) if c == yellow]
    solid = sorted(ln for ln, c in zip(lengths, colors, strict=True) if c != yellow)
    assert len(dashes) == 14 and all(abs(d - 3.0) < 0.05 for d in dashes[:-1])
    # lengths along the 5 % grade: 50 m of the straight on the right; on the left 60 m
    # straight and the 60 m arc (radius 100 m) 3.5 m inside it (0.1 m: the superelevation's
    # 0.12 rad of roll tilts the border a few cm)
    grade = np.sqrt(1.0 + 0.05**2)
    assert solid == pytest.approx([50.0 * grade, (60.0 + 60.0 * 96.5 / 100.0) * grade],
                                  abs=0.1)
    assert sorted(set(np.round(radii, 3))) == [0.06, 0.075]  # half the marks' widths


def test_a_large_grid_is_decimated_to_the_vertex_budget():
    from simserver.core.terrain import heightmap_terrain

    terrain = heightmap_terrain(np.zeros((1001, 1203)), 0.5, 0.5)
    mesh = T.ground_mesh(terrain, max_vertices=250_000)
    stride = T.ground_stride(1001, 1203, 250_000)
    assert stride == 3
    # rows 0, 3, .., 999 and the last, 1000; columns 0, 3, .., 1200 and the last, 1202
    assert len(mesh["vertex_positions"]) == 335 * 402 <= 250_000
    np.testing.assert_allclose(mesh["vertex_positions"][-1], [601.0, 500.0, -0.02])


# -------------------------------------------------------------------------- live
def test_the_live_path_draws_the_wire_pose_on_the_terrain(hill_run, tmp_path):
    """States as the server publishes them (world pose) through the viewer's
    ``rows_from_state`` on the plane fitted under the car: the drawn CG is the wire
    pose, the wheels stand on the ground."""
    import rerun as rr

    from simserver.adapters.viewer import rows_from_state
    from simserver.wire import protocol as proto

    scene = hill_run["scenario"].scene
    result = hill_run["result"]
    h_cg = float(scene.vehicle.vp[VP_CG_HEIGHT_M])
    path = tmp_path / "live.rrd"
    rec = rr.RecordingStream("simserver", recording_id="live")
    rec.save(path)
    logger = S.SceneLogger(rec, scene.vehicle.vp, scene.vehicle.tp, terrain=scene.terrain,
                           terrain_spec=scene.terrain_spec, send_blueprint=False)
    wire = np.zeros((), dtype=proto.STATE_DTYPE)
    x, out, inputs = np.zeros(L.N_STATE), np.zeros(L.N_OUT), np.zeros(L.N_INPUT)
    poses = {}
    for k in range(0, result.time_s.size, 20):
        pose = state_world_pose(result.states[k], h_cg)
        for name, slot in (("x_m", L.POSE_X_M), ("y_m", L.POSE_Y_M), ("z_m", L.POSE_Z_M),
                           ("yaw_rad", L.POSE_YAW_RAD), ("pitch_rad", L.POSE_PITCH_RAD),
                           ("roll_rad", L.POSE_ROLL_RAD)):
            wire[name] = pose[slot]
        wire["sim_time_s"] = result.time_s[k]
        plane = S.terrain_plane_under(scene.terrain, logger.geometry, pose[0], pose[1],
                                      pose[3])
        rows_from_state(wire, road_axes(0.0, 0.0), h_cg, x, out, inputs, plane)
        if logger.log_frame(result.time_s[k], x, out, inputs):
            poses[int(round(result.time_s[k] * 1e9))] = pose
    logger.flush()
    rec.disconnect()
    entities = read_rrd(path)
    assert entities["/" + T.GROUND]["static"] and not entities["/" + T.GROUND]["rows"]
    radius = logger.geometry.wheel_radius_m
    for t_ns, _ in entities["/world/car"]["rows"]:
        cg, r_car, hubs = drawn_cg_and_hubs(entities, t_ns)
        np.testing.assert_allclose(cg, poses[t_ns][:3], atol=1e-3)
        for i in range(L.N_WHEELS):
            contact = hubs[i] - radius[i] * r_car[:, 2]
            assert abs(contact[2] - surface_at(scene.terrain, *contact[:2])[0]) < 0.01
    assert len(entities["/world/car"]["rows"]) == len(poses) == 200


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_simserver_view_draws_the_terrain_and_the_car_on_it(tmp_path, request):
    """``simserver view`` against a server on the height-map scene: its recording holds
    the ground mesh and the car at the published world pose, wheels on the ground.

    About 75 s on a loaded machine (a server and a viewer process); the default suite's
    short form is ``test_the_live_path_draws_the_wire_pose_on_the_terrain``."""
    from tests.conftest import slow_enabled

    if not slow_enabled(request.config.getoption("markexpr")):
        pytest.skip("long form: run with -m slow or SIMSERVER_SLOW=1")
    from simserver.testing import Client, OutputProcess, ServerProcess, wait_until

    rrd = tmp_path / "live.rrd"
    server = ServerProcess(vehicle_id="viewt", scene="hills_paper_sedan")
    watcher = Client(server, state_capacity=1 << 15, keep_history=True)
    env = dict(os.environ, XDG_CONFIG_HOME=str(tmp_path / "xdg_config"),
               XDG_DATA_HOME=str(tmp_path / "xdg_data"))
    viewer = OutputProcess(
        [sys.executable, "-m", "simserver", "view", "--sink", f"save:{rrd}", "--connect",
         server.endpoint, "--vehicle-id", "viewt", "--normal-priority"], env=env)
    try:
        wait_until(lambda: rrd.exists() and rrd.stat().st_size > 500_000
                   or not viewer.alive(), timeout_s=120.0,
                   what="the viewer to draw the terrain (about 2 MB)", interval_s=0.05)
        assert viewer.alive(), viewer.text()
        watcher.poll()
        watcher.history.clear()

        def ran_2000_ticks() -> bool:
            watcher.poll()
            h = watcher.history
            return len(h) > 1 and int(h[-1]["tick"]) - int(h[0]["tick"]) >= 2000

        wait_until(ran_2000_ticks, timeout_s=60.0, what="2 s of states", interval_s=0.02)
        assert viewer.stop(timeout_s=60.0) == 0, viewer.text()
    finally:
        viewer.kill()
        watcher.close()
        server.stop()
    entities = read_rrd(rrd)
    (positions,) = entities["/" + T.GROUND]["static"]["Mesh3D:vertex_positions"]
    assert len(positions) == 49 * 961
    rows = entities["/world/car"]["rows"]
    assert len(rows) >= 10
    pose = {round(float(s["sim_time_s"]) * 1e9): s for s in watcher.history}
    terrain_t = [t for t, _ in rows if t in pose]
    assert terrain_t, "the watcher saw states the viewer drew"
    from simserver.sim.scene import load_scene

    scene = load_scene(REPO / "configs" / "scenes" / "hills_paper_sedan.yaml")
    radius = S.CarGeometry.from_params(scene.vehicle.vp, scene.vehicle.tp).wheel_radius_m
    for t_ns in terrain_t[-5:]:
        cg, r_car, hubs = drawn_cg_and_hubs(entities, t_ns)
        s = pose[t_ns]
        np.testing.assert_allclose(cg, [float(s["x_m"]), float(s["y_m"]), float(s["z_m"])],
                                   atol=1e-3)
        assert abs(cg[2] - surface_at(scene.terrain, cg[0], cg[1])[0]) > 0.3  # above it
        for i in range(L.N_WHEELS):
            contact = hubs[i] - radius[i] * r_car[:, 2]
            assert abs(contact[2] - surface_at(scene.terrain, *contact[:2])[0]) < 0.01
