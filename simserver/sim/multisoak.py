"""Multi-car soak: several cars on one road, seeded, with the soak's invariants every tick.

``run_multi_soak`` runs one world (``World``, the scene's terrain; its road's grade drawn
from the seed: hills) of ``n_cars`` cars in three roles (issue 30 item 5):

- **contact pair** (always two cars, lane ``y = PAIR_LANE_Y_M``): every
  ``PAIR_CYCLE_S`` a held car (foot brake 0.6, gear D) is placed at rest and a second car
  is placed ``PAIR_GAP_M`` behind it rolling at ``PAIR_SPEED_MPS`` with its pedals released
  in N: it rolls into the held car (a contact); after ``PAIR_BRAKE_AT_S`` it brakes and
  holds, resting where it stopped (often against the held car);
- **traffic** (half of the others, lane ``y = 0``): the built-in driver (``core.driver``)
  on one straight path, a queue with seeded desired speeds; the lead car is told to stop
  at a seeded point ahead and to go again after a seeded hold (stop-and-go: the queue
  stops behind it and holds with the brake); the last traffic car keeps a too-small gap
  (IDM ``s0`` 0.1 m, ``T`` 0.1 s), so it may touch the car ahead;
- **keyframed** (the rest, lanes ``y = 40, 80, ...``): the single-car soak's random
  drives (``soak.manoeuvre_plan``, ``segment_inputs``; the road is the world's, so a
  plan's road changes are not applied).

The physics runs closed loop (``core.driver.simulate_driven``) in chunks of
``CHUNK_S``; after each chunk **every recorded row** (every step: ``record_every`` 1) is
checked:

- ``finite`` and the other per-tick bounds of the single-car soak (``soak.check_invariants``,
  per car);
- ``hold_creep``: a car in a hold (a keyframed hold or park segment, a traffic car in the
  driver's hold mode, the pair's cars while braked) moves less than the single-car soak's
  ``HOLD_CREEP_LIMIT_M`` (1 mm) from ``soak.at_rest_index`` (1.5 s after it came to rest)
  until the hold ends; a hold in which a contact event involved the car after it came to
  rest is counted apart (``holds_struck``: it was hit, not creeping); a car resting
  against another from before is judged (contact adds no creep to a held car);
- ``contact_energy``: for each contact event between cars a and b at step k, over the
  rows from k - 1 to the end of the contact window (``ENERGY_WINDOW_S`` or the chunk's
  end, whichever first), the pair's kinetic energy (body translation, yaw, wheel spin)
  does not rise by more than the work put in: the drive torques' positive work
  (sum of max(0, T_drive Omega) dt over the wheels) and gravity's (-m g dh, dh the CG's
  rise on the road plane), plus ``ENERGY_TOL_J`` + ``ENERGY_TOL_REL`` x the pair's energy
  at the start (see the constants: energy the formula leaves out). With pedals released
  on the flat this is ``KE_after <= KE_before + tolerance``.

Seeded: the same seed and arguments give the same states bit for bit (``digest``).
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from simserver.adapters.driver_config import DriverSpec, build_drivers
from simserver.core import driver as D
from simserver.core import layout as L
from simserver.core import params as P
from simserver.core.chassis import static_wheel_load
from simserver.sim.scene import Scene
from simserver.sim.simulation import Simulation, World
from simserver.sim.soak import (
    HOLD,
    HOLD_CREEP_LIMIT_M,
    PARK,
    Segment,
    Violation,
    at_rest_index,
    check_invariants,
    manoeuvre_plan,
    segment_inputs,
)

CHUNK_S = 5.0  # the physics runs this long between checks (every row of it is checked)
GRADES_PCT = (0.0, 4.0, 8.0, -6.0)  # the road's grade is drawn from these (hills)
PAIR_LANE_Y_M = -12.0
PAIR_CYCLE_S = 15.0  # a multiple of CHUNK_S: the pair is placed anew at a chunk's start
PAIR_GAP_M = 0.4  # bumper to bumper when the rolling car is placed
PAIR_SPEED_MPS = 1.5  # the rolling car's speed when placed (a low-speed bump)
PAIR_BRAKE_AT_S = 5.0  # the rolling car brakes (0.6) from this time into the cycle
TRAFFIC_SPACING_M = 20.0  # CG to CG at the start
KEYFRAMED_LANE_SPACING_M = 40.0
ENERGY_WINDOW_S = 1.0
# What the energy balance leaves out, as its tolerance: the suspension's and tires'
# spring energy and the sprung mass's heave, roll and pitch motion (a bump rocks the
# body and the tire springs unload), the contact spring's own energy is not counted at
# all (it only lowers the pair's energy at the window's end), and the drive work is
# summed with the step's start spin (first-order in dt). A 1.5 m/s bump between two
# 1.5 t cars carries ~1.7 kJ.
ENERGY_TOL_J = 20.0
ENERGY_TOL_REL = 0.02

ROLE_PAIR_HELD, ROLE_PAIR_ROLLING, ROLE_TRAFFIC, ROLE_KEYFRAMED = range(4)
ROLE_NAMES = ("pair_held", "pair_rolling", "traffic", "keyframed")

# Test hook: called with (first step, states, outputs, driver states) of each chunk
# before the checks (float64[rows, n_cars, ...]); it may spoil the recorded rows to show
# the checks catch a breach. Never set outside tests.
Spoiler = Callable[[int, np.ndarray, np.ndarray, np.ndarray], None]


@dataclass
class CarHolds:
    """One car's holds."""

    role: str
    checked: int = 0
    unjudged: int = 0
    struck: int = 0
    max_creep_m: float = 0.0


