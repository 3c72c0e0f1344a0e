"""Nothing non-finite leaves the server on any path (issue 34 item 2).

- A height map beyond the documented bounds of ``core.terrain`` (heights, slopes,
  friction, spacing, extent: docs/model.md section 11) is refused with one line naming
  the file, by every loader (``.npy``, ``.npz``, ``.png``, a friction file) and by a live
  server's ``load`` (issue 34: a 64 x 64 map of 1e308 was accepted and 2 001 of 2 029
  states carried non-finite poses and slopes, ``nonfinite_stops`` saturated at 65 535).
- The stop path (``VehicleSlot.check_finite``): a step forced non-finite on a ground that
  also makes the scene's start non-finite publishes the newest finite state with the
  ``FAULT`` and ``PAUSED`` flags, never a non-finite one, and counts the stop once.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from simserver.adapters.terrain_files import load_terrain
from simserver.adapters.validate import ConfigError
from simserver.core.terrain import (
    CELL_KEY,
    EXTENT_ABS_MAX_M,
    FRICTION_SCALE_MAX,
    HEIGHT_ABS_MAX_M,
    SLOPE_MAX,
    heightmap_terrain,
)
from simserver.server.config import REPO_CONFIGS
from simserver.sim.scene import load_scene
from simserver.testing import CONFIGS, Client, ServerProcess, state_is_finite
from simserver.wire import protocol as proto
from tests.test_server_logic import Rig

pytestmark = pytest.mark.timeout(300)

SEDAN = CONFIGS / "vehicles" / "paper_sedan" / "vehicle.yaml"


# ====================================================================== the bounds
@pytest.mark.parametrize("case", ["huge", "bound", "steep", "friction", "extent"])
def test_heightmap_terrain_refuses_values_beyond_its_bounds(case):
    """Each bound, just past it refused naming the sample; at it accepted."""
    flat = np.zeros((8, 8))
    if case == "huge":
        bad = np.full((64, 64), 1e308)  # finite, but every product of the step overflows
        with pytest.raises(ValueError, match=r"heights: 1e\+308 m at row 0, column 0"):
            heightmap_terrain(bad, 1.0, 1.0)
    elif case == "bound":
        heightmap_terrain(flat + HEIGHT_ABS_MAX_M, 1e4, 1e4)  # level at the bound: fine
        bad = flat.copy()
        bad[3, 5] = -1.0001 * HEIGHT_ABS_MAX_M
        with pytest.raises(ValueError, match=r"row 3, column 5 is beyond"):
            heightmap_terrain(bad, 1e4, 1e4)
    elif case == "steep":
        wall = flat.copy()
        wall[:, 4:] = 10.0  # a 10 m wall on a 1 cm grid: at the bound, accepted
        heightmap_terrain(wall, 10.0 / SLOPE_MAX, 10.0 / SLOPE_MAX)
        with pytest.raises(ValueError, match=r"rise of 10 m over 0.001 m at row 0, column 3"):
            heightmap_terrain(wall, 1e-3, 1e-3)
    elif case == "friction":
        mu = np.ones_like(flat)
        mu[2, 1] = FRICTION_SCALE_MAX * 1.001
        with pytest.raises(ValueError, match=r"friction: 3.003 at row 2, column 1"):
            heightmap_terrain(flat, 1.0, 1.0, friction=mu)
    else:
        heightmap_terrain(flat, 1.0, 1.0, EXTENT_ABS_MAX_M - 7.0)
        with pytest.raises(ValueError, match=r"spans x = .* beyond"):
            heightmap_terrain(flat, 1.0, 1.0, EXTENT_ABS_MAX_M - 6.0)


def _scene(tmp: Path, terrain: str) -> Path:
    scene = tmp / "scene.yaml"
    scene.write_text(f"name: bounds\nvehicle: {SEDAN}\nterrain: {terrain}\n"
                     "initial: {x_m: 0.0, y_m: 0.0, yaw_rad: 0.0, u_mps: 0.0}\n",
                     encoding="utf-8")
    return scene


@pytest.mark.parametrize("kind", ["npy", "npz", "npz_friction", "friction_file", "png"])
def test_every_heightmap_loader_names_the_file_beyond_the_bounds(tmp_path, kind):
    huge = np.full((64, 64), 1e308)
    ok = np.zeros((64, 64))
    if kind == "npy":
        np.save(tmp_path / "h.npy", huge)
        raw, named = {"kind": "heightmap", "file": "h.npy", "cell_m": 1.0}, "h.npy"
    elif kind == "npz":
        np.savez(tmp_path / "h.npz", heights=huge)
        raw, named = {"kind": "heightmap", "file": "h.npz", "cell_m": 1.0}, "h.npz"
    elif kind == "npz_friction":
        np.savez(tmp_path / "h.npz", heights=ok, friction=np.full((64, 64), 1e300))
        raw, named = {"kind": "heightmap", "file": "h.npz", "cell_m": 1.0}, "h.npz"
    elif kind == "friction_file":
        np.save(tmp_path / "h.npy", ok)
        np.save(tmp_path / "mu.npy", np.full((64, 64), 50.0))
        raw = {"kind": "heightmap", "file": "h.npy", "cell_m": 1.0, "friction_file": "mu.npy"}
        named = "mu.npy"
    else:
        from PIL import Image

        Image.fromarray(np.full((64, 64), 65535, dtype=np.uint16)).save(tmp_path / "h.png")
        # both keys within their own ranges, their sum beyond the height bound
        raw = {"kind": "heightmap", "file": "h.png", "cell_m": 1.0,
               "height_scale_m": 1e5, "height_offset_m": 1e5}
        named = "h.png"
    with pytest.raises(ConfigError) as err:
        load_terrain(_scene(tmp_path, "{}"), raw)
    message = str(err.value)
    assert "\n" not in message and str(tmp_path / named) in message, message


# ====================================================================== live: ctl/load
def test_a_1e308_height_map_sent_with_load_is_refused_and_nothing_non_finite_is_published(
        tmp_path):
    """Issue 34's figure: 2 001 of 2 029 states non-finite after the load; now the load is
    refused naming the file, the car drives on, every state is finite and no stop."""
    np.save(tmp_path / "huge.npy", np.full((64, 64), 1e308))
    scene = _scene(tmp_path, "{kind: heightmap, file: huge.npy, cell_m: 1.0, "
                             "origin_m: [-32.0, -32.0]}")
    config = tmp_path / "server.yaml"
    config.write_text(f"scene: {CONFIGS / 'scenes' / 'flat_paper_sedan.yaml'}\n"
                      f"config_dirs: [{CONFIGS}, {tmp_path}]\nviewer: 'off'\n",
                      encoding="utf-8")
    with ServerProcess(config=config, scene=None) as server, \
            Client(server, keep_history=True) as client:
        client.wait_controls()
        client.newest()
        before = client.diagnostics()
        reply = client.request("load", {"scene": str(scene)}, timeout_s=30.0)
        if "not prepared within" in reply.get("error", ""):  # a worker starved by a busy
            reply = client.request("load", {"scene": str(scene)}, timeout_s=30.0)  # machine
        assert reply["ok"] is False, reply
        error = reply["error"]
        assert "huge.npy: terrain: heights: 1e+308 m" in error and "\n" not in error
        client.history.clear()
        end = time.monotonic() + 2.0
        while time.monotonic() < end:  # two seconds of driving after the refusal
            client.send(throttle=0.3, gear=proto.Gear.D)
            client.drain_states()
            time.sleep(0.005)
        states = client.history
        bad = [s for s in states if not state_is_finite(s)]
        after = client.wait_diagnostics(lambda d: int(d["tick"]) > int(states[-1]["tick"]))
        print(f"\n1e308 height map: load refused ({reply['error']}); {len(states)} states "
              f"after it, {len(bad)} non-finite; nonfinite_stops "
              f"{int(before['nonfinite_stops'])} -> {int(after['nonfinite_stops'])}")
        assert len(states) > 500 and not bad
        assert int(after["nonfinite_stops"]) == int(before["nonfinite_stops"]) == 0
        assert float(states[-1]["u_mps"]) > 0.5  # it drove on the old scene
        assert server.alive()


# ====================================================================== the stop path
HILLS = REPO_CONFIGS / "scenes" / "hills_paper_sedan.yaml"


def test_a_forced_non_finite_step_publishes_the_last_finite_state_with_its_flags():
    """The ground under the car (and under the scene's start) made 1e308 in place, past
    the load's checks: the step goes non-finite, the stop resets the car to a start that is
    not finite either. Published: the newest finite state, flagged FAULT and PAUSED, with
    the tick running on; the stop counted once, not once a tick."""
    rig = Rig(load_scene(HILLS))
    for _ in range(200):
        rig.send(throttle=0.3, gear=proto.Gear.D)
        rig.run()
    good = rig.out.states[-1]
    assert state_is_finite(good) and not int(good["flags"]) & proto.StateFlag.FAULT
    sim = rig.slot.sim
    sim.model.terrain.heights[:] = 1e308
    sim.data.ws.cells[:, CELL_KEY] = np.nan  # the per-wheel cell memos refill from it
    for _ in range(300):
        rig.send(throttle=0.3, gear=proto.Gear.D)
        rig.run()
    assert not np.isfinite(sim.x).all(), "the forced step stayed finite: tests nothing"
    after = rig.out.states[-300:]
    bad = [int(s["tick"]) for s in after if not state_is_finite(s)]
    assert not bad, f"{len(bad)} non-finite states published, ticks {bad[:5]} ..."
    faulted = [s for s in after if int(s["flags"]) & proto.StateFlag.FAULT]
    assert len(faulted) >= 299
    last = faulted[-1]
    assert int(last["flags"]) & proto.StateFlag.PAUSED
    for name in ("x_m", "y_m", "z_m", "yaw_rad", "u_mps"):  # where the car last was finite
        assert abs(float(last[name]) - float(good[name])) < 0.2, name
    ticks = [int(s["tick"]) for s in after]
    assert ticks == sorted(ticks)  # a repeated state, not an old tick: in order
    assert rig.counters["nonfinite_stops"] == 1
    assert rig.slot.paused
    rig.run(rig.loop.diag_every)  # up to the next diagnostics
    assert int(rig.out.diags[-1]["nonfinite_stops"]) == 1
