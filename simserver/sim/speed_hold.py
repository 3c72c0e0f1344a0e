"""A speed hold for headless scenarios: the throttle a test driver works to keep a speed.

The standard manoeuvres run at a constant speed while the steering changes (ISO 4138's
constant-speed method, FMVSS 126's slowly increasing steer at 80 +- 2 km/h): the drag of
a turn grows with the lateral acceleration, so open-loop keyframes cannot hold the speed
(the paper sedan loses 3.8 m/s over a 36 s steer ramp from 20 m/s on a fixed throttle),
and a speed that drifts moves load between the axles (``m a_x h / L``), which for the
paper's tire shifts the understeer gradient by as much as its whole value
(docs/manoeuvres.md section 1).

A scenario's ``speed_hold`` key::

    speed_hold: {speed_mps: 20.0, gain_per_mps: 0.2, integral_time_s: 2.0,
                 from_s: 0.0, until_s: 40.0, keep_throttle: 1}

Over ``[from_s, until_s)`` the throttle of each control period (``PERIOD_S``) is the
keyframes' throttle (a feed-forward) plus a PI term on ``speed_mps - u``, clipped to [0,
1]; the brake is the keyframes'. With ``keep_throttle: 1`` the throttle stays where the
hold left it from ``until_s`` to the end (a driver keeping the pedal still through a
step steer, ISO 7401); otherwise the keyframes' throttle applies again. The controller
reads the state at the start of each period and writes the period's inputs before the
runner steps them, so the history's ``input_throttle`` is what was applied.
``run_scenario`` applies it (and so the sweep's workers, which run a scenario with a
hold through it); a scenario of several cars (``cars:``) refuses the key.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from simserver.adapters.validate import ConfigError, check_keys, number
from simserver.core import layout as L

PERIOD_S = 0.01
"""Control period: a 100 Hz speed controller, as test drivers' robots run."""
KEYS = ("speed_mps", "gain_per_mps", "integral_time_s", "from_s", "until_s", "keep_throttle")
DEFAULT_GAIN_PER_MPS = 0.2
"""Throttle per m/s of speed error: the paper sedan's 10.9 kN full-throttle force over its
2041 kg closes the loop in about a second."""
DEFAULT_INTEGRAL_TIME_S = 2.0


@dataclass(frozen=True)
class SpeedHold:
    """A validated ``speed_hold`` section (module docstring)."""

    speed_mps: float
    gain_per_mps: float = DEFAULT_GAIN_PER_MPS
    integral_time_s: float = DEFAULT_INTEGRAL_TIME_S
    from_s: float = 0.0
    until_s: float = float("inf")
    keep_throttle: bool = False

    def period_steps(self, dt_s: float) -> int:
        """Steps per control period at step ``dt_s``."""
        return max(1, int(round(PERIOD_S / dt_s)))


def parse_speed_hold(path: Path | str, raw: Any) -> SpeedHold | None:
    """The ``speed_hold`` key of a scenario, or ``None`` if absent; errors name the file
    and the key."""
    if raw is None:
        return None
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: key 'speed_hold': expected a mapping {{speed_mps, ...}}")
    check_keys(f"{path} (speed_hold)", raw, KEYS, required=("speed_mps",))
    values = {"speed_mps": number(path, "speed_hold.speed_mps", raw["speed_mps"], 0.1, 100.0)}
    for key, lo, hi in (("gain_per_mps", 1e-4, 10.0), ("integral_time_s", 1e-2, 1e3),
                        ("from_s", 0.0, 3600.0), ("until_s", 0.0, 3600.0)):
        if key in raw:
            values[key] = number(path, f"speed_hold.{key}", raw[key], lo, hi)
    keep = raw.get("keep_throttle", 0)
    if keep not in (0, 1):  # True == 1 and False == 0 too
        raise ConfigError(f"{path}: key 'speed_hold.keep_throttle': expected 0 or 1")
    values["keep_throttle"] = bool(keep)
    hold = SpeedHold(**values)
    if hold.until_s <= hold.from_s:
        raise ConfigError(f"{path}: key 'speed_hold.until_s': {hold.until_s:g} s is not after "
                          f"from_s {hold.from_s:g} s")
    return hold


class SpeedController:
    """The PI loop of one run: ``control(done, x)`` before each period writes the throttle
    of the steps ``done .. done + period`` of ``inputs`` (in place). The period is
    ``PERIOD_S`` rounded to whole recorded rows (``record_every``), the runner's chunk."""

    def __init__(self, hold: SpeedHold, inputs: np.ndarray, dt_s: float,
                 record_every: int = 1) -> None:
        self.hold = hold
        self.inputs = inputs
        self.dt_s = dt_s
        steps = hold.period_steps(dt_s)  # a whole number of recorded rows a period
        self.period = record_every * max(1, round(steps / record_every))
        self.integral_mps_s = 0.0
        self.last_throttle: float | None = None

    def control(self, done: int, x: np.ndarray) -> None:
        hold = self.hold
        t = done * self.dt_s
        if t >= hold.until_s and hold.keep_throttle and self.last_throttle is not None:
            self.inputs[done:, L.IN_THROTTLE] = self.last_throttle
            self.last_throttle = None  # written once: the rest of the run
            return
        if not hold.from_s <= t < hold.until_s:
            return
        rows = self.inputs[done:done + self.period]
        error = hold.speed_mps - float(x[L.U_MPS])
        feed = float(rows[0, L.IN_THROTTLE])
        trial = feed + hold.gain_per_mps * (
            error + (self.integral_mps_s + error * self.period * self.dt_s)
            / hold.integral_time_s)
        if 0.0 < trial < 1.0:  # integrate only while unsaturated (no wind-up)
            self.integral_mps_s += error * self.period * self.dt_s
        throttle = feed + hold.gain_per_mps * (error + self.integral_mps_s / hold.integral_time_s)
        self.last_throttle = min(1.0, max(0.0, throttle))
        rows[:, L.IN_THROTTLE] = self.last_throttle
