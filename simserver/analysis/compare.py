"""Two histories side by side: aligned time, the differences of signals and of holds.

``simserver compare A B`` (``simserver.analysis.cli``) reads the files; this module only
computes, from two mappings of history columns (``history.parquet`` of ``run-scenario``
or of ``clients/recorder.py``: the same column names, docs/history_columns.md).

**Time alignment.** B's ``time_s`` is moved by ``shift_b_s`` onto A's axis. Without an
explicit shift, ``auto_shift_b`` aligns the *first row where the inputs change* (any
``input_*`` column differs from its first row's value): a headless run starts at 0, a
live recording wherever the server's clock was, but both begin when the driver first
acts. A live recording's inputs are those of the step that ended at its row
(docs/clients.md section 5), so there the step starts one row earlier. If either history
never changes its inputs, the first rows are aligned instead.

**Resampling.** The differences are taken at A's rows inside the common time span: B is
interpolated linearly onto them, except that a B row within ``SAME_ROW_TOL_S`` of an A
row is taken as it is (two runs on the same step grid are compared row for row, with no
interpolation rounding: a run against itself gives exactly 0). Rows where either value
is not finite (a recording's ``x_m`` on a terrain, docs/clients.md section 5) are left
out and counted.

**Holds.** ``find_holds`` (``simserver.analysis.holds``) runs on both histories; the
k-th hold of A is paired with the k-th of B, and their creep, rollback and restart
times are differenced.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from simserver.analysis.holds import COLUMNS as HOLD_COLUMNS
from simserver.analysis.holds import find_holds

WHEELS = ("fl", "fr", "rl", "rr")

SIGNALS = ("u_mps", "v_mps", "x_m", "y_m", "yaw_rad", "yaw_rate_radps", "ax_mps2",
           "ay_mps2", "fx_body_sum_n", "fy_body_sum_n", "fx_sum_n", "fy_sum_n", "fz_sum_n")
"""Signals compared when both histories carry them (the ``*_sum_n`` are ``DERIVED``)."""

DERIVED = {f"{q}_sum_n": f"{q}_{{w}}_n" for q in ("fx", "fy", "fz")}
"""Derived signal -> per-wheel column pattern summed over ``WHEELS`` (wheel frames, as
the summary's ``final.fx_sum_n``; a recording has the per-wheel forces but no body sums)."""

SAME_ROW_TOL_S = 1e-9
"""A B row this close to an A row (after the shift) is taken as it is, not interpolated:
far below any step (10 us at the finest ``dt_s``), far above the rounding of a shift."""

HOLD_FIGURES = ("start_s", "end_s", "creep_m", "peak_speed_mps", "rollback_m",
                "time_to_0p5_mps_s", "time_to_2_mps_s", "peak_jerk_mps3")
"""Per-hold figures differenced (``Hold`` fields; times of B on A's axis)."""

INPUT_PREFIX = "input_"


def with_derived(cols: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``cols`` plus every ``DERIVED`` sum whose four wheel columns are present."""
    out = dict(cols)
    for name, pattern in DERIVED.items():
        wheel_cols = [pattern.format(w=w) for w in WHEELS]
        if name not in out and all(c in out for c in wheel_cols):
            out[name] = np.sum([np.asarray(out[c], dtype=np.float64) for c in wheel_cols],
                               axis=0)
    return out


RECORDING_COLUMN = "tick"
"""A history with this column is a live recording (``clients/recorder.py``): its inputs
belong to the step that *ended* at the row, one row later than a headless history's
(docs/clients.md section 5)."""


def first_input_change_s(cols: Mapping[str, np.ndarray]) -> float | None:
    """Start time of the first step whose inputs differ from the first row's, or ``None``:
    the row's time in a headless history, the row before's in a live recording
    (``RECORDING_COLUMN``)."""
    t = np.asarray(cols["time_s"], dtype=np.float64)
    lag_rows = 1 if RECORDING_COLUMN in cols else 0
    changed = np.zeros(t.size, dtype=bool)
    for name, values in cols.items():
        if name.startswith(INPUT_PREFIX) and len(values):
            v = np.asarray(values, dtype=np.float64)
            changed |= ~((v == v[0]) | (np.isnan(v) & np.isnan(v[0])))
    rows = np.flatnonzero(changed)
    return float(t[max(0, rows[0] - lag_rows)]) if rows.size else None


def auto_shift_b(a: Mapping[str, np.ndarray], b: Mapping[str, np.ndarray]
                 ) -> tuple[float, str]:
    """The shift of B's time onto A's (module docstring) and how it was found."""
    ta, tb = first_input_change_s(a), first_input_change_s(b)
    if ta is not None and tb is not None:
        return ta - tb, "first input change"
    return float(a["time_s"][0]) - float(b["time_s"][0]), "first rows (no input change)"


def resample_b(t_a: np.ndarray, t_b: np.ndarray, y_b: np.ndarray) -> np.ndarray:
    """B's values at A's times ``t_a`` (inside B's span): coinciding rows as they are,
    others linear between B's rows."""
    if t_b.size == 1:
        return np.full(t_a.shape, y_b[0])
    y = np.interp(t_a, t_b, y_b)
    j = np.clip(np.searchsorted(t_b, t_a), 1, t_b.size - 1)
    near = np.where(np.abs(t_b[j - 1] - t_a) <= np.abs(t_b[j] - t_a), j - 1, j)
    same = np.abs(t_b[near] - t_a) <= SAME_ROW_TOL_S
    y[same] = y_b[near[same]]
    return y


def common_rows(t_a: np.ndarray, t_b_on_a: np.ndarray) -> np.ndarray:
    """Indices of A's rows inside B's (shifted) time span."""
    lo = t_b_on_a[0] - SAME_ROW_TOL_S
    hi = t_b_on_a[-1] + SAME_ROW_TOL_S
    return np.flatnonzero((t_a >= lo) & (t_a <= hi))


def signal_differences(a: Mapping[str, np.ndarray], b: Mapping[str, np.ndarray],
                       shift_b_s: float, signals: Sequence[str] = SIGNALS
                       ) -> dict[str, Any]:
    """Per signal, A - B at A's rows in the common span: max ``|A-B|``, its time, RMS.

    Returns
    -------
    dict
        ``common_span_s`` ([first, last] A time compared), ``rows`` (A rows in it),
        ``signals`` (name -> ``max_abs_diff``, ``time_of_max_s``, ``rms_diff``,
        ``rows_compared``; the statistics are ``None`` when no row has both values
        finite), ``missing`` (signals one history lacks: name -> "A", "B" or "A, B"),
        and ``diff`` (name -> (A times, A-B) arrays, for the plot; not JSON).
    """
    a, b = with_derived(a), with_derived(b)
    t_a = np.asarray(a["time_s"], dtype=np.float64)
    t_b = np.asarray(b["time_s"], dtype=np.float64) + shift_b_s
    rows = common_rows(t_a, t_b)
    t = t_a[rows]
    out: dict[str, Any] = {
        "common_span_s": [float(t[0]), float(t[-1])] if t.size else None,
        "rows": int(t.size), "signals": {}, "missing": {}, "diff": {},
    }
    for name in signals:
        lacking = [side for side, cols in (("A", a), ("B", b)) if name not in cols]
        if lacking:
            out["missing"][name] = ", ".join(lacking)
            continue
        ya = np.asarray(a[name], dtype=np.float64)[rows]
        yb = resample_b(t, t_b, np.asarray(b[name], dtype=np.float64))
        d = ya - yb
        ok = np.isfinite(d)
        stats: dict[str, Any] = {"max_abs_diff": None, "time_of_max_s": None,
                                 "rms_diff": None, "rows_compared": int(ok.sum())}
        if ok.any():
            dd = np.abs(d[ok])
            k = int(np.argmax(dd))
            stats.update(max_abs_diff=float(dd[k]), time_of_max_s=float(t[ok][k]),
                         rms_diff=float(np.sqrt(np.mean(dd * dd))))
        out["signals"][name] = stats
        out["diff"][name] = (t, d)
    return out


def hold_differences(a: Mapping[str, np.ndarray], b: Mapping[str, np.ndarray],
                     shift_b_s: float) -> dict[str, Any]:
    """The holds of both (``find_holds``), paired in order, and A - B per figure.

    Returns ``{"skipped": reason}`` when a history lacks a column the hold analysis
    reads (``holds.COLUMNS``).
    """
    for side, cols in (("A", a), ("B", b)):
        lacking = [c for c in HOLD_COLUMNS if c not in cols]
        if lacking:
            return {"skipped": f"{side} has no column(s) {', '.join(lacking)}"}
    holds_a = [h.as_dict() for h in find_holds(a)]
    holds_b = [h.as_dict() for h in find_holds(b)]
    for h in holds_b:  # B's times on A's axis
        for key in ("start_s", "end_s"):
            h[key] += shift_b_s
        h["creep_window_s"] = [x + shift_b_s for x in h["creep_window_s"]]
    pairs = []
    for k in range(max(len(holds_a), len(holds_b))):
        ha = holds_a[k] if k < len(holds_a) else None
        hb = holds_b[k] if k < len(holds_b) else None
        pair: dict[str, Any] = {"index": k, "a": ha, "b": hb, "a_minus_b": None}
        if ha is not None and hb is not None:
            pair["a_minus_b"] = {
                f: (ha[f] - hb[f] if ha[f] is not None and hb[f] is not None else None)
                for f in HOLD_FIGURES}
        pairs.append(pair)
    return {"count_a": len(holds_a), "count_b": len(holds_b), "pairs": pairs}


def _numeric_leaves(obj: Any, prefix: str = "") -> dict[str, float]:
    """Dotted key -> number for every numeric (non-boolean) leaf of a JSON value."""
    out: dict[str, float] = {}
    if isinstance(obj, Mapping):
        for k, v in obj.items():
            out.update(_numeric_leaves(v, f"{prefix}{k}."))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out.update(_numeric_leaves(v, f"{prefix}{i}."))
    elif isinstance(obj, int | float) and not isinstance(obj, bool):
        out[prefix[:-1]] = float(obj)
    return out


SUMMARY_SKIPPED_SECTIONS = ("timing",)
"""Summary sections not differenced (wall-clock figures, not the run's)."""


def summary_differences(sa: Mapping[str, Any], sb: Mapping[str, Any]) -> dict[str, Any]:
    """A - B for every numeric figure both ``summary.json`` files carry (dotted keys,
    list items by index), except ``SUMMARY_SKIPPED_SECTIONS``; keys one lacks are listed."""
    la = {k: v for k, v in _numeric_leaves(sa).items()
          if k.split(".")[0] not in SUMMARY_SKIPPED_SECTIONS}
    lb = {k: v for k, v in _numeric_leaves(sb).items()
          if k.split(".")[0] not in SUMMARY_SKIPPED_SECTIONS}
    both = [k for k in la if k in lb]
    return {
        "figures": {k: {"a": la[k], "b": lb[k], "a_minus_b": la[k] - lb[k]} for k in both},
        "only_a": sorted(set(la) - set(lb)),
        "only_b": sorted(set(lb) - set(la)),
    }
