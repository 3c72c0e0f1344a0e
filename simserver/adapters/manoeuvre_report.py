"""A standard manoeuvre's report beside its summary: ``manoeuvre.md`` and ``manoeuvre.png``.

``simserver run-scenario`` calls :func:`write_manoeuvre_outputs` when the scenario names an
``analysis`` (``simserver.analysis.manoeuvres``): the Markdown report lists the figures
and each criterion with its limit, result and source; the plot shows what the figures
are read from (the response with its 90 % marks, the understeer line and its fit, the
yaw-rate ratios' instants, the rollback and creep on axes scaled to them). Drawn on
``matplotlib.figure.Figure`` with the Agg canvas, as ``simserver.adapters.plots``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from simserver.adapters.plots import DPI, PNG_METADATA, RUN_COLORS
from simserver.analysis.manoeuvres import G_MPS2, report_markdown

REPORT_FILE = "manoeuvre.md"
PLOT_FILE = "manoeuvre.png"

Cols = Mapping[str, np.ndarray]


def write_manoeuvre_outputs(out: Path, title: str, sections: Mapping[str, Mapping[str, Any]],
                            cols: Mapping[str, Cols], plots: bool = True) -> list[str]:
    """Write the report (and, with ``plots``, the plot) of the cars' ``manoeuvre``
    sections (``sections[car_id]``, their histories ``cols[car_id]``); the names written."""
    (out / REPORT_FILE).write_text(report_markdown(title, sections) + "\n")
    written = [REPORT_FILE]
    if plots:
        fig = manoeuvre_figure(title, sections, cols)
        fig.savefig(out / PLOT_FILE, format="png", metadata=PNG_METADATA)
        written.append(PLOT_FILE)
    return written


def _axes(n: int, title: str, ncols: int = 1) -> tuple[Figure, np.ndarray]:
    nrows = -(-n // ncols)
    fig = Figure(figsize=(8.5 if ncols == 1 else 11.0, 0.9 + 2.6 * nrows), dpi=DPI,
                 layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for ax in axes:
        ax.grid(True, alpha=0.3)
    fig.suptitle(title, fontsize=10)
    return fig, axes


def manoeuvre_figure(title: str, sections: Mapping[str, Mapping[str, Any]],
                     cols: Mapping[str, Cols]) -> Figure:
    """The plot of a manoeuvre (one kind for every car of the run)."""
    kind = next(iter(sections.values()))["analysis"]
    if kind == "fmvss126_sine_with_dwell" and len(sections) > 1:
        return _swd_series(title, sections)
    if kind == "iso3888_2_double_lane_change":
        return _dlc(title, sections, cols)
    if kind not in ("hill_start", "fmvss105_parking_brake") and len(sections) > 1:
        first = next(iter(sections))  # a one-car plot: the first car's
        return _DRAW[kind](f"{title} (car {first}, the first of {len(sections)})",
                           {first: sections[first]}, cols)
    return _DRAW[kind](title, sections, cols)


def _fit_line(ax: Any, x0: float, x1: float, slope: float, y_at: float, x_at: float,
              label: str) -> None:
    xs = np.array([x0, x1])
    ax.plot(xs, y_at + slope * (xs - x_at), "k--", lw=1.0, label=label)


def _iso4138(title: str, sections: Mapping[str, Any], cols: Mapping[str, Cols]) -> Figure:
    (cid, m), = sections.items()
    c, f = cols[cid], m["figures"]
    fig, axes = _axes(4, f"{title}: {m['standard']} steady-state circular", ncols=2)
    ay = c["ay_mps2"]
    speed = np.hypot(c["u_mps"], c["v_mps"])
    lo, hi = f["ay_fit_mps2"]
    keep = speed > 0.1
    with np.errstate(divide="ignore", invalid="ignore"):
        excess = np.degrees(c["steering_wheel_angle_rad"] / f["steering_ratio"]
                            - f["wheelbase_m"] * c["yaw_rate_radps"] / speed)
    panels = (
        ("understeer: delta - L/R (deg)", excess, "understeer_gradient_deg_per_mps2"),
        ("steering-wheel angle (deg)", np.degrees(c["steering_wheel_angle_rad"]),
         "steering_wheel_angle_gradient_deg_per_mps2"),
        ("sideslip beta (deg)", np.degrees(np.arctan2(c["v_mps"], np.abs(c["u_mps"]))),
         "sideslip_gradient_deg_per_mps2"),
        ("roll (deg)", np.degrees(c["roll_rad"]), "roll_gradient_deg_per_mps2"),
    )
    for ax, (label, y, key) in zip(axes, panels, strict=True):
        ax.plot(ay[keep], y[keep], lw=1.0)
        sel = keep & (ay >= lo) & (ay <= hi)
        if sel.any() and f.get(key) is not None:
            _fit_line(ax, 0.0, hi * 2.0, f[key], float(np.mean(y[sel])), float(np.mean(ay[sel])),
                      f"{f[key]:.4g} deg/(m/s²) over {lo:g}-{hi:g} m/s²")
            ax.legend(fontsize=8, loc="upper left")
        ax.set_xlabel("lateral acceleration a_y (m/s²)")
        ax.set_ylabel(label)
    return fig


def _iso7401(title: str, sections: Mapping[str, Any], cols: Mapping[str, Cols]) -> Figure:
    (cid, m), = sections.items()
    c, f = cols[cid], m["figures"]
    fig, axes = _axes(3, f"{title}: {m['standard']} step steer")
    t = c["time_s"] - f["t50_s"]
    axes[0].plot(t, np.degrees(c["steering_wheel_angle_rad"]))
    axes[0].set_ylabel("steering-wheel angle (deg)")
    for ax, col, scale, name, unit in ((axes[1], "yaw_rate_radps", math.degrees(1.0),
                                        "yaw_rate", "deg/s"),
                                       (axes[2], "ay_mps2", 1.0, "ay", "m/s²")):
        steady = f[f"{name}_steady_degps" if name == "yaw_rate" else "ay_steady_mps2"]
        ax.plot(t, scale * c[col], label=name)
        ax.axhline(steady, color="k", lw=0.8, ls="--", label="steady")
        ax.axhline(0.9 * steady, color="tab:green", lw=0.8, ls=":", label="90 %")
        tr, tp = f[f"{name}_response_time_s"], f[f"{name}_peak_response_time_s"]
        if tr is not None:
            ax.axvline(tr, color="tab:green", lw=0.8)
            ax.annotate(f"T90 {tr:.3f} s", (tr, 0.9 * steady), fontsize=8,
                        xytext=(5, -15), textcoords="offset points")
        ax.axvline(tp, color="tab:red", lw=0.8)
        ax.annotate(f"peak {tp:.3f} s, overshoot {f[f'{name}_overshoot_pct']:.1f} %",
                    (tp, steady), fontsize=8, xytext=(5, 5), textcoords="offset points")
        ax.set_ylabel(f"{name} ({unit})")
        ax.legend(fontsize=8, loc="lower right")
    for ax in axes:
        ax.axvline(0.0, color="0.5", lw=0.6)
        ax.set_xlim(-0.5, min(4.0, float(t[-1])))
    axes[-1].set_xlabel("time from 50 % steering (s)")
    return fig


def _sis(title: str, sections: Mapping[str, Any], cols: Mapping[str, Cols]) -> Figure:
    (cid, m), = sections.items()
    c, f = cols[cid], m["figures"]
    fig, axes = _axes(1, f"{title}: {m['standard']} slowly increasing steer")
    ax = axes[0]
    ax.plot(np.degrees(np.abs(c["steering_wheel_angle_rad"])), np.abs(c["ay_mps2"]) / G_MPS2,
            label="run")
    if f.get("A_deg") is not None:
        xs = np.array([0.0, 2.0 * f["A_deg"]])
        ax.plot(xs, 0.3 + f["ay_per_deg_g"] * (xs - f["A_deg"]), "k--", lw=1.0,
                label="fit over 0.1-0.375 g")
        ax.plot([f["A_deg"]], [0.3], "ro", label=f"A = {f['A_deg']:.2f} deg at 0.3 g")
    ax.set_xlabel("steering-wheel angle (deg)")
    ax.set_ylabel("lateral acceleration (g)")
    ax.legend(fontsize=8)
    return fig


def _swd(title: str, sections: Mapping[str, Any], cols: Mapping[str, Cols]) -> Figure:
    (cid, m), = sections.items()
    c, f = cols[cid], m["figures"]
    fig, axes = _axes(3, f"{title}: {m['standard']} sine with dwell")
    t = c["time_s"]
    axes[0].plot(t, np.degrees(c["steering_wheel_angle_rad"]))
    axes[0].set_ylabel("steering-wheel angle (deg)")
    r = np.degrees(c["yaw_rate_radps"])
    axes[1].plot(t, r)
    peak = f["yaw_rate_peak_degps"]
    sign = -1.0 if np.degrees(c["steering_wheel_angle_rad"])[np.argmax(
        np.abs(c["steering_wheel_angle_rad"]) >= math.radians(5.0))] > 0 else 1.0
    axes[1].plot([f["yaw_rate_peak_s"]], [sign * peak], "ro", label=f"first peak {peak:.1f} deg/s")
    if f["cos_s"] is not None:
        for after, limit, key in ((1.0, 0.35, "yaw_rate_ratio_1p0_s_pct"),
                                  (1.75, 0.20, "yaw_rate_ratio_1p75_s_pct")):
            tt = f["cos_s"] + after
            axes[1].plot([tt, tt], [0.0, sign * limit * peak], lw=3, alpha=0.5,
                         label=f"limit {100 * limit:g} % at COS+{after:g} s: "
                               f"{_pct(f[key])}")
        axes[1].axvline(f["cos_s"], color="0.5", lw=0.6)
    axes[1].set_ylabel("yaw rate (deg/s)")
    axes[1].legend(fontsize=8)
    if f["bos_s"] is not None:
        k0 = int(np.searchsorted(t, f["bos_s"]))
        yaw0 = c["yaw_rad"][k0]
        lat = (-(c["x_m"] - c["x_m"][k0]) * math.sin(yaw0)
               + (c["y_m"] - c["y_m"][k0]) * math.cos(yaw0))
        axes[2].plot(t, -sign * lat)
        axes[2].axvline(f["bos_s"] + 1.07, color="tab:green", lw=0.8,
                        label=f"BOS+1.07 s: {_num(f['lateral_displacement_1p07_s_m'])} m")
        axes[2].axhline(1.83, color="tab:red", lw=0.8, ls="--", label="1.83 m")
        axes[2].legend(fontsize=8)
    axes[2].set_ylabel("lateral displacement (m)")
    axes[2].set_xlabel("time (s)")
    return fig


def _swd_series(title: str, sections: Mapping[str, Any]) -> Figure:
    """Both series of a sine with dwell: each run's figures against its amplitude."""
    fig, axes = _axes(2, f"{title}: FMVSS 126 sine with dwell, every run")
    for k, side in enumerate(("left first", "right first")):
        runs = [m["figures"] for m in sections.values()
                if (m["figures"]["steer_sign_change_s"] is not None)
                and _first_left(m) == (k == 0)]
        runs.sort(key=lambda f: f["amplitude_deg"])
        amp = [f["amplitude_deg"] for f in runs]
        style = dict(color=RUN_COLORS[k], ls="-" if k == 0 else "--", marker="o", ms=3)
        axes[0].plot(amp, [_nan(f["yaw_rate_ratio_1p0_s_pct"]) for f in runs],
                     label=f"{side}: at COS+1.0 s", **style)
        axes[0].plot(amp, [_nan(f["yaw_rate_ratio_1p75_s_pct"]) for f in runs],
                     label=f"{side}: at COS+1.75 s", alpha=0.5, **style)
        axes[1].plot(amp, [_nan(f["lateral_displacement_1p07_s_m"]) for f in runs],
                     label=side, **style)
    axes[0].axhline(35.0, color="tab:red", lw=0.8, label="limit 35 % (S5.2.1)")
    axes[0].axhline(20.0, color="tab:orange", lw=0.8, label="limit 20 % (S5.2.2)")
    axes[0].set_ylabel("yaw rate / first peak (%)")
    axes[0].legend(fontsize=7)
    axes[1].axhline(1.83, color="tab:red", lw=0.8, label="1.83 m (S5.2.3)")
    axes[1].set_ylabel("lateral displacement at BOS+1.07 s (m)")
    axes[1].set_xlabel("steering amplitude (deg)")
    axes[1].legend(fontsize=7)
    return fig


