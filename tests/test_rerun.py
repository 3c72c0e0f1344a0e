"""The Rerun scene: ``run-scenario --rrd`` read back with Rerun's own reader; the sinks.

The recording is made by the CLI as a real subprocess and read with
``rerun.chunk.RrdReader`` (``rerun.dataframe`` is gone in rerun-sdk 0.41) and checked
with ``rerun rrd verify``. The Rerun CLI writes an analytics config on its first run, so
it runs here with its config and data directories in the test's temporary directory.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from simserver.testing import free_port, wait_until

REPO = Path(__file__).resolve().parents[1]
VEHICLE = REPO / "configs" / "vehicles" / "paper_sedan" / "vehicle.yaml"
DURATION_S = 3.0

SCENARIO = """\
name: rerun_test_turn_and_brake
vehicle: {vehicle}
road: {{grade_pct: -5.0, cross_slope_pct: 3.0}}
initial: {{u_mps: 12.0}}
duration_s: {duration}
inputs:
  - {{t: 0.0, gear: D, steer: 0.0, brake: 0.0}}
  - {{t: 0.5, steer: 0.12}}
  - {{t: 1.8, brake: 0.0}}
  - {{t: 2.1, brake: 0.6}}
"""


def _isolated_env(tmp: Path) -> dict[str, str]:
    """Environment for subprocesses: the repository importable, Rerun's config and data
    (analytics) kept out of the user's home, and Rerun strict (errors raise)."""
    return dict(os.environ, PYTHONPATH=str(REPO), XDG_CONFIG_HOME=str(tmp / "xdg_config"),
                XDG_DATA_HOME=str(tmp / "xdg_data"), RERUN_STRICT="1")