@dataclass
class MultiSoakReport:
    """What a multi-car soak did and found."""

    seed: int
    n_cars: int
    grade_pct: float
    simulated_s: float
    steps: int
    wall_s: float
    holds: dict[str, CarHolds]
    contact_events: list[dict[str, Any]]
    contact_events_lost: int
    energy_checked: int
    max_energy_excess_j: float  # largest (rise - work - tolerance); <= 0 when all pass
    digest: str  # sha256 of every recorded state, in order
    violations: list[Violation] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """No invariant was violated."""
        return not self.violations

    def as_dict(self) -> dict[str, Any]:
        """JSON-friendly summary."""
        return {
            "mode": "multi", "seed": self.seed, "cars": self.n_cars,
            "grade_pct": self.grade_pct, "simulated_s": self.simulated_s,
            "steps": self.steps, "wall_s": round(self.wall_s, 2),
            "real_time_factor": round(self.simulated_s / max(self.wall_s, 1e-9), 2),
            "holds": {cid: h.__dict__ for cid, h in self.holds.items()},
            "contacts": len(self.contact_events),
            "contact_events": self.contact_events,
            "contact_events_lost": self.contact_events_lost,
            "energy_checked": self.energy_checked,
            "max_energy_excess_j": self.max_energy_excess_j,
            "digest": self.digest, "ok": self.ok,
            "violations": [dict(v.__dict__) for v in self.violations],
        }


