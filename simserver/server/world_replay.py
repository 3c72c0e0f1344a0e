"""A multi-car session re-run headless from every car's command log, in one world (issue 30).

A live server with several cars (``cars:``, ``simserver.server.fleet``) writes one command
log a car (``run.<id>.jsonl``). Each holds the inputs its car's steps applied (a person's,
a keyframe table's, the built-in driver's: ``VehicleSlot.advance`` logs what ``drive``
wrote) and the controls that changed its physics; :func:`replay_world` steps every car
together in one world (``simserver.sim.simulation.World``), so cars that touch replay
their contact too, bit for bit.

What the logs say about the world (``world`` lines, ``CommandLog``):

- ``join`` (the car's step 0): the world's step ``W`` it joined at, its id and the world's
  cars in order after it joined (the server's cars at the start, then one car appended
  per ``add_car``). The lines after it, ``load`` (the world's scene with the car's
  vehicle) and ``reset`` (its start pose), make the car as the live server made it: alone
  at rest at its pose, then moved into the world (``fleet.build_world``,
  ``fleet.join_world``).
- ``resume``: after the car was held alone through world steps (a fault stop, or paused
  while another car stepped; its rows put back after the step), its step ``n`` is the
  world's step ``W`` again.
- ``leave``: ``remove_car`` took it out of the world before world step ``W``.

Every other line is the single car's replay's (``command_log.replay_command_log``): a
line at the car's step ``n`` is applied before the world step that is the car's ``n``-th
(as soon as its step ``n - 1`` is done, so a car held after a fault stop is held at its
reset state, as live).

The built-in driver is not run again: its car's log holds the inputs it applied, so the
replay does not depend on the driver's code (a driver changed since still replays old
sessions) nor on the world controls it reacted to; nor do keyframed cars need their
tables. What a replay cannot reproduce: the inputs a car held alone had during the world
steps it was held through (not logged: its own rows are put back, and only a contact with
it during those steps could carry them to another car).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from simserver.adapters.validate import ConfigError
from simserver.server.command_log import apply_logged_reset, read_command_log
from simserver.sim.scene import Scene
from simserver.sim.scene_files import load_scene
from simserver.sim.simulation import Simulation, World


@dataclass
class CarReplay:
    """One car of a world replay: its log, where it joined and left (world steps), its
    steps, and its final state beside the log's."""

    car_id: str
    path: Path
    joined_at: int
    left_at: int | None
    steps: int
    final_state: np.ndarray | None = None
    logged_final_state: np.ndarray | None = None
    cut: str | None = None
    states: list[np.ndarray] = field(default_factory=list)  # with record=True

    @property
    def final_state_matches(self) -> bool | None:
        """Bit for bit equal to the log's end state on the slots both have (None: the log
        holds none)."""
        if self.logged_final_state is None or self.final_state is None:
            return None
        n = self.logged_final_state.size
        return n <= self.final_state.size and bool(
            np.array_equal(self.final_state[:n], self.logged_final_state))


@dataclass
class WorldReplay:
    """A world replay: each car's (in the order of the logs given), the world steps
    replayed and the contact events the replay's world counted."""

    cars: dict[str, CarReplay]
    steps: int
    contact_events: int

    @property
    def all_match(self) -> bool:
        """Every car's final state equals its log's, bit for bit (a log without one, cut
        or unfinished, does not match)."""
        return all(c.final_state_matches for c in self.cars.values())


@dataclass
class _Car:
    """A car's log, parsed for the world's timeline."""

    path: Path
    car_id: str
    scene: str
    dt_s: float
    cars_at_join: list[str]
    vehicle: str | None
    pose: dict[str, float]
    events: list[tuple[int, dict[str, Any]]]  # (step, line): the lines after its start
    syncs: list[tuple[int, int]]  # (car step, world step): join, then each resume
    end: int  # its steps
    left_at: int | None
    logged: np.ndarray | None
    cut: str | None
    sim: Simulation | None = None
    done: int = 0  # steps taken
    next_event: int = 0
    trace: list[np.ndarray] = field(default_factory=list)

    def apply_due(self, scenes: dict[tuple[str, str | None], Scene]) -> None:
        """The lines up to its next step (``done``), once each."""
        events, k = self.events, self.next_event
        while k < len(events) and events[k][0] <= self.done:
            _apply(self, events[k][1], scenes, f"{self.path} (step {events[k][0]})")
            k += 1
        self.next_event = k

    def world_step_of(self, n: int) -> int:
        """The world step at which this car takes its step ``n``."""
        k = max(i for i, (step, _) in enumerate(self.syncs) if step <= n)
        step, world = self.syncs[k]
        return world + n - step


