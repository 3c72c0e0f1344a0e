"""The world: the unit of simulation. Cars on one terrain, advanced by one compiled step.

The shape is mujoco_warp's (docs/model.md section 14): a static world model apart from the
world's mutable data, both with a leading car axis, and one ``step(world, data)`` that
advances every car of the world by ``dt_s``.

- ``WorldModel``: the terrain (one, shared by every car: its road included,
  ``core.terrain``), the step, the registered tire kernels, and per car its vehicle and
  tire parameters and derived constants, stacked along axis 0.
- ``WorldData``: per car its state, inputs, outputs and workspace, stacked along the same
  axis (a workspace per car: the MF 6.1 path reads scratch before writing it, so a shared
  one would let one car's last bits depend on another's).

Car ``c`` of a world is the single-car ``core.model.Model`` / ``Data`` made of row ``c``
of each array (``car_model``, ``car_data``: views, nothing copied), and the world's step is
the car step (``core.integrator.step``) on each car in turn: a car's arithmetic is the
same whatever the other cars are, and a world of one car gives the single car's bits.
Cars touch through the world's contact stage (``core.contact``, docs/model.md section
15), run before the car steps: it gives each car that touches another an equal and
opposite push held over the step (the car's ``B_CONTACT_*`` body slots); a car that
touches nothing steps exactly as alone.

The row views of C-contiguous stacks are C-contiguous arrays of the single car's ranks,
so the car step compiled for one car is the one the world calls: adding or removing a car
(``simserver.sim.simulation.World``) reallocates the stacks but recompiles nothing.
"""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np

from simserver.core import layout as L
from simserver.core.contact import Contacts, contact_stage, make_contacts
from simserver.core.integrator import step as car_step
from simserver.core.model import Data, Model, Workspace, make_data
from simserver.core.terrain import TERRAIN_PLANE, Terrain
from simserver.core.tire_layout import TireKernels


class WorldModel(NamedTuple):
    """The static world: one terrain, the step, the tire kernels; per car (axis 0) the
    vehicle and tire parameters and derived constants."""

    vp: np.ndarray  # float64[n_cars, N_VEHICLE_PARAM] (core.params)
    tp: np.ndarray  # float64[n_cars, N_WHEELS, N_TIRE_PARAM] (core.tire_layout)
    dt_s: float
    tires: TireKernels  # the registered tire models' kernels, by model id
    terrain: Terrain  # the ground and its road, shared by every car (core.terrain)
    derived: np.ndarray  # float64[n_cars, N_DERIVED] (core.model.D_*)


class WorldData(NamedTuple):
    """The world's mutable data, per car (axis 0)."""

    x: np.ndarray  # float64[n_cars, N_STATE], core.layout
    inputs: np.ndarray  # float64[n_cars, N_INPUT]
    out: np.ndarray  # float64[n_cars, N_OUT]
    ws: Workspace  # each array of core.model.Workspace with a leading n_cars axis
    contacts: Contacts  # the cars' contacts (core.contact): per car, per pair, the events


@nb.njit(cache=True, inline="always")
def car_model(world: WorldModel, c: int) -> Model:
    """Car ``c``'s single-car model: views of its rows and the shared terrain."""
    return Model(world.vp[c], world.tp[c], world.dt_s, world.tires, world.terrain,
                 world.derived[c])


@nb.njit(cache=True, inline="always")
def car_data(data: WorldData, c: int) -> Data:
    """Car ``c``'s single-car data: views of its rows."""
    ws = data.ws
    return Data(data.x[c], data.inputs[c], data.out[c],
                Workspace(ws.rk[c], ws.wheel_in[c], ws.wheel[c], ws.body[c], ws.tire_out[c],
                          ws.tire_coef[c], ws.ground[c], ws.axes[c], ws.contact[c],
                          ws.cells[c]))


@nb.njit(cache=True, inline="always")
def step_cars(world: WorldModel, data: WorldData) -> None:
    """``core.integrator.step`` on each car, in the order of axis 0 (no car reads another's
    rows, so the order changes nothing). Inlined into ``step`` and ``simulate``, so that
    ``simulate`` calls the car step as directly as the single car's loop did (a call that
    passes the world's tuples costs about 100 ns, a tenth of the brush car's step)."""
    for c in range(data.x.shape[0]):
        car_step(car_model(world, c), car_data(data, c))


