"""Play an OpenSCENARIO file with physical cars, headless (issue 31 items 2-3;
docs/openscenario.md).

Every entity becomes a car of one world on the scenario's OpenDRIVE terrain, driven by the
built-in driver (``simserver.core.driver``): its own path (the road's reference line offset
to the car's lane), the IDM's desired speed its speed target. The storyboard engine
(:class:`Storyboard`) runs in Python between compiled chunks of ``simulate_driven`` every
:data:`STORYBOARD_PERIOD_S`: it measures the cars (station ``s`` and offset ``t`` on the
road, speed, acceleration, travelled distance), evaluates the triggers and turns the
running actions into driver commands: a speed action sets the desired speed along the
action's shape in time; a lane change or lane offset rewrites the car's path ahead of it
with the lateral offset profile of the action's shape, mapped from time to station at the
car's speed when the action starts. Every storyboard element's state change is kept in a
trace (:attr:`XoscRun.trace`) with the time and the condition values that fired it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from simserver.adapters import openscenario as X
from simserver.adapters.driver_config import pack_params, path_rows
from simserver.adapters.opendrive import OpenDrive, Road, lane_start, load_opendrive
from simserver.adapters.opendrive import reference_points as road_points
from simserver.core import driver as D
from simserver.core import layout as L
from simserver.core.params import ROAD_CROSS_SLOPE_PCT, ROAD_GRADE_PCT
from simserver.core.terrain import TERRAIN_PLANE, terrain_road
from simserver.sim.scenario import (
    ScenarioResult,
    WorldResult,
    WorldScenario,
    load_world_scenario,
    start_run,
)

REPO = Path(__file__).resolve().parents[2]
REFERENCE_CAR = REPO / "configs" / "vehicles" / "paper_sedan" / "vehicle.yaml"
"""The car every ``vehicleCategory="car"`` entity becomes (docs/openscenario.md: what maps)."""
STORYBOARD_PERIOD_S = 0.01
"""The storyboard is evaluated every 10 ms of simulated time (10 world steps at 1 kHz)."""
PATH_STEP_M = 0.5  # spacing of a car's path points along the road
NEAR_SAMPLES = 20  # a car's projection walks from its last sample at most this far
TERRAIN_CELL_M = 0.5
EQUAL_TOLERANCE = 0.01  # ``equalTo``/``notEqualTo`` compare within this (the quantity's unit)
STANDSTILL_MPS = 0.01  # a car slower than this stands still
STOP_MARGIN_M = 0.1  # a target speed of 0: the stop point this beyond the braking distance
STOP_CRAWL_MPS = 0.5  # ... and the desired speed meanwhile (the stop law governs)
DEFAULT_DURATION_S = 60.0  # a run ends here if the stop trigger has not fired
TRACKING_IDM_A_MPS2 = 5.0  # the IDM's a and delta of a scenario car: a tight speed tracker
TRACKING_IDM_DELTA = 10.0  # (the speed lag of a ramp is about 2 v / (a delta): section 15)


def shape(kind: str, x: float) -> float:
    """A transition's fraction done at ``x`` in [0, 1] of its length."""
    x = min(1.0, max(0.0, x))
    if kind == "step":
        return 1.0
    if kind == "linear":
        return x
    if kind == "cubic":
        return x * x * (3.0 - 2.0 * x)
    return 0.5 * (1.0 - math.cos(math.pi * x))  # sinusoidal


def compare(rule: str, value: float, threshold: float) -> bool:
    if rule == "greaterThan":
        return value > threshold
    if rule == "lessThan":
        return value < threshold
    if rule == "greaterOrEqual":
        return value >= threshold
    if rule == "lessOrEqual":
        return value <= threshold
    if rule == "equalTo":
        return abs(value - threshold) <= EQUAL_TOLERANCE
    return abs(value - threshold) > EQUAL_TOLERANCE  # notEqualTo