def _first_left(m: Mapping[str, Any]) -> bool:
    """Whether a sine-with-dwell run turned left first (its first lobe before the sign
    change: the id says it too, but the figures are what was run)."""
    return bool(m["figures"].get("first_left", True))


def _nan(value: float | None) -> float:
    return float("nan") if value is None else float(value)


def _pct(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.1f} %"


def _num(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3f}"


def _hill_start(title: str, sections: Mapping[str, Any], cols: Mapping[str, Cols]) -> Figure:
    fig, axes = _axes(2, f"{title}: hill start (rollback, time to 2 m/s)")
    for k, (cid, m) in enumerate(sections.items()):
        c, f = cols[cid], m["figures"]
        if f.get("release_s") is None:
            continue
        t = c["time_s"]
        k0 = int(np.searchsorted(t, f["release_s"]))
        way = -1.0 if f["gear"] == "R" else 1.0
        yaw0 = c["yaw_rad"][k0]
        travel = way * ((c["x_m"] - c["x_m"][k0]) * math.cos(yaw0)
                        + (c["y_m"] - c["y_m"][k0]) * math.sin(yaw0))
        colour = RUN_COLORS[k % len(RUN_COLORS)]
        label = f"{cid}: rollback {1e3 * f['rollback_m']:.3g} mm, 2 m/s after " \
                f"{_num(f['time_to_2_mps_s'])} s"
        axes[0].plot(t - t[k0], 1e3 * travel, color=colour, label=label)
        axes[1].plot(t - t[k0], way * c["u_mps"], color=colour)
    axes[0].set_ylim(-50.0, 200.0)
    axes[0].set_ylabel("travel in the gear's direction (mm)")
    axes[0].legend(fontsize=8)
    axes[1].axhline(2.0, color="k", lw=0.8, ls="--")
    axes[1].set_ylabel("speed in the gear's direction (m/s)")
    axes[1].set_xlabel("time from the brake release (s)")
    for ax in axes:
        ax.set_xlim(-1.0, None)
    return fig


