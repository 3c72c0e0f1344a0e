"""PNG plots of a headless run, after the figures of SAE 950311, and of tire curves.

Every plot is drawn on its own ``matplotlib.figure.Figure`` rendered by the Agg canvas:
no ``pyplot``, no global state, no display needed, so plotting is safe in any process
and thread. File names are fixed (``PLOT_FILES``) so that runs can be compared by path.

Run plots (``plot_result`` writes all six):

- ``speed.png``: body velocities u and v against time (the paper's speed traces);
- ``forces.png``: per-wheel Fx, Fy, Fz against time, with the body-frame sums;
- ``trajectory.png``: the path in the road plane, equal axes, start and end marked,
  heading arrows every few metres;
- ``slip.png``: the slip fed to the tire model per wheel, k' and tan a';
- ``inputs.png``: the driver inputs;
- ``holds.png``: each hold up close (``simserver.analysis.holds``): travel in mm and
  speed in mm/s over its creep window (a second after the stop to the release), on axes
  scaled to the hold itself, where a micrometre of creep shows (the overview's 25 m/s
  axis hides it).

``plot_comparison`` overlays chosen signals of several runs (the kinematic baseline beside
the lagged model); ``plot_pair`` overlays two histories on one time axis beside their
difference (``simserver compare``); ``plot_tire_curves`` draws a tire's characteristic
curves (the paper's Figs. 5 and 6, combined slip, aligning moment).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from simserver.adapters.history import (
    HISTORY_COLUMNS,
    column_unit,
    model_options,
    result_columns,
)
from simserver.analysis.holds import Hold, find_holds
from simserver.core import layout as L

if TYPE_CHECKING:
    from simserver.sim.scenario import ScenarioResult

WHEEL_LABELS = ("FL", "FR", "RL", "RR")
WHEEL_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red")
WHEEL_STYLES = ("-", "-", "--", "--")  # front solid, rear dashed
RUN_COLORS = ("tab:blue", "tab:red", "tab:green", "tab:purple", "tab:brown", "tab:gray")
DPI = 110
PNG_METADATA = {"Software": None}  # keep the matplotlib version out of the file

DEFAULT_COMPARISON_SIGNALS = ("u_mps", "x_m", "fx_body_sum_n")
"""Signals ``plot_comparison`` overlays unless told otherwise: speed, creep, hold force."""

# Axis labels of the signals people plot most; others get "name (unit)".
_LABELS = {
    "time_s": "time (s)",
    "x_m": "X along e1 (m)",
    "y_m": "Y along e2 (m)",
    "yaw_rad": "yaw (rad)",
    "u_mps": "u, longitudinal (m/s)",
    "v_mps": "v, lateral (m/s)",
    "yaw_rate_radps": "yaw rate (rad/s)",
    "ax_mps2": "a_x (m/s²)",
    "ay_mps2": "a_y (m/s²)",
    "fx_body_sum_n": "ΣFx, body x (N)",
    "fy_body_sum_n": "ΣFy, body y (N)",
    "fx_sum_n": "ΣFx, wheel frames (N)",
    "fy_sum_n": "ΣFy, wheel frames (N)",
    "fz_sum_n": "ΣFz (N)",
}


def signal_label(name: str) -> str:
    """Axis label for a history column: a short name and its unit.

    Parameters
    ----------
    name : str
        A name of ``history.HISTORY_COLUMNS``.

    Returns
    -------
    str
    """
    if name in _LABELS:
        return _LABELS[name]
    unit = column_unit(name)
    return name if unit == "1" else f"{name} ({unit})"


def _figure(n_rows: int, height_per_row: float = 2.3, width: float = 8.5,
            height_ratios: Sequence[float] | None = None) -> tuple[Figure, np.ndarray]:
    """A figure of ``n_rows`` stacked axes sharing the time axis (returned as (n, 1))."""
    ratios = list(height_ratios) if height_ratios is not None else [1.0] * n_rows
    fig = Figure(figsize=(width, 0.9 + height_per_row * sum(ratios)), dpi=DPI,
                 layout="constrained")
    axes = fig.subplots(n_rows, 1, sharex=True, squeeze=False,
                        gridspec_kw={"height_ratios": ratios})
    for ax in axes.flat:
        ax.grid(True, alpha=0.3)
    return fig, axes


def _title(fig: Figure, result: ScenarioResult, what: str) -> None:
    sc = result.scenario
    opts = model_options(result)
    model = ", ".join(f"{k}={opts[k]}" for k in ("slip_model", "damping_model") if k in opts)
    road = sc.scene.road
    road_text = (f"grade {road['grade_pct']:g} %, cross-slope {road['cross_slope_pct']:g} %, "
                 f"friction x{road['friction_scale']:g}")
    sub = f"{sc.scene.vehicle.name}; {road_text}" + (f"; {model}" if model else "")
    fig.suptitle(f"{sc.name}: {what}\n{sub}", fontsize=10)


def _save(fig: Figure, path: Path) -> Path:
    fig.savefig(path, format="png", metadata=PNG_METADATA)
    return path


def _legend_right(ax: Axes) -> None:
    """Legend outside the axes, on the right, so that it never hides a trace."""
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, borderaxespad=0.0)


def _time_figure(result: ScenarioResult, n_rows: int, **figure_options: object
                 ) -> tuple[dict[str, np.ndarray], Figure, np.ndarray]:
    """The history columns of ``result`` and a figure of ``n_rows`` panels against time."""
    fig, axes = _figure(n_rows, **figure_options)
    return result_columns(result), fig, axes


def _finish_time_figure(fig: Figure, axes: np.ndarray, result: ScenarioResult, what: str,
                        path: str | Path) -> Path:
    """Label the shared time axis, title the figure and write it to ``path``."""
    axes[-1, 0].set_xlabel(signal_label("time_s"))
    _title(fig, result, what)
    return _save(fig, Path(path))


def _wheel_panels(axes: np.ndarray, cols: dict[str, np.ndarray],
                  panels: Sequence[tuple[str, str, str | None, str | None]]) -> None:
    """One panel per ``(column template, y label, total column, its label)``: the four
    wheels' lines, the total (thin black; None: none), a zero line and the legend."""
    t = cols["time_s"]
    for ax, (template, ylabel, total, total_label) in zip(axes[:, 0], panels, strict=True):
        for i, wheel in enumerate(L.WHEEL_NAMES):
            ax.plot(t, cols[template.format(w=wheel)], WHEEL_STYLES[i], color=WHEEL_COLORS[i],
                    lw=1.1, label=WHEEL_LABELS[i])
        if total is not None:
            ax.plot(t, cols[total], color="k", lw=0.8, label=total_label)
        ax.axhline(0.0, color="k", lw=0.5, alpha=0.5)
        ax.set_ylabel(ylabel)
        _legend_right(ax)


