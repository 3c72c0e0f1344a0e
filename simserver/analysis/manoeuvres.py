"""The standard manoeuvres' figures and pass criteria, computed from a run's history.

One function per standard (``ANALYSES``), pure numpy on the history's columns: it returns
its figures, the test conditions it checked and its criteria, each criterion with its
limit, the value, pass or fail and the clause it comes from (docs/manoeuvres.md, which
says which texts were read and which were not). A scenario names its analysis with the
``analysis`` key, a name or a mapping with options::

    analysis: iso7401_step_steer
    analysis: {name: fmvss126_sine_with_dwell, sis_angle_deg: 17.9}

and ``simserver run-scenario`` puts the result in ``summary.json`` (section
``manoeuvre``), writes ``manoeuvre.md`` beside it and a plot ``manoeuvre.png``.

Signals used (history columns, docs/history_columns.md): the steering-wheel angle
``steering_wheel_angle_rad`` (the driver's position, docs/model.md section 12), the yaw
rate, the body accelerations ``ay_mps2``, ``ax_mps2`` (the CG's, without gravity: what a
levelled accelerometer reads), ``u_mps``, ``v_mps``, ``roll_rad`` and the plane pose
``x_m``, ``y_m``, ``yaw_rad``.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from simserver.adapters.validate import ConfigError, check_keys, number
from simserver.analysis.holds import find_holds

G_MPS2 = 9.80665
"""Standard gravity: the g of the regulations' limits (0.3 g, 0.1-0.375 g)."""

Cols = Mapping[str, np.ndarray]


@dataclass(frozen=True)
class Car:
    """What an analysis needs of the car beyond its history."""

    wheelbase_m: float
    steering_ratio: float
    mass_kg: float
    # the body box (the viewer's lower body box and the driver's default overhangs): CG
    # to front and rear bumper along the car, width; 0 where not known
    front_m: float = 0.0
    rear_m: float = 0.0
    width_m: float = 0.0


BODY_OVERHANG_M = 0.85
"""Bumper beyond the axle, front and rear: the viewer's body box and the driver's default
(``core.driver`` ``front_overhang_m``, ``rear_overhang_m``)."""
BODY_WIDTH_BEYOND_TRACK_M = 0.2
"""Body width over the wider track: the viewer's body box (``rerun_scene.body_boxes``)."""


def car_facts(vp: np.ndarray) -> Car:
    """The ``Car`` of packed vehicle parameters (``simserver.core.params``)."""
    from simserver.core import params as P

    return Car(wheelbase_m=float(vp[P.VP_CG_TO_FRONT_AXLE_M] + vp[P.VP_CG_TO_REAR_AXLE_M]),
               steering_ratio=float(vp[P.VP_STEERING_RATIO]),
               mass_kg=float(vp[P.VP_MASS_KG]),
               front_m=float(vp[P.VP_CG_TO_FRONT_AXLE_M]) + BODY_OVERHANG_M,
               rear_m=float(vp[P.VP_CG_TO_REAR_AXLE_M]) + BODY_OVERHANG_M,
               width_m=max(float(vp[P.VP_TRACK_FRONT_M]), float(vp[P.VP_TRACK_REAR_M]))
               + BODY_WIDTH_BEYOND_TRACK_M)


def criterion(name: str, value: float | None, limit: float, sense: str, source: str,
              unit: str = "") -> dict[str, Any]:
    """One pass/fail line: ``value`` against ``limit`` (``sense`` ``"<="`` or ``">="``);
    a value that could not be computed (``None``, NaN) fails."""
    ok = value is not None and math.isfinite(value) and (
        value <= limit if sense == "<=" else value >= limit)
    return {"name": name, "value": value, "limit": limit, "sense": sense, "unit": unit,
            "passed": bool(ok), "source": source}


def _result(standard: str, method: str, figures: dict[str, Any],
            criteria: list[dict[str, Any]], note: str = "") -> dict[str, Any]:
    return {"standard": standard, "method": method, "figures": figures,
            "criteria": criteria, "passed": all(c["passed"] for c in criteria),
            "note": note}


