"""``simserver compare A B``: two histories overlaid on one time axis, and their differences.

A and B are run folders (``history.parquet`` and, when there, ``summary.json``, as
``run-scenario`` and ``clients/recorder.py`` write them) or ``history.parquet`` files.
The computation is ``simserver.analysis.compare`` (alignment, resampling, holds); this
module reads the inputs, refuses bad ones in one line naming the file, and writes
``DIR/compare.json``, ``DIR/compare.png`` and a short table on stdout.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

HELP = "overlay two histories (runs or live recordings) on one time axis; their differences"
DESCRIPTION = (
    "Read two run folders or history.parquet files (run-scenario's or the recorder's), "
    "align B's time on A's (--shift-b, or the first row where the inputs change), "
    "resample B linearly onto A's rows and write DIR/compare.json (per signal max |A-B|, "
    "its time and the RMS over the common span; the holds' creep, rollback and restart "
    "times of both and their differences; the summary figures' differences), "
    "DIR/compare.png (overlay and difference panels) and a table on stdout.")

COMPARE_JSON = "compare.json"
COMPARE_PNG = "compare.png"
PLOT_SIGNALS = ("u_mps", "x_m", "y_m", "yaw_rad", "fx_sum_n", "fz_sum_n")
"""Signals drawn in ``compare.png`` (when both histories have them); all of
``analysis.compare.SIGNALS`` are in ``compare.json``."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("a", type=Path, help="run folder or history.parquet (the reference)")
    parser.add_argument("b", type=Path, help="run folder or history.parquet (compared to A)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="output directory (created if missing)")
    parser.add_argument("--shift-b", type=float, default=None, metavar="S",
                        help="add S seconds to B's time_s (default: align the first row "
                             "where the inputs change)")
    for side in ("a", "b"):
        parser.add_argument(f"--segment-{side}", type=int, default=None, metavar="K",
                            help=f"use only the rows of segment K of {side.upper()} (a live "
                                 "recording: a reset or load starts a segment)")
    parser.add_argument("--no-plot", action="store_true", help="skip compare.png")


def _history_path(label: str, path: Path) -> Path:
    from simserver.adapters.history import HISTORY_FILE
    from simserver.adapters.validate import ConfigError

    if path.is_dir():
        if not (path / HISTORY_FILE).is_file():
            raise ConfigError(f"{path}: no {HISTORY_FILE} in this folder ({label})")
        return path / HISTORY_FILE
    if not path.is_file():
        raise ConfigError(f"{path}: no such file or folder ({label})")
    return path


def read_input(label: str, path: Path, segment: int | None = None
               ) -> tuple[dict[str, np.ndarray], dict | None, Path]:
    """The numeric history columns of a run folder or history file (only the rows of
    ``segment`` when given), its summary (a folder's ``summary.json``, if any; none for a
    segment) and the history's path.

    Raises
    ------
    ConfigError
        Missing or unreadable file, no ``time_s``, no rows, or a ``time_s`` that is not
        finite and increasing (a recording of several segments restarts its time).
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    from simserver.adapters.history import SUMMARY_FILE
    from simserver.adapters.validate import ConfigError

    hist = _history_path(label, path)
    try:
        table = pq.read_table(hist)
    except (pa.ArrowException, OSError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ConfigError(f"{hist}: not a readable Parquet file ({first})") from exc
    if "time_s" not in table.column_names:
        raise ConfigError(f"{hist}: no column 'time_s' (not a simserver history)")
    cols = {}
    for name, field in zip(table.column_names, table.schema, strict=True):
        if pa.types.is_integer(field.type) or pa.types.is_floating(field.type):
            cols[name] = np.asarray(table.column(name).to_numpy(zero_copy_only=False),
                                    dtype=np.float64)
    if segment is not None:
        if "segment" not in cols:
            raise ConfigError(f"{hist}: --segment-{label.lower()} {segment}: no column "
                              "'segment' (not a live recording)")
        rows = cols["segment"] == segment
        if not rows.any():
            found = ", ".join(f"{k:g}" for k in np.unique(cols["segment"]))
            raise ConfigError(f"{hist}: --segment-{label.lower()} {segment}: no such "
                              f"segment (found {found})")
        cols = {name: values[rows] for name, values in cols.items()}
    t = cols["time_s"]
    if t.size == 0:
        raise ConfigError(f"{hist}: no rows")
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise ConfigError(f"{hist}: column 'time_s' is not finite at row {bad[0]}")
    back = np.flatnonzero(np.diff(t) <= 0.0)
    if back.size:
        raise ConfigError(f"{hist}: column 'time_s' does not increase at row {back[0] + 1} "
                          f"({t[back[0]]:g} s, then {t[back[0] + 1]:g} s; a recording of "
                          f"several segments: pick one with --segment-{label.lower()})")
    summary = None
    if segment is None and path.is_dir() and (path / SUMMARY_FILE).is_file():
        try:
            summary = json.loads((path / SUMMARY_FILE).read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ConfigError(f"{path / SUMMARY_FILE}: not readable JSON ({exc})") from exc
        if not isinstance(summary, dict):
            raise ConfigError(f"{path / SUMMARY_FILE}: expected a JSON object")
    return cols, summary, hist


def _fmt(x: float | None, spec: str = ".4g") -> str:
    return "-" if x is None else format(x, spec)


def table_lines(report: dict[str, Any]) -> list[str]:
    """The stdout table of a ``compare.json`` report."""
    a, b, al = report["a"], report["b"], report["alignment"]
    span = report["common_span_s"]
    lines = [
        f"A: {a['history']} ({a['rows']} rows, {a['time_span_s'][0]:g} .. "
        f"{a['time_span_s'][1]:g} s)",
        f"B: {b['history']} ({b['rows']} rows, {b['time_span_s'][0]:g} .. "
        f"{b['time_span_s'][1]:g} s), shifted by {al['shift_b_s']:+g} s ({al['how']})",
        f"common span {span[0]:g} .. {span[1]:g} s, {report['rows']} rows of A",
        f"{'signal':<16} {'max|A-B|':>11} {'at t (s)':>10} {'RMS(A-B)':>11}",
    ]
    for name, s in report["signals"].items():
        lines.append(f"{name:<16} {_fmt(s['max_abs_diff'], '11.4g')} "
                     f"{_fmt(s['time_of_max_s'], '10.4f')} {_fmt(s['rms_diff'], '11.4g')}")
    holds = report["holds"]
    if "skipped" in holds:
        lines.append(f"holds: not compared ({holds['skipped']})")
    else:
        lines.append(f"holds: A {holds['count_a']}, B {holds['count_b']}")
        for p in holds["pairs"]:
            if p["a_minus_b"] is None:
                lines.append(f"  hold {p['index']}: only in {'A' if p['a'] else 'B'}")
                continue
            d = p["a_minus_b"]
            lines.append(
                f"  hold {p['index']}: creep A {1e3 * p['a']['creep_m']:.4g} mm, "
                f"B {1e3 * p['b']['creep_m']:.4g} mm; A-B creep {_fmt(d['creep_m'])} m, "
                f"rollback {_fmt(d['rollback_m'])} m, "
                f"time to 2 m/s {_fmt(d['time_to_2_mps_s'])} s")
    if report.get("summary") is not None:
        figs = report["summary"]["figures"]
        differ = {k: v for k, v in figs.items() if v["a_minus_b"] != 0.0}
        lines.append(f"summary figures: {len(figs)} in both, {len(differ)} differ")
    return lines


def run(args: argparse.Namespace) -> int:
    """``simserver compare``: returns 0 (1 if an output cannot be written)."""
    from simserver.adapters.validate import ConfigError
    from simserver.analysis import compare as cmp

    cols_a, summary_a, hist_a = read_input("A", args.a, args.segment_a)
    cols_b, summary_b, hist_b = read_input("B", args.b, args.segment_b)
    if args.shift_b is not None:
        if not math.isfinite(args.shift_b):
            raise ConfigError(f"--shift-b: expected a finite number of seconds, "
                              f"got {args.shift_b}")
        shift, how = float(args.shift_b), "--shift-b"
    else:
        shift, how = cmp.auto_shift_b(cols_a, cols_b)
    diffs = cmp.signal_differences(cols_a, cols_b, shift)
    t_a, t_b = cols_a["time_s"], cols_b["time_s"]
    if diffs["rows"] == 0:
        raise ConfigError(
            f"no common time span: A {hist_a} covers {t_a[0]:g} .. {t_a[-1]:g} s, B {hist_b} "
            f"shifted by {shift:+g} s covers {t_b[0] + shift:g} .. {t_b[-1] + shift:g} s")
    report: dict[str, Any] = {
        "format": "simserver.compare/1",
        "a": {"history": str(hist_a), "rows": int(t_a.size),
              "time_span_s": [float(t_a[0]), float(t_a[-1])]},
        "b": {"history": str(hist_b), "rows": int(t_b.size),
              "time_span_s": [float(t_b[0]), float(t_b[-1])]},
        "alignment": {"shift_b_s": shift, "how": how,
                      "first_input_change_s": {"a": cmp.first_input_change_s(cols_a),
                                               "b": cmp.first_input_change_s(cols_b)}},
        "common_span_s": diffs["common_span_s"],
        "rows": diffs["rows"],
        "signals": diffs["signals"],
        "missing_signals": diffs["missing"],
        "holds": cmp.hold_differences(cols_a, cols_b, shift),
        "summary": (cmp.summary_differences(summary_a, summary_b)
                    if summary_a is not None and summary_b is not None else None),
    }
    out: Path = args.out
    try:
        out.mkdir(parents=True, exist_ok=True)
        (out / COMPARE_JSON).write_text(
            json.dumps(report, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    except OSError as exc:
        from simserver.errors import CliError

        raise CliError(f"{out}: cannot write {COMPARE_JSON}: {exc.strerror}") from exc
    if not args.no_plot:
        from simserver.adapters.plots import plot_pair

        plotted = {k: diffs["diff"][k] for k in PLOT_SIGNALS if k in diffs["diff"]}
        if plotted:
            plot_pair({f"A: {hist_a.parent.name}/{hist_a.name}": cmp.with_derived(cols_a),
                       f"B: {hist_b.parent.name}/{hist_b.name}": cmp.with_derived(cols_b)},
                      shift, plotted, out / COMPARE_PNG,
                      title=f"compare: B shifted by {shift:+g} s ({how})")
    print("\n".join(table_lines(report)))
    return 0
