"""``simserver compare A B`` run as a real subprocess on real ``run-scenario`` outputs."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

REPO = Path(__file__).resolve().parents[1]
SCENARIOS = REPO / "configs" / "scenarios"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def simserver(*args: str | Path, timeout: float = 600.0) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "simserver", *map(str, args)], cwd=REPO,
                          env=env, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Paper examples 1 and 2: the same stop, without and with the Appendix A damping."""
    root = tmp_path_factory.mktemp("compare")
    out = {}
    for key, name in (("e1", "e1_stop_downslope_no_damping"),
                      ("e2", "e2_stop_downslope_paper_damping")):
        proc = simserver("run-scenario", SCENARIOS / f"{name}.yaml", "--out",
                         root / "out" / key, "--no-plots", "--quiet")
        assert proc.returncode == 0, proc.stderr
        out[key] = root / "out" / key
    return root, out


def test_readme_command_as_written(runs):
    """The README's line, run where its out/e2 and out/e1 are (the runs above)."""
    root, _ = runs
    line = next(ln.strip() for ln in (REPO / "README.md").read_text().splitlines()
                if ln.strip().startswith(".venv/bin/simserver compare"))
    proc = subprocess.run([sys.executable, "-m", "simserver", *shlex.split(line)[1:]],
                          cwd=root, env=dict(os.environ, PYTHONPATH=str(REPO)),
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    report = json.loads((root / "out" / "e2_vs_e1" / "compare.json").read_text())
    assert report["signals"]["u_mps"]["max_abs_diff"] > 0.0
    assert (root / "out" / "e2_vs_e1" / "compare.png").is_file()


def compare(a: Path, b: Path, out: Path, *extra: str) -> dict:
    proc = simserver("compare", a, b, "--out", out, *extra)
    assert proc.returncode == 0, proc.stderr
    assert "max|A-B|" in proc.stdout and "u_mps" in proc.stdout
    assert (out / "compare.png").read_bytes()[:8] == PNG_SIGNATURE
    return json.loads((out / "compare.json").read_text(encoding="utf-8"))


def assert_all_zero(report: dict) -> None:
    assert report["rows"] > 1000
    assert set(report["signals"]) >= {"u_mps", "x_m", "y_m", "yaw_rad", "fx_sum_n",
                                      "fy_sum_n", "fz_sum_n", "fx_body_sum_n"}
    for name, s in report["signals"].items():
        assert s["max_abs_diff"] == 0.0 and s["rms_diff"] == 0.0, name
        assert s["rows_compared"] == report["rows"], name
    holds = report["holds"]
    assert holds["count_a"] == holds["count_b"] >= 1
    for pair in holds["pairs"]:
        assert all(v in (0.0, None) for v in pair["a_minus_b"].values()), pair


def test_a_run_against_itself_differs_by_exactly_zero(runs, tmp_path):
    _, r = runs
    report = compare(r["e2"], r["e2"], tmp_path / "out")
    assert_all_zero(report)
    assert report["alignment"]["shift_b_s"] == 0.0
    assert report["alignment"]["how"] == "first input change"
    figures = report["summary"]["figures"]
    assert "holds.holds.0.creep_m" in figures and "final.u_mps" in figures
    assert all(f["a_minus_b"] == 0.0 for f in figures.values())
    assert not any(k.startswith("timing.") for k in figures)


def test_two_damping_models_differ_as_numpy_says(runs, tmp_path):
    _, r = runs
    report = compare(r["e2"], r["e1"], tmp_path / "out")
    a = pq.read_table(r["e2"] / "history.parquet")
    b = pq.read_table(r["e1"] / "history.parquet")
    t = a.column("time_s").to_numpy()
    assert np.array_equal(t, b.column("time_s").to_numpy())  # the same step grid
    for name in ("u_mps", "x_m"):
        d = a.column(name).to_numpy() - b.column(name).to_numpy()
        k = int(np.argmax(np.abs(d)))
        s = report["signals"][name]
        assert s["max_abs_diff"] == np.abs(d[k]) and s["time_of_max_s"] == t[k], name
        assert s["rms_diff"] == pytest.approx(np.sqrt(np.mean(d * d)), rel=1e-12)
    fz = sum(a.column(f"fz_{w}_n").to_numpy() - b.column(f"fz_{w}_n").to_numpy()
             for w in ("fl", "fr", "rl", "rr"))
    assert report["signals"]["fz_sum_n"]["max_abs_diff"] == pytest.approx(
        np.abs(fz).max(), rel=1e-12)
    # the damping is the difference: example 1 rings at 3.5 Hz after the stop
    assert report["signals"]["u_mps"]["max_abs_diff"] > 1e-3
    damping = report["summary"]["figures"]
    assert "final.u_mps" in damping


def test_a_time_shifted_copy_aligns_back_to_zero(runs, tmp_path):
    root, r = runs
    table = pq.read_table(r["e2"] / "history.parquet")
    i = table.column_names.index("time_s")
    shifted = table.set_column(i, table.schema.field(i),
                               pa.array(table.column("time_s").to_numpy() + 3.0))
    copy = root / "shifted.parquet"
    pq.write_table(shifted, copy)
    report = compare(r["e2"] / "history.parquet", copy, tmp_path / "explicit",
                     "--shift-b", "-3.0")
    assert report["alignment"] == {**report["alignment"], "shift_b_s": -3.0,
                                   "how": "--shift-b"}
    assert_all_zero(report)
    # without the option the first input change (the brake at 0.7 s) finds the shift
    auto = compare(r["e2"] / "history.parquet", copy, tmp_path / "auto")
    assert auto["alignment"]["shift_b_s"] == pytest.approx(-3.0, abs=1e-12)
    assert_all_zero(auto)
    # half a step off: B is interpolated linearly onto A's rows inside B's span
    off = compare(r["e2"] / "history.parquet", copy, tmp_path / "off", "--shift-b",
                  "-3.0005")
    t = table.column("time_s").to_numpy()
    u = table.column("u_mps").to_numpy()
    inside = t <= t[-1] - 0.0005
    d = u[inside] - np.interp(t[inside], t - 0.0005, u)
    assert off["rows"] == inside.sum()
    assert off["signals"]["u_mps"]["max_abs_diff"] == pytest.approx(np.abs(d).max(),
                                                                    rel=1e-9)
    assert off["signals"]["u_mps"]["max_abs_diff"] > 1e-3


def test_bad_inputs_give_one_line_naming_the_file(runs, tmp_path):
    _, r = runs
    no_time = tmp_path / "no_time.parquet"
    pq.write_table(pa.table({"t": [0.0, 0.001], "u_mps": [1.0, 1.0]}), no_time)
    text = tmp_path / "text.parquet"
    text.write_text("not parquet\n", encoding="utf-8")
    backwards = tmp_path / "backwards.parquet"
    pq.write_table(pa.table({"time_s": [0.0, 0.001, 0.0005], "u_mps": [1.0, 1.0, 1.0]}),
                   backwards)
    missing = tmp_path / "missing.parquet"
    cases = [
        (missing, "no such file or folder"),
        (no_time, "no column 'time_s'"),
        (text, "not a readable Parquet file"),
        (backwards, "does not increase at row 2"),
        (tmp_path, "no history.parquet in this folder"),
    ]
    for bad, why in cases:
        for args in ((r["e2"], bad), (bad, r["e2"])):
            out = tmp_path / "out"
            proc = simserver("compare", *args, "--out", out)
            assert proc.returncode == 2, (bad, proc.stderr)
            lines = proc.stderr.strip().splitlines()
            assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
            assert str(bad) in lines[0] and why in lines[0], lines[0]
            assert not out.exists()  # nothing written


def test_one_segment_of_a_recording_like_file(runs, tmp_path):
    """Two segments (time restarting at the second, as after a live load) with the
    recorder's ``tick`` and ``segment`` columns: the whole file is refused naming the row,
    ``--segment-b 1`` compares that segment alone."""
    _, r = runs
    table = pq.read_table(r["e2"] / "history.parquet")
    n = table.num_rows
    first = table.slice(0, 500)
    i = first.column_names.index("time_s")
    first = first.set_column(i, first.schema.field(i),
                             pa.array(first.column("time_s").to_numpy() + 31.0))
    both = pa.concat_tables([first, table])
    both = both.append_column("segment", pa.array(np.r_[np.zeros(500), np.ones(n)]
                                                  .astype(np.int64)))
    both = both.append_column("tick", pa.array(np.r_[np.arange(500), np.arange(n)]
                                               .astype(np.int64)))
    rec = tmp_path / "recording.parquet"
    pq.write_table(both, rec)
    whole = simserver("compare", r["e2"], rec, "--out", tmp_path / "whole")
    assert whole.returncode == 2
    assert f"{rec}: column 'time_s' does not increase at row 500" in whole.stderr
    assert "--segment-b" in whole.stderr
    report = compare(r["e2"], rec, tmp_path / "seg", "--segment-b", "1", "--shift-b", "0")
    assert report["b"]["rows"] == n
    assert_all_zero(report)
    assert report["summary"] is None  # a segment has no summary.json of its own
    # a recording's inputs are the step's that ended at the row: its first change is
    # taken one row earlier (this file has headless rows, so the auto shift is one row)
    auto = compare(r["e2"], rec, tmp_path / "auto", "--segment-b", "1")
    assert auto["alignment"]["shift_b_s"] == pytest.approx(0.001, abs=1e-12)
    missing = simserver("compare", r["e2"], rec, "--out", tmp_path / "x", "--segment-b", "7")
    assert missing.returncode == 2 and "no such segment (found 0, 1)" in missing.stderr
    plain = simserver("compare", r["e2"], r["e2"], "--out", tmp_path / "y", "--segment-a",
                      "0")
    assert plain.returncode == 2 and "no column 'segment'" in plain.stderr