# ------------------------------------------------------------------------- road geometry
@dataclass
class RoadFrame:
    """A road's reference line sampled every PATH_STEP_M: for (s, t) of the cars."""

    road: Road
    s: np.ndarray
    x: np.ndarray
    y: np.ndarray
    hdg: np.ndarray
    hdg_unwrapped: np.ndarray  # once here, not per call of xy (it was most of a tick)

    @classmethod
    def of(cls, road: Road) -> RoadFrame:
        s = np.linspace(0.0, road.length, max(2, int(road.length / PATH_STEP_M) + 1))
        x, y, h = road_points(road, s)
        return cls(road, s, x, y, h, np.unwrap(h))

    def st(self, x: float, y: float) -> tuple[float, float]:
        """Station and lateral offset (+ left) of a world point (nearest sample, then
        projected on its tangent)."""
        s, t = self.st_many(np.array([x]), np.array([y]))
        return s[0], t[0]

    def st_many(self, x: np.ndarray, y: np.ndarray,
                near: list[int] | None = None) -> tuple[list[float], list[float]]:
        """:meth:`st` of several points in one pass over the samples (the same arithmetic
        element by element, so the same bits). ``near``: each point's nearest sample of the
        last call (updated in place): the search walks from there (:meth:`_descend`)."""
        if near is None:
            k = np.argmin((self.x[None, :] - x[:, None]) ** 2
                          + (self.y[None, :] - y[:, None]) ** 2, axis=1).tolist()
        else:
            k = [self._descend(float(x[j]), float(y[j]), k0) for j, k0 in enumerate(near)]
            near[:] = k
        out_s, out_t = [], []
        for j, kj in enumerate(k):
            dx, dy = float(x[j]) - self._xs[kj], float(y[j]) - self._ys[kj]
            c, s = self._cos[kj], self._sin[kj]
            out_s.append(self._ss[kj] + dx * c + dy * s)
            out_t.append(-dx * s + dy * c)
        return out_s, out_t

    def _descend(self, x: float, y: float, k: int) -> int:
        """The nearest sample to (x, y), walking downhill in distance from sample ``k``
        (the last tick's: a car moves less than a sample per tick, so a step or two); the
        whole road is searched when ``k`` is unknown (-1) or the walk goes further than
        ``NEAR_SAMPLES`` (the car jumped)."""
        xs, ys = self._xs, self._ys
        n = len(xs)
        if k < 0:
            return int(np.argmin((self.x - x) ** 2 + (self.y - y) ** 2))
        d = (xs[k] - x) * (xs[k] - x) + (ys[k] - y) * (ys[k] - y)
        k0 = k
        for step in (1, -1):
            while 0 <= k + step < n:
                j = k + step
                dj = (xs[j] - x) * (xs[j] - x) + (ys[j] - y) * (ys[j] - y)
                if dj >= d:
                    break
                k, d = j, dj
            if k != k0:
                break
        if abs(k - k0) > NEAR_SAMPLES:
            return int(np.argmin((self.x - x) ** 2 + (self.y - y) ** 2))
        return k

    def xy(self, s: np.ndarray | float, t: np.ndarray | float) -> tuple[Any, Any]:
        x = np.interp(s, self.s, self.x)
        y = np.interp(s, self.s, self.y)
        h = np.interp(s, self.s, self.hdg_unwrapped)
        return x - np.sin(h) * t, y + np.cos(h) * t

    def lane_t(self, s: float, lane: int) -> float:
        """The centre offset of lane ``lane`` at ``s`` (``lane_start``'s placement)."""
        x, y, _ = lane_start(self._od, self.road.id, min(max(s, 0.0), self.road.length), lane)
        return self.st(x, y)[1]

    def lane_at(self, s: float, t: float) -> int:
        """The lane whose centre is nearest ``t`` at ``s``."""
        best, best_d = 0, math.inf
        for sec in self.road.lane_sections:
            for lane in sec.lanes:
                if lane.id == 0:
                    continue
                try:
                    d = abs(self.lane_t(s, lane.id) - t)
                except Exception:  # noqa: BLE001 - a lane absent at s is no candidate
                    continue
                if d < best_d:
                    best, best_d = lane.id, d
        return best

    _od: OpenDrive = field(default=None, repr=False)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        # plain floats for the per-tick projection (Python float arithmetic on them is
        # the same IEEE arithmetic as on numpy scalars, and faster)
        self._xs, self._ys, self._ss = self.x.tolist(), self.y.tolist(), self.s.tolist()
        self._cos = [math.cos(h) for h in self.hdg.tolist()]
        self._sin = [math.sin(h) for h in self.hdg.tolist()]


# ------------------------------------------------------------------------- cars
@dataclass
class Car:
    name: str
    index: int
    vehicle: X.Vehicle
    frame: RoadFrame
    direction: float  # +1: drives along +s, -1: against
    s: float = 0.0
    t: float = 0.0
    u: float = 0.0
    accel: float = 0.0
    travelled: float = 0.0
    still_since: float | None = None
    target_speed: float = 0.0
    speed_action: tuple | None = None  # (t0, v0, v1, T, shape, relative entity/None, ...)
    lateral_action: tuple | None = None  # (t0, T)
    stopping: bool = False  # a speed target of 0: held at a stop point
    xy_now: tuple[Any, Any] | None = None  # frame.xy(s, t) of this tick, once (conditions)

    def road_xy(self) -> tuple[Any, Any]:
        """World x, y of the car's (s, t) on its road, computed once per storyboard tick
        (several conditions ask for it)."""
        if self.xy_now is None:
            self.xy_now = self.frame.xy(self.s, self.t)
        return self.xy_now


def _place(pos: X.Position, cars: dict[str, Car], frames: dict[str, RoadFrame],
           path: Path) -> tuple[str, float, float, float | None]:
    """(road id, s, t, absolute heading or None) of a position of the subset."""
    v = pos.values
    if pos.kind == "LanePosition":
        f = frames.get(v["roadId"])
        if f is None:
            raise X.XoscError(f"{path}:{pos.line}: <LanePosition>: no road {v['roadId']!r} "
                              f"in the road file (roads: {', '.join(frames)})")
        try:
            t = f.lane_t(v["s"], v["laneId"])
        except Exception as exc:  # noqa: BLE001 - LaneStartError: say where
            raise X.XoscError(f"{path}:{pos.line}: <LanePosition>: {exc}") from None
        return v["roadId"], v["s"], t + v.get("offset", 0.0), None
    if pos.kind == "RoadPosition":
        if v["roadId"] not in frames:
            raise X.XoscError(f"{path}:{pos.line}: <RoadPosition>: no road {v['roadId']!r}")
        return v["roadId"], v["s"], v["t"], None
    if pos.kind in ("RelativeRoadPosition", "RelativeLanePosition"):
        ref = cars.get(v["entityRef"])
        if ref is None:
            raise X.XoscError(f"{path}:{pos.line}: <{pos.kind}>: entity {v['entityRef']!r} "
                              "is placed after this one: place it first")
        if pos.kind == "RelativeRoadPosition":
            return ref.frame.road.id, ref.s + v["ds"], ref.t + v["dt"], None
        lane = ref.frame.lane_at(ref.s, ref.t)
        target = lane + int(v["dLane"])
        if lane * target <= 0:  # lane ids skip 0
            target += 1 if v["dLane"] > 0 else -1
        s = ref.s + v.get("ds", v.get("dsLane", 0.0))
        return ref.frame.road.id, s, ref.frame.lane_t(s, target) + v.get("offset", 0.0), None
    # WorldPosition: onto the first road it is nearest
    best = min(frames.values(), key=lambda f: abs(f.st(v["x"], v["y"])[1]))
    s, t = best.st(v["x"], v["y"])
    return best.road.id, s, t, v.get("h")


