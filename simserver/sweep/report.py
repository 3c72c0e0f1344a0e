"""A sweep's summary plots (each metric against each varied parameter) and its report."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from simserver.sweep.spec import Sweep

PLOT_DIR = "plots"
REPORT_FILE = "report.md"
DPI = 110


def _numeric(values: list[Any]) -> bool:
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text.replace("*", "all")).strip("_")


JITTER = 0.012
"""Horizontal spread of the points of one parameter value, as a share of the parameter's
range: runs that differ only in another parameter without effect land on one point, and
the spread (seeded, the same each time) shows them side by side."""


def _spread(xs: list[float], groups: int) -> np.ndarray:
    """``xs`` spread evenly within +-JITTER of the range where several runs share an x
    (the same offsets for the same data: no random draw)."""
    x = np.asarray(xs, dtype=np.float64)
    span = float(np.ptp(x)) or max(abs(float(x[0])), 1.0)
    out = x.copy()
    for value in np.unique(x):
        at = np.flatnonzero(x == value)
        if at.size > 1 and groups > 1:
            out[at] += np.linspace(-JITTER, JITTER, at.size) * span
    return out


def metric_figure(sweep: Sweep, ok: list[dict[str, Any]], metric: str, parameter: str) -> Any:
    """The figure of one (metric, numeric varied parameter) over the runs ``ok``: the
    metric against the parameter, coloured by the next varied numeric parameter when there
    is one (a matplotlib Figure; the caller saves and closes it).

    The axes say what they show in words with units (``sweep.labels``). Runs that share
    the x value are spread a little sideways (``JITTER``) and drawn as translucent markers
    with a dark edge, so points that coincide (another parameter without effect) stay
    visible, each colour of the colour bar among them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from simserver.sweep.labels import metric_label, parameter_label

    numeric = [q for q in sweep.parameters
               if _numeric([r[q] for r in ok if r.get(q) is not None])]
    others = [q for q in numeric if q != parameter]
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    xs = [r[parameter] for r in ok]
    ys = [r.get(metric) for r in ok]
    marker = {"s": 26, "alpha": 0.6, "edgecolors": "0.15", "linewidths": 0.6}
    if others:
        colour_by = others[0]
        sc = ax.scatter(_spread(xs, len(ok)), ys, c=[r[colour_by] for r in ok],
                        cmap="viridis", **marker)
        fig.colorbar(sc, ax=ax, label=parameter_label(colour_by))
    else:
        ax.scatter(xs, ys, **marker)
    ax.set_xlabel(parameter_label(parameter))
    ax.set_ylabel(metric_label(metric))
    ax.set_title(f"{sweep.name}: {metric}", fontsize=10)
    ax.ticklabel_format(axis="y", useOffset=False)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    return fig


def plot_metrics(sweep: Sweep, rows: list[dict[str, Any]], metric_columns: list[str],
                 out: Path) -> list[Path]:
    """One PNG per (metric, numeric varied parameter): :func:`metric_figure` of every run
    that ended ok."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if r["status"] == "ok"]
    params = [p for p in sweep.parameters
              if ok and _numeric([r[p] for r in ok if r.get(p) is not None])]
    written: list[Path] = []
    if not ok or not params:
        return written
    (out / PLOT_DIR).mkdir(parents=True, exist_ok=True)
    for metric in metric_columns:
        if not _numeric([y for y in (r.get(metric) for r in ok) if y is not None]):
            continue
        for p in params:
            fig = metric_figure(sweep, ok, metric, p)
            path = out / PLOT_DIR / f"{_slug(metric)}__{_slug(p)}.png"
            fig.savefig(path, dpi=DPI, metadata={"Software": None})
            plt.close(fig)
            written.append(path)
    return written


def _fmt(value: float) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) \
        else f"{value:.6g}"


def write_report(sweep: Sweep, outcome: Any, plots: list[Path], out: Path) -> Path:
    """``report.md``: what ran, how fast, each metric's range, the failures, the plots."""
    rows = outcome.rows
    statuses: dict[str, int] = {}
    for r in rows:
        statuses[r["status"]] = statuses.get(r["status"], 0) + 1
    rate = 60.0 * outcome.ran / outcome.wall_time_s if outcome.wall_time_s > 0 else math.nan
    lines = [f"# Sweep `{sweep.name}`", ""]
    if sweep.description:
        lines += [sweep.description, ""]
    lines += [f"- sweep file: `{sweep.path}`",
              f"- runs: {len(rows)} in the table "
              f"({', '.join(f'{v} {k}' for k, v in statuses.items())});"
              f" {outcome.ran} run now, {outcome.skipped} already in the table",
              f"- varied: {', '.join(f'`{p}`' for p in sweep.parameters) or 'nothing'}",
              f"- {outcome.ran} runs in {outcome.wall_time_s:.1f} s on {outcome.workers} "
              f"Dask workers: {rate:.0f} runs per minute", "",
              "## Metrics (runs that ended ok)", "",
              "| metric | min | max | mean |", "|---|---|---|---|"]
    ok = [r for r in rows if r["status"] == "ok"]
    for m in outcome.metric_columns:
        vals = [float(r[m]) for r in ok if isinstance(r.get(m), (int, float))
                and not (isinstance(r[m], float) and math.isnan(r[m]))]
        if vals:
            lines.append(f"| `{m}` | {_fmt(min(vals))} | {_fmt(max(vals))} | "
                         f"{_fmt(sum(vals) / len(vals))} |")
        else:
            lines.append(f"| `{m}` | - | - | - |")
    bad = [r for r in rows if r["status"] != "ok"]
    if bad:
        lines += ["", "## Runs that did not end ok", "", "| case | base | status | error |",
                  "|---|---|---|---|"]
        for r in bad:
            error = str(r["error"]).replace("|", "\\|").replace("\n", " ")
            lines.append(f"| {r['case']} | {r['base']} | {r['status']} | {error} |")
    if plots:
        lines += ["", "## Plots", ""]
        lines += [f"![{p.stem}]({p.relative_to(out)})" for p in plots]
    path = out / REPORT_FILE
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