def _slope(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Least-squares slope and intercept of ``y`` on ``x``."""
    a = np.vstack([x, np.ones_like(x)]).T
    (slope, icept), *_ = np.linalg.lstsq(a, y, rcond=None)
    return float(slope), float(icept)


def _crossing(t: np.ndarray, y: np.ndarray, level: float, start: int = 0) -> float | None:
    """First time at or after row ``start`` that ``y`` reaches ``level`` from below,
    linearly interpolated between rows; ``None`` if never."""
    above = np.flatnonzero(y[start:] >= level)
    if above.size == 0:
        return None
    k = start + int(above[0])
    if k == 0 or y[k - 1] >= level:
        return float(t[k])
    return float(t[k - 1] + (level - y[k - 1]) * (t[k] - t[k - 1]) / (y[k] - y[k - 1]))


def _at(t: np.ndarray, y: np.ndarray, time_s: float) -> float | None:
    """``y`` linearly interpolated at ``time_s`` (``None`` outside the history)."""
    if not t[0] <= time_s <= t[-1]:
        return None
    return float(np.interp(time_s, t, y))


# ------------------------------------------------------------------- ISO 4138
def iso4138_steady_state_circular(cols: Cols, car: Car, ay_fit_min_mps2: float = 0.2,
                                  ay_fit_max_mps2: float = 1.0, speed_tolerance: float = 0.02
                                  ) -> dict[str, Any]:
    """Steady-state circular driving, constant-speed method with a slow steer ramp (ISO
    4138; the speed held by ``speed_hold``). Gradients against the lateral acceleration
    ``a_y`` at low lateral acceleration, ``ay_fit_min_mps2 .. ay_fit_max_mps2`` (least
    squares over the ramp's rows; the linear range of an MF 6.1 tire, docs/manoeuvres.md
    section 1):

    - understeer gradient ``K = d(delta - L/R)/d a_y``: ``delta`` the mean road-wheel
      angle (steering-wheel angle over the overall ratio), ``1/R = r / V`` the path's
      curvature, ``L`` the wheelbase (the Ackermann angle's gradient subtracted);
    - steering-wheel angle gradient ``d delta_H / d a_y``;
    - sideslip gradient ``d beta / d a_y`` (``beta = atan(v / u)`` at the CG);
    - roll gradient ``d phi / d a_y``;

    and the local understeer gradient in 1 m/s^2 bands up to the highest ``a_y`` reached.
    """
    t, ay = cols["time_s"], cols["ay_mps2"]
    u, v, r = cols["u_mps"], cols["v_mps"], cols["yaw_rate_radps"]
    speed = np.hypot(u, v)
    delta_h = cols["steering_wheel_angle_rad"]
    delta = delta_h / car.steering_ratio
    with np.errstate(divide="ignore", invalid="ignore"):
        curvature = np.where(speed > 0.1, r / speed, np.nan)
    beta = np.arctan2(v, np.abs(u))
    phi = cols["roll_rad"]
    lo, hi = ay_fit_min_mps2, ay_fit_max_mps2
    rows = np.flatnonzero((ay >= lo) & (ay <= hi) & np.isfinite(curvature))
    figures: dict[str, Any] = {"ay_fit_mps2": [lo, hi], "rows_fitted": int(rows.size),
                               "ay_max_mps2": float(np.max(ay)),
                               "wheelbase_m": car.wheelbase_m,
                               "steering_ratio": car.steering_ratio}
    criteria = []
    if rows.size >= 5:
        excess = delta - car.wheelbase_m * curvature
        k_rad, _ = _slope(ay[rows], excess[rows])
        figures.update(
            understeer_gradient_deg_per_mps2=math.degrees(k_rad),
            understeer_gradient_deg_per_g=math.degrees(k_rad) * G_MPS2,
            steering_wheel_angle_gradient_deg_per_mps2=math.degrees(
                _slope(ay[rows], delta_h[rows])[0]),
            sideslip_gradient_deg_per_mps2=math.degrees(_slope(ay[rows], beta[rows])[0]),
            roll_gradient_deg_per_mps2=math.degrees(_slope(ay[rows], phi[rows])[0]),
            speed_mean_mps=float(np.mean(speed[rows])),
            time_fitted_s=[float(t[rows[0]]), float(t[rows[-1]])],
        )
        bands = []
        for band_lo in np.arange(0.0, math.floor(figures["ay_max_mps2"])):
            sel = np.flatnonzero((ay >= band_lo) & (ay < band_lo + 1.0)
                                 & np.isfinite(curvature))
            if sel.size >= 5:
                bands.append({"ay_mps2": float(band_lo + 0.5), "understeer_gradient_deg_per_mps2":
                              math.degrees(_slope(ay[sel], excess[sel])[0])})
        figures["understeer_gradient_by_ay"] = bands
        drift = float(np.max(np.abs(speed[rows] / figures["speed_mean_mps"] - 1.0)))
        criteria.append(criterion(
            "speed held over the fitted rows (largest deviation from their mean)", drift,
            speed_tolerance, "<=", "ISO 4138 constant-speed method (a tolerance of the "
            "project's: the ISO text was not read)"))
    criteria.append(criterion("rows in the linear range", float(rows.size), 5.0, ">=",
                              "needed for a least-squares gradient"))
    return _result("ISO 4138", "constant speed, slowly increasing steering-wheel angle "
                   "(the speed held by the run's speed_hold)", figures, criteria,
                   "ISO 4138 is a test method: it sets no limits on the gradients; the "
                   "criteria are the test's validity conditions.")


# ------------------------------------------------------------------- ISO 7401
def _step_response(t: np.ndarray, y: np.ndarray, t50: float, steady_rows: np.ndarray
                   ) -> dict[str, float | None]:
    """Response time to 90 %, peak response time and overshoot of ``y`` (the signal's
    sign made positive) after a steering step whose 50 % point is ``t50``."""
    steady = float(np.mean(y[steady_rows]))
    sign = 1.0 if steady >= 0.0 else -1.0
    ys, steady_abs = sign * y, abs(steady)
    start = int(np.searchsorted(t, t50))
    t90 = _crossing(t, ys, 0.9 * steady_abs, start)
    k_peak = start + int(np.argmax(ys[start:steady_rows[0] + 1]))
    peak = float(ys[k_peak])
    return {"steady": steady, "response_time_s": None if t90 is None else t90 - t50,
            "peak": sign * peak, "peak_response_time_s": float(t[k_peak]) - t50,
            "overshoot_pct": 100.0 * (peak - steady_abs) / steady_abs if steady_abs else None}


def iso7401_step_steer(cols: Cols, car: Car, steady_window_s: float = 1.0,
                       steer_rise_max_s: float = 0.15) -> dict[str, Any]:
    """Step steer (ISO 7401): from the time the steering-wheel angle passes 50 % of its
    step (``t50``), the yaw rate's and the lateral acceleration's times to 90 % of their
    steady values, the times to their peaks and their overshoots; steady values are the
    means over the last ``steady_window_s`` of the run."""
    t, delta_h = cols["time_s"], cols["steering_wheel_angle_rad"]
    steady_rows = np.flatnonzero(t >= t[-1] - steady_window_s)
    step = float(np.mean(delta_h[steady_rows]))
    sign = 1.0 if step >= 0.0 else -1.0
    t10 = _crossing(t, sign * delta_h, 0.1 * abs(step))
    t50 = _crossing(t, sign * delta_h, 0.5 * abs(step))
    t90 = _crossing(t, sign * delta_h, 0.9 * abs(step))
    figures: dict[str, Any] = {"steering_wheel_step_deg": math.degrees(step), "t50_s": t50,
                               "steer_rise_10_90_s": None if t10 is None or t90 is None
                               else t90 - t10}
    criteria = [criterion("steering rise time 10-90 %", figures["steer_rise_10_90_s"],
                          steer_rise_max_s, "<=", "ISO 7401 step input (the 0.15 s bound as "
                          "commonly quoted; the ISO text was not read)", "s")]
    if t50 is not None:
        yaw = _step_response(t, cols["yaw_rate_radps"], t50, steady_rows)
        lat = _step_response(t, cols["ay_mps2"], t50, steady_rows)
        figures.update(
            yaw_rate_steady_degps=math.degrees(yaw["steady"]),
            yaw_rate_response_time_s=yaw["response_time_s"],
            yaw_rate_peak_degps=math.degrees(yaw["peak"]),
            yaw_rate_peak_response_time_s=yaw["peak_response_time_s"],
            yaw_rate_overshoot_pct=yaw["overshoot_pct"],
            ay_steady_mps2=lat["steady"],
            ay_response_time_s=lat["response_time_s"],
            ay_peak_mps2=lat["peak"],
            ay_peak_response_time_s=lat["peak_response_time_s"],
            ay_overshoot_pct=lat["overshoot_pct"],
            yaw_rate_gain_per_s=yaw["steady"] / step if step else None,
            speed_at_step_mps=_at(t, cols["u_mps"], t50),
        )
        # steady at the end: the yaw rate's spread over the window, against its mean
        r_end = cols["yaw_rate_radps"][steady_rows]
        spread = float(np.ptp(r_end) / abs(np.mean(r_end))) if np.mean(r_end) else None
        criteria.append(criterion("steady state reached (yaw-rate spread over the last "
                                  f"{steady_window_s:g} s / its mean)", spread, 0.02, "<=",
                                  "the project's reading of 'steady state'"))
    return _result("ISO 7401", "step steer, open loop, throttle held", figures, criteria,
                   "ISO 7401 is a test method: it sets no limits on the response; the "
                   "criteria are the test's validity conditions.")


# ------------------------------------------------------------------- FMVSS 126
SWD_FREQUENCY_HZ = 0.7
SWD_DWELL_S = 0.5
SIS_FIT_G = (0.1, 0.375)
SIS_AT_G = 0.3
FMVSS126 = "FMVSS 126 (49 CFR 571.126)"


def swd_amplitudes_deg(a_deg: float) -> list[float]:
    """The sine-with-dwell series' amplitudes from ``A`` (49 CFR 571.126 S7.9): 1.5 A, then
    steps of 0.5 A, none above the final run's, which is the greater of 6.5 A and 270 deg
    (300 deg if 6.5 A is above 300 deg)."""
    final = 300.0 if 6.5 * a_deg > 300.0 else max(6.5 * a_deg, 270.0)
    out = []
    k = 1.5
    while k * a_deg < final - 1e-9:
        out.append(k * a_deg)
        k += 0.5
    out.append(final)
    return out


def fmvss126_slowly_increasing_steer(cols: Cols, car: Car) -> dict[str, Any]:
    """Slowly increasing steer (49 CFR 571.126 S7.6): ``A``, the steering-wheel angle that
    gives 0.3 g, from a straight line fitted to the lateral acceleration against the
    steering-wheel angle between 0.1 and 0.375 g (the rising ramp's rows), and the
    sine-with-dwell amplitudes it sets (``swd_amplitudes_deg``)."""
    t, ay, delta_h = cols["time_s"], cols["ay_mps2"], cols["steering_wheel_angle_rad"]
    sign = 1.0 if delta_h[np.argmax(np.abs(delta_h))] >= 0.0 else -1.0
    ays = sign * ay / G_MPS2
    top = int(np.argmax(ays))  # the rising part only
    rows = np.flatnonzero((ays[:top + 1] >= SIS_FIT_G[0]) & (ays[:top + 1] <= SIS_FIT_G[1]))
    speed_kmh = 3.6 * np.hypot(cols["u_mps"], cols["v_mps"])
    figures: dict[str, Any] = {"ay_fit_g": list(SIS_FIT_G), "rows_fitted": int(rows.size)}
    criteria = []
    if rows.size >= 5:
        slope, icept = _slope(np.degrees(sign * delta_h[rows]), ays[rows])
        a_deg = (SIS_AT_G - icept) / slope
        figures.update(A_deg=a_deg, ay_per_deg_g=slope,
                       time_fitted_s=[float(t[rows[0]]), float(t[rows[-1]])],
                       swd_amplitudes_deg=swd_amplitudes_deg(a_deg),
                       swd_final_amplitude_deg=swd_amplitudes_deg(a_deg)[-1])
        worst = float(np.max(np.abs(speed_kmh[rows] - 80.0)))
        criteria.append(criterion("speed 80 +- 2 km/h over the fitted rows (largest "
                                  "deviation)", worst, 2.0, "<=", f"{FMVSS126} S7.6", "km/h"))
    criteria.append(criterion("rows between 0.1 and 0.375 g", float(rows.size), 5.0, ">=",
                              f"{FMVSS126} S7.6 (fit range)"))
    return _result(FMVSS126, "slowly increasing steer, 13.5 deg/s at 80 km/h", figures,
                   criteria)


def fmvss126_sine_with_dwell(cols: Cols, car: Car, sis_angle_deg: float | None = None
                             ) -> dict[str, Any]:
    """Sine with dwell (49 CFR 571.126 S5.2, S7.9): Beginning of Steer (BOS, the
    steering-wheel angle first past 5 deg), Completion of Steer (COS, its return to zero
    after the dwell), the first yaw-rate peak after the steering changes sign, the yaw rate
    1.0 s and 1.75 s after COS as shares of that peak (limits 35 % and 20 %, S5.2.1 and
    S5.2.2) and the lateral displacement of the CG from its straight path 1.07 s after BOS
    (at least 1.83 m at a mass up to 3500 kg, S5.2.3; required of the runs with an
    amplitude of 5 A or more, so judged when ``sis_angle_deg`` (A) is given)."""
    t, delta_h, r = cols["time_s"], cols["steering_wheel_angle_rad"], cols["yaw_rate_radps"]
    dh = np.degrees(delta_h)
    amplitude = float(np.max(np.abs(dh)))
    past = np.flatnonzero(np.abs(dh) >= 5.0)
    s1 = 1.0 if past.size and dh[past[0]] > 0.0 else -1.0  # the first lobe's direction
    opposite = np.flatnonzero(s1 * dh[past[0]:] < 0.0) if past.size else past
    if opposite.size == 0:  # no sine with dwell in this run: nothing to judge it by
        return _result(FMVSS126, "sine with dwell", {"amplitude_deg": amplitude}, [
            criterion("a steering input past 5 deg that changes sign", None, 1.0, ">=",
                      f"{FMVSS126} S7.9")])
    k_first = int(past[0])
    bos = _crossing(t, s1 * dh, 5.0)
    k_sign = k_first + int(opposite[0])  # the steering changes sign
    k_dwell_end = k_sign + int(np.flatnonzero(-s1 * dh[k_sign:] >= np.max(-s1 * dh[k_sign:])
                                              - 1e-6)[-1])
    cos_ = _crossing(t, s1 * dh, 0.0, k_dwell_end)
    figures: dict[str, Any] = {"amplitude_deg": amplitude, "first_left": s1 > 0.0,
                               "bos_s": bos, "cos_s": cos_,
                               "steer_sign_change_s": float(t[k_sign])}
    rs = -s1 * r  # the yaw rate in the second lobe's sense
    end = int(np.searchsorted(t, (cos_ if cos_ is not None else t[-1]) + 1.75))
    seg = rs[k_sign:end + 1]
    local = np.flatnonzero((seg[1:-1] >= seg[:-2]) & (seg[1:-1] > seg[2:]))
    k_peak = k_sign + (int(local[0]) + 1 if local.size else int(np.argmax(seg)))
    peak = float(rs[k_peak])
    figures.update(yaw_rate_peak_degps=math.degrees(peak), yaw_rate_peak_s=float(t[k_peak]))
    ratios = {}
    for after, limit, clause in ((1.0, 35.0, "S5.2.1"), (1.75, 20.0, "S5.2.2")):
        value = None if cos_ is None else _at(t, rs, cos_ + after)
        ratio = None if value is None or peak <= 0.0 else 100.0 * value / peak
        ratios[after] = (ratio, limit, clause)
    figures["yaw_rate_ratio_1p0_s_pct"] = ratios[1.0][0]
    figures["yaw_rate_ratio_1p75_s_pct"] = ratios[1.75][0]
    lateral = None
    if bos is not None and t[-1] >= bos + 1.07:
        yaw0 = float(np.interp(bos, t, cols["yaw_rad"]))
        x0, y0 = np.interp(bos, t, cols["x_m"]), np.interp(bos, t, cols["y_m"])
        x1, y1 = np.interp(bos + 1.07, t, cols["x_m"]), np.interp(bos + 1.07, t, cols["y_m"])
        lateral = s1 * float(-(x1 - x0) * math.sin(yaw0) + (y1 - y0) * math.cos(yaw0))
    figures["lateral_displacement_1p07_s_m"] = lateral
    criteria = [criterion(f"yaw rate {a:g} s after COS / first peak", ratios[a][0],
                          ratios[a][1], "<=", f"{FMVSS126} {ratios[a][2]}", "%")
                for a in (1.0, 1.75)]
    if sis_angle_deg is not None:
        figures["amplitude_over_A"] = amplitude / sis_angle_deg
        if amplitude >= 5.0 * sis_angle_deg - 1e-6:
            limit = 1.83 if car.mass_kg <= 3500.0 else 1.52
            criteria.append(criterion("lateral displacement 1.07 s after BOS", lateral,
                                      limit, ">=", f"{FMVSS126} S5.2.3 (mass in place of "
                                      "the GVWR)", "m"))
    return _result(FMVSS126, f"sine with dwell, {SWD_FREQUENCY_HZ:g} Hz, "
                   f"{1e3 * SWD_DWELL_S:g} ms dwell, coasting from 80 km/h", figures, criteria,
                   "no ESC in the model: this is the bare car's response")


def sine_with_dwell_steer(amplitude: float, t_s: np.ndarray) -> np.ndarray:
    """The sine-with-dwell steering-wheel angle at ``t_s`` after its start (S7.9): a
    0.7 Hz sine to its second peak (3/4 of a period), held for 500 ms, then the last
    quarter period back to zero; positive ``amplitude`` turns left first."""
    w = 2.0 * math.pi * SWD_FREQUENCY_HZ
    t_peak = 0.75 / SWD_FREQUENCY_HZ
    t_s = np.asarray(t_s, dtype=np.float64)
    phase = np.where(t_s < t_peak, t_s, np.where(t_s < t_peak + SWD_DWELL_S, t_peak,
                                                 t_s - SWD_DWELL_S))
    out = amplitude * np.sin(w * phase)
    return np.where((t_s < 0.0) | (t_s > 1.0 / SWD_FREQUENCY_HZ + SWD_DWELL_S), 0.0, out)


def sine_with_dwell_keyframes(amplitude_deg: float, wheel_max_deg: float, start_s: float,
                              every_s: float = 0.02) -> list[dict[str, float]]:
    """Steer keyframes of a sine with dwell (``sine_with_dwell_steer``) every ``every_s``
    (the linear interpolation between them is within 0.1 % of the sine at 20 ms), in the
    scenario's normalised steer (``amplitude_deg / wheel_max_deg`` at the peak)."""
    span = 1.0 / SWD_FREQUENCY_HZ + SWD_DWELL_S
    times = np.union1d(np.arange(0.0, span, every_s),
                       [0.75 / SWD_FREQUENCY_HZ, 0.75 / SWD_FREQUENCY_HZ + SWD_DWELL_S, span])
    steer = sine_with_dwell_steer(amplitude_deg / wheel_max_deg, times)
    return [{"t": round(start_s + float(tk), 6), "steer": round(float(s), 6) + 0.0}
            for tk, s in zip(times, steer, strict=True)]


SWD_SCENARIO_START_S = 1.0
SWD_SCENARIO_MULTIPLE = 6.5


def sine_with_dwell_scenario(a_deg: float, vehicle: str, wheel_max_rad: float,
                             multiple: float = SWD_SCENARIO_MULTIPLE) -> str:
    """The text of ``configs/scenarios/fmvss126_sine_with_dwell.yaml``: the run of
    amplitude ``multiple`` x ``A`` (rounded to 0.1 deg) of the series ``A`` sets, coasting
    from 80 km/h, steering from ``SWD_SCENARIO_START_S``. ``A`` comes from
    ``fmvss126_slowly_increasing_steer.yaml``'s summary (a test checks the two agree)."""
    amplitude = round(multiple * a_deg, 1)
    span = 1.0 / SWD_FREQUENCY_HZ + SWD_DWELL_S
    keys = sine_with_dwell_keyframes(amplitude, math.degrees(wheel_max_rad),
                                     SWD_SCENARIO_START_S)
    lines = [
        "# FMVSS 126 (49 CFR 571.126 S7.9) sine with dwell: coasting (throttle closed) from "
        "80 km/h,",
        f"# 0.7 Hz, 500 ms dwell at the second peak, left first; amplitude {multiple:g} A = "
        f"{amplitude:g} deg with",
        f"# A = {a_deg:.2f} deg from fmvss126_slowly_increasing_steer.yaml. Generated by",
        "# simserver.analysis.manoeuvres.sine_with_dwell_scenario (tests/test_manoeuvres.py "
        "checks it).",
        "name: fmvss126_sine_with_dwell",
        f"description: FMVSS 126 sine with dwell, {amplitude:g} deg ({multiple:g} A), from "
        "80 km/h coasting",
        f"vehicle: {vehicle}",
        "initial: {u_mps: 22.2222, relaxed: 1}",
        f"duration_s: {SWD_SCENARIO_START_S + span + 2.0:g}",
        f"analysis: {{name: fmvss126_sine_with_dwell, sis_angle_deg: {a_deg:.4f}}}",
        "inputs:",
        "  - {t: 0.0, steer: 0.0, throttle: 0.0, gear: D}",
    ]
    lines += [f"  - {{t: {k['t']:g}, steer: {k['steer']:g}}}" for k in keys]
    return "\n".join(lines) + "\n"


def sine_with_dwell_series_scenario(a_deg: float, vehicle: str, wheel_max_rad: float) -> str:
    """The text of ``configs/scenarios/fmvss126_sine_with_dwell_series.yaml``: both series
    of S7.9 at once, one car a run (``cars:``, each run as alone): left first, then right
    first, each at every amplitude of ``swd_amplitudes_deg(A)`` (rounded to 0.1 deg)."""
    span = 1.0 / SWD_FREQUENCY_HZ + SWD_DWELL_S
    wheel_max_deg = math.degrees(wheel_max_rad)
    lines = [
        "# FMVSS 126 (49 CFR 571.126 S7.9) sine with dwell, both series: left first and right",
        "# first, from 1.5 A in steps of 0.5 A to the final run (the greater of 6.5 A and "
        "270 deg),",
        f"# A = {a_deg:.2f} deg from fmvss126_slowly_increasing_steer.yaml; one car a run, "
        "each as alone",
        "# (docs/model.md section 14). Generated by",
        "# simserver.analysis.manoeuvres.sine_with_dwell_series_scenario (tests check it).",
        "name: fmvss126_sine_with_dwell_series",
        "description: FMVSS 126 sine with dwell, both series of amplitudes, from 80 km/h "
        "coasting",
        f"duration_s: {SWD_SCENARIO_START_S + span + 2.0:g}",
        f"analysis: {{name: fmvss126_sine_with_dwell, sis_angle_deg: {a_deg:.4f}}}",
        "cars:",
    ]
    k = 0
    for side, sign in (("left", 1.0), ("right", -1.0)):
        for amplitude in swd_amplitudes_deg(a_deg):
            amplitude = round(amplitude, 1)
            keys = sine_with_dwell_keyframes(sign * amplitude, wheel_max_deg,
                                             SWD_SCENARIO_START_S)
            flow = ", ".join(f"{{t: {kf['t']:g}, steer: {kf['steer']:g}}}" for kf in keys)
            wrapped = textwrap.wrap(flow, 84, break_on_hyphens=False)
            lines += [f"  - id: {side}_{amplitude:05.1f}deg".replace(".", "p"),
                      f"    vehicle: {vehicle}",
                      f"    initial: {{u_mps: 22.2222, relaxed: 1, y_m: {100.0 * k:g}}}",
                      "    inputs: [{t: 0.0, steer: 0.0, throttle: 0.0, gear: D},"]
            lines += [f"             {w}" for w in wrapped[:-1]]
            lines.append(f"             {wrapped[-1]}]")
            k += 1  # 100 m apart: a spinning car stays clear of the next
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------- hill start, FMVSS 105
def _grade_pct(cols: Cols) -> float:
    """The grade under the car (the reference plane's, docs/model.md section 11), the
    median over the run to 0.1 %: the plane fitted under a moving car wanders by a few
    thousandths of a percent."""
    return round(float(np.median(cols["ref_grade_pct"])), 1)


def hill_start(cols: Cols, car: Car, rollback_max_m: float = 0.15,
               time_to_2_mps_max_s: float = 4.0) -> dict[str, Any]:
    """Hill start: the run's first hold released by the driver
    (``simserver.analysis.holds``): rollback (the largest travel against the gear's
    direction after the release) and the time to 2 m/s in it."""
    grade = _grade_pct(cols)
    restarts = [h for h in find_holds(cols) if h.released_by == "driver"]
    figures: dict[str, Any] = {"grade_pct": grade}
    rollback = time_2 = None
    if restarts:
        h = restarts[0]
        rollback, time_2 = h.rollback_m, h.time_to_2_mps_s
        k = int(np.searchsorted(cols["time_s"], h.end_s))
        figures.update(release_s=h.end_s, rollback_m=rollback, time_to_0p5_mps_s=
                       h.time_to_0p5_mps_s, time_to_2_mps_s=time_2,
                       peak_jerk_mps3=h.peak_jerk_mps3,
                       gear="R" if int(cols["input_gear"][k]) == 1 else "D",
                       facing="uphill" if math.cos(cols["yaw_rad"][k]) * grade > 0.0
                       else "downhill")
    criteria = [
        criterion("rollback after the release", rollback, rollback_max_m, "<=",
                  "the project's (no regulation limits a car's hill-start rollback)", "m"),
        criterion("time from the release to 2 m/s", time_2, time_to_2_mps_max_s, "<=",
                  "the project's", "s")]
    return _result("hill start", "held on the foot brake from rest, the brake released and "
                   "the throttle pressed (the scenario's inputs)", figures, criteria)


def fmvss105_parking_brake(cols: Cols, car: Car, hold_min_s: float = 300.0,
                           grade_min_pct: float = 30.0, travel_max_m: float = 1e-3
                           ) -> dict[str, Any]:
    """Parking brake (49 CFR 571.105 S5.2.1): held by the parking brake alone (foot brake
    released, throttle closed) on a 30 % grade for 5 minutes. Travel is along the heading
    from the first row so held to the last, from the positions: it includes the settle,
    the tires winding up as the hold moves from the foot brake to the parking brake
    (some millimetres: the longitudinal relaxation length times the slip that carries the
    grade, docs/model.md section 3); creep is the travel after ``holds.CREEP_SETTLE_S``,
    what 'stationary' is judged on."""
    from simserver.analysis.holds import CREEP_SETTLE_S, RELEASE_BRAKE

    t = cols["time_s"]
    held = ((cols["input_parking_brake"] > 0.5) & (cols["input_brake"] < RELEASE_BRAKE)
            & (cols["input_throttle"] < RELEASE_BRAKE))
    figures: dict[str, Any] = {"grade_pct": _grade_pct(cols)}
    creep = None
    duration = 0.0
    if held.any():
        k0 = int(np.argmax(held))
        k1 = k0 + (int(np.argmax(~held[k0:])) - 1 if not held[k0:].all() else
                   len(t) - 1 - k0)
        c, s = math.cos(cols["yaw_rad"][k0]), math.sin(cols["yaw_rad"][k0])

        def along(i: int, j: int) -> float:
            return float((cols["x_m"][j] - cols["x_m"][i]) * c
                         + (cols["y_m"][j] - cols["y_m"][i]) * s)

        k_settle = min(k1, int(np.searchsorted(t, t[k0] + CREEP_SETTLE_S)))
        duration = float(t[k1] - t[k0])
        creep = along(k_settle, k1)
        figures.update(hold_start_s=float(t[k0]), hold_s=duration,
                       travel_mm=1e3 * along(k0, k1), creep_mm=1e3 * creep,
                       creep_window_s=[float(t[k_settle]), float(t[k1])],
                       peak_speed_mps=float(np.max(np.abs(cols["u_mps"][k0:k1 + 1]))),
                       facing="uphill" if c * figures["grade_pct"] > 0.0 else "downhill")
    criteria = [
        criterion("grade", figures["grade_pct"], grade_min_pct, ">=",
                  "49 CFR 571.105 S5.2.1 (30 percent grade)", "%"),
        criterion("held by the parking brake alone for", duration, hold_min_s, ">=",
                  "49 CFR 571.105 S5.2.1 (5 minutes)", "s"),
        criterion("|creep| over the hold after the settle (stationary)", None if creep is None
                  else abs(creep), travel_max_m, "<=", "49 CFR 571.105 S5.2.1 'hold the "
                  "vehicle stationary'; 1 mm after a 1 s settle is the project's reading",
                  "m")]
    return _result("FMVSS 105 (49 CFR 571.105)", "parking brake alone on a 30 % grade",
                   figures, criteria)


# ------------------------------------------------------------------- ISO 3888-2
ISO3888_2 = "ISO 3888-2 (severe lane change, obstacle avoidance)"
DLC_SECTION_LENGTHS_M = (12.0, 13.5, 11.0, 12.5, 12.0)
"""Sections 1 (entry lane) to 5 (exit lane), 61 m in all (docs/manoeuvres.md section 7)."""
DLC_OFFSET_M = 1.0  # section 3's right line: this far left of section 1's left line
DLC_EXIT_MIN_WIDTH_M = 3.0


@dataclass(frozen=True)
class DlcLane:
    """A coned lane of the track in the track's frame: x from the entry gate along the
    track, y to the left from section 1's right cone line (m)."""

    section: int
    x_from_m: float
    x_to_m: float
    y_right_m: float
    y_left_m: float

    @property
    def centre_m(self) -> float:
        return 0.5 * (self.y_right_m + self.y_left_m)


def dlc_lanes(vehicle_width_m: float) -> tuple[DlcLane, DlcLane, DlcLane]:
    """The coned lanes (sections 1, 3, 5) of the ISO 3888-2 track for a car of width
    ``W``: widths ``1.1 W + 0.25``, ``W + 1`` and ``1.3 W + 0.25`` (at least 3 m); section
    3 starts 1 m left of section 1's left line; sections 1 and 5 share their right line
    (the dimensions as commonly reproduced; the ISO text was not read)."""
    w = vehicle_width_m
    edges = np.cumsum((0.0, *DLC_SECTION_LENGTHS_M))
    w1, w3 = 1.1 * w + 0.25, w + 1.0
    w5 = max(1.3 * w + 0.25, DLC_EXIT_MIN_WIDTH_M)
    y3 = w1 + DLC_OFFSET_M
    edges = [float(e) for e in edges]
    return (DlcLane(1, edges[0], edges[1], 0.0, w1), DlcLane(3, edges[2], edges[3], y3, y3 + w3),
            DlcLane(5, edges[4], edges[5], 0.0, w5))


DLC_TRANSITIONS_M = ((-3.0, 4.0), (0.0, 2.0))
"""Where the path's two transitions start before the end of section 1 (3) and end
beyond the start of section 3 (5), in track x of the CG (m): chosen so a car of the
shipped vehicle's body box that follows the path exactly (heading along the path) clears
every cone line by 0.1 m (the kinematic check of docs/manoeuvres.md section 7); the
transitions end in the lane before the next transition starts."""


def dlc_path(vehicle_width_m: float, run_up_m: float, run_out_m: float,
             step_m: float = 0.5) -> np.ndarray:
    """The driver's path in the track's frame (``n x 2``), from ``run_up_m`` before the
    entry gate to ``run_out_m`` beyond the exit: on each lane's centre, a half-cosine
    from one centre to the next over sections 2 and 4, widened by ``DLC_TRANSITIONS_M``
    (continuous heading; the curvature steps at the ends, which the driver's preview
    smooths)."""
    l1, l3, l5 = dlc_lanes(vehicle_width_m)
    xs = [-run_up_m]
    ys = [l1.centre_m]
    for (a, b), (before, after) in zip(((l1, l3), (l3, l5)), DLC_TRANSITIONS_M, strict=True):
        x0, x1 = a.x_to_m + before, b.x_from_m + after
        n = max(2, int(math.ceil((x1 - x0) / step_m)))
        f = np.linspace(0.0, 1.0, n + 1)
        xs += list(x0 + f * (x1 - x0))
        ys += list(a.centre_m + (b.centre_m - a.centre_m) * 0.5 * (1.0 - np.cos(math.pi * f)))
    xs.append(l5.x_to_m + run_out_m)
    ys.append(l5.centre_m)
    return np.column_stack([xs, ys])


def body_corners(x_m: np.ndarray, y_m: np.ndarray, yaw_rad: np.ndarray, front_m: float,
                 rear_m: float, width_m: float) -> np.ndarray:
    """The body box's corners (``rows x 4 x 2``: front left, front right, rear right, rear
    left) in world x, y from the CG's position and the heading."""
    c, s = np.cos(yaw_rad)[:, None], np.sin(yaw_rad)[:, None]
    along = np.array([front_m, front_m, -rear_m, -rear_m])[None, :]
    side = 0.5 * width_m * np.array([1.0, -1.0, -1.0, 1.0])[None, :]
    return np.stack([x_m[:, None] + along * c - side * s,
                     y_m[:, None] + along * s + side * c], axis=-1)


def cone_strikes(corners_xy: np.ndarray, lanes: tuple[DlcLane, ...]) -> np.ndarray:
    """Per row, whether the body box (``body_corners`` in the track's frame) strikes a
    cone line: a corner beyond a lane's line (outside the lane) while within the lane's
    length (the box over the line, or beside the lane: a lane missed fails the run as a
    strike does), or a lane's end cone inside the box (a box that straddles the lane's
    end). Cones are taken as continuous lines tangent to their bases (ISO 3888-2 4.2 as
    publicly previewed): a gap between two cones is not a way through."""
    hit = np.zeros(corners_xy.shape[0], dtype=bool)
    cx, cy = corners_xy[..., 0], corners_xy[..., 1]
    for lane in lanes:
        inside_x = (cx >= lane.x_from_m) & (cx <= lane.x_to_m)
        hit |= np.any(inside_x & ((cy < lane.y_right_m) | (cy > lane.y_left_m)), axis=1)
        for x_cone in (lane.x_from_m, lane.x_to_m):
            for y_cone in (lane.y_right_m, lane.y_left_m):
                hit |= _point_in_box(corners_xy, x_cone, y_cone)
    return hit


def dlc_clearance(corners_xy: np.ndarray, lanes: tuple[DlcLane, ...]) -> float | None:
    """The least distance across the track from a body corner within a lane's length to
    that lane's cone lines (negative: beyond one); ``None`` if no corner was in a lane."""
    cx, cy = corners_xy[..., 0], corners_xy[..., 1]
    margin = []
    for lane in lanes:
        inside = (cx >= lane.x_from_m) & (cx <= lane.x_to_m)
        if inside.any():
            ys = cy[inside]
            margin.append(float(min(np.min(ys) - lane.y_right_m, lane.y_left_m - np.max(ys))))
    return min(margin) if margin else None


def _point_in_box(corners_xy: np.ndarray, px: float, py: float) -> np.ndarray:
    """Per row, whether the point is inside the convex box (corners in order)."""
    inside = np.ones(corners_xy.shape[0], dtype=bool)
    for k in range(4):
        a, b = corners_xy[:, k], corners_xy[:, (k + 1) % 4]
        cross = (b[:, 0] - a[:, 0]) * (py - a[:, 1]) - (b[:, 1] - a[:, 1]) * (px - a[:, 0])
        inside &= cross <= 0.0  # clockwise corners: inside is to the right of each edge
    return inside


def iso3888_2_double_lane_change(cols: Cols, car: Car, run_up_m: float = 60.0
                                 ) -> dict[str, Any]:
    """Double lane change on the ISO 3888-2 track, one run: the track placed with its
    entry gate ``run_up_m`` ahead of the car's start along its start heading and section
    1's centre on the start (the shipped scenarios start the car so), the body box
    (``Car.front_m``, ``rear_m``, ``width_m``) checked against the cone lines at every
    row (``cone_strikes``). Figures: the entry speed (at the gate), the exit speed, the
    first strike (time, section) and the least clearance to a cone line."""
    t, x, y, yaw = cols["time_s"], cols["x_m"], cols["y_m"], cols["yaw_rad"]
    lanes = dlc_lanes(car.width_m)
    c0, s0 = math.cos(yaw[0]), math.sin(yaw[0])
    # the track's frame: origin on section 1's right line at the entry gate
    dx, dy = x - x[0], y - y[0]
    xt = dx * c0 + dy * s0 - run_up_m
    yt = -dx * s0 + dy * c0 + lanes[0].centre_m
    corners = body_corners(xt, yt, yaw - yaw[0], car.front_m, car.rear_m, car.width_m)
    hits = cone_strikes(corners, lanes)
    speed = np.hypot(cols["u_mps"], cols["v_mps"])
    on_track = (np.max(corners[..., 0], axis=1) >= 0.0) & (
        np.min(corners[..., 0], axis=1) <= lanes[-1].x_to_m)
    figures: dict[str, Any] = {
        "vehicle_width_m": car.width_m, "body_front_m": car.front_m, "body_rear_m": car.rear_m,
        "run_up_m": run_up_m,
        "lane_widths_m": [ln.y_left_m - ln.y_right_m for ln in lanes],
        "entry_speed_kmh": _at_x(xt, 3.6 * speed, 0.0),
        "exit_speed_kmh": _at_x(xt, 3.6 * speed, lanes[-1].x_to_m),
        "cone_strikes": int(np.count_nonzero(np.diff(hits.astype(np.int8)) == 1)
                            + int(hits[0])),
    }
    if hits.any():
        k = int(np.argmax(hits))
        sec = [ln.section for ln in lanes
               if np.any((corners[k, :, 0] >= ln.x_from_m - 1e-9)
                         & (corners[k, :, 0] <= ln.x_to_m + 1e-9))]
        figures.update(first_strike_s=float(t[k]), first_strike_x_m=float(xt[k]),
                       first_strike_section=sec[0] if sec else None)
    figures["least_clearance_m"] = dlc_clearance(corners, lanes)
    reached = bool(on_track.any() and np.max(xt) >= lanes[-1].x_to_m)
    criteria = [
        criterion("the car passed the exit gate", float(reached), 1.0, ">=",
                  "ISO 3888-2 (the run is through the 61 m track)"),
        criterion("cones struck", float(figures["cone_strikes"]), 0.0, "<=",
                  "ISO 3888-2 (a run that displaces a cone is invalid; the cone lines from "
                  "the dimensions as commonly reproduced, the ISO text was not read)")]
    return _result(ISO3888_2, "built-in driver on the lanes' centres, throttle released at "
                   "the entry gate", figures, criteria,
                   "the series' figure, the highest entry speed without a strike, is in "
                   "the summary's manoeuvre_series (dlc_series)")


def _at_x(xt: np.ndarray, y: np.ndarray, x_m: float) -> float | None:
    """``y`` where the track's ``x`` first reaches ``x_m`` (``None`` if never)."""
    k = np.flatnonzero(xt >= x_m)
    if k.size == 0:
        return None
    k0 = int(k[0])
    if k0 == 0:
        return float(y[0])
    f = (x_m - xt[k0 - 1]) / (xt[k0] - xt[k0 - 1])
    return float(y[k0 - 1] + f * (y[k0] - y[k0 - 1]))


def dlc_series(sections: Mapping[str, Mapping[str, Any]]) -> dict[str, Any] | None:
    """The figure of a series of double lane changes (one car an entry speed): the highest
    entry speed of a run through the track without a cone strike, and the lowest with a
    strike; ``None`` unless every section is an ``iso3888_2_double_lane_change``."""
    if not sections or any(m.get("analysis") != "iso3888_2_double_lane_change"
                           for m in sections.values()):
        return None
    runs = sorted(((m["figures"]["entry_speed_kmh"], cid, m["passed"])
                   for cid, m in sections.items()
                   if m["figures"]["entry_speed_kmh"] is not None), key=lambda r: r[0])
    clean = [v for v, _, ok in runs if ok]
    struck = [v for v, _, ok in runs if not ok]
    best = max(clean) if clean else None
    return {"standard": ISO3888_2,
            "runs": [{"car": cid, "entry_speed_kmh": v, "passed": ok} for v, cid, ok in runs],
            "highest_entry_speed_without_strike_kmh": best,
            "lowest_entry_speed_with_strike_kmh": min(struck) if struck else None,
            "all_slower_runs_passed": bool(best is not None and all(
                ok for v, _, ok in runs if v <= best))}


DLC_RUN_UP_M = 60.0
DLC_RUN_OUT_M = 200.0  # path beyond the exit: the driver's stop law (at the path's end)
# stays out of reach before the gate, where the driver still holds its speed
DLC_CARS_APART_M = 100.0
DLC_PREVIEW_TIME_S = 0.4
DLC_PREVIEW_MIN_M = 4.0


def dlc_series_scenario(name: str, vehicle: str, vp: np.ndarray,
                        speeds_kmh: list[float]) -> str:
    """The text of a double-lane-change series (``configs/scenarios/iso3888_2_*.yaml``):
    one car an entry speed, each on its own copy of the track ``DLC_CARS_APART_M`` to the
    left of the previous one, started ``DLC_RUN_UP_M`` before the entry gate on section
    1's centre at the entry speed, driven by the built-in driver on ``dlc_path`` holding
    that speed, the pedals released once the front bumper reaches the gate
    (``coast_from_s_m``)."""
    car = car_facts(vp)
    path = dlc_path(car.width_m, DLC_RUN_UP_M, DLC_RUN_OUT_M)
    lane1 = dlc_lanes(car.width_m)[0]
    duration = (DLC_RUN_UP_M + sum(DLC_SECTION_LENGTHS_M) + car.rear_m + 5.0) / (
        min(speeds_kmh) / 3.6)
    lines = [
        "# ISO 3888-2 double lane change (docs/manoeuvres.md section 7): one car an entry "
        "speed,",
        f"# {min(speeds_kmh):g}..{max(speeds_kmh):g} km/h, the built-in driver on the lanes' "
        "centres, pedals released at the",
        f"# entry gate; vehicle width {car.width_m:.3f} m (the body box: track + "
        f"{BODY_WIDTH_BEYOND_TRACK_M:g} m). Generated by",
        "# simserver.analysis.manoeuvres.dlc_series_scenario (tests/test_manoeuvres.py "
        "checks it).",
        f"name: {name}",
        "description: ISO 3888-2 double lane change, the highest entry speed without a "
        "cone strike",
        f"duration_s: {math.ceil(duration):g}",
        "record_every: 5",
        f"analysis: {{name: iso3888_2_double_lane_change, run_up_m: {DLC_RUN_UP_M:g}}}",
        "cars:",
    ]
    for k, v_kmh in enumerate(speeds_kmh):
        y0 = DLC_CARS_APART_M * k
        pts = ", ".join(f"[{px + DLC_RUN_UP_M:.3f}, {py - lane1.centre_m + y0:.4f}]"
                        for px, py in path)
        wrapped = textwrap.wrap(pts, 80, break_on_hyphens=False)
        v = v_kmh / 3.6
        lines += [f"  - id: v{v_kmh:05.1f}kmh".replace(".", "p"),
                  f"    vehicle: {vehicle}",
                  f"    initial: {{u_mps: {v:.4f}, relaxed: 1, y_m: {y0:g}}}",
                  "    driver:",
                  f"      idm: {{v0_mps: {v:.4f}}}",
                  f"      preview_time_s: {DLC_PREVIEW_TIME_S:g}",
                  f"      preview_min_m: {DLC_PREVIEW_MIN_M:g}",
                  f"      coast_from_s_m: {DLC_RUN_UP_M - car.front_m:.3f}",
                  "      path:",
                  f"        points: [{wrapped[0]}"]
        lines += [f"                 {w}" for w in wrapped[1:]]
        lines[-1] += "]"
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------- registry
ANALYSES: dict[str, tuple[Callable[..., dict[str, Any]], dict[str, tuple[float, float]]]] = {
    "iso4138_steady_state_circular": (iso4138_steady_state_circular,
                                      {"ay_fit_min_mps2": (0.0, 20.0),
                                       "ay_fit_max_mps2": (0.0, 20.0)}),
    "iso7401_step_steer": (iso7401_step_steer, {"steady_window_s": (0.1, 60.0)}),
    "fmvss126_slowly_increasing_steer": (fmvss126_slowly_increasing_steer, {}),
    "fmvss126_sine_with_dwell": (fmvss126_sine_with_dwell, {"sis_angle_deg": (0.1, 360.0)}),
    "hill_start": (hill_start, {"rollback_max_m": (0.0, 100.0),
                                "time_to_2_mps_max_s": (0.0, 3600.0)}),
    "fmvss105_parking_brake": (fmvss105_parking_brake, {"hold_min_s": (0.0, 3600.0)}),
    "iso3888_2_double_lane_change": (iso3888_2_double_lane_change,
                                     {"run_up_m": (0.0, 10000.0)}),
}
"""Analysis name: its function and the options a scenario may give it (with ranges)."""


def parse_analysis(path: Path | str, raw: Any) -> dict[str, Any] | None:
    """A scenario's ``analysis`` key as ``{"name": ..., options}``, or ``None``; errors
    name the file and the key."""
    if raw is None:
        return None
    if isinstance(raw, str):
        raw = {"name": raw}
    if not isinstance(raw, dict) or not isinstance(raw.get("name"), str):
        raise ConfigError(f"{path}: key 'analysis': expected a name or a mapping {{name, "
                          f"options}}; one of {', '.join(ANALYSES)}")
    if raw["name"] not in ANALYSES:
        raise ConfigError(f"{path}: key 'analysis.name': {raw['name']!r} is not one of "
                          f"{', '.join(ANALYSES)}")
    options = ANALYSES[raw["name"]][1]
    check_keys(f"{path} (analysis)", raw, ("name", *options), required=("name",))
    out: dict[str, Any] = {"name": raw["name"]}
    for key, (lo, hi) in options.items():
        if key in raw:
            out[key] = number(path, f"analysis.{key}", raw[key], lo, hi)
    return out


def analyse(spec: Mapping[str, Any], cols: Cols, car: Car) -> dict[str, Any]:
    """Run the analysis ``spec`` (``parse_analysis``) on a history."""
    options = {k: v for k, v in spec.items() if k != "name"}
    result = ANALYSES[spec["name"]][0](cols, car, **options)
    return {"analysis": spec["name"], **result}


# ------------------------------------------------------------------- report
def _fmt(value: Any) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    return str(value)


def report_markdown(title: str, sections: Mapping[str, Mapping[str, Any]]) -> str:
    """A short Markdown report of one or more cars' ``manoeuvre`` sections."""
    lines = [f"# {title}", ""]
    series = dlc_series(sections)
    if series is not None:
        best = series["highest_entry_speed_without_strike_kmh"]
        lines += [f"**Highest entry speed without a cone strike: {_fmt(best)} km/h** "
                  f"(lowest with a strike: {_fmt(series['lowest_entry_speed_with_strike_kmh'])}"
                  " km/h)", "", "| car | entry speed km/h | result |", "|---|---|---|"]
        lines += [f"| {r['car']} | {_fmt(r['entry_speed_kmh'])} | "
                  f"{'pass' if r['passed'] else 'FAIL'} |" for r in series["runs"]]
        lines.append("")
    for car_id, m in sections.items():
        head = f"## {m['standard']}: {m['method']}"
        lines += [head if len(sections) == 1 else f"{head} (car {car_id})", "",
                  f"**{'PASS' if m['passed'] else 'FAIL'}**" + (f" - {m['note']}" if m.get(
                      "note") else ""), "", "| figure | value |", "|---|---|"]
        for key, value in m["figures"].items():
            if key == "understeer_gradient_by_ay":
                value = "; ".join(f"{b['ay_mps2']:g}: {b['understeer_gradient_deg_per_mps2']:.4g}"
                                  for b in value)
            lines.append(f"| {key} | {_fmt(value)} |")
        lines += ["", "| criterion | value | limit | result | source |", "|---|---|---|---|---|"]
        for c in m["criteria"]:
            lines.append(f"| {c['name']} | {_fmt(c['value'])} {c['unit']} | {c['sense']} "
                         f"{_fmt(c['limit'])} {c['unit']} | {'pass' if c['passed'] else 'FAIL'}"
                         f" | {c['source']} |")
        lines.append("")
    return "\n".join(lines)
