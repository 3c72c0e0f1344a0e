"""Stops, holds and restarts found in a history: the product's headline as figures.

A *hold* is a stretch of recorded rows at rest (``|u| < HOLD_SPEED_MPS``) lasting at
least ``HOLD_MIN_S``. It ends at the driver's *release* (brake pedal below
``RELEASE_BRAKE`` with the parking brake off, or throttle above ``PRESS_THROTTLE``), or
when the car moves without one (the hill-start assist letting go, a brake too weak).
Per hold:

- ``creep_m``: the body's travel along its heading over the *creep window*, from
  ``CREEP_SETTLE_S`` after the stop (the stop's own transient: the slip states relax onto
  the hold, docs/model.md section 5) to the release; positive forward. From the
  position columns, which are states of the step (exact), not from integrated speed.
- ``peak_speed_mps``: the largest ``|u|`` over the creep window.

Per restart (a release followed by rows):

- ``rollback_m``: the largest travel against the gear's direction (D forward, R backward)
  from the last row held, until the car first reaches ``RESTART_SPEEDS_MPS[0]`` that way;
- ``time_to_0p5_mps_s``, ``time_to_2_mps_s``: from the release to the first row at that
  speed in the gear's direction (``None`` if never);
- ``peak_jerk_mps3``: the largest ``|d ax / dt|`` between recorded rows from the release
  until 2 m/s (or ``JERK_WINDOW_S``), so with ``record_every`` rows, a row-rate figure.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass

import numpy as np

from simserver.core.layout import GEAR_R

HOLD_SPEED_MPS = 1e-3
"""At rest below this ``|u|`` (1 mm/s, the summary's ``rest`` threshold)."""
HOLD_MIN_S = 0.5
"""A rest shorter than this is a pass through zero speed, not a hold."""
CREEP_SETTLE_S = 1.0
"""The creep window starts this long after the stop (or at the stop for shorter holds)."""
RELEASE_BRAKE = 0.02
"""Brake pedal below this (and the parking brake off) is released (the damping release
rule's 2 %)."""
PRESS_THROTTLE = 0.02
"""Throttle above this is a press."""
RESTART_SPEEDS_MPS = (0.5, 2.0)
JERK_WINDOW_S = 5.0
"""Jerk is looked at over at most this long after the release."""

COLUMNS = ("time_s", "x_m", "y_m", "yaw_rad", "u_mps", "ax_mps2", "input_brake",
           "input_throttle", "input_parking_brake", "input_gear")
"""The history columns the analysis reads."""


@dataclass(frozen=True)
class Hold:
    """One hold and, when the driver released it and rows follow, its restart."""

    start_s: float  # the first row at rest
    end_s: float  # the release, or the last row at rest
    released_by: str  # "driver" (pedals), "motion" (moved without a release), "end" (run ended)
    creep_window_s: tuple[float, float]
    creep_m: float
    peak_speed_mps: float
    rollback_m: float | None = None
    time_to_0p5_mps_s: float | None = None
    time_to_2_mps_s: float | None = None
    peak_jerk_mps3: float | None = None

    def as_dict(self) -> dict[str, object]:
        d = asdict(self)
        d["creep_window_s"] = list(self.creep_window_s)
        d["creep_mm"] = 1e3 * self.creep_m
        return d


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Inclusive index ranges of the runs of True in ``mask``."""
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    starts = np.flatnonzero(edges == 1)
    ends = np.flatnonzero(edges == -1) - 1
    return list(zip(starts.tolist(), ends.tolist(), strict=True))


def _travel(cols: Mapping[str, np.ndarray], i0: int, i1: np.ndarray | int) -> np.ndarray:
    """Travel (m) from row ``i0`` to rows ``i1`` along the heading at ``i0``."""
    c, s = np.cos(cols["yaw_rad"][i0]), np.sin(cols["yaw_rad"][i0])
    return ((cols["x_m"][i1] - cols["x_m"][i0]) * c + (cols["y_m"][i1] - cols["y_m"][i0]) * s)


def _first_at_or_after(t: np.ndarray, time_s: float) -> int:
    return int(np.searchsorted(t, time_s - 1e-12, side="left"))


def find_holds(cols: Mapping[str, np.ndarray]) -> list[Hold]:
    """Every hold of a history and its restart (module docstring).

    Parameters
    ----------
    cols : mapping of str to ndarray
        History columns (at least ``COLUMNS``), rows in time order.
    """
    t = np.asarray(cols["time_s"], dtype=np.float64)
    u = np.asarray(cols["u_mps"], dtype=np.float64)
    released = (((cols["input_brake"] < RELEASE_BRAKE) & (cols["input_parking_brake"] < 0.5))
                | (cols["input_throttle"] > PRESS_THROTTLE))
    holds = []
    for i0, i1 in _runs(np.abs(u) < HOLD_SPEED_MPS):
        if t[i1] - t[i0] < HOLD_MIN_S:
            continue
        # the release: the first released row after the first held one (the car may come
        # to rest before the pedal is pressed far enough), up to the first moving row: a
        # release with the throttle moves the car within the rows' interval
        last = min(i1 + 1, len(t) - 1)
        held_rows = np.flatnonzero(~released[i0:last + 1])
        release = None
        if held_rows.size:
            after = np.flatnonzero(released[i0 + held_rows[0]:last + 1])
            if after.size:
                release = i0 + held_rows[0] + int(after[0])
        if release is not None:
            end, how = min(release, i1), "driver"  # the last row at rest and held
        else:
            end, how = i1, ("end" if i1 == len(t) - 1 else "motion")
        w0 = _first_at_or_after(t, t[i0] + CREEP_SETTLE_S)
        if w0 >= end:
            w0 = i0
        hold = dict(start_s=float(t[i0]), end_s=float(t[end]), released_by=how,
                    creep_window_s=(float(t[w0]), float(t[end])),
                    creep_m=float(_travel(cols, w0, end)),
                    peak_speed_mps=float(np.max(np.abs(u[w0:end + 1]))))
        if release is not None and release < len(t) - 1:
            hold.update(_restart(cols, t, u, end, release))
        holds.append(Hold(**hold))
    return holds


def _restart(cols: Mapping[str, np.ndarray], t: np.ndarray, u: np.ndarray, r0: int,
             r: int) -> dict[str, float | None]:
    """Rollback from the last held row ``r0``; times to the restart speeds and peak jerk
    from the release row ``r`` (the first row the pedals say released: the release itself
    is known to the rows' interval)."""
    way = -1.0 if int(cols["input_gear"][r]) == GEAR_R else 1.0
    ahead = way * u[r:]
    reached = [np.flatnonzero(ahead >= v) for v in RESTART_SPEEDS_MPS]
    times = [float(t[r + k[0]] - t[r]) if k.size else None for k in reached]
    until = r + (int(reached[0][0]) if reached[0].size else len(ahead) - 1)
    back = -way * _travel(cols, r0, np.arange(r0, until + 1))
    jerk_end = r + int(reached[1][0]) if reached[1].size else len(t) - 1
    jerk_end = min(jerk_end, _first_at_or_after(t, t[r] + JERK_WINDOW_S), len(t) - 1)
    jerk = None
    if jerk_end > r0:
        ax = np.asarray(cols["ax_mps2"][r0:jerk_end + 1], dtype=np.float64)
        jerk = float(np.max(np.abs(np.diff(ax) / np.diff(t[r0:jerk_end + 1]))))
    return {"rollback_m": float(max(0.0, np.max(back))), "time_to_0p5_mps_s": times[0],
            "time_to_2_mps_s": times[1], "peak_jerk_mps3": jerk}


def holds_summary(cols: Mapping[str, np.ndarray]) -> dict[str, object]:
    """The ``holds`` section of a summary: the thresholds used and every hold."""
    return {
        "rest_below_mps": HOLD_SPEED_MPS,
        "min_hold_s": HOLD_MIN_S,
        "creep_settle_s": CREEP_SETTLE_S,
        "holds": [h.as_dict() for h in find_holds(cols)],
    }
