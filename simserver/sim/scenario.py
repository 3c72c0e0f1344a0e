"""Headless scenarios: a vehicle, a road, an initial state and driver keyframes in time.

Scenario YAML (paths relative to the scenario file)::

    name: e2_stop_downslope_paper_damping
    description: free text
    vehicle: ../vehicles/paper_sedan/vehicle.yaml
    road: {grade_pct: -5.0, cross_slope_pct: 0.0, friction_scale: 1.0}
    initial: {x_m: 0, y_m: 0, yaw_rad: 0, u_mps: 25.0, v_mps: 0, yaw_rate_radps: 0}
    duration_s: 12.0
    dt_s: 0.001              # optional, default 0.001
    record_every: 1          # optional: keep every n-th step in the output
    model: {slip_model: lagged_paper, damping_model: paper}   # optional, see config
    terrain: {kind: heightmap, file: ../roads/hills.npz, cell_m: 1.0}  # optional, default
                             # the plane of road: (keys: simserver.adapters.terrain_files)
    start: {road: "1", s: 250.0, lane: -2}  # optional, on an OpenDRIVE terrain only: the
                             # initial x_m, y_m, yaw_rad from a road, s and lane
    inputs:                  # keyframes
      - {t: 0.0, gear: D}
      - {t: 1.0, brake: 0.0}
      - {t: 1.3, brake: 0.6}
    analysis: iso7401_step_steer   # optional: a standard manoeuvre's figures and criteria
                             # in the summary (simserver.analysis.manoeuvres, docs/manoeuvres.md)
    speed_hold: {speed_mps: 22.2}  # optional: the throttle holds a speed
                             # (simserver.sim.speed_hold; not with cars:)

Several cars on one terrain (``cars:``; docs/model.md section 14): the world's keys
(``name``, ``description``, ``road``, ``terrain``, ``duration_s``, ``dt_s``,
``record_every``, ``max_cars``) at the top, and per car an ``id``, its ``vehicle``, start
(``initial`` or ``start``), ``model`` options and ``inputs``, as a single car's::

    cars:
      - {id: lead, vehicle: ../vehicles/paper_sedan/vehicle.yaml, initial: {x_m: 20.0},
         inputs: [{t: 0.0, brake: 0.8, gear: D}]}
      - {id: follower, vehicle: ..., inputs: [...]}

Each car is run as the car alone would be (``load_world_scenario``, ``run_world_scenario``):
its numbers do not depend on the other cars nor on their order in the file. The list is
checked as the live server's ``cars:``, each error naming the file and the car
(``cars[k] (id)``): each id once, at most ``max_cars`` cars (a world key; default 256,
the most of ``simserver.sim.scene.MAX_CARS_RANGE``: a headless run has no tick to keep,
where the live server's default is 32), each start on the road
(``simserver.sim.scene.check_on_road``: on a lane of an OpenDRIVE terrain, on a height
map's grid), no two starts whose bodies overlap (``simserver.sim.scene.
check_starts_apart``).

The channels are ``steer``, ``throttle``, ``brake``, ``parking_brake`` (0/1 or true/false)
and ``gear`` (P, R, N, D); how each is sampled between, before and after the keyframes that
name it is defined in :mod:`simserver.sim.keyframes`, which the player client shares.
"""

from __future__ import annotations

import time
import weakref
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from simserver.adapters.config import MODEL_OPTION_DEFAULTS, resolve_vehicle
from simserver.adapters.driver_config import DriverSpec, build_drivers, parse_driver
from simserver.adapters.terrain_files import terrain_spec
from simserver.adapters.validate import ConfigError, check_keys, integer, number, read_yaml
from simserver.core import layout as L
from simserver.core.contact import CAR_CONTACT_NAMES, N_CAR_CONTACT_OUT
from simserver.core.driver import N_DRIVER_STATE, simulate_driven
from simserver.sim.keyframes import input_table, read_keyframe_file
from simserver.sim.scene import (
    INITIAL_RANGES,
    MAX_CARS_RANGE,
    SCENARIO_ONLY_KEYS,
    SCENE_KEYS,
    START_POSE_KEYS,
    Scene,
    check_car_count,
    check_on_road,
    check_starts_apart,
    parse_scene,
)
from simserver.sim.simulation import Simulation, world_poses
from simserver.sim.speed_hold import SpeedController, SpeedHold, parse_speed_hold

