"""The published state's table (``protocol.STATE_FIELDS``) resolved against the core's
layouts: what the server copies into a VehicleState, and what the viewer copies back.

``protocol`` names each field's source by the core's own names (``"state:u_mps"``,
``"output:fx_{w}_n"``, ``"pose:x_m"``; ``core.layout``'s ``STATE_NAMES``,
``OUTPUT_NAMES``, ``INPUT_NAMES``, ``POSE_*``), because the clients that import it must
not import the core. This module turns the names into slots once, on import, so that a
row naming a slot the core does not have fails here, not in the tick:

- :data:`FILL`: ``(field, array, slot)`` of every field the server copies from the
  simulation's arrays (:func:`fill_record`, called by ``VehicleSlot.fill_state``);
- :data:`SERVER_FIELDS`: the fields the vehicle slot computes itself (flags, time,
  counters, the held wheels, the ground's slopes);
- :data:`INVERSE`: ``(field, array, slot)`` of every field the live viewer writes back
  into core rows (``viewer.rows_from_state``): into the slot of its history column where
  that is a core slot (``sim_time_s`` into ``time_s``, ``brake_held`` into
  ``wheel_held_*``), else into its source slot. The pose is not among them: the viewer
  takes the world pose (:func:`record_to_pose`) and turns it back into the planar states
  itself (``core.pose.road_pose``).

``array`` indexes :data:`ARRAYS`: ``(x, out, inputs, pose)``.
"""

from __future__ import annotations

from typing import Final, NamedTuple

import numpy as np

from simserver.core import layout as L
from simserver.wire import protocol as proto

ARRAYS: Final[tuple[str, ...]] = ("state", "output", "input", "pose")
"""The simulation's arrays a field is copied from or to, in :func:`fill_record`'s order."""

_NAMES = {"state": L.STATE_NAMES, "output": L.OUTPUT_NAMES, "input": L.INPUT_NAMES}
_INPUT_PREFIX = "input_"  # the history's name of an input (adapters.history.INPUT_PREFIX)


class Copy(NamedTuple):
    """One field copied between a VehicleState and a core array."""

    field: str
    array: int  # index into ARRAYS
    slot: int | slice


def core_slot(kind: str, name: str) -> int | slice:
    """The slot of ``core.layout`` a source names: an index, or the slice of the four
    wheels' slots for a name with ``{w}``.

    Raises
    ------
    ValueError
        Naming the source, when the core has no such slot (or the wheels' slots are not
        contiguous).
    """
    if kind == "pose":
        slot = getattr(L, f"POSE_{name.upper()}", None)
        if not isinstance(slot, int):
            raise ValueError(f"pose:{name}: core.layout has no POSE_{name.upper()}")
        return slot
    names = _NAMES[kind]
    try:
        if "{w}" not in name:
            return names.index(name)
        first, *rest = (names.index(name.format(w=w)) for w in proto.WHEEL_NAMES)
    except ValueError:
        raise ValueError(f"{kind}:{name}: not a slot of core.layout's {kind} names") from None
    if rest != list(range(first + 1, first + len(proto.WHEEL_NAMES))):
        raise ValueError(f"{kind}:{name}: the wheels' slots are not contiguous")
    return slice(first, first + len(proto.WHEEL_NAMES))


def history_slot(column: str) -> tuple[str, int | slice] | None:
    """``(kind, slot)`` of the core slot a history column (template) is written from, or
    None when the column is not a core slot (the history's columns are the core's names,
    inputs prefixed ``input_``: ``adapters.history``)."""
    if column.startswith(_INPUT_PREFIX):
        kind, column = "input", column[len(_INPUT_PREFIX):]
        candidates = ("input",)
    else:
        candidates = ("state", "output")
    for kind in candidates:
        try:
            return kind, core_slot(kind, column)
        except ValueError:
            continue
    return None


def _plans() -> tuple[tuple[Copy, ...], tuple[str, ...], tuple[Copy, ...]]:
    fill, server, inverse = [], [], []
    for f in proto.STATE_FIELDS:
        kind, name = proto.state_source(f)
        if kind == "server":
            server.append(f.name)
        elif kind:
            fill.append(Copy(f.name, ARRAYS.index(kind), core_slot(kind, name)))
        back = history_slot(f.history) if f.history is not None else None
        if back is None and kind in _NAMES:
            back = kind, core_slot(kind, name)
        if back is not None:
            inverse.append(Copy(f.name, ARRAYS.index(back[0]), back[1]))
    return tuple(fill), tuple(server), tuple(inverse)


FILL, SERVER_FIELDS, INVERSE = _plans()


def fill_record(rec: np.ndarray, x: np.ndarray, out: np.ndarray, inputs: np.ndarray,
                pose: np.ndarray) -> None:
    """Copy every :data:`FILL` field from the simulation's arrays into a state record
    (``protocol.new_state_record()``); the :data:`SERVER_FIELDS` are the caller's."""
    arrays = (x, out, inputs, pose)
    for field, array, slot in FILL:
        rec[field] = arrays[array][slot]


def record_to_rows(rec: np.ndarray, x: np.ndarray, out: np.ndarray,
                   inputs: np.ndarray) -> None:
    """Copy every :data:`INVERSE` field of a decoded state back into core rows."""
    arrays = (x, out, inputs)
    for field, array, slot in INVERSE:
        arrays[array][slot] = rec[field]


def record_to_pose(rec: np.ndarray, pose: np.ndarray) -> None:
    """Copy the world pose of a decoded state into a ``core.layout`` pose vector."""
    for field, array, slot in FILL:
        if array == _POSE:
            pose[slot] = rec[field]


_POSE = ARRAYS.index("pose")