# ------------------------------------------------------------------------- the storyboard
STANDBY, RUNNING, COMPLETE = "standby", "running", "complete"


@dataclass
class Element:
    kind: str
    name: str
    obj: Any
    parent: Element | None
    state: str = STANDBY
    executions: int = 0
    children: list[Element] = field(default_factory=list)
    transitions: set[str] = field(default_factory=set)  # this tick's


@dataclass
class CondState:
    prev: bool | None = None
    pending: list[float] = field(default_factory=list)  # fire times waiting for the delay
    history: list[tuple[float, bool]] = field(default_factory=list)  # edge "none" + delay


@dataclass
class XoscRun:
    """A played scenario: the world's result (one ScenarioResult per entity), the trace."""

    scenario: X.Scenario
    result: WorldResult
    trace: list[dict[str, Any]]
    end_time_s: float
    ended_by: str
    wall_time_s: float
    bumpers_m: dict[str, tuple[float, float]]  # per car: CG to front and to rear bumper
    physics_wall_s: float = 0.0  # of wall_time_s, in the compiled simulate_driven
    cpu_time_s: float = 0.0  # the process's CPU time of the run loop


class Storyboard:
    """The storyboard state machine over the cars (module docstring)."""

    def __init__(self, sc: X.Scenario, cars: dict[str, Car], drivers: D.Drivers) -> None:
        self.sc = sc
        self.cars = cars
        self.drivers = drivers
        self.trace: list[dict[str, Any]] = []
        self.cond: dict[int, CondState] = {}
        self.elements: list[Element] = []
        self.by_name: dict[tuple[str, str], Element] = {}
        self.stories = [self._tree("story", s, None) for s in sc.stories]
        self.action_elements: list[Element] = []
        self._targets: dict[tuple[int, str], tuple[float, float]] = {}
        self.contacts: list[dict[str, Any]] = []  # contact events since the last tick
        # each condition's last measured values (the trace's cause); this storyboard's own
        # (a class-level dict was shared by every storyboard of the process, the live
        # worker's and a headless run's alike, and kept every condition ever evaluated)
        self._last_values: dict[int, Any] = {}

    def _tree(self, kind: str, obj: Any, parent: Element | None) -> Element:
        e = Element(kind, obj.name, obj, parent)
        self.elements.append(e)
        self.by_name[kind, obj.name] = e
        sub = {"story": ("act", "acts"), "act": ("maneuverGroup", "groups"),
               "maneuverGroup": ("maneuver", "maneuvers"), "maneuver": ("event", "events"),
               "event": ("action", "actions")}.get(kind)
        if sub is not None:
            e.children = [self._tree(sub[0], c, e) for c in getattr(obj, sub[1])]
        return e

    # -------------------------------------------------------------- state changes
    def set_state(self, e: Element, state: str, now: float, cause: Any = None) -> None:
        if e.state == state:
            return
        transition = {RUNNING: "startTransition", COMPLETE: "endTransition",
                      STANDBY: "standbyTransition"}[state]
        e.transitions.add(transition)
        self.trace.append({"t_s": round(now, 6), "kind": e.kind, "name": e.name,
                           "from": e.state, "to": state, **({"cause": cause} if cause else {})})
        e.state = state

    # -------------------------------------------------------------- conditions
    def condition_value(self, c: X.Condition, now: float) -> tuple[bool, dict[str, float]]:
        v = c.values
        if c.kind == "SimulationTimeCondition":
            return compare(v["rule"], now, v["value"]), {"t_s": now}
        if c.kind == "StoryboardElementStateCondition":
            kind = v["storyboardElementType"]
            e = self.by_name.get((kind, v["storyboardElementRef"]))
            if e is None:
                raise X.XoscError(f"{self.sc.path}:{c.line}: <{c.kind}>: no {kind} named "
                                  f"{v['storyboardElementRef']!r}")
            want = v["state"]
            ok = ({"standbyState": STANDBY, "runningState": RUNNING,
                   "completeState": COMPLETE}.get(want) == e.state) or want in e.transitions
            return ok, {}
        results = []
        seen: dict[str, float] = {}
        for name in c.triggering:
            ok, val = self._entity_condition(c, self.cars[name], now)
            results.append(ok)
            seen[name] = val
        ok = all(results) if c.triggering_rule == "all" else any(results)
        return ok, seen

    def _longitudinal(self, a: Car, b: Car, freespace: bool) -> float:
        """Distance from ``a`` to ``b`` along the road in ``a``'s direction of travel
        (bumper to bumper when ``freespace``: negative when they overlap)."""
        d = a.direction * (b.s - a.s)
        if freespace:
            pa, pb = self.drivers.params[a.index], self.drivers.params[b.index]
            d = d - (pa[D.DP_FRONT_M] + pb[D.DP_REAR_M]) if d >= 0 else \
                d + (pa[D.DP_REAR_M] + pb[D.DP_FRONT_M])
        return d

    def _entity_condition(self, c: X.Condition, car: Car, now: float) -> tuple[bool, float]:
        v = c.values
        free = v.get("freespace", "false") == "true"
        if c.kind == "TimeHeadwayCondition":
            d = self._longitudinal(car, self.cars[v["entityRef"]], free)
            val = d / car.u if car.u > 1e-9 and d > 0 else (math.inf if d > 0 else -math.inf)
            if d <= 0:  # the other car is behind: no headway (esmini: -1 s)
                val = -1.0
            return compare(v["rule"], val, v["value"]), val
        if c.kind == "TimeToCollisionCondition":
            other = self.cars[v["entityRef"]]
            d = self._longitudinal(car, other, free)
            closing = car.u - other.u * other.direction * car.direction
            val = d / closing if d > 0 and closing > 1e-9 else math.inf
            return compare(v["rule"], val, v["value"]), val
        if c.kind == "RelativeDistanceCondition":
            other = self.cars[v["entityRef"]]
            kind = v.get("relativeDistanceType", "longitudinal")
            if kind == "longitudinal":
                val = abs(self._longitudinal(car, other, free))
            elif kind == "lateral":
                val = abs(other.t - car.t)
            else:
                xa, ya = car.road_xy()
                xb, yb = other.road_xy()
                val = float(math.hypot(xb - xa, yb - ya))
            return compare(v["rule"], val, v["value"]), val
        if c.kind == "RelativeSpeedCondition":
            other = self.cars[v["entityRef"]]
            val = car.u - other.u
            return compare(v["rule"], val, v["value"]), val
        if c.kind == "SpeedCondition":
            return compare(v["rule"], car.u, v["value"]), car.u
        if c.kind == "AccelerationCondition":
            return compare(v["rule"], car.accel, v["value"]), car.accel
        if c.kind == "TraveledDistanceCondition":
            return car.travelled >= v["value"], car.travelled
        if c.kind == "StandStillCondition":
            held = 0.0 if car.still_since is None else now - car.still_since
            return car.still_since is not None and held >= v["duration"], held
        if c.kind == "CollisionCondition":
            return self._collision(v, car)
        if c.kind == "ReachPositionCondition":
            key = (id(c), car.name)  # an absolute position is placed once
            if key not in self._targets or c.position.kind.startswith("Relative"):
                _, s, t, _ = _place(c.position, self.cars, {car.frame.road.id: car.frame},
                                    self.sc.path)
                self._targets[key] = car.frame.xy(s, t)
            xa, ya = car.road_xy()
            xb, yb = self._targets[key]
            val = float(math.hypot(xb - xa, yb - ya))
            return val <= v["tolerance"], val
        raise X.XoscError(f"{self.sc.path}:{c.line}: <{c.kind}>: not evaluated")

    def _collision(self, v: dict[str, Any], car: Car) -> tuple[bool, float]:
        """True at the evaluation after a contact event (a pair of cars that starts to
        touch, docs/model.md section 16) of ``car`` with the entity ``entityRef``, or with
        any car for ``objectType="vehicle"`` (only cars are in the world); its value is
        the event's closing speed (m/s; 0 with none). A pulse: the event is the contact's
        start, so the condition is true once per contact (docs/openscenario.md)."""
        ref = v.get("entityRef")
        closing = [e["closing_speed_mps"] for e in self.contacts
                   if car.name in (e["car_a"], e["car_b"])
                   and (ref in (e["car_a"], e["car_b"]) if ref is not None
                        else v.get("objectType") == "vehicle")]
        return bool(closing), max(closing, default=0.0)

    def trigger(self, trig: X.Trigger, now: float) -> dict[str, Any] | None:
        """The cause (condition values) if the trigger fires now, else None. Every
        condition is evaluated every tick (edges need the previous value)."""
        fired = None
        for group in trig:
            cause: dict[str, Any] = {}
            all_ok = True
            for c in group:
                ok = self._edge(c, now)
                cause[c.name or c.kind] = self._last_values.get(id(c))
                all_ok &= ok
            if all_ok and fired is None:
                fired = cause
        return fired

    def _edge(self, c: X.Condition, now: float) -> bool:
        st = self.cond.setdefault(id(c), CondState())
        raw, val = self.condition_value(c, now)
        self._last_values[id(c)] = val
        prev = st.prev
        st.prev = raw
        if c.edge == "none":
            if c.delay_s <= 0.0:
                return raw
            st.history.append((now, raw))
            while len(st.history) > 1 and st.history[1][0] <= now - c.delay_s + 1e-9:
                st.history.pop(0)
            return st.history[0][0] <= now - c.delay_s + 1e-9 and st.history[0][1]
        edge = prev is not None and (
            (c.edge == "rising" and raw and not prev)
            or (c.edge == "falling" and prev and not raw)
            or (c.edge == "risingOrFalling" and raw != prev))
        if prev is None and c.edge in ("rising", "risingOrFalling") and raw:
            edge = False  # true from the first evaluation: no edge (esmini's behaviour)
        if edge:
            st.pending.append(now + c.delay_s)
        if st.pending and st.pending[0] <= now + 1e-9:
            st.pending.pop(0)
            return True
        return False

    # -------------------------------------------------------------- the tick
    def tick(self, now: float) -> str | None:
        """One evaluation: triggers, state changes, actions' commands. Returns the stop
        trigger's cause (the run ends) or None."""
        for e in self.elements:
            e.transitions.clear()
        stop = self.trigger(self.sc.stop, now) if self.sc.stop else None
        for story in self.stories:
            if story.state == COMPLETE:  # ends once: a finished story is not restarted
                continue
            self.set_state(story, RUNNING, now)
            for act in story.children:
                self._act(act, now)
            if all(a.state == COMPLETE for a in story.children):
                self.set_state(story, COMPLETE, now)
        for car in self.cars.values():
            self._command(car, now)
        if stop is not None:
            # the storyboard's stop ends every element with it (running or standby ->
            # complete, the standard's stopTransition/skipTransition), each in the trace
            for story in self.stories:
                if story.state != COMPLETE:
                    self._end_all(story, now)
            self.trace.append({"t_s": round(now, 6), "kind": "storyboard", "name": "stop",
                               "from": RUNNING, "to": COMPLETE, "cause": stop})
            return "stop trigger"
        return None

    def _act(self, act: Element, now: float) -> None:
        a: X.Act = act.obj
        if act.state == STANDBY:
            cause = self.trigger(a.start, now) if a.start else {}
            if cause is not None:
                self.set_state(act, RUNNING, now, cause)
                for g in act.children:
                    self.set_state(g, RUNNING, now)
                    g.executions = 1
                    for m in g.children:
                        self.set_state(m, RUNNING, now)
        if act.state != RUNNING:
            return
        if a.stop:
            cause = self.trigger(a.stop, now)
            if cause is not None:
                self._end_all(act, now, cause)
                return
        for g in act.children:
            if g.state != RUNNING:
                continue
            for m in g.children:
                if m.state != RUNNING:
                    continue
                for ev in m.children:
                    self._event(ev, m, now)
                if all(ev.state == COMPLETE for ev in m.children):
                    self.set_state(m, COMPLETE, now)
            if all(m.state == COMPLETE for m in g.children):
                if g.executions < g.obj.max_executions:  # run the group again
                    g.executions += 1
                    for m in g.children:
                        for ev in m.children:
                            ev.executions = 0
                            self.set_state(ev, STANDBY, now)
                        self.set_state(m, RUNNING, now)
                else:
                    self.set_state(g, COMPLETE, now)
        if all(g.state == COMPLETE for g in act.children):
            self.set_state(act, COMPLETE, now)

    def _end_all(self, e: Element, now: float, cause: Any = None) -> None:
        for c in e.children:
            if c.state != COMPLETE:
                self._end_all(c, now)
        self.set_state(e, COMPLETE, now, cause)

    def _event(self, ev: Element, maneuver: Element, now: float) -> None:
        obj: X.Event = ev.obj
        if ev.state == STANDBY:
            cause = self.trigger(obj.start, now) if obj.start else {}
            if cause is None:
                return
            others = [o for o in maneuver.children if o is not ev and o.state == RUNNING]
            if others and obj.priority == "skip":
                return
            if obj.priority in ("overwrite", "override"):
                for o in others:
                    self._end_all(o, now, {"overwritten by": ev.name})
            ev.executions += 1
            self.set_state(ev, RUNNING, now, cause)
            for act_el in ev.children:
                self.set_state(act_el, RUNNING, now)
                self._start_action(act_el.obj, now)
        if ev.state == RUNNING:
            for act_el in ev.children:
                if act_el.state == RUNNING and self._action_done(act_el.obj, now):
                    self.set_state(act_el, COMPLETE, now)
            if all(a.state == COMPLETE for a in ev.children):
                if ev.executions < obj.max_executions:
                    self.set_state(ev, COMPLETE, now)
                    self.set_state(ev, STANDBY, now)
                else:
                    self.set_state(ev, COMPLETE, now)

    # -------------------------------------------------------------- actions -> the driver
    def _start_action(self, a: X.Action, now: float) -> None:
        for name in a.actors:
            car = self.cars[name]
            if a.kind == "SpeedAction":
                self.start_speed(car, a, now)
            elif a.kind in ("LaneChangeAction", "LaneOffsetAction"):
                self.start_lateral(car, a, now)
            else:
                raise X.XoscError(f"{self.sc.path}:{a.line}: <{a.kind}>: not played in a "
                                  "story (a physical car is not teleported)")

    def start_speed(self, car: Car, a: X.Action, now: float) -> None:
        tgt = a.target
        if tgt["kind"] == "absolute":
            v1 = tgt["value"]
            rel = None
        else:
            other = self.cars[tgt["entityRef"]]
            v1 = (other.u * tgt["value"] if tgt["valueType"] == "factor"
                  else other.u + tgt["value"])
            rel = (other.name, tgt["valueType"], tgt["value"]) if tgt["continuous"] else None
        v0 = car.target_speed if car.speed_action is None else self._speed_now(car, now)
        v0 = car.u if now > 0 else v0
        dyn = a.dynamics
        dv = v1 - v0
        if dyn.shape == "step" or dyn.value == 0.0:
            duration = 0.0
        elif dyn.dimension == "time":
            duration = dyn.value
        elif dyn.dimension == "rate":
            duration = abs(dv) / abs(dyn.value)
        else:  # distance: covered at the mean speed of the change
            duration = 2.0 * dyn.value / max(v0 + v1, 1e-6)
        car.speed_action = (now, v0, v1, duration, dyn.shape, rel)
        self._apply_speed(car, now)

    def _speed_now(self, car: Car, now: float) -> float:
        t0, v0, v1, dur, kind, rel = car.speed_action
        if rel is not None:
            other = self.cars[rel[0]]
            v1 = other.u * rel[2] if rel[1] == "factor" else other.u + rel[2]
        frac = 1.0 if dur <= 0.0 else shape(kind, (now - t0) / dur)
        return v0 + (v1 - v0) * frac

    def _apply_speed(self, car: Car, now: float) -> None:
        if car.speed_action is None:
            return
        car.target_speed = max(0.0, self._speed_now(car, now))
        c = car.index
        if car.target_speed <= 0.0:
            # to rest: the driver's stop law brings the car to a hold (the IDM alone would
            # drive off again from v = 0 towards a desired speed of 0)
            if not car.stopping:
                st, dp = self.drivers.state[c], self.drivers.params[c]
                D.stop_at(self.drivers, c, st[D.DS_STATION_M] + dp[D.DP_FRONT_M]
                          + car.u * car.u / (2.0 * dp[D.DP_STOP_DECEL_MPS2]) + STOP_MARGIN_M)
                car.stopping = True
            D.set_target_speed(self.drivers, c, STOP_CRAWL_MPS)
        else:
            if car.stopping:
                D.go(self.drivers, c)
                car.stopping = False
            D.set_target_speed(self.drivers, c, car.target_speed)

    def start_lateral(self, car: Car, a: X.Action, now: float) -> None:
        tgt = a.target
        if a.kind == "LaneChangeAction":
            if tgt["kind"] == "absolute":
                lane = tgt["value"]
            else:
                other = self.cars[tgt["entityRef"]]
                lane = other.frame.lane_at(other.s, other.t)
                step = int(tgt["value"]) * int(other.direction)
                target = lane + step
                if lane * target <= 0 and step != 0:
                    target += 1 if step > 0 else -1
                lane = target
            t1 = car.frame.lane_t(car.s, lane) + tgt.get("offset", 0.0)
        else:
            if tgt["kind"] == "absolute":
                lane = car.frame.lane_at(car.s, car.t)
                t1 = car.frame.lane_t(car.s, lane) + tgt["value"] * car.direction
            else:
                other = self.cars[tgt["entityRef"]]
                t1 = other.t + tgt["value"] * other.direction
        t0 = car.t
        dyn = a.dynamics
        dt = abs(t1 - t0)
        if dyn.shape == "step" or dt == 0.0:
            duration = 0.0
        elif a.kind == "LaneOffsetAction":  # the peak lateral acceleration of the shape
            k = {"linear": 4.0, "cubic": 6.0, "sinusoidal": math.pi ** 2 / 2.0}[dyn.shape]
            duration = math.sqrt(k * dt / dyn.value) if math.isfinite(dyn.value) else 0.0
        elif dyn.dimension == "time":
            duration = dyn.value
        elif dyn.dimension == "rate":
            duration = dt / abs(dyn.value)
        else:
            duration = dyn.value / max(car.u, 0.1)
        car.lateral_action = (now, duration)
        self.rewrite_path(car, t0, t1, duration, dyn.shape)

    def rewrite_path(self, car: Car, t0: float, t1: float, duration: float,
                     kind: str) -> None:
        """The car's path ahead becomes the lateral profile ``t0 -> t1`` of ``kind`` over
        ``duration``, from time to station at the car's speed now."""
        # the car's own path (its parameter DP_PATH: a live world's path k is not car k)
        first, rows = self.drivers.path_rows[int(self.drivers.params[car.index, D.DP_PATH])]
        seg = self.drivers.paths[first:first + rows]
        s_road = car.frame.s if car.direction > 0 else car.frame.s[::-1]
        ahead = car.direction * (s_road - car.s)
        span = max(car.u, 0.5) * duration
        if span <= 0.0:
            frac = (ahead >= 0).astype(float)
        else:
            frac = np.array([shape(kind, a / span) if a > 0 else 0.0 for a in ahead])
        t = t0 + (t1 - t0) * frac
        x, y = car.frame.xy(s_road, t)
        seg[:, D.PATH_X_M] = x
        seg[:, D.PATH_Y_M] = y

    def _action_done(self, a: X.Action, now: float) -> bool:
        done = True
        for name in a.actors:
            car = self.cars[name]
            if a.kind == "SpeedAction" and car.speed_action is not None:
                t0, _, _, dur, _, rel = car.speed_action
                done &= rel is None and now >= t0 + dur
            elif car.lateral_action is not None:
                t0, dur = car.lateral_action
                done &= now >= t0 + dur
        return done

    def _command(self, car: Car, now: float) -> None:
        self._apply_speed(car, now)


