"""Stops, holds and restarts read from a history (``simserver.analysis.holds``, issue 32):
the summary's figures against a closed form and against an independent reading of
``history.parquet`` written by the real ``run-scenario``."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pyarrow.parquet as pq
import pytest

from simserver.analysis.holds import CREEP_SETTLE_S, find_holds
from simserver.core.layout import GEAR_D, GEAR_R
from simserver.testing import CONFIGS, REPO

pytestmark = pytest.mark.timeout(300)


def _history(t, u, brake, throttle, gear):
    """Columns of a straight run along +X (yaw 0): x integrated exactly from a piecewise
    linear u (trapezoids), ax its slope."""
    x = np.concatenate(([0.0], np.cumsum(0.5 * (u[1:] + u[:-1]) * np.diff(t))))
    return {"time_s": t, "x_m": x, "y_m": np.zeros_like(t), "yaw_rad": np.zeros_like(t),
            "u_mps": u, "ax_mps2": np.gradient(u, t), "input_brake": brake,
            "input_throttle": throttle, "input_parking_brake": np.zeros_like(t),
            "input_gear": gear}


def test_a_hold_and_a_reverse_restart_against_the_closed_form():
    """At rest from 1 s to 5 s creeping at 0.2 mm/s; brake released at 5 s in reverse:
    the car first rolls forward (against R) gaining 0.2 m/s^2 for 0.1 s, then reverses at
    1 m/s^2. u is piecewise linear with its kinks on the 5 ms rows, so x (trapezoids) is
    exact at the rows."""
    t = np.round(np.arange(0.0, 9.0 + 1e-9, 0.005), 9)
    tau = t - 5.0
    u = np.where(t < 1.0, 1.0 - t, 2e-4)  # comes to rest at 1 s
    u = np.where(tau > 0.0, 2e-4 + 0.2 * np.minimum(tau, 0.1) - np.maximum(tau - 0.1, 0.0), u)
    brake = np.where(t <= 5.0, 0.5, 0.0)
    cols = _history(t, u, brake, np.zeros_like(t), np.full_like(t, float(GEAR_R)))
    (hold,) = find_holds(cols)
    stop = t[np.argmax(np.abs(u) < 1e-3)]
    assert hold.start_s == stop and hold.end_s == 5.0 and hold.released_by == "driver"
    assert hold.creep_window_s == (pytest.approx(stop + CREEP_SETTLE_S), 5.0)
    # 0.2 mm/s over the window, exactly (x is the trapezoid of a constant)
    assert hold.creep_m == pytest.approx(2e-4 * (5.0 - stop - CREEP_SETTLE_S), rel=1e-9)
    assert hold.peak_speed_mps == pytest.approx(2e-4)
    # forward travel until u = 0 at tau = 0.1202 s: the integral of u, 1.22402 mm; the
    # rows see it to within 0.5 |du/dt| dt^2 ~ 1e-8 m (the crossing between two rows)
    assert hold.rollback_m == pytest.approx(2e-5 + 0.001 + 0.5 * 0.0202 ** 2, abs=5e-8)
    # reverse speeds at tau = 0.6202 s and 2.1202 s: the next rows (5.625, 7.125 s), timed
    # from the first released row (5.005 s)
    assert hold.time_to_0p5_mps_s == pytest.approx(0.62, abs=1e-9)
    assert hold.time_to_2_mps_s == pytest.approx(2.12, abs=1e-9)
    # ax (central differences) steps 0.2 -> -0.4 -> -1.0 m/s^2 over the kink's rows
    assert hold.peak_jerk_mps3 == pytest.approx(0.6 / 0.005, rel=1e-6)


def test_no_release_in_drive_and_a_pass_through_zero_is_no_hold():
    t = np.round(np.arange(0.0, 4.0 + 1e-9, 0.005), 9)
    u = 1.0 - t  # through zero at 1 s without stopping: no hold
    cols = _history(t, u, np.full_like(t, 0.5), np.zeros_like(t), np.full_like(t, GEAR_D))
    assert find_holds(cols) == []
    u = np.maximum(1.0 - t, 0.0)  # stops at 1 s and stays to the end, brake on
    (hold,) = find_holds(_history(t, u, np.full_like(t, 0.5), np.zeros_like(t),
                                  np.full_like(t, GEAR_D)))
    assert hold.released_by == "end" and hold.rollback_m is None and hold.creep_m == 0.0


def test_run_scenario_e5_summary_agrees_with_the_history(tmp_path):
    """The real ``run-scenario`` on E5 (uphill, released with throttle at 66 s): the
    summary's creep and rollback equal an independent reading of ``history.parquet``
    (to the summary's 7 significant digits), and the hold panel's travel axis spans
    micrometres, so the creep shows."""
    out = tmp_path / "e5"
    subprocess.run([sys.executable, "-m", "simserver", "run-scenario",
                    str(CONFIGS / "scenarios" / "e5_hold_restart_uphill.yaml"), "--out",
                    str(out)], cwd=REPO, check=True, capture_output=True, timeout=240)
    (hold,) = json.loads((out / "summary.json").read_text())["holds"]["holds"]
    h = pq.read_table(out / "history.parquet").to_pydict()
    t, x, u = (np.asarray(h[k]) for k in ("time_s", "x_m", "u_mps"))
    brake = np.asarray(h["input_brake"])
    # the scenario file: brake 0.5 until 66.0 s, then released with throttle 0.5
    release = int(np.flatnonzero((t > 60.0) & (brake < 0.02))[0])
    last_held = release - 1
    moving_before = np.flatnonzero((t < t[last_held]) & (np.abs(u) >= 1e-3))
    stop = moving_before[-1] + 1
    w0 = int(np.flatnonzero(t >= t[stop] + 1.0 - 1e-9)[0])
    assert hold["start_s"] == pytest.approx(t[stop], abs=1e-9)
    assert hold["creep_window_s"] == [pytest.approx(t[w0]), pytest.approx(t[last_held])]
    assert hold["creep_m"] == pytest.approx(x[last_held] - x[w0], rel=1e-6, abs=1e-15)
    moving = np.flatnonzero((t >= t[release]) & (u >= 0.5))[0]
    rollback = max(0.0, -(np.min(x[last_held:moving + 1]) - x[last_held]))
    assert hold["rollback_m"] == pytest.approx(rollback, rel=1e-6, abs=1e-15)
    assert hold["time_to_0p5_mps_s"] == pytest.approx(t[moving] - t[release], abs=1e-9)
    assert abs(hold["creep_m"]) < 1e-5  # the headline: it holds (hundredths of a mm)
    assert (out / "holds.png").stat().st_size > 0


def test_the_hold_panel_shows_a_micrometre():
    """The travel axis of a hold creeping 2 um spans micrometres, not the stop's metres."""
    from simserver.adapters.plots import hold_figure

    t = np.round(np.arange(0.0, 10.0 + 1e-9, 0.005), 9)
    u = np.where(t < 1.0, 1.0 - t, 0.0)
    u[(t > 4.0) & (t < 5.0)] = 2e-6  # 2 um over a second of the hold
    cols = _history(t, u, np.full_like(t, 0.5), np.zeros_like(t), np.full_like(t, GEAR_D))
    fig = hold_figure(cols, find_holds(cols))
    low, high = fig.axes[0].get_ylim()
    assert 2e-3 <= high - low < 2e-2  # mm: the 2 um (0.002 mm) fills most of the axis