class KeyframedDrive:
    """A seeded random drive served chunk by chunk (the whole plan's table would not fit
    in memory for hours): the inputs and each row's hold id (the segment's number + 1 in a
    hold or park segment, else 0)."""

    def __init__(self, rng: np.random.Generator, duration_s: float, dt_s: float) -> None:
        self.plan = manoeuvre_plan(rng, duration_s)
        self.dt_s = dt_s
        self.k = 0
        self.table = np.zeros((0, L.N_INPUT))
        self.hold = np.zeros(0, dtype=np.int64)
        self.previous = np.zeros(L.N_INPUT)

    def take(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """The next ``n`` rows (after the plan: the last hold goes on)."""
        while self.table.shape[0] < n:
            if self.k < len(self.plan):
                seg = self.plan[self.k]
            else:
                seg = Segment(HOLD, 10.0, brake=0.6, gear=self.previous[L.IN_GEAR])
            rows = segment_inputs(seg, self.previous, self.dt_s)
            self.previous = rows[-1].copy()
            hid = self.k + 1 if seg.kind in (HOLD, PARK) else 0
            self.table = np.concatenate([self.table, rows])
            self.hold = np.concatenate([self.hold, np.full(len(rows), hid, dtype=np.int64)])
            self.k += 1
        out = self.table[:n], self.hold[:n]
        self.table, self.hold = self.table[n:], self.hold[n:]
        return out


class HoldTracker:
    """A car's current hold (its rows' x, y, u, v), judged when the hold ends."""

    def __init__(self, holds: CarHolds, dt_s: float) -> None:
        self.holds = holds
        self.dt_s = dt_s
        self.hid = 0
        self.first_step = 0
        self.rows: list[np.ndarray] = []
        self.struck_steps: list[int] = []

    def feed(self, first_step: int, states: np.ndarray, hold_ids: np.ndarray,
             found: dict[str, Violation], car_id: str) -> None:
        """Rows of one chunk with their hold ids (0: not held)."""
        cols = states[:, [L.X_M, L.Y_M, L.U_MPS, L.V_MPS]]
        start = 0
        n = len(hold_ids)
        while start < n:
            hid = int(hold_ids[start])
            end = start + 1
            while end < n and hold_ids[end] == hid:
                end += 1
            if hid != self.hid:
                self.close(found, car_id)
                self.hid, self.first_step = hid, first_step + start
            if hid:
                self.rows.append(cols[start:end])
            start = end

    def strike(self, step: int) -> None:
        """A contact event involving this car at ``step``."""
        if self.hid:
            self.struck_steps.append(step)

    def close(self, found: dict[str, Violation], car_id: str) -> None:
        """Judge the hold that just ended (if any)."""
        if self.hid and self.rows:
            rows = np.concatenate(self.rows)
            st = np.zeros((len(rows), L.N_STATE))
            st[:, [L.X_M, L.Y_M, L.U_MPS, L.V_MPS]] = rows
            rest = at_rest_index(st, self.dt_s)
            h = self.holds
            if rest is None:
                h.unjudged += 1
            elif any(s >= self.first_step + rest - int(1.5 / self.dt_s)
                     for s in self.struck_steps):
                h.struck += 1
            else:
                pos = rows[rest:, :2]
                creep = float(np.hypot(*(pos.max(axis=0) - pos.min(axis=0))))
                h.checked += 1
                h.max_creep_m = max(h.max_creep_m, creep)
                if creep > HOLD_CREEP_LIMIT_M and "hold_creep" not in found:
                    step = self.first_step + rest
                    found["hold_creep"] = Violation(
                        "hold_creep", step, step * self.dt_s,
                        f"car {car_id} ({h.role}) moved {creep * 1e3:.3f} mm in a hold "
                        "after coming to rest")
        self.hid = 0
        self.rows = []
        self.struck_steps = []


def pair_energy(states: np.ndarray, vp: np.ndarray, a: int, b: int, axes: np.ndarray,
                gravity_mps2: float) -> tuple[np.ndarray, np.ndarray]:
    """Per row: the pair's kinetic energy (J) and its potential energy (m g h summed over
    the two cars, h the CG's height from its position on the road plane, J)."""
    ke = np.zeros(states.shape[0])
    pe = np.zeros(states.shape[0])
    for c in (a, b):
        s, p = states[:, c], vp[c]
        iw = np.array([p[P.VP_WHEEL_INERTIA_FRONT_KGM2]] * L.N_FRONT_WHEELS
                      + [p[P.VP_WHEEL_INERTIA_REAR_KGM2]] * (L.N_WHEELS - L.N_FRONT_WHEELS))
        omega = s[:, L.OMEGA0:L.OMEGA0 + L.N_WHEELS]
        ke += 0.5 * p[P.VP_MASS_KG] * (s[:, L.U_MPS] ** 2 + s[:, L.V_MPS] ** 2)
        ke += 0.5 * p[P.VP_YAW_INERTIA_KGM2] * s[:, L.YAW_RATE_RADPS] ** 2
        ke += 0.5 * (iw * omega ** 2).sum(axis=1)
        h = s[:, L.X_M] * axes[0, 2] + s[:, L.Y_M] * axes[1, 2]
        pe += p[P.VP_MASS_KG] * gravity_mps2 * h
    return ke, pe


def check_contact_energy(states: np.ndarray, outputs: np.ndarray, vp: np.ndarray,
                         a: int, b: int, k0: int, k1: int, axes: np.ndarray,
                         gravity_mps2: float, dt_s: float) -> float:
    """The energy balance over rows ``k0`` .. ``k1`` of a chunk for cars ``a``, ``b``:
    returns the excess (J) of the kinetic energy's rise over the drive and gravity work
    plus the tolerance; a breach when positive (module docstring)."""
    win = states[k0:k1 + 1]
    ke, pe = pair_energy(win, vp, a, b, axes, gravity_mps2)
    drive_j = 0.0
    for c in (a, b):
        t = outputs[k0:k1, c, L.O_DRIVE_TORQUE0:L.O_DRIVE_TORQUE0 + L.N_WHEELS]
        w = states[k0:k1, c, L.OMEGA0:L.OMEGA0 + L.N_WHEELS]
        drive_j += float(np.maximum(t * w, 0.0).sum()) * dt_s
    gravity_j = float(pe[0] - pe[-1])
    rise = float(ke[-1] - ke[0])
    return rise - drive_j - gravity_j - (ENERGY_TOL_J + ENERGY_TOL_REL * float(ke[0]))


def _traffic_spec(scene: Scene, length_m: float, v0_mps: float, tight: bool) -> DriverSpec:
    """A driver on the lane y = 0 along +x (defaults of the tables, ``v0`` given)."""
    params = np.zeros(D.N_DRIVER_PARAM)
    for p in D.DRIVER_PARAMS:
        if p.derived:
            continue
        params[p.slot] = np.nan if isinstance(p.default, str) else p.default
    params[D.DP_IDM_V0_MPS] = v0_mps
    if tight:  # a too-small gap: it may touch the car ahead
        params[D.DP_IDM_S0_M] = 0.1
        params[D.DP_IDM_T_S] = 0.1
    return DriverSpec(params=params, path_xy=np.array([[-100.0, 0.0], [length_m, 0.0]]),
                      speed_profile=[], stop_s_m=np.inf, go_t_s=np.inf)


def roles_for(n_cars: int) -> list[int]:
    """The cars' roles: the pair, then traffic and keyframed alternating (traffic first)."""
    if n_cars < 4:
        raise ValueError(f"a multi-car soak needs at least 4 cars, got {n_cars}")
    rest = [ROLE_TRAFFIC if k % 2 == 0 else ROLE_KEYFRAMED for k in range(n_cars - 2)]
    return [ROLE_PAIR_HELD, ROLE_PAIR_ROLLING, *rest]


def run_multi_soak(scene: Scene, n_cars: int, duration_s: float, seed: int = 0,
                   dt_s: float = 0.001,
                   progress: Callable[[float, float], None] | None = None,
                   spoil: Spoiler | None = None) -> MultiSoakReport:
    """Run ``n_cars`` cars of ``scene``'s vehicle for ``duration_s`` (module docstring)."""
    rng = np.random.default_rng(seed)
    roles = roles_for(n_cars)
    ids = [f"car{c}" for c in range(n_cars)]
    grade = float(rng.choice(GRADES_PCT))
    sims = [Simulation(scene, dt_s, car_id=cid) for cid in ids]
    world: World = sims[0].world
    world.set_road(grade, 0.0, 1.0)
    for sim in sims[1:]:
        sim.move_to(world)
    vp = world.model.vp
    half_len = 0.5 * (vp[0, P.VP_CG_TO_FRONT_AXLE_M] + vp[0, P.VP_BODY_FRONT_OVERHANG_M]
                      + vp[0, P.VP_CG_TO_REAR_AXLE_M] + vp[0, P.VP_BODY_REAR_OVERHANG_M])
    car_len = 2.0 * half_len
    traffic = [c for c, r in enumerate(roles) if r == ROLE_TRAFFIC]
    keyframed = [c for c, r in enumerate(roles) if r == ROLE_KEYFRAMED]
    for k, c in enumerate(traffic):
        sims[c].reset({"x_m": -k * TRAFFIC_SPACING_M, "y_m": 0.0, "yaw_rad": 0.0})
    for k, c in enumerate(keyframed):
        sims[c].reset({"x_m": 0.0, "y_m": (k + 1) * KEYFRAMED_LANE_SPACING_M, "yaw_rad": 0.0})
    length_m = 60.0 * duration_s + 1000.0  # beyond any traffic car's reach
    specs: dict[str, DriverSpec | None] = {
        ids[c]: _traffic_spec(scene, length_m, float(rng.uniform(8.0, 14.0)),
                              tight=(c == traffic[-1] and len(traffic) > 1))
        for c in traffic}
    drivers = build_drivers(world, specs)
    drives = {c: KeyframedDrive(rng, duration_s, dt_s) for c in keyframed}
    g = float(world.gravity_mps2)
    holds = {ids[c]: CarHolds(ROLE_NAMES[roles[c]]) for c in range(n_cars)}
    trackers = {c: HoldTracker(holds[ids[c]], dt_s) for c in range(n_cars)}
    found: dict[str, Violation] = {}
    events: list[dict[str, Any]] = []
    lost = 0
    seen = world.contact_count()
    energy_checked = 0
    max_excess = -np.inf
    digest = hashlib.sha256()
    chunk = int(round(CHUNK_S / dt_s))
    total = int(round(duration_s / dt_s))
    cycle = int(round(PAIR_CYCLE_S / dt_s))
    lead_stop_until = -1.0
    traffic_holds = dict.fromkeys(traffic, 0)
    traffic_held = dict.fromkeys(traffic, False)
    step = 0
    t0 = time.perf_counter()
    while step < total:
        m = min(chunk, total - step)
        now_s = step * dt_s
        if step % cycle == 0:  # the pair placed anew: a held car and one rolling into it
            x0 = float(rng.uniform(-20.0, 20.0))
            sims[0].reset({"x_m": x0, "y_m": PAIR_LANE_Y_M, "yaw_rad": 0.0})
            sims[1].reset({"x_m": x0 - car_len - PAIR_GAP_M, "y_m": PAIR_LANE_Y_M,
                           "yaw_rad": 0.0}, u_mps=PAIR_SPEED_MPS)
        if traffic and now_s >= lead_stop_until and rng.random() < 0.5:
            lead = traffic[0]  # stop-and-go at the head of the queue
            station = float(drivers.state[lead, D.DS_STATION_M])
            stop_s = station + float(rng.uniform(20.0, 60.0))
            D.stop_at(drivers, lead, stop_s)
            lead_stop_until = now_s + float(rng.uniform(15.0, 30.0))
            D.go(drivers, lead, lead_stop_until)
        inputs = np.zeros((m, n_cars, L.N_INPUT))
        hold_ids = np.zeros((m, n_cars), dtype=np.int64)
        pair_k = (step % cycle) + np.arange(m)
        braked = pair_k >= int(round(PAIR_BRAKE_AT_S / dt_s))
        inputs[:, 0, L.IN_BRAKE] = 0.6
        inputs[:, 0, L.IN_GEAR] = L.GEAR_D
        hold_ids[:, 0] = 1 + (step // cycle)
        inputs[:, 1, L.IN_BRAKE] = np.where(braked, 0.6, 0.0)
        inputs[:, 1, L.IN_GEAR] = L.GEAR_N
        hold_ids[:, 1] = np.where(braked, 1 + (step // cycle), 0)
        for c, drive in drives.items():
            inputs[:, c], hold_ids[:, c] = drive.take(m)
        states = np.empty((m, n_cars, L.N_STATE))
        outputs = np.empty((m, n_cars, L.N_OUT))
        applied = np.empty((m, n_cars, L.N_INPUT))
        dstates = np.empty((m, n_cars, D.N_DRIVER_STATE))
        D.simulate_driven(world.model, world.data, drivers, inputs, states, outputs, applied,
                          dstates, 1)
        for c in traffic:  # a traffic car holds in the driver's hold mode: a new id each hold
            held = dstates[:, c, D.DS_MODE] == D.MODE_HOLD
            starts = held & ~np.concatenate([[traffic_held[c]], held[:-1]])
            hold_ids[:, c] = np.where(held, traffic_holds[c] + np.cumsum(starts), 0)
            traffic_holds[c] += int(starts.sum())
            traffic_held[c] = bool(held[-1])
        digest.update(states.tobytes())
        if spoil is not None:
            spoil(step, states, outputs, dstates)
        for c in range(n_cars):
            static_max = max(static_wheel_load(vp[c], world.model.terrain.road, i)
                             for i in range(L.N_WHEELS))
            before = set(found)
            check_invariants(states[:, c], outputs[:, c], static_max, step, dt_s, found)
            for name in set(found) - before:
                found[name].detail = f"car {ids[c]}: {found[name].detail}"
        new, seen, missed = world.contact_events(seen)
        lost += missed
        for e in new:
            a, b = world.index(e["car_a"]), world.index(e["car_b"])
            k = int(round(e["time_s"] / dt_s)) - step
            k0 = max(k - 1, 0)
            k1 = min(k0 + int(round(ENERGY_WINDOW_S / dt_s)), m - 1)
            trackers[a].strike(step + k)
            trackers[b].strike(step + k)
            if k1 > k0:
                excess = check_contact_energy(states, outputs, vp, a, b, k0, k1, world.axes,
                                              g, dt_s)
                energy_checked += 1
                max_excess = max(max_excess, excess)
                e["energy_excess_j"] = round(excess, 3)
                if excess > 0.0 and "contact_energy" not in found:
                    found["contact_energy"] = Violation(
                        "contact_energy", step + k, (step + k) * dt_s,
                        f"cars {e['car_a']}, {e['car_b']}: kinetic energy rose {excess:.1f} J "
                        "beyond the drive and gravity work and the tolerance")
            events.append(e)
        for c in range(n_cars):
            trackers[c].feed(step, states[:, c], hold_ids[:, c], found, ids[c])
        step += m
        if step % cycle == 0:  # the pair's holds end before they are placed anew
            trackers[0].close(found, ids[0])
            trackers[1].close(found, ids[1])
        if progress is not None:
            progress(step * dt_s, total * dt_s)
    for c in range(n_cars):
        trackers[c].close(found, ids[c])
    return MultiSoakReport(
        seed=seed, n_cars=n_cars, grade_pct=grade, simulated_s=step * dt_s, steps=step,
        wall_s=time.perf_counter() - t0, holds=holds, contact_events=events,
        contact_events_lost=lost, energy_checked=energy_checked,
        max_energy_excess_j=float(max_excess) if energy_checked else 0.0,
        digest=digest.hexdigest(), violations=sorted(found.values(), key=lambda v: v.step))
