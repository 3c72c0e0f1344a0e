"""One simulation object under every runner: the static model and the mutable data.

``Simulation(scene, dt_s)`` is the one place where a scene becomes something the compiled
step can run: the parameters are copied, the road is set, the tire and variant ids are
checked against their registries, the initial state is built and the workspace made.
The live server, the command-log replay, the headless scenarios, the soak, the
benchmarks and the tests all use it, so they run the very same arithmetic.

- ``sim.world`` (``World``): the world the car is in (``core.world``): the terrain, and
  every car's model and data stacked along a car axis; ``sim.step()`` and ``sim.run()``
  advance it by its one compiled step. A ``Simulation`` makes a world of one car.
- ``sim.model`` (``core.model.Model``): this car's vehicle and tire parameters, the
  world's terrain (with its road), step, the registered tire kernels: views of the
  world's rows. Static while stepping; ``set_road`` (the terrain's road) and ``load``
  change it.
- ``sim.data`` (``core.model.Data``): this car's state, inputs, outputs, workspace
  (views of the world's rows).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from simserver.core import layout as L
from simserver.core import params as P
from simserver.core.chassis import place_on_terrain
from simserver.core.contact import (
    K_EVENTS,
    N_CAR_CONTACT_OUT,
    Contacts,
    drain_events,
    with_car_added,
    with_car_removed,
)
from simserver.core.damping import DAMPING_MODELS
from simserver.core.integrator import derive_constants
from simserver.core.integrator import simulate as car_simulate
from simserver.core.model import B_CONTACT_ACTIVE, N_DERIVED, Data, Model, Workspace, make_data
from simserver.core.params import VP_CG_HEIGHT_M, VP_DAMPING_MODEL, VP_SLIP_MODEL
from simserver.core.pose import world_pose
from simserver.core.powertrain import RADPS_PER_RPM
from simserver.core.road import road_axes, road_frame, set_road
from simserver.core.slip import SLIP_MODELS
from simserver.core.start import BODY_SLOTS, settle_at_velocity, settle_steps, start_powertrain
from simserver.core.terrain import TERRAIN_PLANE, Terrain, with_own_road
from simserver.core.tire import N_TIRE_PARAM
from simserver.core.tire_layout import TP_RADIUS_M
from simserver.core.world import WorldData, WorldModel, car_views, stack_data
from simserver.core.world import simulate as world_simulate
from simserver.core.world import step as world_step
from simserver.tires.registry import check_tire_vectors, tire_kernels

if TYPE_CHECKING:
    from simserver.sim.scene import Scene


def pose_of(x: np.ndarray, on_plane: bool, axes: np.ndarray, cg_height_m: float,
            scratch_axes: np.ndarray, pose: np.ndarray) -> None:
    """The world pose of the state ``x`` into ``pose`` (``core.layout.POSE_*``): on the
    plane terrain the states live on the road plane (``axes``, ``core.road.road_axes``); on
    another terrain on the reference plane fitted under the wheels in the step before
    (its slopes and height are states, docs/model.md section 11; ``scratch_axes`` takes its
    axes). The one rule of the server's published pose (:meth:`Simulation.update_pose`) and
    the headless history's ``world_*`` columns (:func:`world_poses`)."""
    if on_plane:
        world_pose(x, axes, cg_height_m, pose)
    else:
        road_frame(x[L.REF_GRADE_PCT], x[L.REF_CROSS_SLOPE_PCT], scratch_axes)
        world_pose(x, scratch_axes, cg_height_m, pose)
        pose[L.POSE_Z_M] += x[L.REF_HEIGHT_M]


def world_poses(scene: Scene, states: np.ndarray) -> np.ndarray:
    """The world pose of each row of ``states`` (a run's recorded states of a car of
    ``scene``, its road plane being the world's), float64 ``(rows, N_POSE)``: what the
    server publishes for each of those states (:func:`pose_of`)."""
    on_plane = scene.terrain.kind == TERRAIN_PLANE
    axes = road_axes(scene.road["grade_pct"], scene.road["cross_slope_pct"])
    cg_height_m = float(scene.vehicle.vp[VP_CG_HEIGHT_M])
    scratch = np.zeros((3, 3))
    poses = np.zeros((len(states), L.N_POSE))
    for row, x in zip(poses, states, strict=True):
        pose_of(x, on_plane, axes, cg_height_m, scratch, row)
    return poses


