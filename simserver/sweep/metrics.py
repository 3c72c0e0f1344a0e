"""Numbers extracted from one run of a sweep: a registry of metric kinds.

A sweep file's ``metrics:`` list names them; each entry is a kind name, a one-key
mapping ``{kind: {option: value}}``, or ``{column: NAME, stat: min|max|final}`` for any
history column (docs/history_columns.md). Each metric gives one or more named numbers
(the columns of the results table). Rest is ``|u| < REST_SPEED_MPS`` as in summary.json.

| kind | options | columns |
|---|---|---|
| stopping_distance | from_s (0) | stopping_distance_m: path length from from_s to the first rest |
| time_to_rest | from_s (0) | time_to_rest_s: from from_s to the first rest |
| creep | from_s, to_s, limit_m (0.001) | creep_m: displacement over [from_s, to_s]; |
| | | holds: creep_m < limit_m |
| yaw | - | peak_yaw_rate_radps: max abs(r); yaw_change_rad: final - initial yaw |
| resting_forces | - | final {fx,fy}_{front,rear}_n and fx_body_sum_n (the last row) |
| holds | - | the summary's holds (``simserver.analysis.holds``), worst over the run: |
| | | holds_found; hold_creep_max_m (largest abs creep over a hold's window), |
| | | hold_peak_speed_max_mps; rollback_max_m, time_to_2_mps_max_s, |
| | | restart_jerk_max_mps3 over the restarts (NaN without a hold or restart) |

A stopping metric of a car that never comes to rest is NaN.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from simserver.adapters.validate import ConfigError, check_keys, number
from simserver.analysis.holds import COLUMNS as HOLD_COLUMNS
from simserver.analysis.holds import find_holds

REST_SPEED_MPS = 1e-3  # the same threshold as summary.json's rest section (adapters/history.py)
STATS = ("min", "max", "final")


def _first_rest(time_s: np.ndarray, u: np.ndarray, from_s: float) -> int | None:
    at_rest = (np.abs(u) < REST_SPEED_MPS) & (time_s >= from_s)
    return int(np.argmax(at_rest)) if at_rest.any() else None


def _start(time_s: np.ndarray, from_s: float) -> int:
    return int(np.searchsorted(time_s, from_s, side="left"))


def stopping_distance(cols: Mapping[str, np.ndarray], from_s: float = 0.0) -> dict[str, float]:
    t, k = cols["time_s"], _first_rest(cols["time_s"], cols["u_mps"], from_s)
    if k is None:
        return {"stopping_distance_m": math.nan}
    k0 = min(_start(t, from_s), k)
    steps = np.hypot(np.diff(cols["x_m"][k0:k + 1]), np.diff(cols["y_m"][k0:k + 1]))
    return {"stopping_distance_m": float(steps.sum())}


def time_to_rest(cols: Mapping[str, np.ndarray], from_s: float = 0.0) -> dict[str, float]:
    k = _first_rest(cols["time_s"], cols["u_mps"], from_s)
    return {"time_to_rest_s": math.nan if k is None else float(cols["time_s"][k] - from_s)}


def creep(cols: Mapping[str, np.ndarray], from_s: float, to_s: float,
          limit_m: float = 1e-3) -> dict[str, float]:
    t = cols["time_s"]
    k0 = min(_start(t, from_s), len(t) - 1)
    k1 = min(_start(t, to_s), len(t) - 1)
    moved = float(math.hypot(cols["x_m"][k1] - cols["x_m"][k0],
                             cols["y_m"][k1] - cols["y_m"][k0]))
    return {"creep_m": moved, "holds": bool(moved < limit_m)}


def yaw(cols: Mapping[str, np.ndarray]) -> dict[str, float]:
    return {"peak_yaw_rate_radps": float(np.max(np.abs(cols["yaw_rate_radps"]))),
            "yaw_change_rad": float(cols["yaw_rad"][-1] - cols["yaw_rad"][0])}


def resting_forces(cols: Mapping[str, np.ndarray]) -> dict[str, float]:
    out = {}
    for q in ("fx", "fy"):
        out[f"{q}_front_n"] = float(cols[f"{q}_fl_n"][-1] + cols[f"{q}_fr_n"][-1])
        out[f"{q}_rear_n"] = float(cols[f"{q}_rl_n"][-1] + cols[f"{q}_rr_n"][-1])
    out["fx_body_sum_n"] = float(cols["fx_body_sum_n"][-1])
    return out


def _worst(values: list[float | None]) -> float:
    """The largest of the known values, NaN when none is."""
    known = [v for v in values if v is not None]
    return float(max(known)) if known else math.nan


def holds(cols: Mapping[str, np.ndarray]) -> dict[str, float]:
    """The run's holds and restarts (one implementation: ``analysis.holds``, as in
    summary.json's ``holds`` section), one row of numbers: the count and the worst of each
    figure over them."""
    found = find_holds(cols)
    return {"holds_found": float(len(found)),
            "hold_creep_max_m": _worst([abs(h.creep_m) for h in found]),
            "hold_peak_speed_max_mps": _worst([h.peak_speed_mps for h in found]),
            "rollback_max_m": _worst([h.rollback_m for h in found]),
            "time_to_2_mps_max_s": _worst([h.time_to_2_mps_s for h in found]),
            "restart_jerk_max_mps3": _worst([h.peak_jerk_mps3 for h in found])}


@dataclass(frozen=True)
class MetricKind:
    function: Callable[..., dict[str, float]]
    options: tuple[str, ...]
    # the history columns the function reads: a sweep's worker keeps only these of a run
    # (``worker.run_for_metrics``); a column missing here is a KeyError there
    columns: tuple[str, ...]
    required: tuple[str, ...] = ()


_FORCES = tuple(f"{q}_{w}_n" for q in ("fx", "fy") for w in ("fl", "fr", "rl", "rr"))
METRIC_KINDS: dict[str, MetricKind] = {
    "stopping_distance": MetricKind(stopping_distance, ("from_s",),
                                    ("time_s", "u_mps", "x_m", "y_m")),
    "time_to_rest": MetricKind(time_to_rest, ("from_s",), ("time_s", "u_mps")),
    "creep": MetricKind(creep, ("from_s", "to_s", "limit_m"), ("time_s", "x_m", "y_m"),
                        ("from_s", "to_s")),
    "yaw": MetricKind(yaw, (), ("yaw_rate_radps", "yaw_rad")),
    "resting_forces": MetricKind(resting_forces, (), (*_FORCES, "fx_body_sum_n")),
    "holds": MetricKind(holds, (), HOLD_COLUMNS),
}


METRIC_LABELS: dict[str, str] = {
    "stopping_distance_m": "stopping distance",
    "time_to_rest_s": "time to rest",
    "creep_m": "creep over the window",
    "holds": "held: creep under the limit (1 yes, 0 no)",
    "peak_yaw_rate_radps": "peak yaw rate",
    "yaw_change_rad": "yaw change, start to end",
    "fx_front_n": "resting longitudinal force, front axle",
    "fx_rear_n": "resting longitudinal force, rear axle",
    "fy_front_n": "resting lateral force, front axle",
    "fy_rear_n": "resting lateral force, rear axle",
    "fx_body_sum_n": "resting longitudinal force, whole car",
    "holds_found": "holds found",
    "hold_creep_max_m": "largest creep over a hold",
    "hold_peak_speed_max_mps": "largest speed while held",
    "rollback_max_m": "largest rollback at a restart",
    "time_to_2_mps_max_s": "longest time to 2 m/s after a release",
    "restart_jerk_max_mps3": "largest jerk at a restart",
    # a soak case's (sweep.worker.SOAK_METRICS)
    "violations": "invariants broken",
    "holds_checked": "holds judged",
    "holds_unjudged": "holds too short to judge",
    "max_hold_creep_m": "largest creep over a hold",
    "max_speed_mps": "largest speed",
    "min_fz_n": "smallest tire load",
    "simulated_s": "simulated time",
}
"""Each metric column in words, for the plots' axes (``sweep.labels``; the unit comes from
the name's suffix, as the history's). A test keeps every kind's columns here."""