# ------------------------------------------------------------------------- the runner
def _vehicle_block(v: X.Vehicle, path: Path) -> dict[str, Any]:
    if v.category != "car":
        raise X.XoscError(f"{v.path}:{v.line}: <Vehicle>: category {v.category!r}: only "
                          "cars are played (each becomes the reference sedan)")
    front_bumper = v.bbox_center_m[0] + 0.5 * v.bbox_size_m[0] - v.rear_axle_x_m
    rear_bumper = 0.5 * v.bbox_size_m[0] - (v.bbox_center_m[0] - v.rear_axle_x_m)
    return {"front_overhang_m": min(5.0, max(0.0, front_bumper - v.wheelbase_m)),
            "rear_overhang_m": min(5.0, max(0.0, rear_bumper))}


def play(path: str | Path, duration_s: float = DEFAULT_DURATION_S,
         dt_s: float = 0.001, parameters: dict[str, Any] | None = None) -> XoscRun:
    """Read and play an ``.xosc`` headless (module docstring); ``parameters``: values for
    the file's own declared parameters (``openscenario.load_openscenario``)."""
    sc, cars, ws = setup(path, duration_s, dt_s, parameters)
    return _run(sc, ws, cars)


def ego_name(sc: X.Scenario) -> str:
    """The scenario's ego: the entity named ``Ego`` (any case) if there is one, else the
    first entity of ``<Entities>`` (docs/openscenario.md: the live ego)."""
    names = list(sc.entities)
    return next((n for n in names if n.lower() == "ego"), names[0])


