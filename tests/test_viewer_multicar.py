"""The live viewer draws every car of a multi-car world (issue 30 item 4).

A real two-car server (``configs/server/two_cars.yaml``: car0 at x = 0, car1 at x = 25 m)
and ``simserver view --car car1 --sink save:FILE`` as a real subprocess; the ``.rrd`` read
back with ``rerun.chunk.RrdReader``: each car under ``world/cars/{id}`` with its id as a
label, placed at its world pose; the followed car (car1) drawn in full under ``world/car``
with its driver's eye; the blueprint's 3D view opens on it with the driver's-eye view a tab
beside it.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

from simserver.adapters.rerun_fleet import car_path, world_quaternions
from simserver.adapters.rerun_scene import (
    BODY_SHELL,
    CAR,
    DRIVER_EYE,
    TIMELINE,
    scene_blueprint,
)
from simserver.testing import OutputProcess, ServerProcess, wait_until

pytestmark = pytest.mark.timeout(300)

REPO = Path(__file__).resolve().parents[1]
TWO_CARS = REPO / "configs" / "server" / "two_cars.yaml"
DRAWN_BYTES = 150_000
"""Past this size the file holds the static scene and a few dozen frames."""


def _entities(path: Path) -> dict[str, dict[str, list]]:
    """Entity path -> component column name -> values (every row, static and temporal)."""
    from rerun.chunk import RrdReader

    out: dict[str, dict[str, list]] = {}
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        cols = out.setdefault(chunk.entity_path, {})
        for name in batch.schema.names:
            if name == TIMELINE or ":" in name:
                cols.setdefault(name, []).extend(batch.column(name).to_pylist())
    return out


def _column(cols: dict[str, list], suffix: str) -> list:
    (name,) = [n for n in cols if n.endswith(suffix)]
    return cols[name]


def test_the_viewer_draws_every_car_and_follows_the_chosen_one(tmp_path):
    rrd = tmp_path / "world.rrd"
    env = dict(os.environ, XDG_CONFIG_HOME=str(tmp_path / "xdg_config"),
               XDG_DATA_HOME=str(tmp_path / "xdg_data"))
    with ServerProcess(config=TWO_CARS, scene=None) as server:
        viewer = OutputProcess(
            [sys.executable, "-m", "simserver", "view", "--sink", f"save:{rrd}", "--connect",
             server.endpoint, "--car", "car1", "--normal-priority"], env=env)
        try:
            wait_until(lambda: rrd.exists() and rrd.stat().st_size > DRAWN_BYTES
                       or not viewer.alive(), timeout_s=120.0,
                       what="the viewer to draw the world", interval_s=0.05)
            assert viewer.alive(), viewer.text()
            assert viewer.stop(timeout_s=60.0) == 0, viewer.text()
        finally:
            viewer.kill()
    entities = _entities(rrd)
    for car_id, x0_m in (("car0", 0.0), ("car1", 25.0)):
        cols = entities.get("/" + car_path(car_id))
        assert cols, f"no /{car_path(car_id)} in {sorted(entities)}"
        xyz = np.array(_column(cols, "translation"), dtype=float).reshape(-1, 3)
        assert len(xyz) > 5  # one per frame of the followed car
        # parked cars on the flat (two_cars.yaml): at their start pose, CG above the road
        assert np.allclose(xyz[:, 0], x0_m, atol=0.05) and np.allclose(xyz[:, 1], 0.0,
                                                                         atol=0.05)
        assert np.all((xyz[:, 2] > 0.3) & (xyz[:, 2] < 0.8))
    # the label: car1 (followed) on a point above its roof, car0 on its box
    assert _column(entities["/" + car_path("car1") + "/label"], ":labels") == [["car1"]]
    assert _column(entities["/" + car_path("car0") + "/box"], ":labels") == [["car0"]]
    assert "/" + car_path("car1") + "/box" not in entities  # drawn in full under world/car
    # the full model is car1's (x = 25 m), and it has the driver's eye in its body
    car = np.array(_column(entities["/" + CAR], "translation"), dtype=float).reshape(-1, 3)
    assert np.allclose(car[:, 0], 25.0, atol=0.05)
    for path in (BODY_SHELL, DRIVER_EYE):
        assert "/" + path in entities


def test_the_blueprint_opens_on_the_car_with_the_drivers_eye_a_tab_away():
    blueprint = scene_blueprint()
    main = blueprint.root_container
    (tabs, _) = main.contents[0].contents  # the 3D tabs above speed & yaw
    chase, driver = tabs.contents
    assert tabs.active_tab == 0 or tabs.active_tab is None
    assert chase.origin == "world" and driver.origin == DRIVER_EYE
    assert "driver" in driver.name


def test_world_attitudes_turn_as_iso_8855():
    # yaw 90 deg: x forward turns to world y; pitch +: nose down (x toward -z)
    q = world_quaternions(np.array([np.pi / 2, 0.0]), np.array([0.0, 0.3]),
                          np.array([0.0, 0.0]))

    def rotate(quat, v):  # v' = q v q*, (x, y, z, w)
        u, w = np.asarray(quat[:3]), quat[3]
        return 2 * u.dot(v) * u + (w * w - u.dot(u)) * np.asarray(v) + 2 * w * np.cross(u, v)

    assert np.allclose(rotate(q[0], [1.0, 0.0, 0.0]), [0.0, 1.0, 0.0])
    assert rotate(q[1], [1.0, 0.0, 0.0])[2] == pytest.approx(-np.sin(0.3))
