"""Scenario keyframes (simserver.sim.keyframes): parsed and sampled without the compiled core."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from simserver.adapters.validate import ConfigError
from simserver.sim import keyframes as K

REPO = Path(__file__).resolve().parents[1]
SCENARIOS = [p for p in sorted((REPO / "configs" / "scenarios").glob("*.yaml"))
             if "\ncars:" not in p.read_text()]  # several cars: keyframes per car


@pytest.mark.parametrize("call", [
    "from clients.player import load_track; load_track(PATH, 1000.0, None)",
    "from simserver.sim.keyframes import load_keyframe_file, input_table; "
    "input_table(load_keyframe_file(PATH).keyframes, __import__('numpy').arange(9.0))",
])
def test_reading_keyframes_loads_neither_numba_nor_the_core(call):
    """A client that plays keyframes depends on the file format and the protocol only."""
    path = REPO / "configs" / "scenarios" / "e2_stop_downslope_paper_damping.yaml"
    code = (
        f"import json, sys\nPATH = {str(path)!r}\n{call}\n"
        "print(json.dumps(sorted(m for m in sys.modules if m == 'numba' or "
        "m.startswith(('numba.', 'simserver.core', 'simserver.sim.scenario', "
        "'simserver.adapters.config')))))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout) == []


def test_keyframe_columns_and_gears_are_the_cores_input_layout():
    from simserver.core import layout as L

    assert K.INPUT_CHANNELS == L.INPUT_NAMES
    assert K.GEAR_CODES == {name: code for code, name in enumerate(L.GEAR_NAMES)}
    assert (L.GEAR_P, L.GEAR_R, L.GEAR_N, L.GEAR_D) == tuple(K.GEAR_CODES[g] for g in "PRND")


def _reference_input_table(keyframes, times_s):
    """The headless input table as the core's layout defines it, written out column by
    column (the form it had before the keyframes left simserver.sim.scenario)."""
    from simserver.core import layout as L

    table = np.zeros((times_s.size, L.N_INPUT), dtype=np.float64)
    table[:, L.IN_GEAR] = L.GEAR_D
    columns = {"steer": L.IN_STEER, "throttle": L.IN_THROTTLE, "brake": L.IN_BRAKE,
               "parking_brake": L.IN_PARKING_BRAKE, "gear": L.IN_GEAR}
    for channel, col in columns.items():
        pts = [(f["t"], f[channel]) for f in keyframes if channel in f]
        if not pts:
            continue
        t_k = np.array([p[0] for p in pts])
        v_k = np.array([p[1] for p in pts])
        if channel in ("steer", "throttle", "brake"):
            table[:, col] = np.interp(times_s, t_k, v_k)
        else:
            idx = np.searchsorted(t_k, times_s, side="right") - 1
            held = idx >= 0
            table[held, col] = v_k[idx[held]]
    return table


@pytest.mark.parametrize("path", SCENARIOS, ids=lambda p: p.stem)
def test_input_table_of_every_scenario_is_bit_identical_to_the_layouts_columns(path):
    kf = K.load_keyframe_file(path)
    times = np.arange(int(round(kf.duration_s / 0.001))) * 0.001
    got = K.input_table(kf.keyframes, times)
    assert got.dtype == np.float64 and got.flags.c_contiguous
    np.testing.assert_array_equal(got, _reference_input_table(kf.keyframes, times))


def test_sampling_rule_linear_and_switched_channels():
    frames = [{"t": 1.0, "steer": -0.5, "parking_brake": 1.0},
              {"t": 3.0, "steer": 0.5, "gear": float(K.GEAR_CODES["R"])}]
    ch = K.sample_keyframes(frames, np.array([0.0, 1.0, 2.0, 3.0, 4.0]))
    np.testing.assert_array_equal(ch["steer"], [-0.5, -0.5, 0.0, 0.5, 0.5])
    np.testing.assert_array_equal(ch["parking_brake"], [0.0, 1.0, 1.0, 1.0, 1.0])
    np.testing.assert_array_equal(ch["gear"], [3.0, 3.0, 3.0, 1.0, 1.0])
    np.testing.assert_array_equal(ch["throttle"], np.zeros(5))


def test_keyframe_file_matches_the_full_scenario_loader():
    from simserver.sim.scenario import load_scenario

    path = REPO / "configs" / "scenarios" / "e5_hold_restart_uphill.yaml"
    kf, sc = K.load_keyframe_file(path), load_scenario(path)
    assert (kf.name, kf.duration_s, kf.keyframes) == (sc.name, sc.duration_s, sc.keyframes)


@pytest.mark.parametrize("text, message", [
    ("name: x\ninputs: [{t: 0}]\n", "missing key 'duration_s'"),
    ("name: x\nduration_s: 1\ninputs: []\n", "key 'inputs'"),
    ("name: x\nduration_s: 1\ninputs: [{t: 0, gear: X}]\n", "key 'inputs[0].gear'"),
    ("name: x\nduration_s: 1\ninputs: [{t: 1}, {t: 0}]\n", "key 'inputs[1].t'"),
    ("name: x\nduration_s: 1\ninputs: [{t: 0, brake: 2}]\n", "key 'inputs[0].brake'"),
    ("name: x\nduration_s: 1\ninputs: [{t: 0, clutch: 1}]\n", "unknown key 'clutch'"),
])
def test_bad_keyframe_files_name_the_file_and_key(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=re.escape(message)) as err:
        K.load_keyframe_file(path)
    assert str(path) in str(err.value)
