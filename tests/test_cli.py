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
PLOTS = ("speed.png", "forces.png", "trajectory.png", "slip.png", "inputs.png", "holds.png")

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
    expected |= {"world_x_m", "world_y_m", "world_z_m", "world_yaw_rad", "world_pitch_rad",
                 "world_roll_rad"}  # the world pose of each row
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
    import simserver.sim.scenario
    from simserver.cli import main
    from simserver.core.layout import U_MPS

    real_run = simserver.sim.scenario.run_scenario

    def run_then_break(scenario, **kwargs):
        result = real_run(scenario, **kwargs)
        result.states[-1, U_MPS] = float("nan")
        return result

    monkeypatch.setattr(simserver.sim.scenario, "run_scenario", run_then_break)
    path = write_scenario(tmp_path / "s.yaml", SCENARIO.replace("2.5", "0.2"))
    out = tmp_path / "out"
    assert main(["run-scenario", str(path), "--out", str(out), "--quiet"]) == 1
    assert "non-finite" in capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    assert summary["finite"]["all"] is False and summary["final"]["u_mps"] is None
    assert (out / "trajectory.png").exists()


# ------------------------------------------------------------------- the fuzz corpus
# Issue 14 item 6: inputs that gave a traceback, a wrong acceptance or an error that did
# not name the key. Each is run through the CLI's entry point in-process: exit 2, one
# "error:" line naming the file and the key (or option), never a traceback.
SERVER_YAML = REPO / "configs" / "server" / "default.yaml"
FLAT_SCENE = REPO / "configs" / "scenes" / "flat_paper_sedan.yaml"


def cli_error(capsys, *argv: str | Path) -> str:
    """Run the CLI in-process; it must exit 2 with an error line, which is returned."""
    from simserver.cli import main

    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith("error: ") and "Traceback" not in err, err
    return err


def _nested(depth: int) -> str:
    return "[" * depth + "]" * depth


SCENARIO_CASES = {
    # name: (replace, with, the text the error must hold besides the file)
    "deep-nesting": ("inputs:\n", f"extra: {_nested(5000)}\ninputs:\n", "nested deeper"),
    "record-every-400-digits": ("duration_s: 2.5", "duration_s: 2.5\nrecord_every: "
                                + "9" * 400, "key 'record_every'"),
    "gear-list": ("{t: 0.0, gear: D}", "{t: 0.0, gear: [D]}", "key 'inputs[0].gear'"),
    "gear-mapping": ("{t: 0.0, gear: D}", "{t: 0.0, gear: {{a: 1}}}", "key 'inputs[0].gear'"),
    "duration-1e6": ("duration_s: 2.5", "duration_s: 1.0e+6", "key 'duration_s'"),
    "record-every-float": ("duration_s: 2.5", "duration_s: 2.5\nrecord_every: 1.5",
                           "key 'record_every'"),
    "alias-bomb": ("inputs:\n", "a: &a [x, x, x, x, x, x, x, x, x, x]\n"
                   + "".join(f"{c}: &{c} [*{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}]\n"
                             for p, c in zip("abcdefgh", "bcdefghi", strict=True))
                   + "inputs:\n", "aliases"),
    "missing-vehicle": ("vehicle: {vehicle}", "vehicle: no_such_vehicle.yaml",
                        "key 'vehicle': "),
    "vehicle-is-a-device": ("vehicle: {vehicle}", "vehicle: /dev/zero", "not a regular file"),
}


@pytest.mark.timeout(60)
@pytest.mark.parametrize("case", list(SCENARIO_CASES))
def test_fuzz_corpus_scenarios_exit_2_naming_file_and_key(tmp_path, capsys, case):
    old, new, needle = SCENARIO_CASES[case]
    assert old in SCENARIO
    path = write_scenario(tmp_path / "fuzz.yaml", SCENARIO.replace(old, new))
    err = cli_error(capsys, "run-scenario", path, "--out", tmp_path / "out")
    assert str(path) in err and needle in err, err
    assert not (tmp_path / "out" / "history.parquet").exists()


@pytest.mark.timeout(60)
def test_fuzz_corpus_nested_files(tmp_path, capsys):
    """A FIFO as vehicle (read without blocking), a 3 000-deep vehicle file, a missing
    tire file: each error names the file that refers to it and the key."""
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)
    path = write_scenario(tmp_path / "s.yaml", SCENARIO.replace("vehicle: {vehicle}",
                                                                f"vehicle: {fifo}"))
    err = cli_error(capsys, "run-scenario", path, "--out", tmp_path / "out")
    assert f"{path}: key 'vehicle': {fifo}: not a regular file" in err
    deep = tmp_path / "vehicle.yaml"
    deep.write_text(f"name: {_nested(3000)}\n")
    path = write_scenario(tmp_path / "s.yaml", SCENARIO.replace("vehicle: {vehicle}",
                                                                f"vehicle: {deep}"))
    err = cli_error(capsys, "run-scenario", path, "--out", tmp_path / "out")
    assert f"{deep}: not valid YAML: nested deeper" in err
    vehicle = tmp_path / "v" / "vehicle.yaml"
    vehicle.parent.mkdir()
    text = VEHICLE.read_text()
    for name in ("chassis", "suspension", "steering", "brakes", "powertrain"):
        text = text.replace(f"{name}.yaml", str(VEHICLE.parent / f"{name}.yaml"))
    vehicle.write_text(re_sub_front(text))
    path = write_scenario(tmp_path / "s.yaml", SCENARIO.replace("vehicle: {vehicle}",
                                                                f"vehicle: {vehicle}"))
    err = cli_error(capsys, "run-scenario", path, "--out", tmp_path / "out")
    assert f"{vehicle}: key 'tires.front': " in err and "no_such_tire.yaml" in err, err