def initial_state(scene: Scene) -> np.ndarray:
    """The state at t = 0: given pose and velocities, wheels rolling freely, springs
    static, no previous wheel loads, the engine (automatic powertrain) at idle, no gear
    engaged yet."""
    x = np.zeros(L.N_STATE, dtype=np.float64)
    init = scene.initial
    x[L.X_M] = init["x_m"]
    x[L.Y_M] = init["y_m"]
    x[L.YAW_RAD] = init["yaw_rad"]
    x[L.U_MPS] = init["u_mps"]
    x[L.V_MPS] = init["v_mps"]
    x[L.YAW_RATE_RADPS] = init["yaw_rate_radps"]
    tp = scene.vehicle.tp
    for i in range(L.N_WHEELS):
        x[L.OMEGA0 + i] = init["u_mps"] / tp[i, TP_RADIUS_M]
        x[L.HUB_U_PREV0 + i] = init["u_mps"]
    x[L.FZ_PREV] = L.FZ_PREV_NONE
    vp = scene.vehicle.vp
    if int(vp[P.VP_POWERTRAIN_KIND]) == P.POWERTRAIN_AUTOMATIC:  # the engine idles,
        x[L.ENGINE_SPEED_RADPS] = vp[P.VP_ENGINE_IDLE_SPEED_RPM] * RADPS_PER_RPM
        # its idle controller settled against the drag torque (as in P or N)
        x[L.IDLE_CONTROL_NM] = vp[P.VP_ENGINE_DRAG_TORQUE_NM]
    return x


def check_model(vp: np.ndarray, tp: np.ndarray) -> None:
    """Raise ``ValueError`` unless every model id in ``vp`` and ``tp`` is registered."""
    SLIP_MODELS.by_id(vp[VP_SLIP_MODEL])
    DAMPING_MODELS.by_id(vp[VP_DAMPING_MODEL])
    check_tire_vectors(tp)


@dataclasses.dataclass
class PreparedStart:
    """A reset or load made ready beside the running simulation (``Simulation.prepare_reset``,
    ``prepare_load``): its own state, inputs and workspace, and the settling steps of a start
    at speed still to run (``core.start.settle_at_velocity``: up to ``SETTLE_STEPS_MAX``,
    8 ms). The live server runs them a few at a time between ticks (:meth:`advance`), so no
    tick waits for them; run in pieces or at once the result is the same to the bit (each
    piece holds the body at the values the previous one left)."""

    scene: Scene
    model: Model
    road: dict[str, float]
    data: Data
    steps_left: int
    settled: bool  # the wheels are relaxed (a start at speed): the out vector is its forces
    load: bool = False  # a load (its model replaces the car's and its terrain the world's)
    _body: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(BODY_SLOTS))

    def advance(self, max_steps: int) -> bool:
        """Run up to ``max_steps`` of the settling; True when it is done."""
        n = min(self.steps_left, max_steps)
        if n > 0:
            settle_at_velocity(self.model, self.data, n, self._body)
            self.steps_left -= n
        return self.steps_left == 0

    def finish(self) -> PreparedStart:
        """Run what is left of the settling at once (headless runs, replays, tools)."""
        self.advance(self.steps_left)
        return self