MAX_SCENARIO_STEPS = 10_000_000
"""Most steps of a headless run: its input table holds 40 bytes a step (400 MB here)."""
MAX_RECORDED_ROWS = 1_000_000
"""Most recorded rows of a headless run: 840 bytes each (state, outputs, inputs; 840 MB)."""


def check_run_size(path: Path | str, duration_s: float, dt_s: float, record_every: int) -> None:
    """Refuse a run whose arrays would not fit (:data:`MAX_SCENARIO_STEPS`,
    :data:`MAX_RECORDED_ROWS`) before allocating them; errors name the key to change."""
    steps = int(round(duration_s / dt_s))
    if steps > MAX_SCENARIO_STEPS:
        raise ConfigError(f"{path}: key 'duration_s': {duration_s:g} s at dt_s {dt_s:g} s is "
                          f"{steps} steps, more than {MAX_SCENARIO_STEPS}")
    rows = -(-steps // record_every)
    if rows > MAX_RECORDED_ROWS:
        raise ConfigError(f"{path}: key 'record_every': {rows} recorded rows, more than "
                          f"{MAX_RECORDED_ROWS}: record_every must be at least "
                          f"{-(-steps // MAX_RECORDED_ROWS)}")


@dataclass
class Scenario:
    """A validated scenario, ready to run: a scene (vehicle, road, initial state, model
    options) driven by keyframes for a duration."""

    name: str
    path: Path
    description: str
    scene: Scene
    duration_s: float
    dt_s: float
    record_every: int
    keyframes: list[dict[str, Any]]
    driver: DriverSpec | None = None  # the built-in driver drives the car (``driver:``)
    analysis: dict[str, Any] | None = None  # analysis.manoeuvres.parse_analysis
    speed_hold: SpeedHold | None = None  # speed_hold.parse_speed_hold

    @property
    def n_steps(self) -> int:
        """Number of fixed steps in the run."""
        return int(round(self.duration_s / self.dt_s))


@dataclass
class ScenarioResult:
    """The time history of a run, one row per recorded step.

    Row ``k`` is the state at ``time_s[k]`` (``core.layout.STATE_NAMES``), the forces and
    accelerations evaluated at that state (``OUTPUT_NAMES``) and the inputs applied over
    the step that starts there (``INPUT_NAMES``).
    """

    scenario: Scenario
    time_s: np.ndarray
    states: np.ndarray
    outputs: np.ndarray
    inputs: np.ndarray
    final_state: np.ndarray
    wall_time_s: float
    driver_states: np.ndarray | None = None  # a driven car's driver state per row (DS_*)

    def state(self, index: int) -> np.ndarray:
        """Column ``index`` of the states (a ``core.layout`` constant)."""
        return self.states[:, index]

    def output(self, index: int) -> np.ndarray:
        """Column ``index`` of the outputs (a ``core.layout`` ``O_*`` constant)."""
        return self.outputs[:, index]

    @property
    def poses(self) -> np.ndarray:
        """The world pose of each row's state, ``(rows, N_POSE)`` (``core.layout.POSE_*``):
        what the server publishes for that state (``simulation.world_poses``; made once
        per states array, 3-7 us a row)."""
        key = id(self.states)
        hit = _POSES.get(key)
        if hit is not None and hit[0]() is self.states:
            return hit[1]
        poses = world_poses(self.scenario.scene, self.states)
        _POSES[key] = (weakref.ref(self.states, lambda _, k=key: _POSES.pop(k, None)), poses)
        return poses


_POSES: dict[int, tuple[weakref.ref, np.ndarray]] = {}
"""``ScenarioResult.poses`` by the states array they were made from (kept while it lives;
a result copied with other states makes its own)."""


def load_scenario(path: str | Path, data: dict[str, Any] | None = None) -> Scenario:
    """Load and validate a scenario file (errors name the file and the key).

    ``data``: the scenario's mapping, e.g. from ``resolve_scenario`` (then ``path`` only
    labels the errors and the run).
    """
    path = Path(path)
    data = read_yaml(path) if data is None else data
    allowed = ("name", "description", *SCENE_KEYS, *SCENARIO_ONLY_KEYS)
    driven = data.get("driver") is not None
    check_keys(path, data, allowed, required=("name", "vehicle", "duration_s")
               + (() if driven else ("inputs",)))
    scene = parse_scene(path, data)
    if driven and "inputs" not in data:  # the driver gives every input
        data = {**data, "inputs": [{"t": 0.0, "gear": "D"}]}
    run = read_keyframe_file(path, data)
    driver = parse_driver(path, data["driver"], scene) if driven else None
    dt = number(path, "dt_s", data.get("dt_s", 0.001), 1e-5, 0.01)
    record_every = integer(path, "record_every", data.get("record_every", 1), 1, 1_000_000)
    check_run_size(path, run.duration_s, dt, record_every)
    from simserver.analysis.manoeuvres import parse_analysis

    if driven and data.get("speed_hold") is not None:
        raise ConfigError(f"{path}: key 'speed_hold': the driver holds its own speed "
                          "profile; give one or the other")
    return Scenario(
        name=run.name, path=path, description=str(data.get("description", "")), scene=scene,
        duration_s=run.duration_s, dt_s=dt, record_every=record_every,
        keyframes=run.keyframes, driver=driver,
        analysis=parse_analysis(path, data.get("analysis")),
        speed_hold=parse_speed_hold(path, data.get("speed_hold")),
    )


def resolve_scenario(path: str | Path) -> dict[str, Any]:
    """A scenario file as one mapping holding everything it refers to: the vehicle with its
    subsystem and tire files inline (``resolve_vehicle``), the terrain section with every
    default written out and its files as absolute paths (``terrain_spec``: a height map or
    an ``.xodr`` is data too large to inline; a run's hash covers their contents,
    ``simserver.sweep.resolved.run_id``) and every other default written out.
    ``load_scenario(path, resolve_scenario(path))`` is ``load_scenario(path)``."""
    path = Path(path)
    data = dict(read_yaml(path))
    if isinstance(data.get("vehicle"), str):
        data["vehicle"] = resolve_vehicle((path.parent / data["vehicle"]).resolve())
    initial_keys = [key for key in INITIAL_RANGES  # a start: gives the pose
                    if not (data.get("start") is not None and key in START_POSE_KEYS)]
    if data.get("terrain") is not None:
        data["terrain"] = terrain_spec(path, data["terrain"])
    defaults = {"road": {"grade_pct": 0.0, "cross_slope_pct": 0.0, "friction_scale": 1.0},
                "initial": dict.fromkeys(initial_keys, 0.0),
                "model": dict(MODEL_OPTION_DEFAULTS)}
    for section, values in defaults.items():
        given = data.get(section) or {}
        if isinstance(given, dict):
            data[section] = {**values, **given}
    data.setdefault("description", "")
    data.setdefault("dt_s", 0.001)
    data.setdefault("record_every", 1)
    return data


def start_run(scenario: Scenario, car_id: str = "car0") -> tuple[Simulation, np.ndarray]:
    """A run's simulation at its start and its inputs, one row per step (the keyframes
    sampled, ``input_table``): what ``run_scenario`` steps through, and any other runner
    of a scenario (the sweep's workers) with it. ``car_id``: the car's id in its world."""
    sim = Simulation(scenario.scene, scenario.dt_s, car_id=car_id)
    n = scenario.n_steps
    inputs = input_table(scenario.keyframes, np.arange(n) * scenario.dt_s)
    if scenario.scene.initial.get("relaxed", 0.0) and n > 0:
        sim.inputs[:] = inputs[0]  # a relaxed start settles with the first inputs
        sim.reset(None)
    return sim, inputs


def step_chunks(
    sim: Simulation,
    inputs: np.ndarray,
    every: int,
    chunk_steps: int,
    rows_at: Callable[[int, int], tuple[np.ndarray, np.ndarray]],
) -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
    """Step ``sim`` through ``inputs`` (one row a step) in compiled calls of about
    ``chunk_steps`` steps, recording every ``every``-th step: ``rows_at(r0, rows)`` gives
    the states and outputs arrays that the chunk's recorded rows ``r0 .. r0 + rows`` of the
    run go into. Yields ``(steps done, r0, states, outputs)`` after each chunk."""
    # a whole number of records a chunk, so that a chunk's first step is a recorded one
    chunk_steps = max(every, chunk_steps - chunk_steps % every)
    n = len(inputs)
    done = 0
    while done < n:
        m = min(chunk_steps, n - done)
        r0 = done // every
        states, outputs = rows_at(r0, (m + every - 1) // every)
        sim.run(inputs[done:done + m], states, outputs, every)
        done += m
        yield done, r0, states, outputs


def run_scenario(
    scenario: Scenario,
    progress: Callable[[int, int], None] | None = None,
    chunk_steps: int = 2000,
) -> ScenarioResult:
    """Run a scenario headless as fast as the CPU allows.

    Deterministic: the same scenario gives the same arrays bit for bit.
    ``progress(done_steps, total_steps)`` is called after each chunk. A car driven by the
    built-in driver runs closed loop, as a world of one car (``run_world_scenario``).
    """
    if scenario.driver is not None:
        world = WorldScenario(name=scenario.name, path=scenario.path,
                              description=scenario.description, cars={"car0": scenario})
        return run_world_scenario(world, progress, chunk_steps).cars["car0"]
    sim, inputs = start_run(scenario)
    n = scenario.n_steps
    every = scenario.record_every
    n_rec = (n + every - 1) // every
    states = np.zeros((n_rec, L.N_STATE))
    outputs = np.zeros((n_rec, L.N_OUT))
    hold = None
    if scenario.speed_hold is not None:  # the throttle of each period set from the state
        hold = SpeedController(scenario.speed_hold, inputs, scenario.dt_s, every)
        chunk_steps = hold.period
        hold.control(0, sim.x)
    t0 = time.perf_counter()
    for done, _, _, _ in step_chunks(sim, inputs, every, chunk_steps,
                                     lambda r0, rows: (states[r0:r0 + rows],
                                                       outputs[r0:r0 + rows])):
        if hold is not None and done < n:
            hold.control(done, sim.x)
        if progress is not None:
            progress(done, n)
    wall = time.perf_counter() - t0
    return ScenarioResult(
        scenario=scenario, time_s=states[:, L.TIME_S].copy(), states=states, outputs=outputs,
        inputs=inputs[::every].copy(), final_state=sim.x.copy(), wall_time_s=wall,
    )


# ------------------------------------------------------------------- several cars, one world
WORLD_KEYS = ("name", "description", "road", "terrain", "duration_s", "dt_s", "record_every",
              "analysis", "max_cars", "cars")
"""The keys of a scenario with ``cars:``: the world's (shared by every car) and the list."""
CAR_KEYS = ("id", "vehicle", "initial", "start", "model", "inputs", "driver")
"""The keys of one car of ``cars:``: what a single car's scenario gives for its car."""


@dataclass
class WorldScenario:
    """A validated scenario of several cars on one terrain: per car (in file order) the
    scenario that car alone would be (the world's keys with its own)."""

    name: str
    path: Path
    description: str
    cars: dict[str, Scenario]

    @property
    def first(self) -> Scenario:
        return next(iter(self.cars.values()))

    @property
    def n_steps(self) -> int:
        return self.first.n_steps


@dataclass
class WorldResult:
    """The time histories of a world's run, one ``ScenarioResult`` per car (file order)."""

    scenario: WorldScenario
    cars: dict[str, ScenarioResult]
    wall_time_s: float
    contact_rows: np.ndarray | None = None  # float64[rows, n_cars, N_CAR_CONTACT_OUT]
    contact_events: list[dict[str, Any]] = field(default_factory=list)  # core.contact
    contact_events_lost: int = 0  # events the ring overwrote before they were read

    def contact(self, car_id: str, name: str) -> np.ndarray:
        """One car's contact column (``core.contact.CAR_CONTACT_NAMES``) per recorded row."""
        c = list(self.cars).index(car_id)
        return self.contact_rows[:, c, CAR_CONTACT_NAMES.index(name)]

    def contact_summary(self) -> dict[str, Any]:
        """The summary's ``contacts`` section: the events (the two cars' ids, the time, the
        closing speed, the contact point), their number, and per car its events, the
        recorded rows it was in contact and its deepest recorded penetration."""
        cars = {}
        for cid in self.cars if self.contact_rows is not None else ():
            flag = self.contact(cid, "contact")
            cars[cid] = {"events": int(self.contact(cid, "contact_events")[-1])
                         if len(flag) else 0,
                         "rows_in_contact": int(np.count_nonzero(flag > 0.5)),
                         "max_penetration_m": float(self.contact(cid, "contact_penetration_m")
                                                    .max(initial=0.0))}
        events = [{k: e[k] for k in ("time_s", "car_a", "car_b", "closing_speed_mps",
                                     "x_m", "y_m")} for e in self.contact_events]
        return {"count": len(events) + self.contact_events_lost,
                "lost": self.contact_events_lost, "events": events, "cars": cars}


def is_world_scenario(data: dict[str, Any]) -> bool:
    """Whether a scenario file's mapping lists several cars (``cars:``)."""
    return isinstance(data, dict) and "cars" in data


def load_world_scenario(path: str | Path, data: dict[str, Any] | None = None) -> WorldScenario:
    """Load and validate a scenario with ``cars:`` (errors name the file, the car and the
    key). Each car's scenario is validated as a single car's (``load_scenario``); the
    world's checks are the live server's ``cars:`` (``simserver.server.cars_config``): at
    most ``max_cars`` cars (default the most of ``scene.MAX_CARS_RANGE``), each id once,
    each start on the road (``scene.check_on_road``) and no two start poses whose bodies
    overlap (``scene.check_starts_apart``: a start the contact would push apart on the
    first step)."""
    path = Path(path)
    data = read_yaml(path) if data is None else data
    check_keys(path, data, WORLD_KEYS, required=("name", "duration_s", "cars"))
    raw = data["cars"]
    if not isinstance(raw, list) or not raw:
        raise ConfigError(f"{path}: key 'cars': expected a non-empty list of cars")
    # no tick to keep headless: by default as many cars as any world may hold (a file
    # meant for the live server too sets the server's max_cars)
    max_cars = integer(path, "max_cars", data.get("max_cars", MAX_CARS_RANGE[1]),
                       *MAX_CARS_RANGE)
    check_car_count(path, len(raw), max_cars)
    cars: dict[str, Scenario] = {}
    where: dict[str, str] = {}
    shared = {key: data[key] for key in WORLD_KEYS if key in data
              and key not in ("cars", "max_cars")}
    for k, car in enumerate(raw):
        if not isinstance(car, dict):
            raise ConfigError(f"{path}: key 'cars[{k}]': expected a mapping")
        check_keys(f"{path} (cars[{k}])", car, CAR_KEYS,
                   required=("id", "vehicle") + (() if "driver" in car else ("inputs",)))
        car_id = car["id"]
        if not isinstance(car_id, str) or not car_id:
            raise ConfigError(f"{path}: key 'cars[{k}].id': expected a non-empty string")
        if car_id in cars:
            raise ConfigError(f"{path}: key 'cars[{k}].id': {car_id!r} is given twice "
                              f"(the id of {where[car_id].removeprefix(f'{path}: ')} too); "
                              "each car needs its own")
        where[car_id] = f"{path}: cars[{k}] ({car_id})"
        one = shared | {key: car[key] for key in CAR_KEYS if key in car and key != "id"}
        try:
            cars[car_id] = load_scenario(path, one)
        except ConfigError as exc:
            raise ConfigError(f"car {car_id!r} (cars[{k}]): {exc}") from None
    for cid, sc in cars.items():
        check_on_road(where[cid], sc.scene)
    check_starts_apart([(where[cid], cid, sc.scene.initial, sc.scene.vehicle.vp)
                        for cid, sc in cars.items()])
    return WorldScenario(name=str(data["name"]), path=path,
                         description=str(data.get("description", "")), cars=cars)


def run_world_scenario(world_scenario: WorldScenario,
                       progress: Callable[[int, int], None] | None = None,
                       chunk_steps: int = 2000) -> WorldResult:
    """Run the cars of a world together, headless: each car starts as alone
    (``start_run``: a relaxed start settles the car by itself), then all are moved into
    the first car's world (its terrain and road, the world's keys) and advanced by the
    world's step (``simserver.sim.simulation.World.run``)."""
    ids = list(world_scenario.cars)
    starts = {cid: start_run(sc, car_id=cid) for cid, sc in world_scenario.cars.items()}
    world = starts[ids[0]][0].world
    for cid in ids[1:]:
        starts[cid][0].move_to(world)
    first = world_scenario.first
    n, every = first.n_steps, first.record_every
    inputs = np.stack([starts[cid][1] for cid in ids], axis=1)
    n_rec = (n + every - 1) // every
    states = np.zeros((n_rec, len(ids), L.N_STATE))
    outputs = np.zeros((n_rec, len(ids), L.N_OUT))
    specs = {cid: sc.driver for cid, sc in world_scenario.cars.items()}
    driven = any(spec is not None for spec in specs.values())
    if driven:  # closed loop: the inputs applied are the drivers' (core.driver)
        drivers = build_drivers(world, specs)
        applied = np.zeros((n_rec, len(ids), L.N_INPUT))
        driver_states = np.zeros((n_rec, len(ids), N_DRIVER_STATE))
    # the cars' contact outputs per row (not recorded by the drivers' loop: events only)
    contact_rows = None if driven else np.zeros((n_rec, len(ids), N_CAR_CONTACT_OUT))
    events: list[dict[str, Any]] = []
    seen = world.contact_count()
    lost = 0
    chunk = max(every, chunk_steps - chunk_steps % every)
    t0 = time.perf_counter()
    done = 0
    while done < n:
        m = min(chunk, n - done)
        r0 = done // every
        rows = (m + every - 1) // every
        if driven:
            simulate_driven(world.model, world.data, drivers, inputs[done:done + m],
                            states[r0:r0 + rows], outputs[r0:r0 + rows],
                            applied[r0:r0 + rows], driver_states[r0:r0 + rows], every)
        else:
            world.run(inputs[done:done + m], states[r0:r0 + rows], outputs[r0:r0 + rows],
                      every, contact_rows[r0:r0 + rows])
        new, seen, missed = world.contact_events(seen)
        events += new
        lost += missed
        done += m
        if progress is not None:
            progress(done, n)
    wall = time.perf_counter() - t0
    cars = {}
    for c, cid in enumerate(ids):
        st = np.ascontiguousarray(states[:, c])
        cars[cid] = ScenarioResult(
            scenario=world_scenario.cars[cid], time_s=st[:, L.TIME_S].copy(), states=st,
            outputs=np.ascontiguousarray(outputs[:, c]),
            inputs=np.ascontiguousarray(applied[:, c] if driven else inputs[::every, c]),
            final_state=world.data.x[world.index(cid)].copy(), wall_time_s=wall,
            driver_states=(np.ascontiguousarray(driver_states[:, c])
                           if specs[cid] is not None else None))
    return WorldResult(scenario=world_scenario, cars=cars, wall_time_s=wall,
                       contact_rows=contact_rows, contact_events=events,
                       contact_events_lost=lost)
