"""OpenDRIVE reader (simserver.adapters.opendrive): the reference-line geometry of the three
third-party files chains end to start, each geometry kind against its closed form, the
profiles are their polynomials, bad files are named."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from simserver.adapters.opendrive import (
    Cubic,
    Geometry,
    OpenDriveError,
    load_opendrive,
    profile_at,
)

ROADS = Path(__file__).resolve().parents[1] / "configs" / "roads"
FILES = ("crest-curve.xodr", "curves_elevation.xodr", "velodrome.xodr")


def angle_diff(a: float, b: float) -> float:
    return abs((a - b + math.pi) % (2.0 * math.pi) - math.pi)


@pytest.mark.parametrize("name", FILES)
def test_each_geometry_ends_where_the_next_starts(name):
    """Every geometry's computed end point and heading equal the next geometry's start
    values written in the file, to 1 mm and 1e-4 rad; the pieces add up to the road."""
    od = load_opendrive(ROADS / name)
    checked = 0
    for road in od.roads:
        for geo, nxt in zip(road.geometries[:-1], road.geometries[1:], strict=True):
            x, y, hdg = geo.end()
            assert math.hypot(x - nxt.x, y - nxt.y) < 1e-3, (road.id, nxt.s)
            assert angle_diff(hdg, nxt.hdg) < 1e-4, (road.id, nxt.s)
            assert geo.s + geo.length == pytest.approx(nxt.s, abs=1e-6)
            checked += 1
        assert sum(g.length for g in road.geometries) == pytest.approx(road.length, abs=1e-6)
    assert checked >= 1


def test_arc_is_a_circle():
    k = 0.008
    arc = Geometry(0.0, 3.0, -2.0, 0.4, 250.0, "arc", {"curvature": k})
    cx, cy = 3.0 - math.sin(0.4) / k, -2.0 + math.cos(0.4) / k  # centre, left of the start
    for ds in (0.0, 10.0, 123.4, 250.0):
        x, y, hdg = arc.point(ds)
        assert math.hypot(x - cx, y - cy) == pytest.approx(1.0 / k, abs=1e-9)
        assert hdg == pytest.approx(0.4 + k * ds, abs=1e-12)


def fresnel_clothoid(a: float, length: float) -> tuple[float, float]:
    """``(int_0^L cos(a s^2) ds, int_0^L sin(a s^2) ds)`` by their power series."""
    x = y = 0.0
    for n in range(30):
        x += (-1) ** n * a ** (2 * n) * length ** (4 * n + 1) / (math.factorial(2 * n)
                                                                 * (4 * n + 1))
        y += (-1) ** n * a ** (2 * n + 1) * length ** (4 * n + 3) / (
            math.factorial(2 * n + 1) * (4 * n + 3))
    return x, y


def test_spiral_against_the_fresnel_integrals():
    """A clothoid from zero curvature: heading a s^2, position the Fresnel integrals."""
    length, k_end = 107.300918301276, 0.008
    spiral = Geometry(0.0, 0.0, 0.0, 0.0, length, "spiral",
                      {"curvStart": 0.0, "curvEnd": k_end})
    a = 0.5 * k_end / length
    for ds in (20.0, 60.0, length):
        x, y, hdg = spiral.point(ds)
        fx, fy = fresnel_clothoid(a, ds)
        assert (x, y) == (pytest.approx(fx, abs=1e-9), pytest.approx(fy, abs=1e-9))
        assert hdg == pytest.approx(a * ds * ds, abs=1e-12)


def test_poly3_and_param_poly3_on_a_known_curve():
    # v = 0.01 u^2 (a parabola); its arc length from 0 to u = 10: closed form
    u_end = 10.0
    c = 0.01
    w = 2.0 * c * u_end
    arc_len = (w * math.sqrt(1 + w * w) + math.asinh(w)) / (4.0 * c)
    poly = Geometry(0.0, 1.0, 2.0, 0.3, arc_len, "poly3", {"a": 0.0, "b": 0.0, "c": c, "d": 0.0})
    x, y, hdg = poly.end()
    ex = 1.0 + math.cos(0.3) * u_end - math.sin(0.3) * c * u_end ** 2
    ey = 2.0 + math.sin(0.3) * u_end + math.cos(0.3) * c * u_end ** 2
    assert (x, y) == (pytest.approx(ex, abs=1e-9), pytest.approx(ey, abs=1e-9))
    assert hdg == pytest.approx(0.3 + math.atan(2 * c * u_end), abs=1e-12)
    para = Geometry(0.0, 1.0, 2.0, 0.3, arc_len, "paramPoly3", {
        "aU": 0.0, "bU": u_end, "cU": 0.0, "dU": 0.0, "aV": 0.0, "bV": 0.0,
        "cV": c * u_end ** 2, "dV": 0.0, "pRange": "normalized"})
    px, py, phdg = para.end()
    assert (px, py) == (pytest.approx(ex, abs=1e-9), pytest.approx(ey, abs=1e-9))
    assert phdg == pytest.approx(hdg, abs=1e-12)


def test_profiles_are_their_polynomials():
    od = load_opendrive(ROADS / "crest-curve.xodr")
    road = od.roads[0]
    # the 6 m crest: continuous at the piece boundaries, 6 m at s = 270
    for s in (200.0, 270.0, 340.0):
        before = profile_at(road.elevation, s - 1e-7)
        assert profile_at(road.elevation, s) == pytest.approx(before, abs=1e-5)
    assert profile_at(road.elevation, 270.0) == pytest.approx(6.0, abs=1e-9)
    piece = road.elevation[1]
    assert profile_at(road.elevation, 230.0) == pytest.approx(
        piece.a + piece.b * 30 + piece.c * 30 ** 2 + piece.d * 30 ** 3, abs=1e-12)
    velodrome = load_opendrive(ROADS / "velodrome.xodr").roads[0]
    assert profile_at(velodrome.superelevation, 750.0) == pytest.approx(-math.pi / 3, abs=1e-9)
    assert profile_at([Cubic(0.0, 1.0, 2.0, 3.0, 4.0)], 0.5) == pytest.approx(
        1 + 1 + 0.75 + 0.5)


GOOD_HEAD = ('<OpenDRIVE><header/><road id="7" length="10"><planView>'
             '<geometry s="0" x="0" y="0" hdg="0" length="10">')
GOOD_TAIL = ('</geometry></planView><lanes><laneSection s="0"><center><lane id="0" '
             'type="none"/></center><right><lane id="-1" type="driving">{width}</lane></right>'
             '</laneSection></lanes></road></OpenDRIVE>')
WIDTH = '<width sOffset="0" a="3.5" b="0" c="0" d="0"/>'


@pytest.mark.parametrize("text, needle", [
    (GOOD_HEAD + "<clothoid/>" + GOOD_TAIL.format(width=WIDTH), "road 7 <geometry> #0"),
    (GOOD_HEAD + "<line/>" + GOOD_TAIL.format(width=""), "lane -1: no <width>"),
    (GOOD_HEAD + "<line/>" + GOOD_TAIL.format(width=WIDTH.replace('a="3.5"', 'a="x"')),
     "attribute 'a'"),
    ((GOOD_HEAD + "<line/>" + GOOD_TAIL.format(width=WIDTH))[:150], "unreadable XML"),
])
def test_bad_files_name_the_file_and_element(tmp_path, text, needle):
    path = tmp_path / "bad.xodr"
    path.write_text(text)
    with pytest.raises(OpenDriveError) as err:
        load_opendrive(path)
    assert str(path) in str(err.value) and needle in str(err.value)
    path.write_text(GOOD_HEAD + "<line/>" + GOOD_TAIL.format(width=WIDTH))
    assert load_opendrive(path).roads[0].lane_sections[0].lanes[1].widths[0].a == 3.5


def test_missing_file_is_named(tmp_path):
    with pytest.raises(OpenDriveError, match="nope.xodr: no such file"):
        load_opendrive(tmp_path / "nope.xodr")


# ---------------------------------------------------------------- start by road, s and lane
def test_lane_start_on_the_lane_centre_heading_along_its_travel():
    """The velodrome's straight (s = 250 m, heading 0 along +x, three 3 m right lanes): lane
    -2's centre is at t = -(3 + 1.5) m, heading along +s (right-hand traffic). On the
    crest road's straight (heading 0), the left lane 1 (3.2 m) travels against s."""
    from simserver.adapters.opendrive import lane_start

    velodrome = load_opendrive(ROADS / "velodrome.xodr")
    assert lane_start(velodrome, "1", 250.0, -2) == pytest.approx((250.0, -4.5, 0.0), abs=1e-12)
    assert lane_start(velodrome, "1", 250.0, -3) == pytest.approx((250.0, -7.5, 0.0), abs=1e-12)
    # mid-turn (arc of radius 125 m, 60 degree bank): t cos(roll) across the heading
    ref_x, ref_y, hdg = velodrome.roads[0].reference(750.0)
    x, y, yaw = lane_start(velodrome, "1", 750.0, -1)
    lateral = -1.5 * math.cos(math.radians(60.0))
    assert (x, y) == (pytest.approx(ref_x - math.sin(hdg) * lateral, abs=1e-9),
                      pytest.approx(ref_y + math.cos(hdg) * lateral, abs=1e-9))
    assert angle_diff(yaw, hdg) < 1e-12
    crest = load_opendrive(ROADS / "crest-curve.xodr")
    x, y, yaw = lane_start(crest, "0", 50.0, 1)
    ref_x, ref_y, hdg = crest.roads[0].reference(50.0)
    assert math.hypot(x - ref_x, y - ref_y) == pytest.approx(1.6, abs=1e-12)
    assert angle_diff(yaw, hdg + math.pi) < 1e-12