class World:
    """Cars on one terrain (``core.world``): the stacked model and data, the cars' ids in
    the order of the car axis, and the step that advances them all.

    Adding or removing a car (between steps: :meth:`add_car`, :meth:`remove_car`)
    reallocates the stacks (``np.concatenate``, ``np.delete``: about 20 kB per car) and the
    per-car views are rebuilt (:attr:`generation` counts the replacements); nothing is
    recompiled: the stacks keep their dtype, rank and layout whatever the number of cars,
    so the compiled step's argument types are those of a world of any size
    (docs/model.md section 14). Every car of a world has the world's ``dt_s`` and gravity
    (the terrain's road resolves gravity once for all)."""

    def __init__(self, terrain: Terrain, dt_s: float) -> None:
        self._read_road(terrain)
        self.ids: list[str] = []
        self.model = WorldModel(vp=np.zeros((0, P.N_VEHICLE_PARAM)),
                                tp=np.zeros((0, L.N_WHEELS, N_TIRE_PARAM)), dt_s=float(dt_s),
                                tires=tire_kernels(), terrain=terrain,
                                derived=np.zeros((0, N_DERIVED)))
        self.data: WorldData = stack_data([])
        self.generation = 0
        # steps taken (:meth:`step`, ``Simulation.step``): the world's clock, which a multi-car
        # command log names so that a replay steps every car at its world step
        # (``simserver.server.command_log.replay_world``)
        self.steps = 0

    def __len__(self) -> int:
        return len(self.ids)

    def index(self, car_id: str) -> int:
        """The car's row on the car axis (``KeyError`` naming it if there is none)."""
        try:
            return self.ids.index(car_id)
        except ValueError:
            raise KeyError(f"no car {car_id!r} in the world (cars: {self.ids})") from None

    @property
    def gravity_mps2(self) -> float | None:
        """The world's gravity: its cars' (None with no car)."""
        return float(self.model.vp[0, P.VP_GRAVITY_MPS2]) if self.ids else None

    def add_car(self, car_id: str, model: Model, data: Data) -> int:
        """Append a car (copies of ``model``'s vehicle and tire parameters and derived
        constants, and of ``data``); its terrain is the world's, ``model.terrain`` is not
        read. Returns its row. Raises ``ValueError`` for an id already taken or a car whose
        ``dt_s`` or gravity differs from the world's."""
        if car_id in self.ids:
            raise ValueError(f"car {car_id!r}: the world has a car of that id already")
        if model.dt_s != self.model.dt_s:
            raise ValueError(f"car {car_id!r}: dt_s {model.dt_s} differs from the world's "
                             f"{self.model.dt_s}")
        g = self.gravity_mps2
        if g is not None and model.vp[P.VP_GRAVITY_MPS2] != g:
            raise ValueError(f"car {car_id!r}: gravity_mps2 {model.vp[P.VP_GRAVITY_MPS2]} "
                             f"differs from the world's {g}")
        m = self.model
        self.model = m._replace(vp=np.concatenate([m.vp, model.vp[None]]),
                                tp=np.concatenate([m.tp, model.tp[None]]),
                                derived=np.concatenate([m.derived, model.derived[None]]))
        d = self.data
        self.data = WorldData(
            *(np.concatenate([a, b[None]]) for a, b in zip(d[:3], data[:3], strict=True)),
            ws=Workspace(*(np.concatenate([a, b[None]])
                           for a, b in zip(d.ws, data.ws, strict=True))),
            contacts=with_car_added(d.contacts))
        self.ids.append(car_id)
        self.generation += 1
        return len(self.ids) - 1

    def remove_car(self, car_id: str) -> None:
        """Take a car out; the others keep their order (and their bits)."""
        c = self.index(car_id)
        m = self.model
        self.model = m._replace(vp=np.delete(m.vp, c, axis=0), tp=np.delete(m.tp, c, axis=0),
                                derived=np.delete(m.derived, c, axis=0))
        d = self.data
        self.data = WorldData(*(np.delete(a, c, axis=0) for a in d[:3]),
                              ws=Workspace(*(np.delete(a, c, axis=0) for a in d.ws)),
                              contacts=with_car_removed(d.contacts, c))
        del self.ids[c]
        self.generation += 1

    def set_terrain(self, terrain: Terrain) -> None:
        """Swap the world's terrain (with its road) for every car, from the next step."""
        self.model = self.model._replace(terrain=terrain)
        self._read_road(terrain)
        self.generation += 1

    def set_road(self, grade_pct: float, cross_slope_pct: float, friction_scale: float) -> None:
        """Change the road under every car (the terrain's road; from the next step)."""
        g = self.gravity_mps2
        set_road(self.model.terrain.road, grade_pct, cross_slope_pct, friction_scale,
                 P.MODEL_OPTIONS.defaults["gravity_mps2"] if g is None else g)
        self._read_road(self.model.terrain)

    def _read_road(self, terrain: Terrain) -> None:
        """``road`` (the ``road:`` keys as set) and ``axes`` (the plane's, for the pose)
        from the terrain's road."""
        r = terrain.road
        self.road = {"grade_pct": float(r[P.ROAD_GRADE_PCT]),
                     "cross_slope_pct": float(r[P.ROAD_CROSS_SLOPE_PCT]),
                     "friction_scale": float(r[P.ROAD_FRICTION_SCALE])}
        self.axes = road_axes(self.road["grade_pct"], self.road["cross_slope_pct"])

    def car(self, car_id: str) -> tuple[Model, Data]:
        """The car's ``Model`` and ``Data``: views of its rows (``core.world.car_views``)."""
        return car_views(self.model, self.data, self.index(car_id))

    def step(self) -> None:
        """One fixed step of every car (``core.world.step``)."""
        world_step(self.model, self.data)
        self.steps += 1

    def run(self, inputs_per_step: np.ndarray, states: np.ndarray, outputs: np.ndarray,
            record_every: int = 1, contacts: np.ndarray | None = None) -> None:
        """``core.world.simulate``: inputs float64[n_steps, n_cars, N_INPUT], states and
        outputs float64[rows, n_cars, N_STATE / N_OUT], and, if given, the cars' contacts
        float64[rows, n_cars, N_CAR_CONTACT_OUT] (``core.contact.CC_*``)."""
        if contacts is None:
            contacts = np.zeros((states.shape[0], len(self.ids), 0))
        world_simulate(self.model, self.data, np.ascontiguousarray(inputs_per_step), states,
                       outputs, record_every, contacts)

    def contact_events(self, seen: int) -> tuple[list[dict], int, int]:
        """The contact events after the first ``seen`` (``core.contact.drain_events``), each
        with the two cars' ids (``car_a``, ``car_b``, rows mapped to the ids of now: drain
        before adding or removing a car), the number written so far and how many were
        lost (the ring overwritten before this call)."""
        events, total, lost = drain_events(self.data.contacts, seen)
        for e in events:
            e["car_a"] = self.ids[e["car_a"]]
            e["car_b"] = self.ids[e["car_b"]]
        return events, total, lost

    def car_contact(self, car_id: str) -> np.ndarray:
        """The car's contact output of the last step, a view (``core.contact.CC_*``, names
        ``CAR_CONTACT_NAMES``: the flag, the force on it and its moment, its depth, its
        events so far)."""
        return self.data.contacts.car[self.index(car_id), :N_CAR_CONTACT_OUT]

    def contact_count(self) -> int:
        """Contact events since the world was made (a pair of cars that starts to touch)."""
        return int(self.data.contacts.count[K_EVENTS])


