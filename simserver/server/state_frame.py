"""Every car's VehicleState of a live world, filled in one go a tick (issue 30's 32 cars).

A car's state record (``protocol.STATE_DTYPE``) is mostly copies of its rows of the world's
arrays (``state_schema.FILL``: the state, outputs, inputs and the world pose) and a few
fields its slot computes (``state_schema.SERVER_FIELDS``: flags, tick, command fields,
held wheels, ground slopes, contact). Filling the copies field by field in Python cost
about 25 us a car (some 60 numpy scalar assignments), so a tick that published five cars
of 32 spent most of its budget there (``benchmarks.bench_multicar``). :class:`StateFrame`
holds one record per car of the world, in the world's car order, and fills the copied
fields of the cars that publish this tick (the loop's plan: the clients' cars and the
traffic at its phase) with a fixed number of numpy calls, whatever their number:

1. their world poses by one compiled call (``core.pose.world_poses``, the rule
   of ``simserver.sim.simulation.pose_of``);
2. their rows of the world's state, outputs, inputs and poses side by side in one
   float64 table (four gathers);
3. per destination type of the record (float64, float32, uint8, int8): one gather of
   that type's source columns (``numpy.take``) and one scatter into the records seen as
   that type (every field is aligned to its size), cast as numpy casts a field's
   assignment; the places are precomputed once, on import, from the state table.

The bytes are those of ``state_schema.fill_record`` (``tests/test_state_frame.py``
compares them for every car on the flat and on a terrain). Each slot's ``record`` is a
view of its row, so ``VehicleSlot.fill_state(..., filled=True)`` only adds the server's
fields of the cars that publish this tick.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from simserver.core import layout as L
from simserver.core.params import VP_CG_HEIGHT_M
from simserver.core.pose import world_poses
from simserver.core.terrain import TERRAIN_PLANE
from simserver.wire import protocol as proto
from simserver.wire.state_schema import ARRAYS, FILL

_WIDTHS = {"state": L.N_STATE, "output": L.N_OUT, "input": L.N_INPUT, "pose": L.N_POSE}
_FIRST = dict(zip(ARRAYS, np.cumsum([0, *(_WIDTHS[a] for a in ARRAYS)])[:-1].tolist(),
                  strict=True))
N_SOURCE = sum(_WIDTHS.values())
"""Columns of the side-by-side table: state, outputs, inputs, pose (``ARRAYS`` order)."""


class Group(NamedTuple):
    """The copied fields of one destination type: where their values come from (columns
    of the side-by-side table) and which bytes of a record they go to."""

    dtype: np.dtype
    columns: np.ndarray  # int64[k]
    byte_index: np.ndarray  # int64[k * itemsize]: record bytes, in the columns' order
    index: np.ndarray  # int64[k]: the values' places in a record seen as this type


def _groups() -> tuple[Group, ...]:
    by_type: dict[np.dtype, tuple[list[int], list[int]]] = {}
    fields = proto.STATE_DTYPE.fields
    for field, array, slot in FILL:
        dtype, offset = fields[field][0], fields[field][1]
        base = dtype.base
        first = _FIRST[ARRAYS[array]]
        cols = [first + slot] if isinstance(slot, int) else \
            list(range(first + slot.start, first + slot.stop))
        if len(cols) != max(1, int(np.prod(dtype.shape))):
            raise ImportError(f"state table: {field} has {len(cols)} sources for "
                              f"{dtype.shape or 1} values")
        columns, index = by_type.setdefault(base, ([], []))
        for j, col in enumerate(cols):
            columns.append(col)
            start = offset + j * base.itemsize
            index.extend(range(start, start + base.itemsize))
    groups = []
    for t, (c, i) in by_type.items():
        first_bytes = np.array(i[::t.itemsize], dtype=np.int64)
        if np.any(first_bytes % t.itemsize) or proto.STATE_SIZE % t.itemsize:
            raise ImportError(f"state table: a {t} field is not aligned to its size")
        groups.append(Group(t, np.array(c, dtype=np.int64), np.array(i, dtype=np.int64),
                            first_bytes // t.itemsize))
    return tuple(groups)


GROUPS = _groups()


class StateFrame:
    """The state records of every car of a world (one row each, the world's car order),
    their copied fields filled together by :meth:`fill`. :meth:`bind` (between ticks,
    when the cars change) sizes it and points each slot's ``record`` at its row."""

    def __init__(self) -> None:
        self.n = -1
        self.scratch_axes = np.zeros((3, 3))

    def bind(self, slots: list[Any]) -> None:
        """Rows for ``slots`` (the loop's cars, the world's order); each slot's ``record``
        becomes a view of its row, its server fields carried over."""
        n = len(slots)
        self.n = n
        self.records = np.zeros(n, dtype=proto.STATE_DTYPE)
        self.raw = self.records.view(np.uint8).reshape(n, proto.STATE_SIZE)
        self.poses = np.zeros((n, L.N_POSE))
        self.source = np.zeros((n, N_SOURCE))
        self.values = [np.zeros((n, len(g.columns))) for g in GROUPS]
        self.typed = [self.raw.view(g.dtype) for g in GROUPS]  # the records as each type
        for k, slot in enumerate(slots):
            self.records[k] = slot.record
            slot.record = self.records[k:k + 1].reshape(())  # a 0-d view of row k
        self.records["version"] = proto.PROTOCOL_VERSION

    def fill(self, world: Any, rows: np.ndarray) -> None:
        """The copied fields (``state_schema.FILL``) of the cars ``rows`` (int64, the
        world's order: those that publish this tick) from ``world``'s rows now, and their
        world poses into :attr:`poses`."""
        data, model = world.data, world.model
        if data.x.shape[0] != self.n:
            raise RuntimeError(f"state frame of {self.n} cars for a world of "
                               f"{data.x.shape[0]}: bind it when the cars change")
        poses = self.poses
        world_poses(data.x, model.vp, VP_CG_HEIGHT_M, model.terrain.kind == TERRAIN_PLANE,
                    world.axes, self.scratch_axes, rows, poses)
        source = self.source[:len(rows)]
        for name, array in zip(ARRAYS, (data.x, data.out, data.inputs, poses), strict=True):
            first = _FIRST[name]
            np.take(array, rows, axis=0, out=source[:, first:first + _WIDTHS[name]])
        column = rows[:, None]
        for group, values, typed in zip(GROUPS, self.values, self.typed, strict=True):
            values = values[:len(rows)]
            np.take(source, group.columns, axis=1, out=values)
            typed[column, group.index] = values  # numpy's cast, as a field's assignment