def xosc_scene(path: str | Path, vehicle_path: str | Path | None = None,
               parameters: dict[str, Any] | None = None) -> Any:
    """An ``.xosc`` as a scene (``simserver.sim.scene.load_scene``: wherever a scene file
    is accepted, ``ctl/load`` included): the ego's car (:func:`ego_name`) at its start on
    the scenario's road (the terrain), at its initial speed; the other entities and the
    storyboard are not in a scene (``serve --scenario`` serves them). ``parameters``: as
    :func:`play`'s."""
    import dataclasses

    from simserver.adapters.config import load_vehicle

    sc, _, ws = setup(path, 1.0, 0.001, parameters)
    scene = ws.cars[ego_name(sc)].scene
    if vehicle_path is not None:
        scene = dataclasses.replace(scene, vehicle=load_vehicle(
            Path(vehicle_path), scene.model_options, options_source=str(path)))
    return scene


def setup(path: str | Path, duration_s: float = DEFAULT_DURATION_S, dt_s: float = 0.001,
          parameters: dict[str, Any] | None = None
          ) -> tuple[X.Scenario, dict[str, Car], WorldScenario]:
    """Read an ``.xosc`` and make its world's scenario: the reader's scenario, each
    entity's :class:`Car` (placed on its road, its initial speed) and the world scenario of
    the cars (each the reference sedan with its own path and tracking IDM)."""
    path = Path(path)
    sc = X.load_openscenario(path, parameters)
    if sc.road_file is None:
        raise X.XoscError(f"{path}: <RoadNetwork>: a <LogicFile> (OpenDRIVE road) is needed")
    od = load_opendrive(sc.road_file)
    frames = {r.id: RoadFrame.of(r) for r in od.roads}
    for f in frames.values():
        f._od = od
    cars: dict[str, Car] = {}
    speeds: dict[str, X.Action] = {}
    wrong_way: dict[str, bool] = {}
    for k, (name, ent) in enumerate(sc.entities.items()):
        tele = [a for a in sc.init[name] if a.kind == "TeleportAction"]
        if not tele:
            raise X.XoscError(f"{path}:{ent.line}: <ScenarioObject>: entity {name!r} has no "
                              "TeleportAction in <Init>: where does it start?")
        pos = tele[-1].position
        road, s, t, heading = _place(pos, cars, frames, path)
        frame = frames[road]
        hdg = float(np.interp(s, frame.s, frame.hdg_unwrapped))
        if heading is None:
            lane = frame.lane_at(s, t)
            along = (lane < 0) == (frame.road.rule == "RHT")
            direction = 1.0 if along else -1.0
            o = pos.orientation
            if o is not None:
                if o["type"] == "relative" and math.cos(o["h"]) < 0:
                    direction = -direction
                elif o["type"] == "absolute":
                    direction = 1.0 if math.cos(o["h"] - hdg) >= 0 else -1.0
        else:
            direction = 1.0 if math.cos(heading - hdg) >= 0 else -1.0
        cars[name] = Car(name, k, ent.vehicle, frame, direction, s=s, t=t)
        # a car set against its lane's direction of travel overtakes in the oncoming lane:
        # it does not stop for the cars coming its way (docs/openscenario.md)
        lane_along = (frame.lane_at(s, t) < 0) == (frame.road.rule == "RHT")
        wrong_way[name] = lane_along != (direction > 0)
        sp = [a for a in sc.init[name] if a.kind == "SpeedAction"]
        if sp:
            speeds[name] = sp[-1]
    for name, a in speeds.items():  # absolute ones first: relative ones refer to them
        if a.target["kind"] == "absolute":
            cars[name].target_speed = cars[name].u = a.target["value"]
    for name, a in speeds.items():
        if a.target["kind"] == "relative":
            other = cars[a.target["entityRef"]]
            cars[name].target_speed = cars[name].u = (
                other.u * a.target["value"] if a.target["valueType"] == "factor"
                else other.u + a.target["value"])
    data_cars = []
    for name, car in cars.items():
        f = car.frame
        x, y = f.xy(car.s, car.t)
        hdg = float(np.interp(car.s, f.s, f.hdg_unwrapped)) + (0 if car.direction > 0
                                                                  else math.pi)
        s_path = f.s if car.direction > 0 else f.s[::-1]
        px, py = f.xy(s_path, car.t)
        data_cars.append({
            "id": name, "vehicle": str(REFERENCE_CAR),
            "initial": {"x_m": float(x), "y_m": float(y),
                        "yaw_rad": (hdg + math.pi) % (2 * math.pi) - math.pi,
                        "u_mps": car.u, "relaxed": 1},
            "driver": {"path": {"points": np.column_stack([px, py]).tolist()},
                       "idm": {"v0_mps": max(car.u, 0.1), "a_mps2": TRACKING_IDM_A_MPS2,
                               "delta": TRACKING_IDM_DELTA},
                       **({"oncoming_stop": 0.0} if wrong_way[name] else {}),
                       **_vehicle_block(car.vehicle, path)}})
    data = {"name": path.stem, "description": sc.description,
            "terrain": {"kind": "opendrive", "file": str(sc.road_file),
                        "cell_m": TERRAIN_CELL_M},
            "duration_s": duration_s, "dt_s": dt_s,
            "record_every": max(1, int(round(STORYBOARD_PERIOD_S / dt_s))), "cars": data_cars}
    ws = load_world_scenario(path, data)
    return sc, cars, ws


