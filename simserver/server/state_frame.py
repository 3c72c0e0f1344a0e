"""Every car's VehicleState of a live world, filled in one go a tick (issue 30's 32 cars).

A car's state record (``protocol.STATE_DTYPE``) is mostly copies of its rows of the world's
arrays (``state_schema.FILL``: the state, outputs, inputs and the world pose) and a few
fields its slot computes (``state_schema.SERVER_FIELDS``: flags, tick, command fields,
held wheels, ground slopes, contact). Filling the copies field by field in Python cost
about 25 us a car (some 60 numpy scalar assignments), so a tick that published five cars
of 32 spent most of its budget there (``benchmarks.bench_multicar``). :class:`StateFrame`
holds one record per car of the world, in the world's car order, and fills the copied
fields of the cars that publish this tick (the loop's plan: the clients' cars and the
traffic at its phase) with a fixed number of compiled calls, whatever their number:

1. their world poses (``core.pose.world_poses``, the rule of
   ``simserver.sim.simulation.pose_of``);
2. per destination type of the record (float64, float32, uint8, int8), that type's
   copied fields from the world's rows (state, outputs, inputs, pose) into the records
   seen as that type (every field is aligned to its size), cast as numpy casts a field's
   assignment (:func:`copy_fields`; the places are precomputed once, on import, from the
   state table);
3. the server's fields that follow from the physics (the held wheels and the flag bits
   ``BRAKE_HOLD`` and ``HILL_HOLD``, the ground's slopes along and across the heading,
   the car-to-car contact force and flag; ``VehicleSlot.fill_state``'s rules) and whether
   the pose and those fields are finite (:func:`physics_fields`).

Steps 2 and 3 replace numpy gathers, a fancy-indexed scatter and per-car Python that cost
about 45-65 us a tick of 8 cars (plus some 10 us a publishing car) in the live tick,
whose work runs cold after the pacer's sleep (``benchmarks.bench_multicar``), most of it
numpy's and the interpreter's per-call overhead, not the bytes.

The bytes are those of ``state_schema.fill_record`` and of the slot's own fields
(``tests/test_state_frame.py`` compares whole records, every car, on the flat and on a
terrain, braked, parked and in contact). Each slot's ``record`` is a view of its row, so
``VehicleSlot.fill_state(..., frame=...)`` only adds the fields that are the slot's own
(its flags, tick, time and command fields) to the cars that publish this tick.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np
from numba import njit

from simserver.core import layout as L
from simserver.core.contact import CC_ACTIVE, CC_FORCE_X_N, CC_FORCE_Y_N
from simserver.core.params import VP_CG_HEIGHT_M
from simserver.core.pose import world_poses
from simserver.core.terrain import TERRAIN_PLANE
from simserver.wire import protocol as proto
from simserver.wire.state_schema import ARRAYS, FILL

_WIDTHS = {"state": L.N_STATE, "output": L.N_OUT, "input": L.N_INPUT, "pose": L.N_POSE}
_FIRST = dict(zip(ARRAYS, np.cumsum([0, *(_WIDTHS[a] for a in ARRAYS)])[:-1].tolist(),
                  strict=True))


class Group(NamedTuple):
    """The copied fields of one destination type: where their values come from (each
    column's array, an index into ``ARRAYS``, and its slot there; ``columns`` numbers them
    as if state, outputs, inputs and pose stood side by side) and which bytes of a record
    they go to."""

    dtype: np.dtype
    columns: np.ndarray  # int64[k]
    byte_index: np.ndarray  # int64[k * itemsize]: record bytes, in the columns' order
    index: np.ndarray  # int64[k]: the values' places in a record seen as this type
    array: np.ndarray  # int64[k]: each column's source array (ARRAYS' order)
    slot: np.ndarray  # int64[k]: each column's slot in its source array


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
        columns = np.array(c, dtype=np.int64)
        starts = np.array([_FIRST[a] for a in ARRAYS], dtype=np.int64)
        array = np.searchsorted(starts, columns, side="right") - 1
        groups.append(Group(t, columns, np.array(i, dtype=np.int64),
                            first_bytes // t.itemsize, array, columns - starts[array]))
    return tuple(groups)


GROUPS = _groups()


def _place(name: str, dtype: type) -> int:
    """The place of the server's field ``name`` in a record seen as ``dtype`` (the field
    must be of that type and aligned to it: checked on import)."""
    field_dtype, offset = proto.STATE_DTYPE.fields[name][:2]
    if field_dtype.base != np.dtype(dtype) or offset % np.dtype(dtype).itemsize:
        raise ImportError(f"state table: {name} is {field_dtype} at byte {offset}; the "
                          f"state frame writes it as an aligned {np.dtype(dtype)}")
    return offset // np.dtype(dtype).itemsize


_AT_BRAKE_HELD = _place("brake_held", np.uint8)  # its four wheels follow
_AT_CAR_CONTACT = _place("car_contact", np.uint8)
_AT_GRADE = _place("ground_grade_pct", np.float32)
_AT_CROSS = _place("ground_cross_slope_pct", np.float32)
_AT_CONTACT_FORCE = _place("contact_force_n", np.float32)
FLAG_BRAKE_HOLD = int(proto.StateFlag.BRAKE_HOLD)
FLAG_HILL_HOLD = int(proto.StateFlag.HILL_HOLD)
_WHEEL_HELD0 = L.WHEEL_HELD.start


@njit(cache=True)
def copy_fields(rows: np.ndarray, x: np.ndarray, out: np.ndarray, inputs: np.ndarray,
                poses: np.ndarray, array: np.ndarray, slot: np.ndarray,
                typed: np.ndarray, index: np.ndarray) -> None:
    """One destination type's copied fields of the cars ``rows``: value ``j`` from row
    ``r`` of array ``array[j]`` (state, outputs, inputs, pose) at ``slot[j]`` into
    ``typed[r, index[j]]`` (the records seen as that type), cast as numpy casts a field's
    assignment (float64 to float32 rounds to nearest; to an integer type truncates)."""
    for i in range(rows.size):
        r = rows[i]
        for j in range(index.size):
            a = array[j]
            s = slot[j]
            if a == 0:
                typed[r, index[j]] = x[r, s]
            elif a == 1:
                typed[r, index[j]] = out[r, s]
            elif a == 2:
                typed[r, index[j]] = inputs[r, s]
            else:
                typed[r, index[j]] = poses[r, s]


@njit(cache=True)
def physics_fields(rows: np.ndarray, x: np.ndarray, inputs: np.ndarray, poses: np.ndarray,
                   contact: np.ndarray, plane: bool, road_grade_pct: float,
                   road_cross_slope_pct: float, f32: np.ndarray, u8: np.ndarray,
                   flag_bits: np.ndarray, pose_ok: np.ndarray) -> None:
    """The server's fields of the cars ``rows`` that follow from the physics, by the rules
    of ``VehicleSlot.fill_state`` (docs/protocol.md 2.2):

    - ``brake_held``: a wheel the core holds at zero spin (``WHEEL_HELD``) while a brake
      acts on it (the pedal, gear P's park lock, or the parking brake on the rear
      wheels); any of them sets the flag bit ``BRAKE_HOLD``; the hill-hold assist's
      state sets ``HILL_HOLD`` (``flag_bits[r]``: the bits to add to the slot's own);
    - the ground's slopes along and across the heading (``protocol.ground_slopes_pct``)
      of the road plane (``plane``) or of the reference plane under the wheels (the
      state's ``REF_*``, docs/model.md section 11);
    - the car-to-car contact force in the ground plane and the contact flag (the
      world's contact output, docs/model.md section 16);
    - ``pose_ok[r]``: the world pose and these fields (as published, float32) finite."""
    for i in range(rows.size):
        r = rows[i]
        braking = inputs[r, L.IN_BRAKE] > 0.0 or inputs[r, L.IN_GEAR] == L.GEAR_P
        parked = inputs[r, L.IN_PARKING_BRAKE] > 0.0
        bits = 0
        for w in range(L.N_WHEELS):
            held = x[r, _WHEEL_HELD0 + w] > 0.5 and (braking or (parked and w >= 2))
            u8[r, _AT_BRAKE_HELD + w] = 1 if held else 0
            if held:
                bits |= FLAG_BRAKE_HOLD
        if x[r, L.HILL_HOLD_ACTIVE] > 0.5:
            bits |= FLAG_HILL_HOLD
        flag_bits[r] = bits
        if plane:
            grade, cross = road_grade_pct, road_cross_slope_pct
        else:
            grade, cross = x[r, L.REF_GRADE_PCT], x[r, L.REF_CROSS_SLOPE_PCT]
        yaw = poses[r, L.POSE_YAW_RAD]
        c, s = math.cos(yaw), math.sin(yaw)
        f32[r, _AT_GRADE] = grade * c + cross * s
        f32[r, _AT_CROSS] = -grade * s + cross * c
        f32[r, _AT_CONTACT_FORCE] = math.hypot(contact[r, CC_FORCE_X_N],
                                               contact[r, CC_FORCE_Y_N])
        u8[r, _AT_CAR_CONTACT] = 1 if contact[r, CC_ACTIVE] > 0.5 else 0
        ok = math.isfinite(f32[r, _AT_GRADE] + f32[r, _AT_CROSS] + f32[r, _AT_CONTACT_FORCE])
        for k in range(poses.shape[1]):
            ok = ok and math.isfinite(poses[r, k])
        pose_ok[r] = ok


@njit(cache=True)
def all_finite(x: np.ndarray, out: np.ndarray) -> bool:
    """Every value of the world's states and outputs finite (the loop's one look a tick;
    ``numpy.isfinite(...).all()`` of both allocated two temporaries and cost about
    10-20 us at 8 cars)."""
    for v in x.flat:
        if not math.isfinite(v):
            return False
    for v in out.flat:
        if not math.isfinite(v):
            return False
    return True


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
        self._allocate(len(slots))
        for k, slot in enumerate(slots):
            self.records[k] = slot.record
            slot.record = self.records[k:k + 1].reshape(())  # a 0-d view of row k
        self.records["version"] = proto.PROTOCOL_VERSION

    def _allocate(self, n: int) -> None:
        self.n = n
        self.records = np.zeros(n, dtype=proto.STATE_DTYPE)
        self.raw = self.records.view(np.uint8).reshape(n, proto.STATE_SIZE)
        self.poses = np.zeros((n, L.N_POSE))
        self.typed = [self.raw.view(g.dtype) for g in GROUPS]  # the records as each type
        self.f32 = self.raw.view(np.float32)
        self.u8 = self.raw
        self.flag_bits = np.zeros(n, dtype=np.int64)  # physics_fields' flag bits, per car
        self.pose_ok = np.zeros(n, dtype=np.bool_)  # and its verdict on the pose

    def fill(self, world: Any, rows: np.ndarray) -> None:
        """The copied fields (``state_schema.FILL``) and the physics' server fields
        (:func:`physics_fields`) of the cars ``rows`` (int64, the world's order: those that
        publish this tick) from ``world``'s rows now, their world poses into
        :attr:`poses`, their flag bits into :attr:`flag_bits` and the verdicts on their
        poses into :attr:`pose_ok`."""
        data, model = world.data, world.model
        if data.x.shape[0] != self.n:
            raise RuntimeError(f"state frame of {self.n} cars for a world of "
                               f"{data.x.shape[0]}: bind it when the cars change")
        poses = self.poses
        world_poses(data.x, model.vp, VP_CG_HEIGHT_M, model.terrain.kind == TERRAIN_PLANE,
                    world.axes, self.scratch_axes, rows, poses)
        x, out, inputs = data.x, data.out, data.inputs
        for group, typed in zip(GROUPS, self.typed, strict=True):
            copy_fields(rows, x, out, inputs, poses, group.array, group.slot, typed,
                        group.index)
        road = world.road
        physics_fields(rows, x, inputs, poses, data.contacts.car,
                       model.terrain.kind == TERRAIN_PLANE, road["grade_pct"],
                       road["cross_slope_pct"], self.f32, self.u8, self.flag_bits,
                       self.pose_ok)


def compile_kernels(world: Any) -> None:
    """Compile (or load from the kernel cache) the frame's kernels for ``world``'s arrays,
    as a live world's first :meth:`StateFrame.bind` does (``docker/warmup.py`` calls this
    so that an image's first server start finds them cached); ``world`` is left as it
    was."""
    frame = StateFrame()
    frame._allocate(len(world.ids))
    frame.fill(world, np.arange(len(world.ids), dtype=np.int64))
    all_finite(world.data.x, world.data.out)
