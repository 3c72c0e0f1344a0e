"""Headless soak: hours of seeded, plausible random driving with invariants checked every tick.

The driver is a sequence of manoeuvres drawn from a seeded generator (``manoeuvre_plan``):
accelerate, cruise and weave, brake to a stop, hold on the slope, restart, reverse, hard
cornering, handbrake spins, parking; the road (grade, cross-slope, friction) changes
between manoeuvres while the car is held. The physics runs in compiled chunks as fast as
the CPU allows; after each chunk the recorded ticks are checked (``check_invariants``):

- every state and output is finite;
- speeds are bounded (|u|, |v| < 80 m/s, |Omega| < 600 rad/s, |r| < 10 rad/s);
- normal loads are never negative and never above 6 x static;
- a car held by its brakes does not creep: once at rest in a hold (foot brake 0.6 or
  parking brake and P, throttle 0), it moves less than 1 mm until the hold ends. It is
  checked from 1.5 s after the car first comes to rest (|u|, |v| < 1 mm/s) in the hold
  and the pedals have reached their hold positions (the tire springs settle onto a new
  balance first); a hold in which the car is still sliding is not checked
  (``at_rest_index``) but counted apart.

The first violation of each kind is reported with its tick and simulated time.

Every hold is also measured as a headless summary measures it (``holds``:
``analysis.holds.find_holds``: its start and end, creep over its window, peak speed while
held, and its restart's rollback, times to 0.5 and 2 m/s and peak jerk). A hold's rows
are kept only while they are needed: the segment before a run of hold/park segments (the
stop), the run, and the segment after it (the restart), only the columns the analysis
reads, made by the history's own mapping (``adapters.history.rows_columns``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from simserver.adapters.history import rows_columns
from simserver.analysis.holds import COLUMNS as HOLD_COLUMNS
from simserver.analysis.holds import find_holds
from simserver.core import layout as L
from simserver.core.chassis import static_wheel_load
from simserver.sim.scene import Scene
from simserver.sim.simulation import Simulation

SPEED_LIMIT_MPS = 80.0
SPIN_LIMIT_RADPS = 600.0
YAW_RATE_LIMIT_RADPS = 10.0
LOAD_LIMIT_X_STATIC = 6.0
HOLD_SETTLE_S = 1.5
HOLD_MIN_WINDOW_S = 1.0
HOLD_CREEP_LIMIT_M = 1e-3
REST_MPS = 1e-3
RAMP_S = 0.3  # pedals and steer move to a segment's values over this time

# manoeuvre kinds (columns of the plan)
ACCELERATE, CRUISE, BRAKE_STOP, HOLD, REVERSE, CORNER, SPIN, PARK = range(8)
MANOEUVRE_NAMES = ("accelerate", "cruise", "brake_stop", "hold", "reverse", "corner",
                   "spin", "park")


@dataclass
class Segment:
    """A stretch of constant driver intent: inputs ramp to these values, then hold."""

    kind: int
    duration_s: float
    steer: float = 0.0
    throttle: float = 0.0
    brake: float = 0.0
    parking_brake: float = 0.0
    gear: float = L.GEAR_D
    road: tuple[float, float, float] | None = None  # set at the segment start (car held)


def manoeuvre_plan(rng: np.random.Generator, duration_s: float) -> list[Segment]:
    """A seeded random drive of ``duration_s``: stop-and-go cycles with every manoeuvre."""
    plan: list[Segment] = []
    total = 0.0
    while total < duration_s:
        # a new road while the car is held
        road = (float(rng.uniform(-12, 12)), float(rng.uniform(-8, 8)),
                float(rng.choice([1.0, 1.0, 0.8, 0.5])))
        plan.append(Segment(HOLD, 4.0, brake=0.6, road=road))
        forward = rng.random() < 0.8
        gear = L.GEAR_D if forward else L.GEAR_R
        plan.append(Segment(ACCELERATE, float(rng.uniform(3, 10)), gear=gear,
                            throttle=float(rng.uniform(0.3, 1.0))))
        if forward:
            kind = rng.choice([CRUISE, CORNER, SPIN])
            if kind == CRUISE:
                plan.append(Segment(CRUISE, float(rng.uniform(3, 10)), gear=gear,
                                    throttle=0.25, steer=float(rng.uniform(-0.1, 0.1))))
            elif kind == CORNER:
                plan.append(Segment(CORNER, float(rng.uniform(3, 8)), gear=gear,
                                    throttle=float(rng.uniform(0.1, 0.5)),
                                    steer=float(rng.choice([-1, 1]) * rng.uniform(0.1, 0.6))))
            else:
                plan.append(Segment(CORNER, 1.5, gear=gear, throttle=0.3,
                                    steer=float(rng.choice([-1, 1]) * rng.uniform(0.2, 0.5))))
                plan.append(Segment(SPIN, float(rng.uniform(2, 4)), gear=gear, brake=0.3,
                                    parking_brake=1.0,
                                    steer=float(rng.choice([-1, 1]) * rng.uniform(0.3, 1.0))))
        else:
            plan.append(Segment(REVERSE, float(rng.uniform(2, 5)), gear=gear, throttle=0.3,
                                steer=float(rng.uniform(-0.5, 0.5))))
        plan.append(Segment(BRAKE_STOP, float(rng.uniform(6, 10)), gear=gear,
                            brake=float(rng.uniform(0.4, 1.0))))
        plan.append(Segment(HOLD, float(rng.uniform(4, 12)), gear=gear, brake=0.6))
        if rng.random() < 0.3:
            plan.append(Segment(PARK, float(rng.uniform(4, 8)), gear=L.GEAR_P,
                                parking_brake=1.0))
        total = sum(s.duration_s for s in plan)
    return plan


def segment_inputs(seg: Segment, previous: np.ndarray, dt_s: float) -> np.ndarray:
    """Per-step inputs for one segment, ramping the continuous channels from ``previous``."""
    n = int(round(seg.duration_s / dt_s))
    table = np.empty((n, L.N_INPUT))
    ramp = np.clip((np.arange(n) + 1) * dt_s / RAMP_S, 0.0, 1.0)
    for col, target in ((L.IN_STEER, seg.steer), (L.IN_THROTTLE, seg.throttle),
                        (L.IN_BRAKE, seg.brake)):
        table[:, col] = previous[col] + (target - previous[col]) * ramp
    table[:, L.IN_PARKING_BRAKE] = seg.parking_brake
    table[:, L.IN_GEAR] = seg.gear
    return table


@dataclass
class Violation:
    """The first breach of one invariant."""

    invariant: str
    step: int
    time_s: float
    detail: str


@dataclass
class SoakReport:
    """What a soak did and found."""

    seed: int
    simulated_s: float
    steps: int
    wall_s: float
    manoeuvres: dict[str, int]
    holds_checked: int
    holds_unjudged: int  # hold/park segments whose car never came to rest in time (below)
    max_hold_creep_m: float
    max_speed_mps: float
    min_fz_n: float
    violations: list[Violation] = field(default_factory=list)
    unjudged_hold_times_s: list[float] = field(default_factory=list)
    holds: list[dict[str, Any]] = field(default_factory=list)  # Hold.as_dict() per hold

    UNJUDGED_MEANING = (
        "hold or park segments not judged for creep: the car never came to rest (|u|, |v| "
        "below 1 mm/s), or came to rest too late to leave 1 s to judge after its 1.5 s to "
        "settle, e.g. still sliding on a low-friction road when the segment ended; not a "
        "violation (the speed and load invariants still held every tick)")
    """What ``holds_unjudged`` counts (printed by ``simserver soak`` when it is not 0)."""

    def holds_digest(self) -> str:
        """One line: how many holds, the worst creep and the worst restart rollback."""
        if not self.holds:
            return "holds: none"
        worst = max(self.holds, key=lambda h: abs(h["creep_m"]))
        rolls = [h for h in self.holds
                 if h["rollback_m"] is not None and "restart_cut_at_s" not in h]
        cut = sum("restart_cut_at_s" in h for h in self.holds)
        text = (f"holds: {len(self.holds)}, worst creep {worst['creep_m'] * 1e3:+.3f} mm "
                f"(t = {worst['start_s']:.3f} s, window {worst['creep_window_s'][0]:.3f}-"
                f"{worst['creep_window_s'][1]:.3f} s)")
        if rolls:
            back = max(rolls, key=lambda h: h["rollback_m"])
            text += (f", worst rollback {back['rollback_m'] * 1e3:.3f} mm "
                     f"(restart at t = {back['end_s']:.3f} s)")
        if cut:
            text += f", {cut} restart(s) not at 2 m/s by the next segment's end (not ranked)"
        return text

    @property
    def ok(self) -> bool:
        """No invariant was violated."""
        return not self.violations

    def as_dict(self) -> dict[str, Any]:
        """JSON-friendly summary."""
        return {
            "seed": self.seed, "simulated_s": self.simulated_s,
            "simulated_h": self.simulated_s / 3600.0, "steps": self.steps,
            "wall_s": round(self.wall_s, 2),
            "real_time_factor": round(self.simulated_s / max(self.wall_s, 1e-9), 1),
            "manoeuvres": self.manoeuvres, "holds_checked": self.holds_checked,
            "holds_unjudged": self.holds_unjudged,
            "unjudged_hold_times_s": [round(t, 3) for t in self.unjudged_hold_times_s],
            "max_hold_creep_m": self.max_hold_creep_m, "max_speed_mps": self.max_speed_mps,
            "min_fz_n": self.min_fz_n, "ok": self.ok,
            "violations": [v.__dict__ for v in self.violations],
            "holds": self.holds,
        }


def at_rest_index(states: np.ndarray, dt_s: float) -> int | None:
    """Row from which a hold is checked.

    ``HOLD_SETTLE_S`` after the car first came to rest (|u| and |v| below 1 mm/s) in the
    hold and the pedals reached their hold values; None if the car never came to rest, or
    too late to leave ``HOLD_MIN_WINDOW_S`` (a car still sliding on a slippery road is not
    held yet).
    """
    still = np.maximum(np.abs(states[:, L.U_MPS]), np.abs(states[:, L.V_MPS])) < REST_MPS
    if not still.any():
        return None
    # the pedals reach their hold values after RAMP_S; the tire springs then take up the
    # new balance (a car settling onto its parking brake, or onto a road whose slope just
    # changed, moves millimetres on its tire springs; the 3.5 Hz and 1.7 Hz tire modes
    # are damped out within about a second)
    start = max(int(np.argmax(still)), int(RAMP_S / dt_s)) + int(HOLD_SETTLE_S / dt_s)
    if (states.shape[0] - start) * dt_s < HOLD_MIN_WINDOW_S:
        return None
    return start


def check_invariants(states: np.ndarray, outputs: np.ndarray, static_max_n: float,
                     first_step: int, dt_s: float, found: dict[str, Violation]) -> None:
    """Check the per-tick invariants on a chunk; record the first breach of each kind."""
    def report(name: str, bad: np.ndarray, detail: str) -> None:
        if name not in found and bad.any():
            k = int(np.argmax(bad))
            found[name] = Violation(name, first_step + k, (first_step + k) * dt_s, detail)

    finite = np.isfinite(states).all(axis=1) & np.isfinite(outputs).all(axis=1)
    report("finite", ~finite, "a state or output is NaN or infinite")
    speed = np.maximum(np.abs(states[:, L.U_MPS]), np.abs(states[:, L.V_MPS]))
    report("speed", speed > SPEED_LIMIT_MPS, f"|u| or |v| above {SPEED_LIMIT_MPS} m/s")
    spin = np.abs(states[:, L.OMEGA]).max(axis=1)
    report("wheel_spin", spin > SPIN_LIMIT_RADPS, f"|Omega| above {SPIN_LIMIT_RADPS} rad/s")
    report("yaw_rate", np.abs(states[:, L.YAW_RATE_RADPS]) > YAW_RATE_LIMIT_RADPS,
           f"|r| above {YAW_RATE_LIMIT_RADPS} rad/s")
    fz = outputs[:, L.O_FZ]
    report("normal_load_negative", (fz < 0.0).any(axis=1), "a normal load below zero")
    report("normal_load_bound", (fz > LOAD_LIMIT_X_STATIC * static_max_n).any(axis=1),
           f"a normal load above {LOAD_LIMIT_X_STATIC} x static")


def hold_columns(states: np.ndarray, outputs: np.ndarray, inputs: np.ndarray,
                 first_step: int, dt_s: float) -> dict[str, np.ndarray]:
    """The columns ``analysis.holds`` reads, of a segment's rows starting at step
    ``first_step`` (row ``k``'s time is ``(first_step + k) * dt_s``)."""
    time_s = (first_step + np.arange(states.shape[0])) * dt_s
    cols = rows_columns(states, outputs, inputs, time_s=time_s)
    return {name: cols[name] for name in HOLD_COLUMNS}


def window_holds(window: list[dict[str, np.ndarray]], held_from_s: float,
                 held_to_s: float) -> list[dict[str, Any]]:
    """The holds of a window of segments' columns (``hold_columns``) that overlap the
    hold/park segments ``[held_from_s, held_to_s)``, as ``Hold.as_dict()``.

    A restart that does not reach 2 m/s in the gear's direction within the window (the
    segment after the holds) is measured on the window's rows only: its dict says so with
    ``restart_cut_at_s`` (the window's last row); its rollback is then a lower bound and
    its times and jerk those of the rows kept (the whole drive may reach the speeds later).
    """
    cols = {name: np.concatenate([w[name] for w in window]) for name in HOLD_COLUMNS}
    rows = []
    for h in find_holds(cols):
        if not (h.start_s < held_to_s and h.end_s >= held_from_s):
            continue
        row = h.as_dict()
        if h.rollback_m is not None and h.time_to_2_mps_s is None:
            row["restart_cut_at_s"] = float(cols["time_s"][-1])
        rows.append(row)
    return rows


def run_soak(scene: Scene, duration_s: float, seed: int = 0, dt_s: float = 0.001,
             progress: Callable[[float, float], None] | None = None) -> SoakReport:
    """Drive ``scene``'s car for ``duration_s`` of simulated time; check every tick."""
    rng = np.random.default_rng(seed)
    plan = manoeuvre_plan(rng, duration_s)
    sim = Simulation(scene, dt_s)
    found: dict[str, Violation] = {}
    counts = dict.fromkeys(MANOEUVRE_NAMES, 0)
    previous = np.zeros(L.N_INPUT)
    step_no = 0
    holds = 0
    unjudged_at: list[float] = []
    max_creep = 0.0
    hold_rows: list[dict[str, Any]] = []
    # the columns of the last segment (a stop, when hold segments follow) and, from a hold
    # segment to the segment after the run of hold/park segments, the window measured
    previous_cols: dict[str, np.ndarray] | None = None
    window: list[dict[str, np.ndarray]] = []
    held_from = held_to = 0
    max_speed = 0.0
    min_fz = np.inf
    t0 = time.perf_counter()
    for seg in plan:
        if step_no * dt_s >= duration_s:
            break
        counts[MANOEUVRE_NAMES[seg.kind]] += 1
        if seg.road is not None:
            sim.set_road(*seg.road)
        static_max = max(static_wheel_load(sim.vp, sim.model.terrain.road, i)
                         for i in range(L.N_WHEELS))
        inputs = segment_inputs(seg, previous, dt_s)
        previous = inputs[-1].copy()
        n = inputs.shape[0]
        states = np.empty((n, L.N_STATE))
        outputs = np.empty((n, L.N_OUT))
        sim.run(inputs, states, outputs)
        check_invariants(states, outputs, static_max, step_no, dt_s, found)
        max_speed = max(max_speed, float(np.abs(states[:, L.U_MPS]).max()))
        min_fz = min(min_fz, float(outputs[:, L.O_FZ].min()))
        cols = hold_columns(states, outputs, inputs, step_no, dt_s)
        if seg.kind in (HOLD, PARK):
            if not window:
                window = [previous_cols] if previous_cols is not None else []
                held_from = step_no
            window.append(cols)
            held_to = step_no + n
        elif window:  # the restart: the window is complete
            window.append(cols)
            hold_rows += window_holds(window, held_from * dt_s, held_to * dt_s)
            window = []
        previous_cols = cols
        if seg.kind in (HOLD, PARK):
            rest = at_rest_index(states, dt_s)
            if rest is None:
                unjudged_at.append(step_no * dt_s)
            else:
                pos = states[rest:, L.X_M:L.Y_M + 1]
                creep = float(np.hypot(*(pos.max(axis=0) - pos.min(axis=0))))
                holds += 1
                max_creep = max(max_creep, creep)
                if creep > HOLD_CREEP_LIMIT_M and "hold_creep" not in found:
                    found["hold_creep"] = Violation(
                        "hold_creep", step_no + rest, (step_no + rest) * dt_s,
                        f"held car moved {creep * 1e3:.3f} mm after coming to rest "
                        f"({MANOEUVRE_NAMES[seg.kind]})")
        step_no += n
        if progress is not None:
            progress(min(step_no * dt_s, duration_s), duration_s)
    if window:  # the run ended held
        hold_rows += window_holds(window, held_from * dt_s, held_to * dt_s)
    return SoakReport(seed=seed, simulated_s=step_no * dt_s, steps=step_no,
                      wall_s=time.perf_counter() - t0, manoeuvres=counts, holds_checked=holds,
                      holds_unjudged=len(unjudged_at), unjudged_hold_times_s=unjudged_at,
                      max_hold_creep_m=max_creep, max_speed_mps=max_speed, min_fz_n=min_fz,
                      violations=sorted(found.values(), key=lambda v: v.step),
                      holds=hold_rows)