def re_sub_front(vehicle_text: str) -> str:
    """The vehicle file with its front tire file replaced by a missing one."""
    import re

    return re.sub(r"front:\s*[^,}\s]+", "front: no_such_tire.yaml", vehicle_text)


SERVER_CASES = {
    "state-every-1.5": ({"state_every": 1.5}, (), "key 'state_every'"),
    "viewer-port-99999": ({"viewer": "serve:99999"}, (), "key 'viewer'"),
    "listen-port-99999": ({"listen": ["tcp/127.0.0.1:99999"]}, (), "key 'listen'"),
    "listen-unknown-protocol": ({"listen": ["xyz/127.0.0.1:7447"]}, (), "key 'listen'"),
    "listen-option": ({}, ("--listen", "tcp/127.0.0.1:99999"), "option '--listen'"),
    "command-log-dot": ({"command_log": "."}, (), "key 'command_log'"),
    "command-log-missing-folder": ({"command_log": "no/such/folder/log.jsonl"}, (),
                                   "key 'command_log'"),
    "missing-scene": ({"scene": "no_such_scene.yaml"}, (), "key 'scene'"),
    "missing-zenoh-config": ({"zenoh_config": "no_such.json5"}, (), "key 'zenoh_config'"),
    "tls-front-on": ({"tls_front": "on"}, (), "key 'tls_front'"),
}


@pytest.mark.timeout(60)
@pytest.mark.parametrize("case", list(SERVER_CASES))
def test_fuzz_corpus_server_configs_exit_2_naming_file_and_key(tmp_path, capsys, case):
    import yaml

    changes, argv, needle = SERVER_CASES[case]
    data = {"scene": str(FLAT_SCENE), "viewer": "off", **changes}
    path = tmp_path / "server.yaml"
    path.write_text(yaml.safe_dump(data))
    err = cli_error(capsys, "serve", "--config", path, *argv)
    assert needle in err, err
    if not argv:
        assert str(path) in err, err


def _log_lines(*lines: str) -> str:
    header = json.dumps({"simserver_command_log": 1, "scene": str(FLAT_SCENE),
                         "dt_s": 0.001, "step": 0})
    return "\n".join((header, *lines)) + "\n"


STATE_HEX = json.dumps([0.0.hex()] * 37)
REPLAY_CASES = {
    "negative-end": (_log_lines(f'{{"end": -1, "state": {STATE_HEX}}}'), ":2: key 'end'"),
    "huge-end": (_log_lines(f'{{"end": {10**15}, "state": {STATE_HEX}}}'), ":2: key 'end'"),
    "non-hex-state": (_log_lines('{"end": 5, "state": ' + json.dumps(["zz"] * 37) + "}"),
                      ":2: key 'state[0]'"),
    "dt-zero": (_log_lines().replace('"dt_s": 0.001', '"dt_s": 0'), ":1: key 'dt_s'"),
    "step-a-string": (_log_lines('{"step": "a", "inputs": [0, 0, 0, 0, 3]}'),
                      ":2: key 'step'"),
    "inputs-a-string": (_log_lines('{"step": 1, "inputs": "x"}'), ":2: key 'inputs'"),
    "a-list-line": (_log_lines("[1, 2]"), ":2: expected a JSON object"),
    "nan-inputs": (_log_lines('{"step": 0, "inputs": [NaN, 0, 0, 0, 3]}'), ":2: "),
    "inputs-out-of-range": (_log_lines('{"step": 0, "inputs": [0, 7, 0, 0, 3]}'),
                            ":2: key 'inputs.throttle'"),
    "steps-going-back": (_log_lines('{"step": 5, "inputs": [0, 0, 0, 0, 3]}',
                                    '{"step": 4, "reset": null}'), ":3: key 'step'"),
    "set-road-wrong-type": (_log_lines('{"step": 0, "set_road": [1]}'), ":2: key 'set_road'"),
    "no-header": ('{"step": 0}\n', "not a simserver command log"),
}


@pytest.mark.timeout(60)
@pytest.mark.parametrize("case", list(REPLAY_CASES))
def test_fuzz_corpus_malformed_command_logs_exit_2(tmp_path, capsys, case):
    text, needle = REPLAY_CASES[case]
    path = tmp_path / "log.jsonl"
    path.write_text(text)
    err = cli_error(capsys, "replay", path)
    assert f"{path}" in err and needle in err, err


@pytest.mark.timeout(60)
def test_a_binary_command_log_exits_2(tmp_path, capsys):
    path = tmp_path / "log.jsonl"
    path.write_bytes(b"\x00\xff\xfe garbage \x80" * 100)
    assert "not a simserver command log" in cli_error(capsys, "replay", path)


@pytest.mark.timeout(60)
def test_a_command_log_whose_scene_is_missing_names_the_line_and_the_key(tmp_path, capsys):
    path = tmp_path / "log.jsonl"
    path.write_text(_log_lines().replace(str(FLAT_SCENE), str(tmp_path / "gone.yaml")))
    err = cli_error(capsys, "replay", path)
    assert f"{path}:1: key 'scene': {tmp_path / 'gone.yaml'}: cannot read" in err, err