def _parse(path: Path) -> _Car:
    entries = read_command_log(path)
    header, events = entries[0], entries[1:]
    first = events[0] if events else {}
    if "world" not in first or first["world"]["event"] != "join":
        raise ConfigError(f"{path}:2: not the log of a car of a world of several (no "
                          "'world' join line first): replay it alone (simserver replay "
                          f"{path})")
    if len(events) < 3 or "load" not in events[1] or "reset" not in events[2] or \
            events[1]["step"] != 0 or events[2]["step"] != 0 or \
            not isinstance(events[2]["reset"], dict):
        raise ConfigError(f"{path}:3: expected the car's start after its join line: a "
                          "'load' and a 'reset' to its pose at step 0")
    join = first["world"]
    syncs = [(0, join["step"])]
    left_at = None
    rest: list[tuple[int, dict[str, Any]]] = []
    end, logged, cut = None, None, None
    for line, e in enumerate(events[3:], 5):
        if "end" in e:
            end = int(e["end"])
            cut = e.get("cut")
            if "state" in e:
                logged = np.array([float.fromhex(v) for v in e["state"]])
        elif "world" in e:
            w = e["world"]
            if w["event"] == "join":
                raise ConfigError(f"{path}:{line}: a second 'world' join line")
            if w["event"] == "resume":
                syncs.append((e["step"], w["step"]))
            else:
                left_at = w["step"]
        else:
            rest.append((e["step"], e))
    if end is None:  # a server killed: the steps its lines reach
        end = max((step for step, _ in rest), default=0)
    pose = dict(events[2]["reset"])
    if "u_mps" in pose:
        raise ConfigError(f"{path}:4: a car's start is at rest (its reset has u_mps)")
    return _Car(path=path, car_id=join["car"], scene=header["scene"],
                dt_s=float(header["dt_s"]), cars_at_join=list(join["cars"]),
                vehicle=events[1]["load"]["vehicle"], pose=pose, events=rest, syncs=syncs,
                end=end, left_at=left_at, logged=logged, cut=cut)


def _car_scene(car: _Car, scenes: dict[tuple[str, str | None], Scene]) -> Scene:
    """The car's scene as ``cars_config.car_scenes`` made it: the world's scene with the
    car's vehicle, starting at rest at its pose."""
    key = (car.scene, car.vehicle)
    if key not in scenes:
        try:
            scenes[key] = load_scene(car.scene, vehicle_path=car.vehicle)
        except ConfigError as exc:
            raise ConfigError(f"{car.path}:3: key 'load': {exc}") from None
    scene = scenes[key]
    initial = {**scene.initial, "u_mps": 0.0, "v_mps": 0.0, "yaw_rate_radps": 0.0,
               **car.pose}
    return dataclasses.replace(scene, initial=initial)


def _apply(car: _Car, e: dict[str, Any], scenes: dict[tuple[str, str | None], Scene],
           line_of: str) -> None:
    """One log line of a car in the world (as ``replay_command_log`` applies it alone; a
    ``load`` keeps the world's terrain, as the live server's)."""
    sim = car.sim
    if "inputs" in e:
        sim.inputs[:] = e["inputs"]
    elif "reset" in e:
        apply_logged_reset(sim, e["reset"])
    elif "set_road" in e:
        sim.set_road(**e["set_road"])
    elif "load" in e:
        spec = e["load"]
        key = (spec["scene"], spec["vehicle"])
        if key not in scenes:
            try:
                scenes[key] = load_scene(spec["scene"], vehicle_path=spec["vehicle"])
            except ConfigError as exc:
                raise ConfigError(f"{line_of}: key 'load': {exc}") from None
        sim.commit(sim.prepare_load(scenes[key], keep_terrain=True).finish())