def _own_paths(world: Any, ws: WorldScenario) -> D.Drivers:
    """The drivers with one path per car (a lane change rewrites only its car's)."""
    paths, params = [], np.zeros((len(world.ids), D.N_DRIVER_PARAM))
    state = D.initial_driver_state(len(world.ids))
    for c, cid in enumerate(world.ids):
        spec = ws.cars[cid].driver
        paths.append(path_rows(spec.path_xy, world.model.terrain, spec.speed_profile,
                               spec.params[D.DP_IDM_V0_MPS]))
        params[c] = pack_params(spec, world.model.vp[c], world.model.tp[c], c)
    counts = np.array([len(p) for p in paths], dtype=np.int64)
    rows = np.stack([np.concatenate([[0], np.cumsum(counts)[:-1]]), counts], axis=1)
    proj = np.zeros((len(world.ids), len(paths), D.N_PROJ))
    proj[:, :, D.PROJ_SEG] = -1.0
    return D.Drivers(params=params, state=state, paths=np.ascontiguousarray(np.concatenate(paths)),
                     path_rows=np.ascontiguousarray(rows), proj=proj,
                     pose=np.zeros((len(world.ids), 4)), axes=np.zeros((len(world.ids), 3, 3)))


def _cg_xy(world: Any, drivers: D.Drivers, c: int, axes: np.ndarray,
           road: np.ndarray, plane: bool) -> tuple[float, float]:
    """World x, y of car ``c``'s CG now (the driver's own placement, ``core.driver``);
    ``road``, ``plane``: the terrain's road row and whether it is the plane (per run)."""
    px, py, _, _ = D._horizontal_pose(  # noqa: SLF001 - the one placement of the driver
        world.data.x[c], drivers.params[c, D.DP_CG_HEIGHT_M], road[ROAD_GRADE_PCT],
        road[ROAD_CROSS_SLOPE_PCT], plane, axes)
    return float(px), float(py)