def plot_speed(result: ScenarioResult, path: str | Path) -> Path:
    """Body velocities u and v against time (``PLOT_FILES``)."""
    cols, fig, axes = _time_figure(result, 2)
    for ax, name, color in zip(axes[:, 0], ("u_mps", "v_mps"), ("tab:blue", "tab:red"),
                               strict=True):
        ax.plot(cols["time_s"], cols[name], color=color, lw=1.2)
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_ylabel(signal_label(name))
    return _finish_time_figure(fig, axes, result, "body velocities", path)


def plot_forces(result: ScenarioResult, path: str | Path) -> Path:
    """Per-wheel tire forces Fx, Fy (wheel frame) and Fz against time (``PLOT_FILES``).

    The Fx and Fy panels also show the sum of the four tires along body x and y
    (thin black), the number to compare with the weight component on a slope.
    """
    cols, fig, axes = _time_figure(result, 3)
    _wheel_panels(axes, cols, (("fx_{w}_n", "Fx, wheel frame (N)", "fx_body_sum_n", "Σ body x"),
                               ("fy_{w}_n", "Fy, wheel frame (N)", "fy_body_sum_n", "Σ body y"),
                               ("fz_{w}_n", "Fz (N)", None, None)))
    return _finish_time_figure(fig, axes, result, "tire forces (ISO 8855: x forward, y left)",
                               path)


def _nice_step(raw: float) -> float:
    """The nearest 1, 2 or 5 times a power of ten at or above ``raw``."""
    if raw <= 0.0:
        return 1.0
    exp = math.floor(math.log10(raw))
    for mult in (1.0, 2.0, 5.0, 10.0):
        step = mult * 10.0**exp
        if step >= raw * 0.999:
            return step
    return 10.0 ** (exp + 1)


