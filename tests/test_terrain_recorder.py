"""The recorder on a terrain: the road-frame columns on the state's reference plane.

On a terrain the headless history's planar states live on the plane fitted under the
wheels each step (docs/model.md section 11), not on the road of ``set_road``. A real
server on the hills height map, the recorder beside it, and the same scene stepped
headless with the inputs the server applied: once the car rests, the recorded plane and
body angles must be the headless state's, and the world pose the headless one's.
"""

from __future__ import annotations

import numpy as np
import pytest

from clients import recorder
from simserver.testing import (
    CONFIGS,
    Client,
    OutputProcess,
    ServerProcess,
    client_command,
    client_env,
)

pytestmark = pytest.mark.timeout(240)

SCENE = "hills_paper_sedan"


def test_recorder_on_a_height_map_uses_the_reference_plane(tmp_path):
    from simserver.adapters.history import read_history
    from simserver.core import layout as L
    from simserver.sim.scene import load_scene
    from simserver.sim.simulation import Simulation

    server = ServerProcess(vehicle_id="terr", scene=SCENE)
    out = tmp_path / "rec"
    proc = OutputProcess(client_command("recorder", "--out", str(out), "--quiet",
                                        *server.client_args()), env=client_env())
    try:
        assert proc.wait_ready(60.0), proc.text()
        with Client(server) as watcher:  # 1 s of states to record
            start = int(watcher.fresh_state()["tick"])
            watcher.wait_state(lambda s: int(s["tick"]) >= start + 1000, 60.0, "1000 ticks")
            period_s = float(watcher.request("get_config")["config"]["server"]["period_s"])
        assert proc.stop(timeout_s=60.0) == 0, proc.text()
    finally:
        proc.kill()
        server.stop()
    live = read_history(out)
    assert live["tick"].size > 500, proc.text()

    # headless from the same start with the inputs the server applied last (nobody
    # drives: the car settles at rest in its gear on the slope), to the last row's tick
    row = -1
    sim = Simulation(load_scene(CONFIGS / "scenes" / f"{SCENE}.yaml"), period_s)
    for name, slot in (("input_steer", L.IN_STEER), ("input_throttle", L.IN_THROTTLE),
                       ("input_brake", L.IN_BRAKE),
                       ("input_parking_brake", L.IN_PARKING_BRAKE),
                       ("input_gear", L.IN_GEAR)):
        sim.inputs[slot] = live[name][row]
    for _ in range(int(live["tick"][row])):
        sim.step()
    head = sim.x
    pose = sim.update_pose()
    assert abs(head[L.U_MPS]) < 1e-3 and abs(float(live["u_mps"][row])) < 1e-3  # at rest
    # the car stands on a slope: the old conversion (the scene's flat road) is far off
    assert abs(head[L.REF_GRADE_PCT]) > 1.0
    # Both runs rest at the same place to what an early watchdog brake could change of
    # the settling (micrometres): 1 mm. On the hills (curvature below 0.1 / m) that moves
    # the plane by 1e-4 (1e-2 %) and the body on it by 1e-4 rad; the old conversion is
    # off by the whole slope (> 1 %, 0.01 rad).
    for col, slot in (("world_x_m", L.POSE_X_M), ("world_y_m", L.POSE_Y_M),
                      ("world_z_m", L.POSE_Z_M)):
        assert live[col][row] == pytest.approx(pose[slot], abs=1e-3), col
    for col, slot in (("road_grade_pct", L.REF_GRADE_PCT),
                      ("road_cross_slope_pct", L.REF_CROSS_SLOPE_PCT)):
        assert live[col][row] == pytest.approx(head[slot], abs=1e-2), col
    for col, slot in (("yaw_rad", L.YAW_RAD), ("pitch_rad", L.PITCH_RAD),
                      ("roll_rad", L.ROLL_RAD)):
        assert live[col][row] == pytest.approx(head[slot], abs=1e-4), col
    # every row: the plane is the state's own (the wire's float32 slopes turned to world
    # axes), and the position along it needs its height, which the wire does not carry
    assert np.isnan(live["x_m"]).all() and np.isnan(live["y_m"]).all()
    assert np.isnan(live["cg_above_road_m"]).all()
    assert np.isfinite(live["pitch_rad"]).all() and np.isfinite(live["road_grade_pct"]).all()


def test_recorder_reference_plane_slopes_invert_the_servers():
    """``reference_plane_slopes`` undoes ``vehicle_slot.ground_slopes_pct``'s turn."""
    rng = np.random.default_rng(3)
    grade, cross, yaw = rng.uniform(-30, 30, 50), rng.uniform(-20, 20, 50), \
        rng.uniform(-10, 10, 50)
    c, s = np.cos(yaw), np.sin(yaw)
    along, across = grade * c + cross * s, -grade * s + cross * c
    got = recorder.reference_plane_slopes(yaw, along, across)
    np.testing.assert_allclose(got, (grade, cross), rtol=0, atol=1e-12)