def _fmvss105(title: str, sections: Mapping[str, Any], cols: Mapping[str, Cols]) -> Figure:
    fig, axes = _axes(2, f"{title}: FMVSS 105 parking brake on a 30 % grade")
    for k, (cid, m) in enumerate(sections.items()):
        c, f = cols[cid], m["figures"]
        if f.get("hold_start_s") is None:
            continue
        t = c["time_s"]
        k0 = int(np.searchsorted(t, f["hold_start_s"]))
        yaw0 = c["yaw_rad"][k0]
        travel = ((c["x_m"] - c["x_m"][k0]) * math.cos(yaw0)
                  + (c["y_m"] - c["y_m"][k0]) * math.sin(yaw0))
        colour = RUN_COLORS[k % len(RUN_COLORS)]
        axes[0].plot(t[k0:], 1e3 * travel[k0:], color=colour,
                     label=f"{cid}: travel {f['travel_mm']:.3g} mm, creep after the settle "
                           f"{f['creep_mm']:.3g} mm")
        axes[1].plot(t[k0:], 1e3 * c["u_mps"][k0:], color=colour)
    axes[0].set_ylabel("travel along the heading (mm)")
    axes[0].legend(fontsize=8)
    axes[1].set_ylabel("u (mm/s)")
    axes[1].set_yscale("symlog", linthresh=1e-3)
    axes[1].set_xlabel("time (s)")
    return fig


