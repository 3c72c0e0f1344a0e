"""The built-in driver in the live server: cars ``driven_by: driver`` (issue 30 item 2).

The headless closed loop (``simserver.sim.scenario``) and the live loop drive the same way
(docs/model.md section 15): each tick, once, before the world's step, ``core.driver.drive``
writes every driven car's steer, throttle, brake, parking brake and gear into the world's
input rows from the states now (every car is an obstacle on the paths).

What the tick must not do is read files or sample roads, so that work is split:

- :meth:`LiveDrivers.prepare` (off the tick: the server's start): a driven car's
  ``driver:`` block parsed against its scene (``cars_config.driver_spec``) and its path's
  rows sampled over the terrain (:func:`sample_path`), kept by car id. A car added while
  the world runs (``world_desk``, ``add_car`` with ``driven_by: driver``) has its block
  parsed and its path sampled in the load worker (``world_desk.prepare_added_car``), and
  the desk hands both over between two ticks (:meth:`LiveDrivers.take`).
- :meth:`LiveDrivers.assemble` (between two ticks, when the world's cars change: the
  start, a car added or removed, a reset): the ``core.driver.Drivers`` arrays of the
  world's car axis from what was prepared, each car's parameters packed (microseconds
  of numpy per car), the driven cars' driver states carried over by id (a car added or
  removed leaves the others' modes, commands and stop points as they were); a reset
  starts every driver afresh.

The tick itself then calls ``drive`` on arrays that already exist: nothing allocated.

Replay: a car's command log records the inputs its step applied (``VehicleSlot.advance``
logs them after ``drive`` wrote them), so ``simserver replay`` plays the driver's inputs
back as it plays a person's, bit for bit, without running the driver again (the driver is
deterministic from the world's states, so running it again would give the same inputs
too, but the log does not depend on that).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from simserver.core import driver as D
from simserver.core import layout as L


def sample_path(spec: Any, terrain: Any) -> np.ndarray:
    """A driven car's path rows (``PATH_*``) over ``terrain`` (off the tick: the server's
    start, or the load worker for a car added while the world runs)."""
    from simserver.adapters.driver_config import path_rows

    return path_rows(spec.path_xy, terrain, spec.speed_profile, spec.params[D.DP_IDM_V0_MPS])


class LiveDrivers:
    """The driven cars of a live world: what each needs, prepared off the tick."""

    def __init__(self) -> None:
        self.specs: dict[str, Any] = {}  # id -> adapters.driver_config.DriverSpec
        self.rows: dict[str, np.ndarray] = {}  # id -> its path's PATH_* rows
        # each car a path of its own even when two are equal (a served OpenSCENARIO
        # scenario rewrites one car's path for a lane change: simserver.server.scenario_live)
        self.own_paths = False

    def __bool__(self) -> bool:
        return bool(self.specs)

    def prepare(self, car_id: str, spec: Any, terrain: Any) -> None:
        """Keep a driven car's validated ``driver:`` block and sample its path over
        ``terrain`` (off the tick)."""
        self.take(car_id, spec, sample_path(spec, terrain))

    def take(self, car_id: str, spec: Any, rows: np.ndarray) -> None:
        """Keep a driven car's validated block and its path's rows, sampled already (the
        load worker's, for a car added while the world runs): microseconds, between
        ticks; the car drives once the world's drivers are assembled with it."""
        self.specs[car_id] = spec
        self.rows[car_id] = rows

    def forget(self, car_id: str) -> None:
        self.specs.pop(car_id, None)
        self.rows.pop(car_id, None)

    def assemble(self, world: Any, old: D.Drivers | None = None,
                 old_ids: list[str] | None = None) -> D.Drivers | None:
        """The drivers of ``world``'s cars now (None: no car of it is driven). ``old``
        (the drivers of the world's cars ``old_ids`` before the change): each driven
        car's driver state is carried over by id; a car new to the driver starts with its
        block's stop point and go time, held if it is at rest (as ``build_drivers``)."""
        from simserver.adapters.driver_config import pack_params

        ids = list(world.ids)
        if not any(cid in self.specs for cid in ids):
            return None
        n = len(ids)
        paths: list[np.ndarray] = []
        params = np.zeros((n, D.N_DRIVER_PARAM))
        state = D.initial_driver_state(n)
        before = {cid: k for k, cid in enumerate(old_ids or ())}
        for c, cid in enumerate(ids):
            spec = self.specs.get(cid)
            index = 0
            if spec is not None:
                rows = self.rows[cid]
                index = len(paths) if self.own_paths else next(
                    (k for k, p in enumerate(paths) if p is rows
                     or (p.shape == rows.shape and np.array_equal(p, rows))), len(paths))
                if index == len(paths):
                    paths.append(rows)
                if old is not None and cid in before:
                    state[c] = old.state[before[cid]]
                else:
                    state[c, D.DS_STOP_STATION_M] = spec.stop_s_m
                    state[c, D.DS_GO_TIME_S] = spec.go_t_s
                    if abs(world.data.x[c, L.U_MPS]) < D.HOLD_SPEED_MPS:
                        state[c, D.DS_MODE] = D.MODE_HOLD
            params[c] = pack_params(spec, world.model.vp[c], world.model.tp[c], index)
        counts = np.array([len(p) for p in paths], dtype=np.int64)
        first = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        proj = np.zeros((n, len(paths), D.N_PROJ))
        proj[:, :, D.PROJ_SEG] = -1.0  # every car's nearest segment searched afresh
        return D.Drivers(params=params, state=state,
                         paths=np.ascontiguousarray(np.concatenate(paths)),
                         path_rows=np.ascontiguousarray(np.stack([first, counts], axis=1)),
                         proj=proj, pose=np.zeros((n, 4)), axes=np.zeros((n, 3, 3)))