def _scene(tmp_path, start: str, initial: str = "{u_mps: 0.0}",
           terrain: str = "{kind: opendrive, file: road.xodr, cell_m: 1.0}"):
    import shutil

    shutil.copy(ROADS / "velodrome.xodr", tmp_path / "road.xodr")
    vehicle = ROADS.parent / "vehicles" / "paper_sedan" / "vehicle.yaml"
    path = tmp_path / "scene.yaml"
    path.write_text(f"vehicle: {vehicle}\nterrain: {terrain}\nstart: {start}\n"
                    f"initial: {initial}\n", encoding="utf-8")
    return path


def test_a_scene_starts_by_road_s_and_lane_on_the_surface(tmp_path):
    """``start: {road, s, lane}`` gives the initial x, y and yaw of ``lane_start``; the
    car is put on the surface (its wheels on the 60 degree bank, all four in contact)."""
    from simserver.adapters.opendrive import lane_start
    from simserver.core import layout as L
    from simserver.sim.scene import load_scene
    from simserver.sim.simulation import Simulation

    scene = load_scene(_scene(tmp_path, '{road: "1", s: 750.0, lane: -2}'))
    x, y, yaw = lane_start(scene.roads, "1", 750.0, -2)
    assert (scene.initial["x_m"], scene.initial["y_m"], scene.initial["yaw_rad"]) == (x, y, yaw)
    sim = Simulation(scene, 0.001)
    pose = sim.update_pose()
    assert math.hypot(pose[L.POSE_X_M] - x, pose[L.POSE_Y_M] - y) < 0.6  # CG above the lane
    # the surface of lane -2's centre: t = -4.5 m up the 60 degree bank
    assert pose[L.POSE_Z_M] > 4.5 * math.sin(math.radians(60.0))
    assert abs(pose[L.POSE_ROLL_RAD]) == pytest.approx(math.radians(60.0), abs=0.02)
    sim.step()
    assert np.all(sim.x[L.IN_CONTACT] == 1.0)