HELPER_KERNELS = ("world_pose", "start_powertrain", "place_on_terrain")
"""The live warm-up's entry points (:meth:`Simulation.warm_up_calls`) that call no car step:
a helper process compiles them into the kernel cache while the server compiles the step,
the server's own warm-up then loads them from the cache
(``simserver.sim.scene_files.warm_up_in_helper``)."""


class Simulation:
    """A vehicle on its road: one car of a world, and the world's step (module docstring).

    ``Simulation(scene, dt_s)`` makes a world of one car (id ``car_id``); ``model`` and
    ``data`` are that car's views of the world's rows (``World.car``), so every single-car
    call (``core.start``, ``place_on_terrain``, the server's reads of ``x``, ``inputs``,
    ``out``) works on the world's arrays, and :meth:`step` and :meth:`run` are the world's
    (every car of the world)."""

    def __init__(self, scene: Scene, dt_s: float, car_id: str = "car0") -> None:
        self.dt_s = float(dt_s)
        self.car_id = car_id
        self.world: World | None = None
        self._views: tuple[Model, Data] | None = None
        self._views_generation = -1
        self._contact_view = np.zeros(N_CAR_CONTACT_OUT)
        self._contact_key: tuple[int, int] = (-1, 0)
        self._first_data: Data = make_data()  # the data before the world exists
        self.pose = np.zeros(L.N_POSE)
        self._reference_axes = np.zeros((3, 3))  # update_pose's scratch: no allocation
        self.load(scene)

    def _car(self) -> tuple[Model, Data]:
        world = self.world
        if world is None:
            raise RuntimeError("the simulation has no world before its first load")
        if self._views_generation != world.generation:
            self._views = world.car(self.car_id)
            self._views_generation = world.generation
        return self._views

    def contact_output(self) -> np.ndarray:
        """This car's contact output of the last step (``World.car_contact``: a view,
        ``core.contact.CC_*``), looked up again only when the world's rows changed."""
        world = self.world
        if world is None:
            raise RuntimeError("the simulation has no world before its first load")
        car = world.data.contacts.car
        if self._contact_key != (world.generation, id(car)):
            self._contact_view = world.car_contact(self.car_id)
            self._contact_key = (world.generation, id(car))
        return self._contact_view

    @property
    def model(self) -> Model:
        """This car's static model (``core.model.Model``; views of the world's rows)."""
        return self._car()[0]

    @property
    def data(self) -> Data:
        """This car's mutable data (``core.model.Data``; views of the world's rows)."""
        if self.world is None:
            return self._first_data
        return self._car()[1]

    # ---- the model
    def load(self, scene: Scene) -> None:
        """Take a scene (vehicle, road, initial state); the state is reset to it and the
        inputs are kept."""
        self.commit(self.prepare_load(scene).finish())

    def prepare_load(self, scene: Scene, keep_terrain: bool = False) -> PreparedStart:
        """A ``load`` of ``scene`` made ready beside the running model (which is not
        touched): its model and initial state, the settling left to :meth:`PreparedStart.advance`;
        :meth:`commit` swaps it in. ``keep_terrain``: the car takes the scene's vehicle and
        start only, on the world's terrain and road as they are (a car of a world of
        several: the other cars' ground does not change)."""
        vp = scene.vehicle.vp.copy()
        tp = np.ascontiguousarray(scene.vehicle.tp, dtype=np.float64).copy()
        check_model(vp, tp)
        # the terrain with a road of its own: set_road writes it, never the scene's
        model = Model(vp=vp, tp=tp, dt_s=self.dt_s, tires=tire_kernels(),
                      terrain=with_own_road(scene.terrain),
                      derived=derive_constants(vp, tp, self.dt_s))
        road = {key: scene.road[key] for key in ("grade_pct", "cross_slope_pct",
                                                  "friction_scale")}
        if keep_terrain and self.world is not None:
            model = model._replace(terrain=self.world.model.terrain)
            road = dict(self.world.road)
        else:
            set_road(model.terrain.road, **road, gravity_mps2=vp[P.VP_GRAVITY_MPS2])
        return self._prepare(scene, model, road, None, None, load=True)

    def set_road(self, grade_pct: float, cross_slope_pct: float, friction_scale: float) -> None:
        """Change the road plane (the world's terrain's road, under every car of the world;
        takes effect at the next step)."""
        self.world.set_road(grade_pct, cross_slope_pct, friction_scale)

    @property
    def road(self) -> dict[str, float]:
        """The world's road as set (``grade_pct``, ``cross_slope_pct``, ``friction_scale``)."""
        return self.world.road

    @property
    def axes(self) -> np.ndarray:
        """The world's road plane axes (``core.road.road_axes``)."""
        return self.world.axes

    def move_to(self, world: World) -> None:
        """Move this car into another world, between steps: its parameters and data are
        copied in as a car of ``world`` (the id ``car_id``; ``ValueError`` if it is taken
        or the car's ``dt_s`` or gravity differ) and taken out of the world it was in; from
        then on ``model``, ``data``, :meth:`step` are ``world``'s, and the car stands on
        ``world``'s terrain and road (its scene's road no longer applies). Nothing is
        recompiled (``World``)."""
        model, data = self._car()
        world.add_car(self.car_id, model, data)
        old = self.world
        if old is not world:
            old.remove_car(self.car_id)
        self.world = world
        self._views_generation = -1
        others = [c for c in world.ids if c != self.car_id]
        if others:  # one clock: a car joining a running world takes the world's time
            self.data.x[L.TIME_S] = world.data.x[world.index(others[0]), L.TIME_S]

    @property
    def vp(self) -> np.ndarray:
        """Vehicle parameters (``core.params``)."""
        return self.model.vp

    @property
    def tp(self) -> np.ndarray:
        """Tire parameters per wheel (``core.tire_layout``)."""
        return self.model.tp

    # ---- the data
    @property
    def x(self) -> np.ndarray:
        """The state (``core.layout``), advanced in place by ``step``."""
        return self.data.x

    @property
    def inputs(self) -> np.ndarray:
        """The driver inputs applied by the next ``step`` (``core.layout.IN_*``)."""
        return self.data.inputs

    @property
    def out(self) -> np.ndarray:
        """Forces and accelerations at the start of the last step (``core.layout.O_*``)."""
        return self.data.out

    def reset(self, pose: dict[str, float] | None, u_mps: float | None = None) -> None:
        """Back to the scene's initial state, or to ``pose`` (x_m, y_m, yaw_rad) at rest or,
        with ``u_mps``, driving straight on at that speed.

        A start at speed with ``u_mps`` (or the scene's ``initial.relaxed: 1``) has the
        wheels, slip states and powertrain relaxed to their steady values at the initial
        velocity (``core.start``), with the current steer, throttle and gear (P as N) and
        the brakes off; the inputs are kept.
        """
        self.commit(self.prepare_reset(pose, u_mps).finish())

    def prepare_reset(self, pose: dict[str, float] | None,
                      u_mps: float | None = None) -> PreparedStart:
        """A :meth:`reset` made ready beside the running state (untouched until
        :meth:`commit`), with the inputs of now; the settling of a start at speed is left to
        :meth:`PreparedStart.advance`, so the live server runs it in small pieces."""
        return self._prepare(self.scene, self.model, self.road, pose, u_mps)

    def _prepare(self, scene: Scene, model: Model, road: dict[str, float],
                 pose: dict[str, float] | None, u_mps: float | None,
                 load: bool = False) -> PreparedStart:
        relaxed = bool(scene.initial.get("relaxed", 0.0))
        start_scene = scene
        if pose is not None or u_mps is not None:
            start = {**scene.initial, **(pose or {}), "u_mps": 0.0, "v_mps": 0.0,
                     "yaw_rate_radps": 0.0}
            if u_mps is not None:
                start["u_mps"] = float(u_mps)
                relaxed = True
            start_scene = dataclasses.replace(scene, initial=start)
        # the workspace copied, not new: the MF 6.1 path reads some of it before writing it
        # (the last bits of its forces differ with a fresh one), and a reset prepared
        # aside must give the very state a reset in place gives
        ws = Workspace(*(a.copy() for a in self.data.ws))
        ws.body[B_CONTACT_ACTIVE] = 0.0  # a start is the car alone (core.start steps it)
        data = Data(x=initial_state(start_scene), inputs=self.data.inputs.copy(),
                    out=self.data.out.copy(), ws=ws)
        if model.terrain.kind != TERRAIN_PLANE:
            place_on_terrain(model, data.ws, data.x)
        steps = 0
        if relaxed:  # settled with the inputs of now, but the brakes off and P as N
            steps = settle_steps(model, data.x[L.U_MPS])
            inputs = data.inputs
            inputs[L.IN_BRAKE] = 0.0
            inputs[L.IN_PARKING_BRAKE] = 0.0
            if inputs[L.IN_GEAR] == L.GEAR_P:
                inputs[L.IN_GEAR] = L.GEAR_N
            start_powertrain(model, data)
        return PreparedStart(scene=scene, model=model, road=road, data=data,
                             steps_left=steps, settled=relaxed, load=load)

    def commit(self, prepared: PreparedStart) -> tuple[Scene, Model] | None:
        """Swap a finished :class:`PreparedStart` in: its state (and, for a load, its scene,
        model and road); the inputs are kept. Returns the scene and model a load replaced
        (None otherwise): dropping them frees a terrain's grids, which the live server does
        outside the tick (``simserver.server.load_worker.release_later``).

        A load writes the car's rows of the world's parameters in place (their shapes are
        fixed) and swaps the world's terrain; the first load makes the world of one car."""
        assert prepared.steps_left == 0, "commit a prepared start once it is settled"
        replaced = None
        if prepared.load:
            new = prepared.model
            if self.world is None:
                self.world = World(new.terrain, self.dt_s)
                self.world.add_car(self.car_id, new, self._first_data)
            else:
                model = self.model
                replaced = (self.scene, model._replace(vp=model.vp.copy(), tp=model.tp.copy(),
                                                       derived=model.derived.copy()))
                model.vp[:] = new.vp
                model.tp[:] = new.tp
                model.derived[:] = new.derived
                self.world.set_terrain(new.terrain)
            self.scene = prepared.scene
        data = self.data
        # one clock per world (docs/protocol.md section 5.1): a car that shares its world
        # with others keeps the world's time through its reset or load (its events and
        # states carry the world's time); a car alone restarts it at 0, as always
        clock = float(data.x[L.TIME_S]) if self.world is not None and \
            len(self.world) > 1 else None
        data.x[:] = prepared.data.x
        if clock is not None and math.isfinite(clock):
            data.x[L.TIME_S] = clock
        for live, ready in zip(data.ws, prepared.data.ws, strict=True):  # see _prepare
            live[...] = ready
        if prepared.settled:  # the forces of the last settling step, as before
            data.out[:] = prepared.data.out
        return replaced

    # ---- stepping
    def step(self) -> None:
        """One fixed step of the world (this car's, and any other car's) with the current
        inputs (``core.world.step``)."""
        world = self.world
        world_step(world.model, world.data)
        world.steps += 1

    def run(self, inputs_per_step: np.ndarray, states: np.ndarray, outputs: np.ndarray,
            record_every: int = 1) -> None:
        """``len(inputs_per_step)`` steps in one compiled loop: row ``k`` of
        ``states``/``outputs`` is the start state of step ``k * record_every`` and the
        forces at it. A world of this one car only (several cars: ``World.run``).

        The loop is the single car's (``core.integrator.simulate`` on this car's views of
        the world's rows): ``core.world.simulate``'s is the same car step on the same rows,
        so the same bits, but its loop over the car axis cost the brush car 7 % a step
        (issue 29)."""
        world = self.world
        if len(world) != 1:
            raise ValueError(f"Simulation.run steps a world of one car; this one has "
                             f"{len(world)} (use World.run)")
        model, data = self._car()
        data.ws.body[B_CONTACT_ACTIVE] = 0.0  # alone: nothing touches it (a car left behind)
        car_simulate(model, data, np.ascontiguousarray(inputs_per_step), states, outputs,
                     record_every)

    def update_pose(self) -> np.ndarray:
        """The world pose of the current state into ``self.pose`` (``core.layout.POSE_*``)."""
        pose_of(self.data.x, self.model.terrain.kind == TERRAIN_PLANE, self.axes,
                self.model.vp[VP_CG_HEIGHT_M], self._reference_axes, self.pose)
        return self.pose

    def warm_up(self, live: bool = False) -> None:
        """Compile (or load from cache) every kernel the runners use, before the clock starts;
        the state is left as it was. ``live``: only the live server's (no headless loop,
        see :meth:`warm_up_calls`)."""
        for _name, call in self.warm_up_calls(live):
            call()

    def warm_up_calls(self, live: bool = False) -> list[tuple[str, Callable[[], object]]]:
        """The compiled entry points :meth:`warm_up` calls, by name, in order (each compiles
        or loads its kernel on its first call; ``benchmarks.bench_compile`` times them one by
        one). They run on a copy of the state. ``live``: without ``simulate``, the headless
        loop (``core.world.simulate``: scenarios, soak, sweep runs), which the live server
        never runs: it steps tick by tick (``step``). Its compile (2.7 s of CPU of 78, the
        car step being compiled already: ``python -m benchmarks.bench_compile``) was paid by
        every cold server start for nothing."""
        world = self.world.model
        wd = self.world.data
        saved_world = WorldData(x=wd.x.copy(), inputs=wd.inputs.copy(), out=wd.out.copy(),
                                ws=wd.ws, contacts=Contacts(*(a.copy() for a in wd.contacts)))
        model, saved = car_views(world, saved_world, self.world.index(self.car_id))
        n = len(self.world)
        headless = [] if live else [
            ("simulate", lambda: world_simulate(world, saved_world, np.zeros((1, n, L.N_INPUT)),
                                                np.zeros((1, n, L.N_STATE)),
                                                np.zeros((1, n, L.N_OUT)), 1,
                                                np.zeros((1, n, N_CAR_CONTACT_OUT))))]
        return [
            ("step", lambda: world_step(world, saved_world)),
            ("world_pose", lambda: world_pose(self.data.x, self.axes,
                                              model.vp[VP_CG_HEIGHT_M], self.pose)),
            *headless,
            ("start_powertrain", lambda: start_powertrain(model, saved)),
            ("settle_at_velocity", lambda: settle_at_velocity(model, saved, 1,
                                                              np.zeros(BODY_SLOTS))),
            # a later load of a terrain places the car with it: loaded now, not in a tick
            # (it took 10 ms from the cache on the first terrain load of a server started
            # flat)
            ("place_on_terrain", lambda: place_on_terrain(model, saved.ws, saved.x.copy())),
        ]
