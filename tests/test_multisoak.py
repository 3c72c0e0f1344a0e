"""The multi-car soak (issue 30 item 5): a short form in the default suite, the long form
behind ``slow_enabled``; its checks shown to fail on spoiled rows."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from simserver.core import driver as D
from simserver.core import layout as L
from simserver.sim import multisoak as M
from simserver.sim.scene import load_scene
from tests.conftest import CONFIGS, REPO, slow_enabled

SCENE = CONFIGS / "scenes" / "flat_paper_sedan.yaml"


@pytest.fixture(scope="module")
def short():
    """Two simulated minutes of 4 cars (seed 1: a 4 % grade)."""
    return M.run_multi_soak(load_scene(SCENE), 4, 120.0, seed=1)


def test_short_multi_soak_holds_every_invariant(short):
    assert short.ok, short.violations
    assert short.grade_pct == 4.0 and short.simulated_s == 120.0
    # the pair bumps every cycle: every event's energy judged
    assert len(short.contact_events) >= 120.0 / M.PAIR_CYCLE_S
    assert short.energy_checked == len(short.contact_events) and short.contact_events_lost == 0
    assert {e["car_a"] for e in short.contact_events} | {
        e["car_b"] for e in short.contact_events} >= {"car0", "car1"}
    roles = {h.role for h in short.holds.values()}
    assert roles == {"pair_held", "pair_rolling", "traffic", "keyframed"}
    for cid, h in short.holds.items():
        assert h.checked >= 1, cid  # every car was held and judged at least once
        assert h.max_creep_m < M.HOLD_CREEP_LIMIT_M


def test_same_seed_same_bits(short):
    again = M.run_multi_soak(load_scene(SCENE), 4, 120.0, seed=1)
    assert again.digest == short.digest
    assert again.contact_events == short.contact_events
    other = M.run_multi_soak(load_scene(SCENE), 4, 20.0, seed=2)
    assert other.digest != short.digest


def _spoiled(spoil, duration_s=20.0):
    return M.run_multi_soak(load_scene(SCENE), 4, duration_s, seed=1, spoil=spoil)


def test_a_nan_is_caught():
    def nan(step, states, outputs, dstates):
        if step == 5000:
            states[123, 2, L.U_MPS] = np.nan

    report = _spoiled(nan)
    assert [v.invariant for v in report.violations] == ["finite"]
    assert report.violations[0].step == 5123 and "car2" in report.violations[0].detail


def test_creep_in_a_hold_is_caught():
    """The traffic car's rows moved 2 mm along x in its first hold, after it settled."""
    def creep(step, states, outputs, dstates):
        held = dstates[:, 2, D.DS_MODE] == D.MODE_HOLD
        if held.sum() > 3000:
            rows = np.flatnonzero(held)
            states[rows[-1], 2, L.X_M] += 2e-3

    report = _spoiled(creep, 30.0)
    assert [v.invariant for v in report.violations] == ["hold_creep"]
    assert "car2" in report.violations[0].detail


def test_energy_gained_at_a_contact_is_caught():
    """The rolling car's recorded speed doubled after its first bump: energy from nowhere."""
    def boost(step, states, outputs, dstates):
        if step == 0:
            states[400:, 1, L.U_MPS] *= 2.0

    report = _spoiled(boost, 5.0)
    assert "contact_energy" in [v.invariant for v in report.violations]


def test_multi_soak_command(tmp_path):
    out = tmp_path / "soak.json"
    proc = subprocess.run([sys.executable, "-m", "simserver", "soak", "--cars", "4",
                           "--duration", "15", "--seed", "3", "--out", str(out)], cwd=REPO,
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(out.read_text())
    assert summary["ok"] and summary["cars"] == 4 and summary["contacts"] >= 1
    bad = subprocess.run([sys.executable, "-m", "simserver", "soak", "--cars", "2"],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and "--cars" in bad.stderr


@pytest.mark.slow
def test_long_multi_soak(request):
    if not slow_enabled(request.config.getoption("markexpr")):
        pytest.skip("slow: an hour of 8 cars (SIMSERVER_SLOW=1 or -m slow)")
    report = M.run_multi_soak(load_scene(SCENE), 8, 3600.0, seed=11)
    assert report.ok, report.violations
    assert report.contact_events_lost == 0
