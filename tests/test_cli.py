"""``simserver run-scenario`` and ``simserver tire-curves``, run as real subprocesses."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
VEHICLE = REPO / "configs" / "vehicles" / "paper_sedan" / "vehicle.yaml"
TIRES = REPO / "configs" / "tires"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PLOTS = ("speed.png", "forces.png", "trajectory.png", "slip.png", "inputs.png")

SCENARIO = """\
name: cli_test_stop
vehicle: {vehicle}
road: {{grade_pct: -5.0, cross_slope_pct: 2.0}}
initial: {{u_mps: 6.0}}
duration_s: 2.5
model: {{slip_model: lagged_paper, damping_model: paper}}
inputs:
  - {{t: 0.0, gear: D}}
  - {{t: 0.2, steer: 0.1, brake: 0.0}}
  - {{t: 0.4, brake: 0.7}}
"""


def simserver(*args: str | Path, timeout: float = 300.0) -> subprocess.CompletedProcess:
    """Run ``python -m simserver.cli ARGS`` from the repository root."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run(
        [sys.executable, "-m", "simserver.cli", *map(str, args)],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout,
    )


def write_scenario(path: Path, text: str = SCENARIO) -> Path:
    path.write_text(text.format(vehicle=VEHICLE.as_posix()), encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    """The same scenario run twice: once with plots, once without."""
    root = tmp_path_factory.mktemp("cli")
    scenario = write_scenario(root / "stop.yaml")
    first = simserver("run-scenario", scenario, "--out", root / "a")
    second = simserver("run-scenario", scenario, "--out", root / "b", "--no-plots", "--quiet")
    return root, first, second


def test_run_scenario_writes_history_summary_and_plots(two_runs):
    root, first, _ = two_runs
    assert first.returncode == 0, first.stderr
    out = root / "a"
    assert "2500 steps" in first.stdout and "real time" in first.stdout
    assert str(out) in first.stdout
    assert len(first.stdout.strip().splitlines()) == 1
    assert "Traceback" not in first.stderr
    for name in ("history.parquet", "summary.json", *PLOTS):
        assert (out / name).stat().st_size > 0, name
    for name in PLOTS:
        assert (out / name).read_bytes()[:8] == PNG_SIGNATURE


def test_parquet_columns_match_the_layout(two_runs):
    from simserver.adapters.history import read_history
    from simserver.core import layout as L

    cols = read_history(two_runs[0] / "a" / "history.parquet")
    expected = {"time_s", *L.OUTPUT_NAMES, *("input_" + n for n in L.INPUT_NAMES)}
    expected |= {n for n in L.STATE_NAMES if not n.startswith("hub_u_prev_")}
    assert set(cols) == expected
    assert cols["time_s"][0] == 0.0 and cols["time_s"].size == 2500
    assert all(arr.dtype == np.float64 for arr in cols.values())


def test_summary_is_consistent_with_the_history(two_runs):
    from simserver.adapters.history import read_history

    out = two_runs[0] / "a"
    cols = read_history(out / "history.parquet")
    s = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    assert s["scenario"]["name"] == "cli_test_stop"
    assert s["vehicle"]["name"] == "paper_sedan"
    assert s["road"] == {"grade_pct": -5.0, "cross_slope_pct": 2.0, "friction_scale": 1.0}
    assert s["model_options"]["damping_model"] == "paper"
    assert s["run"]["steps"] == 2500 and s["run"]["dt_s"] == 0.001
    assert s["final"]["u_mps"] == pytest.approx(cols["u_mps"][-1], rel=1e-6, abs=1e-9)
    assert s["final"]["yaw_rad"] == pytest.approx(cols["yaw_rad"][-1], rel=1e-6, abs=1e-9)
    assert s["final"]["fx_n"]["fl"] == pytest.approx(cols["fx_fl_n"][-1], rel=1e-6, abs=1e-6)
    assert s["finite"]["all"] is True
    assert s["timing"]["real_time_factor"] > 0


def test_same_scenario_same_bytes(two_runs):
    root, first, second = two_runs
    assert second.returncode == 0, second.stderr
    a, b = root / "a", root / "b"
    assert (a / "history.parquet").read_bytes() == (b / "history.parquet").read_bytes()
    sa = json.loads((a / "summary.json").read_text(encoding="utf-8"))
    sb = json.loads((b / "summary.json").read_text(encoding="utf-8"))
    sa.pop("timing")
    sb.pop("timing")
    assert sa == sb
    assert not list(b.glob("*.png"))  # --no-plots


@pytest.mark.parametrize(
    ("old", "new", "key"),
    [
        ("duration_s: 2.5", "duration_s: 2.5\nwheelbase_m: 2.9", "wheelbase_m"),
        ("duration_s: 2.5", "duration_s: .nan", "duration_s"),
        ("{t: 0.0, gear: D}", "{t: 0.0, gear: X}", "inputs[0].gear"),
    ],
    ids=["unknown-key", "nan", "bad-gear"],
)
def test_broken_scenario_exits_2_naming_file_and_key(tmp_path, old, new, key):
    assert old in SCENARIO
    path = write_scenario(tmp_path / "broken.yaml", SCENARIO.replace(old, new))
    proc = simserver("run-scenario", path, "--out", tmp_path / "out")
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.startswith("error: ")
    assert str(path) in proc.stderr and key in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "out" / "history.parquet").exists()