def _read_rrd(path: Path) -> dict[str, dict]:
    """Every entity of the recording: its static columns, and its temporal columns sorted
    by ``sim_time`` (int64 ns), as Python lists per row; plus the timelines seen."""
    from rerun.chunk import RrdReader

    entities: dict[str, dict] = {}
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        entry = entities.setdefault(chunk.entity_path, {"static": {}, "rows": [],
                                                        "timelines": set()})
        entry["timelines"].update(chunk.timeline_names)
        names = [n for n in batch.schema.names if n != "rerun.controls.RowId"]
        if chunk.is_static:
            for n in names:
                entry["static"][n] = batch.column(n).to_pylist()
            continue
        times = batch.column("sim_time").cast("int64").to_pylist()
        columns = {n: batch.column(n).to_pylist() for n in names if n != "sim_time"}
        for k, t in enumerate(times):
            entry["rows"].append((t, {n: col[k] for n, col in columns.items()}))
    for entry in entities.values():
        entry["rows"].sort(key=lambda row: row[0])
    return entities


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A 3 s scenario on a sloped, cross-sloped road, run by the CLI with ``--rrd``."""
    root = tmp_path_factory.mktemp("rerun")
    scenario = root / "turn.yaml"
    scenario.write_text(SCENARIO.format(vehicle=VEHICLE.as_posix(), duration=DURATION_S),
                        encoding="utf-8")
    rrd = root / "scene.rrd"
    proc = subprocess.run(
        [sys.executable, "-m", "simserver", "run-scenario", str(scenario), "--out",
         str(root / "out"), "--no-plots", "--quiet", "--rrd", str(rrd)],
        cwd=REPO, env=_isolated_env(root), capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr and "rerun" not in proc.stderr.lower(), proc.stderr
    from simserver.adapters.history import read_history

    history = read_history(root / "out" / "history.parquet")
    return {"root": root, "rrd": rrd, "history": history, "entities": _read_rrd(rrd),
            "stdout": proc.stdout}


def _history_row(history: dict, t_ns: int) -> int:
    t = np.round(history["time_s"] * 1e9).astype(np.int64)
    (idx,) = np.nonzero(t == t_ns)
    assert idx.size == 1, t_ns
    return int(idx[0])


def test_declared_entity_paths_are_in_the_file(recorded):
    from simserver.adapters.rerun_scene import PLOT_GROUPS, RESULT_ENTITY_PATHS

    entities = recorded["entities"]
    missing = [p for p in RESULT_ENTITY_PATHS if "/" + p not in entities]
    assert not missing, missing
    for group in PLOT_GROUPS:  # each plot's series are named in the file
        names = entities["/" + group.path]["static"]["SeriesLines:names"]
        assert names == [list(group.labels)], group.path
    assert str(recorded["rrd"]) in recorded["stdout"]


def test_the_only_timeline_is_sim_time(recorded):
    timelines = set().union(*(e["timelines"] for e in recorded["entities"].values()))
    assert timelines == {"sim_time"}  # no log_time, no log_tick
    car = recorded["entities"]["/world/car"]["rows"]
    times_s = np.array([t for t, _ in car]) * 1e-9
    # 3D frames decimated to 50 per simulated second, first and last row included
    assert times_s[0] == 0.0 and times_s[-1] == pytest.approx(DURATION_S - 1e-3)
    assert np.allclose(np.diff(times_s[:-1]), 0.02)


def test_car_translation_is_the_history_position_on_the_road_plane(recorded):
    from simserver.core.road import road_axes

    history = recorded["history"]
    e1, e2, _ = road_axes(-5.0, 3.0)
    rows = recorded["entities"]["/world/car"]["rows"]
    checked = 0
    for t_ns, cols in rows[:: max(1, len(rows) // 12)]:
        k = _history_row(history, t_ns)
        expected = history["x_m"][k] * e1 + history["y_m"][k] * e2
        (translation,) = cols["Transform3D:translation"]
        np.testing.assert_allclose(translation, expected, rtol=1e-6, atol=2e-6)
        checked += 1
    assert checked >= 10
    assert abs(history["y_m"][-1]) > 1.0  # the car turned: both axes were exercised


def test_plotted_values_equal_the_history(recorded):
    history = recorded["history"]
    entities = recorded["entities"]
    for path, instance, column in (
        ("/plots/speed", 0, "u_mps"), ("/plots/speed", 1, "v_mps"),
        ("/plots/yaw_rate", 0, "yaw_rate_radps"), ("/plots/forces/fl", 2, "fz_fl_n"),
        ("/plots/slip/kappa", 2, "kappa_rl"), ("/plots/slip/tan_alpha", 1, "tan_alpha_fr"),
        ("/plots/inputs/driver", 2, "input_brake"),
    ):
        rows = entities[path]["rows"]
        assert len(rows) == 151, path  # 3 s at 50 per second, and the last row
        for t_ns, cols in rows[::37]:
            value = cols["Scalars:scalars"][instance]  # float64: exact
            assert value == history[column][_history_row(history, t_ns)], (path, t_ns)


def test_force_arrows_are_the_forces_at_the_stated_scale(recorded):
    from simserver.adapters.rerun_scene import FORCE_SCALE_M_PER_N, friction_colors

    history = recorded["history"]
    t_ns, cols = recorded["entities"]["/world/car/forces/fr"]["rows"][120]
    k = _history_row(history, t_ns)
    vectors = np.array(cols["Arrows3D:vectors"])
    delta = history["steer_fr_rad"][k]
    fx, fy, fz = history["fx_fr_n"][k], history["fy_fr_n"][k], history["fz_fr_n"][k]
    expected = FORCE_SCALE_M_PER_N * np.array([
        [fx * np.cos(delta), fx * np.sin(delta), 0.0],
        [-fy * np.sin(delta), fy * np.cos(delta), 0.0],
        [0.0, 0.0, fz],
    ])
    np.testing.assert_allclose(vectors, expected, rtol=1e-6, atol=1e-6)
    rgba = friction_colors(history["friction_use_fr"][k])
    packed = int.from_bytes(bytes(rgba.tolist()), "big")
    assert cols["Arrows3D:colors"] == [packed] * 3


def test_blueprint_is_in_the_file_and_rrd_verify_passes(recorded):
    from rerun.chunk import RrdReader

    reader = RrdReader(recorded["rrd"])
    assert [r.application_id for r in reader.recordings()] == ["simserver"]
    assert reader.blueprints(), "the blueprint travels with the recording"
    proc = subprocess.run([sys.executable, "-m", "rerun", "rrd", "verify", str(recorded["rrd"])],
                          env=_isolated_env(recorded["root"]), capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "verified without error" in proc.stdout + proc.stderr


# ------------------------------------------------------------------ per-frame logger
def test_scene_logger_logs_the_same_frames_as_log_result(tmp_path):
    """The live path (``SceneLogger.log_frame``, one ``rec.log`` per entity) and the
    batch path (``log_result``, ``send_columns``) write the same poses and values."""
    import rerun as rr

    from simserver.adapters import rerun_scene as S
    from simserver.sim.scenario import load_scenario, run_scenario

    scenario_file = tmp_path / "turn.yaml"
    scenario_file.write_text(SCENARIO.format(vehicle=VEHICLE.as_posix(), duration=1.0),
                             encoding="utf-8")
    scenario = load_scenario(scenario_file)
    result = run_scenario(scenario)

    batch_rrd, live_rrd = tmp_path / "batch.rrd", tmp_path / "live.rrd"
    rec = rr.RecordingStream("simserver", recording_id="batch")
    rec.save(batch_rrd)
    S.log_result(rec, result, send_blueprint=False)
    rec.disconnect()

    rec = rr.RecordingStream("simserver", recording_id="live")
    rec.save(live_rrd)
    logger = S.SceneLogger(rec, scenario.scene.vehicle.vp, scenario.scene.vehicle.tp,
                           scenario.scene.road["grade_pct"], scenario.scene.road["cross_slope_pct"],
                           flush_every=7, send_blueprint=False)
    t0 = time.perf_counter()
    kept = [logger.log_frame(t, result.states[k], result.outputs[k], result.inputs[k])
            for k, t in enumerate(result.time_s)]
    logger.flush()
    per_frame_s = (time.perf_counter() - t0) / max(1, sum(kept))
    logger.log_diagnostics(result.time_s[-1], tick_jitter_us=12.5, dropped_frames=3)
    rec.disconnect()
    assert sum(kept) == logger.frames_logged == 50  # 1 kHz rows, 50 frames per second
    assert per_frame_s < 0.02

    batch, live = _read_rrd(batch_rrd), _read_rrd(live_rrd)
    assert set().union(*(e["timelines"] for e in live.values())) == {"sim_time"}
    for path, component in (("/world/car", "Transform3D:translation"),
                            ("/world/car/wheel_fl", "Transform3D:quaternion"),
                            ("/world/car/body", "Transform3D:quaternion"),
                            ("/world/car/forces/rl", "Arrows3D:vectors"),
                            ("/plots/slip/tan_alpha", "Scalars:scalars")):
        b = dict(batch[path]["rows"])
        rows = live[path]["rows"]
        assert len(rows) == 50, path
        for t_ns, cols in rows:
            np.testing.assert_allclose(cols[component], b[t_ns][component], rtol=1e-6,
                                       atol=1e-6, err_msg=path)
    assert live["/plots/diagnostics/tick_jitter_us"]["rows"][0][1]["Scalars:scalars"] == [12.5]
    assert len(live["/world/trail"]["rows"]) == 10  # 10 Hz trail


def test_spin_integrated_incrementally_equals_the_batch_integral():
    from simserver.adapters.rerun_scene import integrate_spin

    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(0.001, 0.03, 200))
    omega = rng.normal(0.0, 60.0, (200, 4))
    batch = integrate_spin(t, omega)
    angle = np.zeros(4)
    for k in range(1, t.size):
        angle = integrate_spin(t[k:k + 1], omega[k:k + 1], t[k - 1], omega[k - 1], angle)[0]
        np.testing.assert_allclose(np.cos(angle), np.cos(batch[k]), atol=1e-9)
    const = integrate_spin(np.array([0.0, 0.5, 1.0]), np.full((3, 4), 2.0))
    np.testing.assert_allclose(const[:, 0], [0.0, 1.0, 2.0])


# ---------------------------------------------------------------------------- sinks
def test_sink_off_and_bad_options():
    from simserver.adapters.rerun_sink import RerunSinkError, open_recording, parse_sink

    assert open_recording("off") is None
    assert parse_sink("save:out/a.rrd") == ("save", "out/a.rrd")
    assert parse_sink("connect:rerun+http://10.0.0.2:9876/proxy") == (
        "connect", "rerun+http://10.0.0.2:9876/proxy")
    assert parse_sink("serve") == ("serve", None)
    for bad in ("spawnn", "file:x.rrd"):
        with pytest.raises(RerunSinkError, match="expected one of"):
            parse_sink(bad)
    with pytest.raises(RerunSinkError, match="target .rrd file is required"):
        open_recording("save")
    with pytest.raises(RerunSinkError, match="port"):
        open_recording("serve", "127.0.0.1:notaport")


def test_save_to_an_unwritable_place_fails_clearly(tmp_path):
    from simserver.adapters.rerun_sink import RerunSinkError, open_recording

    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    with pytest.raises(RerunSinkError, match="cannot write"):
        open_recording("save", blocker / "scene.rrd", announce=None)


def test_connect_to_a_missing_viewer_fails_at_once():
    from simserver.adapters.rerun_sink import RerunSinkError, open_recording

    url = f"rerun+http://127.0.0.1:{free_port()}/proxy"
    t0 = time.perf_counter()
    with pytest.raises(RerunSinkError, match="no viewer listens"):
        open_recording("connect", url, announce=None)
    assert time.perf_counter() - t0 < 2.0  # rerun's own connect_grpc would block 5 s


def test_spawn_without_a_display_is_refused(monkeypatch):
    from simserver.adapters.rerun_sink import RerunSinkError, open_recording

    if not sys.platform.startswith("linux"):
        pytest.skip("the display check is for Linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    t0 = time.perf_counter()
    with pytest.raises(RerunSinkError, match="no display"):
        open_recording("spawn", announce=None)
    assert time.perf_counter() - t0 < 1.0


def test_serve_binds_loopback_and_refuses_a_taken_port():
    from simserver.adapters.rerun_sink import RerunSinkError, open_recording

    port = free_port()
    lines: list[str] = []
    rec = open_recording("serve", str(port), web_port=None, announce=lines.append)
    try:
        assert rec is not None
        assert f"rerun+http://127.0.0.1:{port}/proxy" in lines[0]
        def accepts() -> bool:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            except OSError:
                return False
            return True

        # the server starts on a background thread
        wait_until(accepts, timeout_s=5.0, what="the gRPC server", interval_s=0.05)
        with pytest.raises(RerunSinkError, match="in use"):
            open_recording("serve", str(port), web_port=None, announce=None)
    finally:
        if rec is not None:
            rec.disconnect()


def test_cli_reports_an_unwritable_rrd(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    scenario = tmp_path / "short.yaml"
    scenario.write_text(SCENARIO.format(vehicle=VEHICLE.as_posix(), duration=0.05),
                        encoding="utf-8")
    proc = subprocess.run(
        [sys.executable, "-m", "simserver", "run-scenario", str(scenario), "--out",
         str(tmp_path / "out"), "--no-plots", "--quiet", "--rrd", str(blocker / "x.rrd")],
        cwd=REPO, env=_isolated_env(tmp_path), capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 1
    assert proc.stderr.startswith("error: rerun save:") and "Traceback" not in proc.stderr


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _rot(axis: int, a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    m = np.eye(3)
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    return m


def test_scene_body_pose_is_the_wire_world_pose():
    """``world/car`` then ``world/car/body`` put the CG where ``core.pose.world_pose`` (the
    state topic's pose) does, with the same attitude, on a sloped and cross-sloped road."""
    from simserver.adapters.rerun_scene import body_pose, car_pose
    from simserver.core import layout as L
    from simserver.core.pose import world_pose
    from simserver.core.road import road_axes

    rng = np.random.default_rng(11)
    axes = road_axes(-8.0, 4.0)
    cg_height = 0.55
    for _ in range(20):
        x = np.zeros(L.N_STATE)
        x[[L.X_M, L.Y_M]] = rng.uniform(-200.0, 200.0, 2)
        x[L.YAW_RAD] = rng.uniform(-7.0, 7.0)
        x[[L.HEAVE_M, L.ROLL_RAD, L.PITCH_RAD]] = rng.uniform(-0.08, 0.08, 3)
        car_t, car_q = car_pose(x[None], axes)
        body_t, body_q = body_pose(x[None], cg_height)
        r_car = _quat_matrix(car_q[0])
        position = car_t[0] + r_car @ body_t[0]
        attitude = r_car @ _quat_matrix(body_q[0])
        pose = np.zeros(L.N_POSE)
        world_pose(x, axes, cg_height, pose)
        np.testing.assert_allclose(position, pose[[L.POSE_X_M, L.POSE_Y_M, L.POSE_Z_M]],
                                   atol=1e-9)
        yaw, pitch, roll = pose[[L.POSE_YAW_RAD, L.POSE_PITCH_RAD, L.POSE_ROLL_RAD]]
        np.testing.assert_allclose(attitude, _rot(2, yaw) @ _rot(1, pitch) @ _rot(0, roll),
                                   atol=1e-9)
