"""A sweep worker's run in this process (issue 18): ``run_for_metrics`` keeps only the
history columns the metrics read, through reused rows, and must give what ``run_scenario``
gives bit for bit; every metric kind must name every column it reads."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from simserver.adapters.history import result_columns
from simserver.core import layout as L
from simserver.sim.scenario import load_scenario, resolve_scenario, run_scenario
from simserver.sim.simulation import Simulation
from simserver.sweep.metrics import METRIC_KINDS, Metric
from simserver.sweep.spec import Case
from simserver.sweep.worker import (
    NON_FINITE,
    OK,
    STREAM_ROWS,
    history_column_places,
    run_case,
    run_for_metrics,
)
from simserver.testing import CONFIGS

E2 = CONFIGS / "scenarios" / "e2_stop_downslope_paper_damping.yaml"
E3 = CONFIGS / "scenarios" / "e3_stop_from_turn.yaml"
E5 = CONFIGS / "scenarios" / "e5_hold_restart_uphill.yaml"
EVERY_METRIC = (Metric("stopping_distance", (("from_s", 0.7),)),
                Metric("time_to_rest", (("from_s", 0.7),)),
                Metric("creep", (("from_s", 2.0), ("to_s", 5.0))), Metric("yaw"),
                Metric("resting_forces"), Metric("holds"),
                Metric("column", column="u_mps", stat="min"),
                Metric("column", column="input_brake", stat="max"),
                Metric("column", column="ax_mps2", stat="final"))


@pytest.mark.parametrize(("path", "every"), [(E2, 1), (E3, 1), (E2, 7)])
def test_every_kept_column_is_run_scenarios_bit_for_bit(path, every):
    # 10 000 and 14 000 steps: many STREAM_ROWS chunks and a short last one; with
    # record_every 7 a chunk holds 7 x STREAM_ROWS steps and the run ends mid-chunk
    scenario = dataclasses.replace(load_scenario(path), record_every=every)
    assert scenario.n_steps // every > 2 * STREAM_ROWS and scenario.n_steps % (every * STREAM_ROWS)
    full = result_columns(run_scenario(scenario))
    kept = run_for_metrics(scenario, list(history_column_places()))
    assert set(kept.columns) == set(full)
    for name, values in full.items():
        assert np.array_equal(kept.columns[name], values), name
    assert kept.first_non_finite_s is None and kept.final_finite


def test_each_metric_kind_names_the_columns_it_reads():
    """Evaluated on only its declared columns, each metric gives what it gives on all."""
    cols = result_columns(run_scenario(load_scenario(E2)))
    assert {m.kind for m in EVERY_METRIC} == {*METRIC_KINDS, "column"}
    for metric in EVERY_METRIC:
        only = {name: cols[name] for name in metric.columns}
        # assert_equal: a figure that is NaN on both (no restart in E2) is the same figure
        np.testing.assert_equal(metric.evaluate(only), metric.evaluate(cols), err_msg=str(metric))


def test_the_holds_metric_is_the_summarys_holds_section():
    """A sweep's ``holds`` metric reports the summary's holds (issue 32: the sweep report
    has the hold and restart figures, from the one implementation): on E5 (a hold on the
    10 % grade, then a restart) the count and the worst figures are those of
    ``holds_summary`` of the same run, which ``run-scenario`` writes into summary.json."""
    from simserver.analysis.holds import holds_summary

    cols = result_columns(run_scenario(load_scenario(E5)))
    section = holds_summary(cols)["holds"]
    restarts = [h for h in section if h["rollback_m"] is not None]
    assert section and restarts  # E5 holds and restarts
    got = Metric("holds").evaluate(cols)
    assert got["holds_found"] == len(section)
    assert got["hold_creep_max_m"] == max(abs(h["creep_m"]) for h in section)
    assert got["hold_peak_speed_max_mps"] == max(h["peak_speed_mps"] for h in section)
    assert got["rollback_max_m"] == max(h["rollback_m"] for h in restarts)
    assert got["time_to_2_mps_max_s"] == max(h["time_to_2_mps_s"] for h in restarts
                                              if h["time_to_2_mps_s"] is not None)
    assert got["restart_jerk_max_mps3"] == max(h["peak_jerk_mps3"] for h in restarts)
    # and a run without a hold says so: E3 (a stop from a turn, released never) has one
    # hold at most and no restart, so its restart figures are NaN, not 0
    none = Metric("holds").evaluate(result_columns(run_scenario(load_scenario(E3))))
    assert math.isnan(none["rollback_max_m"]) and math.isnan(none["time_to_2_mps_max_s"])


def test_a_run_that_goes_non_finite_says_when_with_or_without_its_history(tmp_path,
                                                                          monkeypatch):
    """The streamed path and the full-history path report the same first non-finite time.
    The NaN is put into the recorded state at t = 3.217 s after the compiled loop (no real
    configuration goes non-finite: the config checks refuse them)."""
    real_run = Simulation.run
    t_nan = 3.217

    def run_then_break(self, inputs, states, outputs, every=1):
        real_run(self, inputs, states, outputs, every)
        hit = np.flatnonzero(np.isclose(states[:, L.TIME_S], t_nan, rtol=0.0, atol=1e-9))
        states[hit, L.U_MPS] = math.nan

    assert load_scenario(E2).duration_s > t_nan
    case = Case(index=0, base=str(E2), params={}, resolved=resolve_scenario(E2), run_id="x")
    metrics = (Metric("time_to_rest", (("from_s", 0.7),)),)
    assert run_case(case, metrics, None)["status"] == OK
    monkeypatch.setattr(Simulation, "run", run_then_break)
    streamed = run_case(case, metrics, None)
    full = run_case(case, metrics, str(tmp_path))
    assert streamed["status"] == full["status"] == NON_FINITE
    assert streamed["error"] == full["error"] == f"the run went non-finite (NaN or inf) at " \
                                                 f"t = {t_nan:g} s"
    assert streamed["metrics"] == full["metrics"]


def test_threads_of_one_worker_do_not_share_their_rows():
    """A ``dask worker`` with several threads runs several cases at once in one process:
    each thread streams through its own rows (shared ones mixed the runs' columns)."""
    from concurrent.futures import ThreadPoolExecutor

    scenarios = [load_scenario(E2), load_scenario(E3)] * 3
    names = ("time_s", "u_mps", "x_m", "fx_fl_n")
    serial = [{k: v.copy() for k, v in run_for_metrics(s, names).columns.items()}
              for s in scenarios[:2]]

    def one(scenario):
        return {k: v.copy() for k, v in run_for_metrics(scenario, names).columns.items()}

    with ThreadPoolExecutor(3) as pool:
        together = list(pool.map(one, scenarios))
    for i, cols in enumerate(together):
        for name in names:
            assert np.array_equal(cols[name], serial[i % 2][name]), (i, name)