def heading_marks(x: np.ndarray, y: np.ndarray, n_target: int = 12) -> tuple[np.ndarray, float]:
    """Rows at which to draw heading arrows: every ``spacing`` metres of path.

    Parameters
    ----------
    x, y : ndarray
        Path in the road plane (m).
    n_target : int, optional
        About how many arrows to draw along the whole path.

    Returns
    -------
    rows : ndarray of int
        Row indices, the first row always included.
    spacing_m : float
        Path length between arrows (a 1-2-5 number, at least 0.5 m).
    """
    ds = np.hypot(np.diff(x), np.diff(y))
    s = np.concatenate(([0.0], np.cumsum(np.where(np.isfinite(ds), ds, 0.0))))
    spacing = max(0.5, _nice_step(s[-1] / n_target)) if s.size else 1.0
    marks = np.arange(0.0, s[-1] + 1e-9, spacing) if s.size else np.zeros(1)
    rows = np.unique(np.searchsorted(s, marks, side="left").clip(0, max(s.size - 1, 0)))
    return rows, spacing


def plot_trajectory(result: ScenarioResult, path: str | Path) -> Path:
    """The path in the road plane with heading arrows, start and end marked (``PLOT_FILES``)."""
    cols = result_columns(result)
    x, y, yaw = cols["x_m"], cols["y_m"], cols["yaw_rad"]
    fig = Figure(figsize=(7.5, 7.0), dpi=DPI, layout="constrained")
    ax = fig.subplots()
    ax.grid(True, alpha=0.3)
    ax.plot(x, y, color="tab:blue", lw=1.3, label="CG path")
    finite = np.isfinite(x) & np.isfinite(y)
    xf, yf = (x[finite], y[finite]) if finite.any() else (np.zeros(1), np.zeros(1))
    span = max(float(np.ptp(xf)), float(np.ptp(yf)), 5.0)
    rows, spacing = heading_marks(xf, yf)
    arrow = 0.06 * span
    yaw_f = yaw[finite] if finite.any() else np.zeros(1)
    ax.quiver(xf[rows], yf[rows], arrow * np.cos(yaw_f[rows]), arrow * np.sin(yaw_f[rows]),
              angles="xy", scale_units="xy", scale=1.0, color="tab:gray", width=0.004,
              label=f"heading, every {spacing:g} m")
    ax.plot(xf[0], yf[0], "o", color="tab:green", ms=9, label=f"start, t = {cols['time_s'][0]:g} s")
    ax.plot(xf[-1], yf[-1], "s", color="tab:red", ms=9,
            label=f"end, t = {cols['time_s'][finite][-1] if finite.any() else 0.0:g} s")
    ax.set_aspect("equal", adjustable="box")
    cx, cy = 0.5 * (xf.min() + xf.max()), 0.5 * (yf.min() + yf.max())
    half = 0.5 * span + arrow
    ax.set_xlim(cx - half, cx + half)
    ax.set_ylim(cy - half, cy + half)
    ax.set_xlabel(signal_label("x_m"))
    ax.set_ylabel(signal_label("y_m"))
    ax.legend(loc="best", fontsize=8)
    _title(fig, result, "trajectory in the road plane")
    return _save(fig, Path(path))


def plot_slip(result: ScenarioResult, path: str | Path) -> Path:
    """The slip fed to the tire model per wheel: k' and tan a' against time (``PLOT_FILES``).

    For the lagged models these are the state variables of SAE 950311 eqs. 16 and 26;
    for the kinematic baseline, the classic slips with the eq. (1) patch.
    """
    cols, fig, axes = _time_figure(result, 2)
    _wheel_panels(axes, cols, (("kappa_{w}", "k', longitudinal slip (–)", None, None),
                               ("tan_alpha_{w}", "tan a', lateral slip (–)", None, None)))
    return _finish_time_figure(
        fig, axes, result,
        "slip fed to the tire model (driving k' > 0; hub sliding left tan a' > 0)", path)