def _dlc(title: str, sections: Mapping[str, Any], cols: Mapping[str, Cols]) -> Figure:
    """Every run's body box corners' outline on the track (track frame) over the cone
    lines, struck runs dashed; beside it, each run's result against its entry speed."""
    from simserver.analysis.manoeuvres import body_corners, dlc_lanes

    first = next(iter(sections.values()))["figures"]
    width, front, rear = first["vehicle_width_m"], first["body_front_m"], first["body_rear_m"]
    lanes = dlc_lanes(width)
    fig, axes = _axes(2, f"{title}: ISO 3888-2 double lane change")
    ax = axes[0]
    for ln in lanes:
        for y in (ln.y_right_m, ln.y_left_m):
            ax.plot([ln.x_from_m, ln.x_to_m], [y, y], "o-", color="tab:orange", ms=3, lw=1)
    for k, (cid, m) in enumerate(sections.items()):
        c = cols[cid]
        x, y, yaw = c["x_m"], c["y_m"], c["yaw_rad"]
        c0, s0 = np.cos(yaw[0]), np.sin(yaw[0])
        dx, dy = x - x[0], y - y[0]
        run_up = m["figures"]["run_up_m"]
        xt = dx * c0 + dy * s0 - run_up
        yt = -dx * s0 + dy * c0 + lanes[0].centre_m
        corners = body_corners(xt, yt, yaw - yaw[0], front, rear, width)
        keep = (xt > -5.0) & (xt < lanes[-1].x_to_m + 5.0)
        color = RUN_COLORS[k % len(RUN_COLORS)]
        for j in range(4):
            ax.plot(corners[keep, j, 0], corners[keep, j, 1], "-" if m["passed"] else "--",
                    color=color, lw=0.7, label=f"{cid}" if j == 0 else None)
    ax.set_xlabel("along the track from the entry gate (m)")
    ax.set_ylabel("across (m)")
    ax.legend(fontsize=6, ncols=3)
    ax = axes[1]
    v = [_nan(m["figures"]["entry_speed_kmh"]) for m in sections.values()]
    ax.scatter(v, [1 if m["passed"] else 0 for m in sections.values()])
    ax.set_yticks([0, 1], ["struck", "clean"])
    ax.set_xlabel("entry speed (km/h)")
    return fig


_DRAW = {
    "iso4138_steady_state_circular": _iso4138,
    "iso7401_step_steer": _iso7401,
    "fmvss126_slowly_increasing_steer": _sis,
    "fmvss126_sine_with_dwell": _swd,
    "hill_start": _hill_start,
    "fmvss105_parking_brake": _fmvss105,
}
