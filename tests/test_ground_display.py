"""The grade and cross-slope under the car (issue 15 item 4): the server puts them in the
state (``ground_grade_pct``, ``ground_cross_slope_pct``, with ``wheel_contact``) and the
driver's status shows them.

The states are the real server's: a ``VehicleSlot`` on the real simulation writes them
(``fill_state``, the bytes the loop publishes); the expected slopes come from the terrain
itself (``core.terrain.surface_at``) or the road's definition (``core.road``).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from clients.driver import ground_text
from simserver.core.chassis import wheel_position
from simserver.core.params import VP_CG_HEIGHT_M
from simserver.core.terrain import surface_at
from simserver.server.app import new_simulation
from simserver.server.config import DEFAULT_SERVER_CONFIG, REPO_CONFIGS, load_server_config
from simserver.server.slot import VehicleSlot
from simserver.sim.scene import load_scene
from simserver.wire import protocol as proto

HILLS = REPO_CONFIGS / "scenes" / "hills_paper_sedan.yaml"
HILL_10 = REPO_CONFIGS / "scenes" / "hill_10pct_paper_sedan.yaml"


def _slot(scene_path):
    cfg = load_server_config(DEFAULT_SERVER_CONFIG, viewer="off")
    scene = load_scene(scene_path)
    return VehicleSlot(cfg, new_simulation(scene, cfg.period_s)), scene


def _state(slot) -> np.void:
    return proto.decode_state(slot.fill_state(0, False))


@pytest.mark.parametrize("x_m", [25.0, 55.0, 90.0, 120.0])
def test_the_state_gives_the_grade_of_the_height_map_under_the_car(x_m):
    """At rest across the height map's hills (uniform across y): the grade is the rise of
    the surface from the rear contact points to the front ones over their distance, the
    cross-slope zero, every wheel on the ground, and the pose the body's world pose
    (its CG its height above the ground)."""
    slot, scene = _slot(HILLS)
    slot.sim.reset({"x_m": x_m, "y_m": 0.0, "yaw_rad": 0.0})
    for _ in range(5):  # in P: the contact flags are the step's
        slot.advance()
    s = _state(slot)
    vp, terrain = scene.vehicle.vp, scene.terrain
    front, rear = wheel_position(vp, 0)[0], wheel_position(vp, 2)[0]
    # the contact points lie on the tilted plane, so horizontally a factor cos(slope)
    # nearer the CG: iterate that to the fixed point (two steps reach 1e-6)
    slope = 0.0
    for _ in range(4):
        scale = 1.0 / math.sqrt(1.0 + slope * slope)
        xf, xr = x_m + front * scale, x_m + rear * scale
        slope = (surface_at(terrain, xf, 0.0)[0] - surface_at(terrain, xr, 0.0)[0]) / (xf - xr)
    # 0.05 %: the CG's world x sits h_cg sin(slope) from the plane point the wheels are
    # placed around (place_on_terrain puts that point under the given x), a few mm along
    # a surface whose slope changes by under 1 % per metre
    assert float(s["ground_grade_pct"]) == pytest.approx(100.0 * slope, abs=0.05)
    assert abs(float(s["ground_cross_slope_pct"])) < 1e-6
    assert list(s["wheel_contact"]) == [1, 1, 1, 1]
    h_cg = float(vp[VP_CG_HEIGHT_M])
    # the CG is h_cg above the plane through the contact points, along its normal:
    # h_cg / cos(slope) above that plane vertically (5 mm: the CG's few mm of horizontal
    # offset from the plane point, and 5 ms of settling on the springs)
    x_cg = float(s["x_m"])
    plane_z = surface_at(terrain, xr, 0.0)[0] + slope * (x_cg - xr)
    assert float(s["z_m"]) - plane_z == pytest.approx(h_cg * math.sqrt(1.0 + slope**2),
                                                      abs=0.005)
    assert "wheels on ground all 4" in ground_text(s)
    assert f"grade {float(s['ground_grade_pct']):+5.1f} %" in ground_text(s)


def test_the_grade_and_cross_slope_turn_with_the_heading_on_the_plane():
    """The 10 % plane (rising along world x): 10 % uphill facing +x, -10 % facing -x;
    facing +y the grade is 0 and the cross-slope -10 % (the left side, toward -x, is
    lower)."""
    slot, _ = _slot(HILL_10)
    for yaw, grade, cross in ((0.0, 10.0, 0.0), (math.pi, -10.0, 0.0),
                              (0.5 * math.pi, 0.0, -10.0), (-0.5 * math.pi, 0.0, 10.0)):
        slot.sim.reset({"x_m": 3.0, "y_m": -2.0, "yaw_rad": yaw})
        s = _state(slot)
        assert float(s["ground_grade_pct"]) == pytest.approx(grade, abs=1e-5), yaw
        assert float(s["ground_cross_slope_pct"]) == pytest.approx(cross, abs=1e-5), yaw
    text = ground_text(s)
    assert "grade  -0.0 %" in text or "grade  +0.0 %" in text
    assert "cross +10.0 %" in text


def test_a_wheel_in_the_air_is_shown():
    slot, _ = _slot(HILL_10)
    s = np.frombuffer(bytearray(slot.fill_state(0, False)), dtype=proto.STATE_DTYPE)[0]
    s["wheel_contact"] = [1, 0, 1, 1]  # the field as a lifted wheel sets it
    assert "wheels on ground FL RL RR" in ground_text(s)
    s["wheel_contact"] = [0, 0, 0, 0]
    assert "wheels on ground none" in ground_text(s)
