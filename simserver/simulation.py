"""One simulation object under every runner: the static model and the mutable data.

``Simulation(scene, dt_s)`` is the one place where a scene becomes something the compiled
step can run: the parameters are copied, the road is set, the tire and variant ids are
checked against their registries, the initial state is built and the workspace made.
The live server, the command-log replay, the headless scenarios, the soak, the
benchmarks and the tests all use it, so they run the very same arithmetic.

- ``sim.model`` (``core.model.Model``): vehicle and tire parameters, the terrain (with
  its road), step, the registered tire kernels. Static while stepping; ``set_road`` (the
  terrain's road) and ``load`` change it.
- ``sim.data`` (``core.model.Data``): state, inputs, outputs, workspace.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from simserver.core import layout as L
from simserver.core import params as P
from simserver.core.chassis import place_on_terrain
from simserver.core.damping import DAMPING_MODELS
from simserver.core.integrator import derive_constants, simulate, step
from simserver.core.model import Data, Model, Workspace, make_data
from simserver.core.params import VP_CG_HEIGHT_M, VP_DAMPING_MODEL, VP_SLIP_MODEL
from simserver.core.pose import world_pose
from simserver.core.powertrain import RADPS_PER_RPM
from simserver.core.road import road_axes, road_frame, set_road
from simserver.core.slip import SLIP_MODELS
from simserver.core.start import BODY_SLOTS, settle_at_velocity, settle_steps, start_powertrain
from simserver.core.terrain import TERRAIN_PLANE, with_own_road
from simserver.core.tire_layout import TP_RADIUS_M
from simserver.tire_models import check_tire_vectors, tire_kernels

if TYPE_CHECKING:
    from simserver.scenario import Scene


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


class Simulation:
    """A vehicle on its road: the model, the data and the step (module docstring)."""

    def __init__(self, scene: Scene, dt_s: float) -> None:
        self.dt_s = float(dt_s)
        self.data: Data = make_data()
        self.pose = np.zeros(L.N_POSE)
        self._reference_axes = np.zeros((3, 3))  # update_pose's scratch: no allocation
        self.load(scene)

    # ---- the model
    def load(self, scene: Scene) -> None:
        """Take a scene (vehicle, road, initial state); the state is reset to it and the
        inputs are kept."""
        self.commit(self.prepare_load(scene).finish())

    def prepare_load(self, scene: Scene) -> PreparedStart:
        """A ``load`` of ``scene`` made ready beside the running model (which is not
        touched): its model and initial state, the settling left to :meth:`PreparedStart.advance`;
        :meth:`commit` swaps it in."""
        vp = scene.vehicle.vp.copy()
        tp = np.ascontiguousarray(scene.vehicle.tp, dtype=np.float64).copy()
        check_model(vp, tp)
        # the terrain with a road of its own: set_road writes it, never the scene's
        model = Model(vp=vp, tp=tp, dt_s=self.dt_s, tires=tire_kernels(),
                      terrain=with_own_road(scene.terrain),
                      derived=derive_constants(vp, tp, self.dt_s))
        road = {key: scene.road[key] for key in ("grade_pct", "cross_slope_pct",
                                                  "friction_scale")}
        set_road(model.terrain.road, **road, gravity_mps2=vp[P.VP_GRAVITY_MPS2])
        return self._prepare(scene, model, road, None, None)

    def set_road(self, grade_pct: float, cross_slope_pct: float, friction_scale: float) -> None:
        """Change the road plane (the terrain's road; takes effect at the next step)."""
        set_road(self.model.terrain.road, grade_pct, cross_slope_pct, friction_scale,
                 self.model.vp[P.VP_GRAVITY_MPS2])
        self.road = {"grade_pct": grade_pct, "cross_slope_pct": cross_slope_pct,
                     "friction_scale": friction_scale}
        self.axes = road_axes(grade_pct, cross_slope_pct)

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
                 pose: dict[str, float] | None, u_mps: float | None) -> PreparedStart:
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
                             steps_left=steps, settled=relaxed)

    def commit(self, prepared: PreparedStart) -> tuple[Scene, Model] | None:
        """Swap a finished :class:`PreparedStart` in: its state (and, for a load, its scene,
        model and road); the inputs are kept. Returns the scene and model a load replaced
        (None otherwise): dropping them frees a terrain's grids, which the live server does
        outside the tick (``simserver.load_worker.release_later``)."""
        assert prepared.steps_left == 0, "commit a prepared start once it is settled"
        replaced = None
        if prepared.model is not getattr(self, "model", None):  # a load (or the first)
            if hasattr(self, "model"):
                replaced = (self.scene, self.model)
            self.scene = prepared.scene
            self.model = prepared.model
            self.road = prepared.road
            self.axes = road_axes(prepared.road["grade_pct"], prepared.road["cross_slope_pct"])
        self.data.x[:] = prepared.data.x
        for live, ready in zip(self.data.ws, prepared.data.ws, strict=True):  # see _prepare
            live[...] = ready
        if prepared.settled:  # the forces of the last settling step, as before
            self.data.out[:] = prepared.data.out
        return replaced

    # ---- stepping
    def step(self) -> None:
        """One fixed step with the current inputs."""
        step(self.model, self.data)

    def run(self, inputs_per_step: np.ndarray, states: np.ndarray, outputs: np.ndarray,
            record_every: int = 1) -> None:
        """``len(inputs_per_step)`` steps in one compiled loop (``core.integrator.simulate``):
        row ``k`` of ``states``/``outputs`` is the start state of step ``k * record_every``
        and the forces at it."""
        simulate(self.model, self.data, np.ascontiguousarray(inputs_per_step), states, outputs,
                 record_every)

    def update_pose(self) -> np.ndarray:
        """The world pose of the current state into ``self.pose`` (``core.layout.POSE_*``)."""
        x = self.data.x
        if self.model.terrain.kind == TERRAIN_PLANE:
            world_pose(x, self.axes, self.model.vp[VP_CG_HEIGHT_M], self.pose)
        else:  # the states live on the reference plane of the last step
            axes = self._reference_axes
            road_frame(x[L.REF_GRADE_PCT], x[L.REF_CROSS_SLOPE_PCT], axes)
            world_pose(x, axes, self.model.vp[VP_CG_HEIGHT_M], self.pose)
            self.pose[L.POSE_Z_M] += x[L.REF_HEIGHT_M]
        return self.pose

    def warm_up(self) -> None:
        """Compile (or load from cache) every kernel the server uses, before the clock starts;
        the state is left as it was."""
        for _name, call in self.warm_up_calls():
            call()

    def warm_up_calls(self) -> list[tuple[str, Callable[[], object]]]:
        """The compiled entry points :meth:`warm_up` calls, by name, in order (each compiles
        or loads its kernel on its first call; ``benchmarks.bench_compile`` times them one by
        one). They run on a copy of the state."""
        saved = Data(x=self.data.x.copy(), inputs=self.data.inputs.copy(),
                     out=self.data.out.copy(), ws=self.data.ws)
        model = self.model
        return [
            ("step", lambda: step(model, saved)),
            ("world_pose", lambda: world_pose(self.data.x, self.axes,
                                              model.vp[VP_CG_HEIGHT_M], self.pose)),
            ("simulate", lambda: simulate(model, saved, np.zeros((1, L.N_INPUT)),
                                          np.zeros((1, L.N_STATE)), np.zeros((1, L.N_OUT)),
                                          1)),
            ("start_powertrain", lambda: start_powertrain(model, saved)),
            ("settle_at_velocity", lambda: settle_at_velocity(model, saved, 1,
                                                              np.zeros(BODY_SLOTS))),
            # a later load of a terrain places the car with it: loaded now, not in a tick
            # (it took 10 ms from the cache on the first terrain load of a server started
            # flat)
            ("place_on_terrain", lambda: place_on_terrain(model, saved.ws, saved.x.copy())),
        ]