def test_bad_dt_is_a_config_error(tmp_path, capsys):
    from simserver.cli import main

    path = write_scenario(tmp_path / "s.yaml")
    assert main(["run-scenario", str(path), "--out", str(tmp_path / "o"), "--dt", "0.5"]) == 2
    assert "--dt" in capsys.readouterr().err


@pytest.mark.parametrize("tire", ["paper_sti.yaml", "mf61_sample.yaml",
                                  "data/mf61_225_50R17_sample.tir"])
def test_tire_curves_writes_a_png(tmp_path, tire):
    out = tmp_path / "curves" / f"{Path(tire).name}.png"
    proc = simserver("tire-curves", TIRES / tire, "--out", out)
    assert proc.returncode == 0, proc.stderr
    assert out.read_bytes()[:8] == PNG_SIGNATURE
    assert str(out) in proc.stdout


def test_tire_curve_data_signs_and_nominal_loads():
    from simserver.adapters.config import load_tire
    from simserver.cli import nominal_load_n, tire_curve_data

    tp_sti, _ = load_tire(TIRES / "paper_sti.yaml")
    tp_mf, _ = load_tire(TIRES / "mf61_sample.yaml")
    assert nominal_load_n(tp_sti) == 5005.0
    assert nominal_load_n(tp_mf) == 4000.0  # FNOMIN of the sample .tir
    c = tire_curve_data(tp_sti, [5005.0], n_points=41, alpha_max_deg=20.0, kappa_max=1.0)
    fy, fx = c["fy_alpha"][0], c["fx_kappa"][0]
    assert fy[c["alpha_deg"] > 0].max() < 0 < fy[c["alpha_deg"] < 0].min()  # ISO signs
    assert fx[c["kappa"] > 0].min() > 0 > fx[c["kappa"] < 0].max()
    assert np.abs(fy).max() == pytest.approx(0.9 * 5005.0, rel=0.01)  # mu Fz when sliding
    half = tire_curve_data(tp_sti, [5005.0], mu_scale=0.5, n_points=41)
    assert np.abs(half["fx_kappa"]).max() == pytest.approx(0.45 * 5005.0, rel=0.01)


def test_help_lists_the_subcommands():
    proc = subprocess.run([sys.executable, "-m", "simserver", "--help"], cwd=REPO,
                          capture_output=True, text=True, timeout=60,
                          env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert proc.returncode == 0
    assert "run-scenario" in proc.stdout and "tire-curves" in proc.stdout


def test_a_run_that_goes_non_finite_exits_1_but_writes_its_files(tmp_path, capsys,
                                                                   monkeypatch):
    import simserver.scenario
    from simserver.cli import main
    from simserver.core.layout import U_MPS

    real_run = simserver.scenario.run_scenario

    def run_then_break(scenario, **kwargs):
        result = real_run(scenario, **kwargs)
        result.states[-1, U_MPS] = float("nan")
        return result

    monkeypatch.setattr(simserver.scenario, "run_scenario", run_then_break)
    path = write_scenario(tmp_path / "s.yaml", SCENARIO.replace("2.5", "0.2"))
    out = tmp_path / "out"
    assert main(["run-scenario", str(path), "--out", str(out), "--quiet"]) == 1
    assert "non-finite" in capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    assert summary["finite"]["all"] is False and summary["final"]["u_mps"] is None
    assert (out / "trajectory.png").exists()