def plot_inputs(result: ScenarioResult, path: str | Path) -> Path:
    """Driver inputs against time: steering, pedals and parking brake, gear (``PLOT_FILES``)."""
    cols, fig, axes = _time_figure(result, 3, height_per_row=2.0, height_ratios=(1.0, 1.0, 0.6))
    t = cols["time_s"]
    ax_steer, ax_pedal, ax_gear = axes[:, 0]
    ax_steer.plot(t, cols["input_steer"], color="tab:purple", lw=1.2)
    ax_steer.set_ylabel("steer (–1..1, left +)")
    ax_steer.axhline(0.0, color="k", lw=0.5, alpha=0.5)
    ax_pedal.plot(t, cols["input_throttle"], color="tab:green", lw=1.2, label="throttle")
    ax_pedal.plot(t, cols["input_brake"], color="tab:red", lw=1.2, label="brake")
    ax_pedal.plot(t, cols["input_parking_brake"], color="k", lw=1.0, ls=":",
                  label="parking brake")
    ax_pedal.set_ylim(-0.05, 1.05)
    ax_pedal.set_ylabel("pedal (0..1)")
    _legend_right(ax_pedal)
    ax_gear.step(t, cols["input_gear"], where="post", color="tab:blue", lw=1.2)
    ax_gear.set_yticks(range(len(L.GEAR_NAMES)), L.GEAR_NAMES)
    ax_gear.set_ylim(-0.4, len(L.GEAR_NAMES) - 0.6)
    ax_gear.set_ylabel("gear")
    return _finish_time_figure(fig, axes, result, "driver inputs", path)


HOLDS_SHOWN = 4
"""``holds.png`` draws at most this many holds (the first ones), a column each."""


def hold_figure(cols: dict[str, np.ndarray], holds: Sequence[Hold]) -> Figure:
    """The hold panels (``plot_holds``): a column per hold, over its creep window, travel
    along the heading at the window's start (mm) above speed u (mm/s)."""
    shown = list(holds)[:HOLDS_SHOWN]
    n = max(1, len(shown))
    fig = Figure(figsize=(3.6 * n + 1.0, 5.2), dpi=DPI, layout="constrained")
    axes = fig.subplots(2, n, squeeze=False, sharex="col")
    t = cols["time_s"]
    if not shown:
        axes[0, 0].text(0.5, 0.5, "no hold in this run", ha="center", va="center",
                        transform=axes[0, 0].transAxes)
    for k, hold in enumerate(shown):
        # the creep window only: the stop's own settling (tens of micrometres) and the
        # restart's metres would set the scale and flatten the creep
        rows = (t >= hold.creep_window_s[0]) & (t <= hold.creep_window_s[1])
        w0 = int(np.flatnonzero(rows)[0])
        c, s_ = np.cos(cols["yaw_rad"][w0]), np.sin(cols["yaw_rad"][w0])
        travel_mm = 1e3 * ((cols["x_m"][rows] - cols["x_m"][w0]) * c
                           + (cols["y_m"][rows] - cols["y_m"][w0]) * s_)
        top, bottom = axes[0, k], axes[1, k]
        top.plot(t[rows], travel_mm, color="tab:blue", lw=1.1)
        bottom.plot(t[rows], 1e3 * cols["u_mps"][rows], color="tab:red", lw=1.0)
        for ax in (top, bottom):
            ax.grid(True, alpha=0.3)
            ax.ticklabel_format(axis="y", useOffset=False)
            ax.axhline(0.0, color="k", lw=0.5, alpha=0.5)
        top.set_title(f"hold {k + 1}: {hold.start_s:.2f}-{hold.end_s:.2f} s "
                      f"({hold.released_by})\ncreep {1e3 * hold.creep_m:.2e} mm"
                      + ("" if hold.rollback_m is None
                         else f", rollback {1e3 * hold.rollback_m:.2e} mm"), fontsize=8)
        bottom.set_xlabel(signal_label("time_s"))
    axes[0, 0].set_ylabel("travel along heading (mm)")
    axes[1, 0].set_ylabel("u (mm/s)")
    return fig


def plot_holds(result: ScenarioResult, path: str | Path) -> Path:
    """Each hold up close (``PLOT_FILES``, ``hold_figure``)."""
    cols = result_columns(result)
    fig = hold_figure(cols, find_holds(cols))
    fig.suptitle(f"{result.scenario.name}: each hold over its creep window", fontsize=10)
    return _save(fig, Path(path))


PLOT_FILES: dict[str, Callable[[ScenarioResult, str | Path], Path]] = {
    "speed.png": plot_speed,
    "forces.png": plot_forces,
    "trajectory.png": plot_trajectory,
    "slip.png": plot_slip,
    "inputs.png": plot_inputs,
    "holds.png": plot_holds,
}
"""File name of each run plot and the function that draws it: ``plot(result, path)`` draws
the finished run ``result`` (a ``ScenarioResult``) into the PNG file ``path`` and returns
that path."""


