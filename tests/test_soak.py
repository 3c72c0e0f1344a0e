"""The headless soak: a short form in the default suite (the README quotes an hour)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from simserver.core import layout as L
from simserver.sim.scene import load_scene
from simserver.sim.soak import check_invariants, manoeuvre_plan, run_soak
from tests.conftest import CONFIGS, REPO


@pytest.mark.parametrize("scene", ["flat_paper_sedan", "flat_mf_hatchback"])
def test_short_soak_holds_every_invariant(scene):
    report = run_soak(load_scene(CONFIGS / "scenes" / f"{scene}.yaml"), 300.0, seed=7)
    assert report.ok, report.violations
    assert report.holds_checked >= 5 and report.max_hold_creep_m < 1e-3
    for kind in ("accelerate", "brake_stop", "hold"):
        assert report.manoeuvres[kind] > 0


def test_plan_is_seeded_and_varied():
    a = manoeuvre_plan(np.random.default_rng(3), 3600.0)
    b = manoeuvre_plan(np.random.default_rng(3), 3600.0)
    assert [(s.kind, s.duration_s) for s in a] == [(s.kind, s.duration_s) for s in b]
    assert {s.kind for s in a} == set(range(8))  # every manoeuvre appears in an hour


def test_invariant_checker_catches_each_breach():
    """The checker itself can fail: feed it one bad tick of each kind."""
    n = 10
    states = np.zeros((n, L.N_STATE))
    outputs = np.zeros((n, L.N_OUT))
    outputs[:, L.O_FZ] = 5000.0
    cases = {
        "finite": lambda s, o: s.__setitem__((4, L.U_MPS), np.nan),
        "speed": lambda s, o: s.__setitem__((4, L.V_MPS), 90.0),
        "wheel_spin": lambda s, o: s.__setitem__((4, L.OMEGA0 + 2), -700.0),
        "yaw_rate": lambda s, o: s.__setitem__((4, L.YAW_RATE_RADPS), 11.0),
        "normal_load_negative": lambda s, o: o.__setitem__((4, L.O_FZ0 + 1), -1.0),
        "normal_load_bound": lambda s, o: o.__setitem__((4, L.O_FZ0), 40000.0),
    }
    for name, spoil in cases.items():
        s, o = states.copy(), outputs.copy()
        spoil(s, o)
        found: dict = {}
        check_invariants(s, o, 5000.0, 100, 0.001, found)
        assert list(found) == [name] and found[name].step == 104
    found = {}
    check_invariants(states, outputs, 5000.0, 0, 0.001, found)
    assert not found


def test_soak_command(tmp_path):
    out = tmp_path / "soak.json"
    proc = subprocess.run([sys.executable, "-m", "simserver", "soak", "--duration", "60",
                           "--seed", "2", "--out", str(out)], cwd=REPO, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(out.read_text())
    assert summary["ok"] and summary["simulated_s"] >= 60.0
