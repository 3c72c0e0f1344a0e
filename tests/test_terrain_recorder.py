"""The recorder on a terrain: the road-frame columns on the state's reference plane.

On a terrain the headless history's planar states live on the plane fitted under the
wheels each step (docs/model.md section 11), not on the road of ``set_road``. A real
server on the hills height map, the recorder beside it, and the same scene stepped
headless with the inputs the server applied: each recorded row's plane and body angles
must be the headless state's at the same tick, and the world pose the headless one's.
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
    from simserver.scenario import load_scene
    from simserver.simulation import Simulation

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

    # headless, with the inputs the server applied (the same at every tick: nobody drives)
    for name in ("input_steer", "input_throttle", "input_brake", "input_parking_brake",
                 "input_gear"):
        assert np.unique(live[name]).size == 1, name
    sim = Simulation(load_scene(CONFIGS / "scenes" / f"{SCENE}.yaml"), period_s)
    sim.inputs[L.IN_STEER] = live["input_steer"][0]
    sim.inputs[L.IN_THROTTLE] = live["input_throttle"][0]
    sim.inputs[L.IN_BRAKE] = live["input_brake"][0]
    sim.inputs[L.IN_PARKING_BRAKE] = live["input_parking_brake"][0]
    sim.inputs[L.IN_GEAR] = live["input_gear"][0]
    last = int(live["tick"][-1])
    states = np.zeros((last + 1, L.N_STATE))
    poses = np.zeros((last + 1, L.N_POSE))
    for k in range(last + 1):
        states[k] = sim.x
        poses[k] = sim.update_pose()
        sim.step()
    ticks = live["tick"].astype(np.int64)
    head = states[ticks]
    pose = poses[ticks]
    # the car stands on a slope: the old conversion (the scene's flat road) is not this
    assert np.abs(head[:, L.REF_GRADE_PCT]).min() > 1.0
    # the same states: the world pose to rounding (float64 on the wire)
    np.testing.assert_allclose(live["world_x_m"], pose[:, L.POSE_X_M], rtol=0, atol=1e-9)
    np.testing.assert_allclose(live["world_z_m"], pose[:, L.POSE_Z_M], rtol=0, atol=1e-9)
    # the plane: the wire's slopes are float32 (relative rounding 6e-8)
    for col, slot in (("road_grade_pct", L.REF_GRADE_PCT),
                      ("road_cross_slope_pct", L.REF_CROSS_SLOPE_PCT)):
        np.testing.assert_allclose(live[col], head[:, slot], rtol=0,
                                   atol=1e-6 * (1.0 + np.abs(head[:, slot]).max()))
    # the body on that plane: a float32 slope error of 1e-8 tilts it by 1e-8 rad
    for col, slot in (("yaw_rad", L.YAW_RAD), ("pitch_rad", L.PITCH_RAD),
                      ("roll_rad", L.ROLL_RAD)):
        np.testing.assert_allclose(live[col], head[:, slot], rtol=0, atol=1e-7)
    # the position along the plane needs its height, which the wire does not carry
    assert np.isnan(live["x_m"]).all() and np.isnan(live["y_m"]).all()
    assert np.isnan(live["cg_above_road_m"]).all()


def test_recorder_reference_plane_slopes_invert_the_servers():
    """``reference_plane_slopes`` undoes ``vehicle_slot.ground_slopes_pct``'s turn."""
    rng = np.random.default_rng(3)
    grade, cross, yaw = rng.uniform(-30, 30, 50), rng.uniform(-20, 20, 50), \
        rng.uniform(-10, 10, 50)
    c, s = np.cos(yaw), np.sin(yaw)
    along, across = grade * c + cross * s, -grade * s + cross * c
    got = recorder.reference_plane_slopes(yaw, along, across)
    np.testing.assert_allclose(got, (grade, cross), rtol=0, atol=1e-12)