def plot_result(result: ScenarioResult, out_dir: str | Path) -> list[Path]:
    """Write every run plot of ``PLOT_FILES`` into ``out_dir``.

    Parameters
    ----------
    result : ScenarioResult
        A finished run.
    out_dir : str or Path
        Existing directory.

    Returns
    -------
    list of Path
        The files written, in ``PLOT_FILES`` order.
    """
    out_dir = Path(out_dir)
    return [plot(result, out_dir / name) for name, plot in PLOT_FILES.items()]


def _overlay(axes: Sequence[Axes], runs: Mapping[str, Mapping[str, np.ndarray]],
             signals: Sequence[str], time_shifts_s: Sequence[float] | None = None) -> None:
    """Draw each signal of every run (label -> history columns) on its own axes, runs in
    ``RUN_COLORS`` order, each run's time moved by its entry of ``time_shifts_s``."""
    for k, (label, cols) in enumerate(runs.items()):
        color = RUN_COLORS[k % len(RUN_COLORS)]
        style = "-" if k < len(RUN_COLORS) else "--"
        t = np.asarray(cols["time_s"], dtype=np.float64)
        if time_shifts_s is not None:
            t = t + time_shifts_s[k]
        for ax, name in zip(axes, signals, strict=True):
            ax.plot(t, cols[name], style, color=color, lw=1.2, label=label)
    for ax, name in zip(axes, signals, strict=True):
        ax.set_ylabel(signal_label(name))
        ax.axhline(0.0, color="k", lw=0.5, alpha=0.5)


def plot_comparison(
    results: dict[str, ScenarioResult],
    path: str | Path,
    signals: Sequence[str] = DEFAULT_COMPARISON_SIGNALS,
    title: str | None = None,
) -> Path:
    """Overlay the same signals from several runs, one panel per signal.

    Parameters
    ----------
    results : dict of str to ScenarioResult
        Legend label to run, drawn in this order (e.g. ``{"lagged (default)": r1,
        "kinematic baseline": r2}``).
    path : str or Path
        PNG file to write.
    signals : sequence of str, optional
        Names of ``history.HISTORY_COLUMNS``; default speed u, position x and the body-x
        force sum.
    title : str, optional
        Figure title; default names the runs' scenarios.

    Returns
    -------
    Path

    Raises
    ------
    ValueError
        No runs, no signals, or a signal that is not a history column.
    """
    if not results:
        raise ValueError("plot_comparison: no results given")
    if not signals:
        raise ValueError("plot_comparison: no signals given")
    unknown = [s for s in signals if s not in HISTORY_COLUMNS]
    if unknown:
        raise ValueError(f"plot_comparison: unknown signal(s) {unknown}; "
                         "expected names of simserver.adapters.history.HISTORY_COLUMNS")
    fig, axes = _figure(len(signals))
    _overlay(axes[:, 0], {label: result_columns(r) for label, r in results.items()}, signals)
    _legend_right(axes[0, 0])
    axes[-1, 0].set_xlabel(signal_label("time_s"))
    if title is None:
        names = sorted({r.scenario.name for r in results.values()})
        title = "comparison: " + ", ".join(names)
    fig.suptitle(title, fontsize=10)
    return _save(fig, Path(path))


def plot_pair(
    runs: Mapping[str, Mapping[str, np.ndarray]],
    shift_b_s: float,
    differences: Mapping[str, tuple[np.ndarray, np.ndarray]],
    path: str | Path,
    title: str,
) -> Path:
    """Two histories overlaid on A's time axis (left) and their difference A - B (right),
    one row per signal of ``differences`` (``simserver compare``).

    Parameters
    ----------
    runs : mapping of str to history columns
        Exactly two, A then B (legend label -> columns with ``time_s`` and the signals;
        derived signals already added).
    shift_b_s : float
        Added to B's ``time_s`` (the alignment of ``simserver.analysis.compare``).
    differences : mapping of str to (times, A - B)
        Signal name -> A's times in the common span and the difference there.
    path : str or Path
        PNG file to write.
    title : str
        Figure title.
    """
    if len(runs) != 2 or not differences:
        raise ValueError("plot_pair: expected two runs and at least one signal")
    signals = list(differences)
    fig = Figure(figsize=(12.0, 0.9 + 2.0 * len(signals)), dpi=DPI, layout="constrained")
    axes = fig.subplots(len(signals), 2, sharex=True, squeeze=False)
    for ax in axes.flat:
        ax.grid(True, alpha=0.3)
    _overlay(axes[:, 0], runs, signals, time_shifts_s=(0.0, shift_b_s))
    axes[0, 0].legend(fontsize=8, loc="best")
    for ax, name in zip(axes[:, 1], signals, strict=True):
        t, d = differences[name]
        ax.plot(t, d, "-", color="k", lw=1.0)
        ax.axhline(0.0, color="k", lw=0.5, alpha=0.5)
        ax.set_ylabel(f"A - B: {signal_label(name)}", fontsize=8)
    axes[0, 0].set_title("overlay (B on A's time axis)", fontsize=9)
    axes[0, 1].set_title("difference A - B at A's rows", fontsize=9)
    for ax in axes[-1]:
        ax.set_xlabel(signal_label("time_s"))
    fig.suptitle(title, fontsize=10)
    return _save(fig, Path(path))