def replay_world(paths: list[str | Path], record: bool = False,
                 progress: Any = None) -> WorldReplay:
    """Re-run the command logs of every car of a multi-car session in one world.

    Parameters
    ----------
    paths : list of paths
        One log a car (``run.<id>.jsonl``): every car the world had (a car named by a
        ``join`` line with no log given is an error).
    record : bool
        Keep every car's state after each of its steps (``CarReplay.states``).
    progress : callable, optional
        ``progress(world_step, total)`` every 10 000 world steps.

    Raises
    ------
    ConfigError
        Naming the file (and line): a log that is not a world car's, logs of different
        scenes or step sizes, a car missing, a car twice.
    """
    cars = [_parse(Path(p)) for p in paths]
    if not cars:
        raise ConfigError("replay: no command log given")
    by_id: dict[str, _Car] = {}
    for car in cars:
        if car.car_id in by_id:
            raise ConfigError(f"{car.path}: car {car.car_id!r} is the car of "
                              f"{by_id[car.car_id].path} too")
        by_id[car.car_id] = car
        first = cars[0]
        if car.dt_s != first.dt_s or Path(car.scene) != Path(first.scene):
            raise ConfigError(f"{car.path}:1: scene {car.scene} and dt_s {car.dt_s:g} differ "
                              f"from {first.path}'s ({first.scene}, {first.dt_s:g}): not "
                              "the logs of one world")
    start = min(c.syncs[0][1] for c in cars)
    initial = [c for c in cars if c.syncs[0][1] == start]
    order = initial[0].cars_at_join
    for car in initial:
        if car.cars_at_join != order:
            raise ConfigError(f"{car.path}:2: the world's cars {car.cars_at_join} differ "
                              f"from {initial[0].path}'s {order}: not one world")
    missing = [cid for cid in order if cid not in by_id]
    if missing:
        raise ConfigError(f"{initial[0].path}:2: the world started with car(s) "
                          f"{', '.join(missing)}: give their command logs too")

    # the world's last step: where the last car left or the session ended; a log without
    # its end state (cut, or the server killed) knows its car's inputs up to its end only
    total = max(c.left_at if c.left_at is not None else c.world_step_of(c.end)
                for c in cars)
    for c in cars:
        if c.logged is None and c.left_at is None:
            total = min(total, c.world_step_of(c.end))
    joins = sorted((c for c in cars if c.syncs[0][1] > start), key=lambda c: c.syncs[0][1])
    scenes: dict[tuple[str, str | None], Scene] = {}
    world: World | None = None
    present: list[_Car] = []

    def join(car: _Car, check: bool = True) -> None:
        nonlocal world
        sim = Simulation(_car_scene(car, scenes), car.dt_s, car_id=car.car_id)
        if world is None:
            world = sim.world
        else:
            sim.move_to(world)
        car.sim = sim
        present.append(car)
        if check and world.ids != car.cars_at_join:
            missing = [cid for cid in car.cars_at_join if cid not in by_id]
            raise ConfigError(f"{car.path}:2: the world's cars were {car.cars_at_join} "
                              f"when it joined, the replay's are {world.ids}" + (
                                  f": give the logs of {', '.join(missing)} too"
                                  if missing else ""))

    for cid in order:
        join(by_id[cid], check=cid == order[-1])
    for car in present:  # as the server's start (each car's kernels warmed on its rows)
        car.sim.warm_up()
    results: dict[str, CarReplay] = {}

    def finish(car: _Car) -> None:
        results[car.car_id] = CarReplay(
            car_id=car.car_id, path=car.path, joined_at=car.syncs[0][1],
            left_at=car.left_at, steps=car.done, final_state=car.sim.x.copy(),
            logged_final_state=car.logged, cut=car.cut,
            states=car.trace)

    next_join = 0
    for w in range(start, total):
        # between two world steps, as the live tick: each car's controls, then the world
        # desk's removal or join (a joining car's warm-up steps copies beside the others)
        for car in present:
            car.apply_due(scenes)
        for car in [c for c in present if c.left_at == w]:
            finish(car)
            world.remove_car(car.car_id)
            present.remove(car)
        while next_join < len(joins) and joins[next_join].syncs[0][1] == w:
            join(joins[next_join])
            joins[next_join].sim.warm_up()  # as fleet.join_world's slot.warm_up()
            joins[next_join].apply_due(scenes)  # its inputs of its first step
            next_join += 1
        stepping = []
        for car in present:
            if car.done >= car.end:
                continue  # its log ends here: held to the world's end
            at = car.world_step_of(car.done)
            if at == w:
                stepping.append(car)
            elif at < w:
                raise ConfigError(f"{car.path}: its step {car.done} was the world's step "
                                  f"{at}, but the replay's world is at {w}: not the logs of "
                                  "one world")
        held = [(c.sim, c.sim.x.copy(), c.sim.out.copy()) for c in present
                if c not in stepping]
        world.step()
        for sim, x, out in held:
            sim.x[:] = x
            sim.out[:] = out
        for car in stepping:
            car.done += 1
            if record:
                car.trace.append(car.sim.x.copy())
        if progress is not None and (w - start) % 10000 == 0:
            progress(w - start, total - start)
    for car in present:
        car.apply_due(scenes)
        finish(car)
    for car in cars:  # a car that joined after the replay's end (a cut log): not replayed
        results.setdefault(car.car_id, CarReplay(
            car_id=car.car_id, path=car.path, joined_at=car.syncs[0][1],
            left_at=car.left_at, steps=0, logged_final_state=car.logged, cut=car.cut))
    return WorldReplay(cars={c.car_id: results[c.car_id] for c in cars},
                       steps=total - start,
                       contact_events=0 if world is None else world.contact_count())