@pytest.mark.parametrize("start, initial, terrain, needle", [
    ('{road: "9", s: 10.0, lane: -1}', "{}", None, "key 'start.road': no road '9'"),
    ('{road: 1, s: 2500.0, lane: -1}', "{}", None, "key 'start.s'"),
    ('{road: "1", s: 10.0, lane: -4}', "{}", None, "key 'start.lane': road 1 has no lane -4"),
    ('{road: "1", s: 10.0, lane: 0}', "{}", None, "key 'start.lane'"),
    ('{road: "1", s: 10.0}', "{}", None, "missing key 'lane'"),
    ('{road: "1", s: 10.0, lane: -1}', "{x_m: 3.0}", None, "key 'initial.x_m'"),
    ('{road: "1", s: 10.0, lane: -1}', "{}", "{kind: plane}", "key 'start': a start by road"),
])
def test_a_bad_start_names_the_key(tmp_path, start, initial, terrain, needle):
    from simserver.adapters.validate import ConfigError
    from simserver.sim.scene import load_scene

    path = _scene(tmp_path, start, initial, *([terrain] if terrain else []))
    with pytest.raises(ConfigError) as err:
        load_scene(path)
    assert str(path) in str(err.value) and needle in str(err.value), str(err.value)


def test_a_scenario_with_a_start_resolves_to_the_same_run(tmp_path):
    from simserver.sim.scenario import load_scenario, resolve_scenario

    path = _scene(tmp_path, '{road: "1", s: 100.0, lane: -1}')
    text = path.read_text(encoding="utf-8")
    path.write_text("name: s\nduration_s: 0.01\ninputs: [{t: 0.0, gear: N}]\n" + text,
                    encoding="utf-8")
    direct = load_scenario(path)
    resolved = load_scenario(path, resolve_scenario(path))
    assert direct.scene.initial == resolved.scene.initial
    assert direct.scene.initial["x_m"] == pytest.approx(100.0)