# ------------------------------------------------------------------------- tire curves
def plot_tire_curves(
    curves: dict[str, np.ndarray],
    path: str | Path,
    title: str,
) -> Path:
    """Draw a tire's characteristic curves (computed by ``cli.tire_curve_data``).

    Four panels: Fy against slip angle at several loads (SAE 950311 Fig. 5), Fx against
    longitudinal slip at the same loads (its Fig. 6), combined slip (Fx solid and Fy
    dashed against kappa at several fixed slip angles, nominal load), and Mz against slip
    angle. Signs are ISO 8855 as in the model: Fy < 0 for a positive slip angle.

    Parameters
    ----------
    curves : dict of str to ndarray
        ``alpha_deg`` (n_a,), ``kappa`` (n_k,), ``loads_n`` (n_load,),
        ``combined_alpha_deg`` (n_c,), ``fy_alpha`` and ``mz_alpha`` (n_load, n_a),
        ``fx_kappa`` (n_load, n_k), ``fx_combined`` and ``fy_combined`` (n_c, n_k),
        ``combined_load_n`` (scalar array).
    path : str or Path
        PNG file to write.
    title : str
        First title line (tire file, model, friction scale).

    Returns
    -------
    Path
    """
    fig = Figure(figsize=(11.0, 8.5), dpi=DPI, layout="constrained")
    axes = fig.subplots(2, 2)
    (ax_fy, ax_fx), (ax_comb, ax_mz) = axes
    load_colors = [f"C{i}" for i in range(len(curves["loads_n"]))]
    for i, load in enumerate(curves["loads_n"]):
        label = f"Fz = {load:,.0f} N"
        ax_fy.plot(curves["alpha_deg"], curves["fy_alpha"][i], color=load_colors[i], label=label)
        ax_fx.plot(curves["kappa"], curves["fx_kappa"][i], color=load_colors[i], label=label)
        ax_mz.plot(curves["alpha_deg"], curves["mz_alpha"][i], color=load_colors[i], label=label)
    for j, alpha in enumerate(curves["combined_alpha_deg"]):
        color = f"C{j}"
        ax_comb.plot(curves["kappa"], curves["fx_combined"][j], "-", color=color,
                     label=f"Fx, α = {alpha:g}°")
        ax_comb.plot(curves["kappa"], curves["fy_combined"][j], "--", color=color,
                     label=f"Fy, α = {alpha:g}°")
    ax_fy.set(xlabel="slip angle α (deg)", ylabel="Fy (N)",
              title="lateral force, pure slip (paper Fig. 5)")
    ax_fx.set(xlabel="longitudinal slip κ (–)", ylabel="Fx (N)",
              title="longitudinal force, pure slip (paper Fig. 6)")
    load = float(np.asarray(curves["combined_load_n"]))
    ax_comb.set(xlabel="longitudinal slip κ (–)", ylabel="force (N)",
                title=f"combined slip at Fz = {load:,.0f} N")
    ax_mz.set(xlabel="slip angle α (deg)", ylabel="Mz (N m)", title="aligning moment")
    for ax in axes.flat:
        ax.grid(True, alpha=0.3)
        ax.axhline(0.0, color="k", lw=0.5, alpha=0.5)
        ax.axvline(0.0, color="k", lw=0.5, alpha=0.5)
        ax.legend(fontsize=7, loc="best")
    fig.suptitle(f"{title}\nISO 8855: κ > 0 driving, Fy < 0 for α > 0", fontsize=10)
    return _save(fig, Path(path))
