"""The history file and the summary: columns from the layout, units, round trip, digest."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from simserver.adapters import history as H
from simserver.core import layout as L

REPO = Path(__file__).resolve().parents[1]
VEHICLE = REPO / "configs" / "vehicles" / "paper_sedan" / "vehicle.yaml"

SCENARIO = """\
name: history_test_stop
description: brake to a stop in a gentle left turn on a 5 % downslope
vehicle: {vehicle}
road: {{grade_pct: -5.0}}
initial: {{u_mps: 8.0}}
duration_s: 3.0
inputs:
  - {{t: 0.0, steer: 0.0, gear: D}}
  - {{t: 0.2, steer: 0.1, brake: 0.0}}
  - {{t: 0.4, brake: 0.7}}
"""


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    """A short run: brake to a stop from 8 m/s."""
    from simserver.sim.scenario import load_scenario, run_scenario

    path = tmp_path_factory.mktemp("scenario") / "stop.yaml"
    path.write_text(SCENARIO.format(vehicle=VEHICLE.as_posix()), encoding="utf-8")
    return run_scenario(load_scenario(path))


def test_columns_come_from_the_layout():
    expected = (
        ["time_s"]
        + [n for n in L.STATE_NAMES if n != "time_s" and not n.startswith("hub_u_prev_")]
        + list(L.OUTPUT_NAMES)
        + ["input_" + n for n in L.INPUT_NAMES]
        + ["world_x_m", "world_y_m", "world_z_m", "world_yaw_rad", "world_pitch_rad",
           "world_roll_rad"]
    )
    assert list(H.HISTORY_COLUMNS) == expected
    assert [slot for _, slot in H.POSE_COLUMNS] == [
        L.POSE_X_M, L.POSE_Y_M, L.POSE_Z_M, L.POSE_YAW_RAD, L.POSE_PITCH_RAD, L.POSE_ROLL_RAD]
    assert len(set(expected)) == len(expected)


def test_every_column_is_documented_with_a_unit_matching_its_name():
    doc = list(H.column_doc())
    assert [name for name, _, _ in doc] == list(H.HISTORY_COLUMNS)
    for name, unit, description in doc:
        assert description and description != "(undocumented)", name
        assert unit
    units = {name: unit for name, unit, _ in doc}
    assert units["fx_fl_n"] == "N"
    assert units["mz_rr_nm"] == "N m"
    assert units["u_mps"] == "m/s"
    assert units["ax_mps2"] == "m/s^2"
    assert units["yaw_rate_radps"] == "rad/s"
    assert units["yaw_acc_radps2"] == "rad/s^2"
    assert units["time_s"] == "s"
    assert units["kappa_lag_fl"] == H.DIMENSIONLESS
    assert units["input_gear"] == H.DIMENSIONLESS
    assert "front-left" in dict((n, d) for n, _, d in doc)["fx_fl_n"]
    assert "| `fz_rl_n` | N |" in H.column_doc_markdown()


def test_round_trip_and_field_metadata(result, tmp_path):
    path = H.write_history(result, tmp_path)
    assert path == tmp_path / H.HISTORY_FILE
    cols = H.read_history(path)
    assert list(cols) == list(H.HISTORY_COLUMNS)
    n = result.states.shape[0]
    for name, arr in cols.items():
        assert arr.dtype == np.float64 and arr.shape == (n,), name
    np.testing.assert_array_equal(cols["time_s"], result.states[:, L.TIME_S])
    np.testing.assert_array_equal(cols["u_mps"], result.states[:, L.U_MPS])
    np.testing.assert_array_equal(cols["fz_rr_n"], result.outputs[:, L.O_FZ0 + L.RR])
    np.testing.assert_array_equal(cols["input_brake"], result.inputs[:, L.IN_BRAKE])
    schema = pq.read_schema(path)
    for field in schema:
        assert str(field.type) == "double"
        meta = {k.decode(): v.decode() for k, v in field.metadata.items()}
        assert meta == {"unit": H.column_unit(field.name),
                        "description": H.column_description(field.name)}
    file_meta = {k.decode(): v.decode() for k, v in schema.metadata.items()
                 if k.startswith(b"simserver.")}
    assert file_meta["simserver.scenario"] == "history_test_stop"


def test_same_result_same_bytes(result, tmp_path):
    a = H.write_history(result, tmp_path / "a.parquet")
    b = H.write_history(result, tmp_path / "b.parquet")
    assert a.read_bytes() == b.read_bytes()
    assert pq.read_metadata(a).created_by.startswith("parquet-cpp-arrow")


def test_summary_agrees_with_the_history(result, tmp_path):
    s = json.loads(H.write_summary(H.summarize(result), tmp_path).read_text(encoding="utf-8"))
    cols = H.read_history(H.write_history(result, tmp_path))
    final = s["final"]
    approx = {"rel": 1e-6, "abs": 1e-9}
    assert final["time_s"] == pytest.approx(cols["time_s"][-1], **approx)
    assert final["u_mps"] == pytest.approx(cols["u_mps"][-1], **approx)
    assert final["x_m"] == pytest.approx(cols["x_m"][-1], **approx)
    for w in L.WHEEL_NAMES:
        assert final["fz_n"][w] == pytest.approx(cols[f"fz_{w}_n"][-1], **approx)
    assert final["fx_sum_n"] == pytest.approx(
        sum(cols[f"fx_{w}_n"][-1] for w in L.WHEEL_NAMES), rel=1e-6, abs=1e-3)
    fz = np.stack([cols[f"fz_{w}_n"] for w in L.WHEEL_NAMES])
    assert s["extremes"]["min_fz_n"] == pytest.approx(fz.min(), **approx)
    assert s["extremes"]["max_abs_u_mps"] == pytest.approx(np.abs(cols["u_mps"]).max(), **approx)
    assert s["run"]["steps"] == 3000 and s["run"]["rows"] == 3000
    assert s["finite"]["all"] is True
    # the stop: the car is at rest at the end, having first stopped after the brake came on
    assert s["rest"]["at_rest_at_end"] is True
    assert 0.4 < s["rest"]["first_time_s"] <= s["rest"]["settled_time_s"] < 3.0
    assert set(s["timing"]) == {"wall_time_s", "real_time_factor", "us_per_step"}
    assert s["model_options"]["slip_model"] == "lagged_passive"  # the default, filled in


def test_summary_serialisation_is_sorted_and_rounded(result):
    text = H.summary_json(H.summarize(result))
    data = json.loads(text)
    assert list(data) == sorted(data)
    assert text.endswith("\n")

    def floats(obj):
        if isinstance(obj, dict):
            for v in obj.values():
                yield from floats(v)
        elif isinstance(obj, list):
            for v in obj:
                yield from floats(v)
        elif isinstance(obj, float):
            yield obj

    for value in floats(data):
        assert value == float(f"{value:.{H.SUMMARY_SIGNIFICANT_DIGITS}g}")


def test_non_finite_values_become_null_and_are_flagged(result):
    broken = type(result)(**{**result.__dict__, "states": result.states.copy()})
    broken.states[-1, L.U_MPS] = math.nan
    s = H.summarize(broken)
    assert s["finite"] == {"states": False, "outputs": True, "final_state": True, "all": False}
    assert s["final"]["u_mps"] is None
    H.summary_json(s)  # still valid JSON (no NaN literal)


def test_rest_times():
    t = np.arange(6) * 0.5
    first, settled = H._rest_times(t, np.array([2.0, 0.0, 0.5, 0.0, 0.0, 0.0]))
    assert (first, settled) == (0.5, 1.5)
    assert H._rest_times(t, np.ones(6)) == (None, None)
    assert H._rest_times(t, np.array([0.0, 0.0, 1.0, 1.0, 0.0, 1.0])) == (0.0, None)
    assert H._rest_times(t, np.zeros(6)) == (0.0, 0.0)