@dataclass(frozen=True)
class Metric:
    """One entry of ``metrics:``: a kind with its options, or a column statistic."""

    kind: str  # a METRIC_KINDS key, or "column"
    options: tuple[tuple[str, float], ...] = ()
    column: str = ""
    stat: str = ""

    @property
    def columns(self) -> tuple[str, ...]:
        """The history columns this metric reads."""
        return (self.column,) if self.kind == "column" else METRIC_KINDS[self.kind].columns

    def evaluate(self, cols: Mapping[str, np.ndarray]) -> dict[str, float]:
        if self.kind == "column":
            values = cols[self.column]
            if self.stat == "final":
                value = values[-1]
            else:
                value = np.min(values) if self.stat == "min" else np.max(values)
            return {f"{self.stat}_{self.column}": float(value)}
        return METRIC_KINDS[self.kind].function(cols, **dict(self.options))


def parse_metrics(origin: str, entries: Any, columns: tuple[str, ...]) -> tuple[Metric, ...]:
    """Validate a sweep file's ``metrics:`` list (errors name ``metrics[i]``)."""
    if not isinstance(entries, list) or not entries:
        raise ConfigError(f"{origin}: key 'metrics': expected a non-empty list")
    metrics = []
    for i, entry in enumerate(entries):
        where = f"metrics[{i}]"
        if isinstance(entry, str):
            entry = {entry: {}}
        if not isinstance(entry, dict):
            raise ConfigError(f"{origin}: key '{where}': expected a name or a mapping")
        if "column" in entry:
            check_keys(f"{origin} ({where})", entry, ("column", "stat"),
                       required=("column", "stat"))
            if entry["column"] not in columns:
                raise ConfigError(f"{origin}: key '{where}.column': unknown history column "
                                  f"{entry['column']!r}")
            if entry["stat"] not in STATS:
                raise ConfigError(f"{origin}: key '{where}.stat': expected one of "
                                  f"{', '.join(STATS)}")
            metrics.append(Metric("column", column=entry["column"], stat=entry["stat"]))
            continue
        if len(entry) != 1 or next(iter(entry)) not in METRIC_KINDS:
            raise ConfigError(f"{origin}: key '{where}': expected one of "
                              f"{', '.join(METRIC_KINDS)} or {{column: NAME, stat: STAT}}")
        (name, options), = entry.items()
        kind = METRIC_KINDS[name]
        options = options or {}
        if not isinstance(options, dict):
            raise ConfigError(f"{origin}: key '{where}.{name}': expected a mapping of options")
        check_keys(f"{origin} ({where}.{name})", options, kind.options, required=kind.required)
        values = tuple((k, number(origin, f"{where}.{name}.{k}", v, 0.0, 1e6))
                       for k, v in options.items())
        metrics.append(Metric(name, options=values))
    return tuple(metrics)


def evaluate(metrics: tuple[Metric, ...], cols: Mapping[str, np.ndarray]) -> dict[str, float]:
    """Every metric's numbers for one run's history columns."""
    out: dict[str, float] = {}
    for metric in metrics:
        out.update(metric.evaluate(cols))
    return out