def _contacts_since(world: Any, seen: int) -> tuple[list[dict[str, Any]], int]:
    """The world's contact events after the first ``seen`` and the new count (the ring's
    lost events are gone either way: more than ``core.contact.EVENT_RING`` in 10 ms)."""
    if world.contact_count() == seen:
        return [], seen
    events, total, _lost = world.contact_events(seen)
    return events, total


def frame_groups(cars: dict[str, Car]) -> list[tuple[RoadFrame, list[Car], list[int]]]:
    """The cars by road (each road's cars projected on it in one pass), with each car's
    nearest sample (-1: unknown yet)."""
    by_frame: dict[int, tuple[RoadFrame, list[Car]]] = {}
    for car in cars.values():
        by_frame.setdefault(id(car.frame), (car.frame, []))[1].append(car)
    return [(f, members, [-1] * len(members)) for f, members in by_frame.values()]


def measure(cars: dict[str, Car], groups: list[tuple[RoadFrame, list[Car], list[int]]],
            world: Any, drivers: D.Drivers, axes: np.ndarray, road: np.ndarray,
            plane: bool, now: float, since_s: float,
            prev_xy: dict[str, tuple[float, float]]) -> None:
    """Each car's measures for the storyboard at ``now`` from ``world.data.x`` (its CG
    projected on its road for ``s`` and ``t``, its speed; its acceleration and travelled
    distance over the ``since_s`` since the last measure, 0: the first)."""
    cg = {car.name: _cg_xy(world, drivers, car.index, axes, road, plane)
          for car in cars.values()}
    for frame, members, near in groups:
        ss, ts = frame.st_many(np.array([cg[c.name][0] for c in members]),
                               np.array([cg[c.name][1] for c in members]), near)
        for car, s_m, t_m in zip(members, ss, ts, strict=True):
            car.s, car.t, car.xy_now = s_m, t_m, None
    for car in cars.values():
        px, py = cg[car.name]
        u = float(world.data.x[car.index, L.U_MPS])
        if since_s > 0.0 and car.name in prev_xy:
            car.accel = (u - car.u) / since_s
            car.travelled += math.hypot(px - prev_xy[car.name][0], py - prev_xy[car.name][1])
        prev_xy[car.name] = (px, py)
        car.u = u
        if abs(u) < STANDSTILL_MPS:
            car.still_since = now if car.still_since is None else car.still_since
        else:
            car.still_since = None