@nb.njit(cache=True, inline="always")
def contacts(world: WorldModel, data: WorldData) -> None:
    """The contact stage (``core.contact.contact_stage``): each car's push from the cars it
    touches, held over the step, before the cars step."""
    contact_stage(world.vp, data.x, data.ws.body, data.ws.axes,
                  world.terrain.kind == TERRAIN_PLANE, world.dt_s, data.contacts)


# As core.integrator.step: no reference counting (the views are of the caller's arrays,
# which the caller keeps alive) and numpy's error model.
@nb.njit(cache=True, _nrt=False, error_model="numpy")
def step(world: WorldModel, data: WorldData) -> None:
    """Advance every car of the world by ``world.dt_s``: the contacts, then ``step_cars``."""
    contacts(world, data)
    step_cars(world, data)


@nb.njit(cache=True, _nrt=False, error_model="numpy")
def simulate(world: WorldModel, data: WorldData, inputs_per_step: np.ndarray,
             states: np.ndarray, outputs: np.ndarray, record_every: int,
             contact_rows: np.ndarray) -> None:
    """Run ``len(inputs_per_step)`` world steps, recording every ``record_every``-th one.

    ``inputs_per_step``: float64[n_steps, n_cars, N_INPUT]; row ``k`` of ``states``
    (float64[rows, n_cars, N_STATE]) and ``outputs`` (float64[rows, n_cars, N_OUT]) holds
    each car's state at the start of step ``k * record_every`` and the forces evaluated at
    it (``core.integrator.simulate``'s rows, per car), and ``contact_rows``
    (float64[rows, n_cars, N_CAR_CONTACT_OUT]) the contacts of that step
    (``core.contact.CC_*``, the output block). ``data.inputs`` ends holding the last row
    of ``inputs_per_step``."""
    x, out, inputs = data.x, data.out, data.inputs
    n_cars = x.shape[0]
    row = 0
    for k in range(inputs_per_step.shape[0]):
        for c in range(n_cars):
            for j in range(inputs.shape[1]):
                inputs[c, j] = inputs_per_step[k, c, j]
        if k % record_every == 0:
            for c in range(n_cars):
                for j in range(L.N_STATE):
                    states[row, c, j] = x[c, j]
        contacts(world, data)
        step_cars(world, data)
        if k % record_every == 0:
            for c in range(n_cars):
                for j in range(L.N_OUT):
                    outputs[row, c, j] = out[c, j]
                for j in range(contact_rows.shape[2]):
                    contact_rows[row, c, j] = data.contacts.car[c, j]
            row += 1


def stack_data(cars: list[Data]) -> WorldData:
    """World data holding copies of ``cars``' data along axis 0 (allocates)."""
    if not cars:  # a world of no car: each array with a car axis of length 0
        empty = make_data()
        return WorldData(*(np.zeros((0, *a.shape)) for a in empty[:3]),
                         Workspace(*(np.zeros((0, *a.shape)) for a in empty.ws)),
                         make_contacts(0))
    return WorldData(x=np.stack([d.x for d in cars]), inputs=np.stack([d.inputs for d in cars]),
                     out=np.stack([d.out for d in cars]),
                     ws=Workspace(*(np.stack(parts) for parts in zip(*(d.ws for d in cars),
                                                                     strict=True))),
                     contacts=make_contacts(len(cars)))


def car_views(world: WorldModel, data: WorldData, c: int) -> tuple[Model, Data]:
    """Car ``c``'s ``Model`` and ``Data`` as numpy views of the world's rows (Python side,
    for the single-car calls: what they write lands in the world)."""
    model = Model(vp=world.vp[c], tp=world.tp[c], dt_s=world.dt_s, tires=world.tires,
                  terrain=world.terrain, derived=world.derived[c])
    ws = Workspace(*(a[c] for a in data.ws))
    return model, Data(x=data.x[c], inputs=data.inputs[c], out=data.out[c], ws=ws)