def _run(sc: X.Scenario, ws: WorldScenario, cars: dict[str, Car]) -> XoscRun:
    ids = list(ws.cars)
    starts = {cid: start_run(s, car_id=cid) for cid, s in ws.cars.items()}
    world = starts[ids[0]][0].world
    for cid in ids[1:]:
        starts[cid][0].move_to(world)
    first = ws.first
    n, every, dt = first.n_steps, first.record_every, first.dt_s
    drivers = _own_paths(world, ws)
    board = Storyboard(sc, cars, drivers)
    inputs = np.zeros((every, len(ids), L.N_INPUT))
    inputs[:, :, L.IN_GEAR] = L.GEAR_D  # the driver gives the rest
    n_rec = (n + every - 1) // every
    states = np.zeros((n_rec, len(ids), L.N_STATE))
    outputs = np.zeros((n_rec, len(ids), L.N_OUT))
    applied = np.zeros((n_rec, len(ids), L.N_INPUT))
    dstates = np.zeros((n_rec, len(ids), D.N_DRIVER_STATE))
    ended_by = "duration"
    axes = np.zeros((3, 3))
    road = terrain_road(world.model.terrain)
    plane = world.model.terrain.kind == TERRAIN_PLANE
    groups = frame_groups(cars)
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    physics = 0.0
    row = 0
    prev_xy = {}
    seen = world.contact_count()
    for row in range(n_rec):
        now = row * every * dt
        measure(cars, groups, world, drivers, axes, road, plane, now,
                every * dt if row else 0.0, prev_xy)
        board.contacts, seen = _contacts_since(world, seen)
        if board.tick(now) is not None:
            ended_by = "stop trigger"
            break
        tp = time.perf_counter()
        D.simulate_driven(world.model, world.data, drivers, inputs, states[row:row + 1],
                          outputs[row:row + 1], applied[row:row + 1], dstates[row:row + 1],
                          every)
        physics += time.perf_counter() - tp
    else:
        row = n_rec
    wall = time.perf_counter() - t0
    cpu = time.process_time() - cpu0
    rows = row if ended_by == "stop trigger" else n_rec
    out = {}
    for c, cid in enumerate(ids):
        st = np.ascontiguousarray(states[:rows, c])
        out[cid] = ScenarioResult(
            scenario=ws.cars[cid], time_s=st[:, L.TIME_S].copy(), states=st,
            outputs=np.ascontiguousarray(outputs[:rows, c]),
            inputs=np.ascontiguousarray(applied[:rows, c]),
            final_state=world.data.x[c].copy(), wall_time_s=wall,
            driver_states=np.ascontiguousarray(dstates[:rows, c]))
    bumpers = {cid: (float(drivers.params[c, D.DP_FRONT_M]),
                     float(drivers.params[c, D.DP_REAR_M])) for c, cid in enumerate(ids)}
    # the contacts of the run (core.contact's ring; a run of the shipped files has none)
    events, _, lost = world.contact_events(0)
    return XoscRun(sc, WorldResult(ws, out, wall, contact_events=events,
                                   contact_events_lost=lost),
                   board.trace, rows * every * dt, ended_by,
                   wall, bumpers, physics, cpu)
