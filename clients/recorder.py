"""``simserver-recorder``: record a live car's state and diagnostics to Parquet.

Writes ``OUT/history.parquet`` (one row per VehicleState received) with the headless
runner's column names (``simserver run-scenario``'s ``history.parquet``,
``docs/history_columns.md``) wherever the state carries the quantity, plus state-only
columns: every field of the state, named by the state table (``protocol.STATE_FIELDS``,
whose ``STATE_COLUMNS`` give each column's name, field, type and unit; docs/protocol.md
section 2.2), so a field added to the state is recorded without a change here. And
``OUT/diagnostics.parquet`` (one row per Diagnostics message). Rows are
buffered in preallocated chunks and streamed as Parquet row groups (``--flush-rows``);
Ctrl-C, SIGTERM, ``--duration`` or the server's liveliness token staying away for 3 s
stop the recording after a last drain of what zenoh already delivered, and the files are
completed (nothing received is lost; a SIGKILL loses the unfinished file). Then the
recording's stops, holds and restarts (per hold its creep and peak speed, per restart its
rollback, times to 0.5 and 2 m/s and peak jerk: ``simserver.analysis.holds``, the figures
of a headless summary's ``holds`` section) go to ``OUT/holds.json`` and one line per hold
to the terminal.

Frames
------
The state's pose is in **world** axes (``x_m``, ``y_m``, ``z_m`` of the CG, yaw, pitch
and roll of the body, z up). ``history.parquet`` of a headless run holds **road-plane**
coordinates: ``x_m``, ``y_m`` along the road plane's axes ``e1``, ``e2``, ``yaw_rad`` in
that plane, ``roll_rad`` and ``pitch_rad`` of the body relative to the road. On a flat
road the two coincide (and the body angles are the same); on a slope they do not. The
recorder writes the history's names in the **road-plane** frame, converted from the
world pose with the road the server reports (``ctl/get_config``, read at start, after
every reset or load, and every ``--road-poll`` seconds: a ``set_road`` between two polls
is converted with the previous road for at most that long), and the world pose itself
under distinct names, as the headless history does: ``world_x_m``, ``world_y_m``,
``world_z_m``, ``world_yaw_rad``, ``world_pitch_rad``, ``world_roll_rad``. The road plane
is the one ``ctl/set_road`` describes: it passes through the world origin and rises
``grade_pct`` % along world x and ``cross_slope_pct`` % along world y; ``e1`` is its
direction above world x, ``n`` its upward normal, ``e2 = n x e1`` (the server's
convention; the tests check this inverse against it).

On a terrain (a height map or an OpenDRIVE road: ``get_config``'s ``scene.terrain``) the
headless history's planar states live on the *reference plane* fitted under the four
wheels each step (docs/model.md section 11), ``Z = (grade X + cross Y) / 100 + height``,
not on the road of ``set_road``. The state carries that plane's slopes
(``ground_grade_pct``, ``ground_cross_slope_pct``, along and across the world heading),
so each row's ``road_grade_pct``, ``road_cross_slope_pct`` are that plane's, turned to
world x and y, and ``yaw_rad``, ``pitch_rad``, ``roll_rad`` are relative to it, as in the
history. The plane's height is not on the wire, and the position along a tilted plane
depends on it: on a terrain ``x_m``, ``y_m`` and ``cg_above_road_m`` are NaN (the
position is ``world_x_m``, ``world_y_m``, ``world_z_m``).

Timing
------
Row ``time_s`` is the state's ``sim_time_s``. Pose, velocities, wheel spins and slip
states are at that time, as in ``history.parquet``. The forces (``fx_*``, ``fy_*``,
``fz_*``), accelerations, road-wheel steer angles and ``input_*`` (the inputs the server
*applied*, after its watchdog) are those of the physics step that *ended* at the row's
tick: in ``history.parquet`` they sit one row earlier (a headless row holds the inputs of
the step that starts there and the forces at its start state). After a reset or a load
(``segment`` increases, ``tick`` restarts) the tick-0 row's step quantities are from
before it.

Segments
--------
A reset or a load restarts the server's tick: the recorder sees the tick go back and
begins a new segment (the ``segment`` column), asks ``get_config`` what is running now,
and keeps one metadata entry per segment (:data:`SEGMENTS_KEY`, written to both files'
Parquet footer when they are completed; :func:`read_segments` reads it).

An ``.rrd`` (``--rrd FILE``) is not drawn here: the recorder starts ``simserver view
--sink save:FILE`` (the package's live viewer, which builds the 3D scene from the same
state topic in its own process) beside itself and stops it with SIGTERM when the
recording ends. The recorder itself imports only the protocol and the zenoh adapter.
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from clients.common import (
    DEFAULT_CONNECT,
    EXIT_FAILED,
    EXIT_NO_SERVER,
    EXIT_OK,
    ClientError,
    Connection,
    ServerPresence,
    StopFlag,
    add_connection_args,
    check_server_config,
    client_main,
    connect,
    state_filter,
)
from simserver.analysis.holds import COLUMNS as HOLD_COLUMNS
from simserver.analysis.holds import HOLD_MIN_S, HOLD_SPEED_MPS, holds_summary
from simserver.wire import protocol as proto
from simserver.wire.protocol import reference_plane_slopes, world_to_road

# the wire's frames (docs/protocol.md section 2.4) live in the protocol; kept here by name
# for this module's readers (recorder.road_axes, recorder.world_to_road, ...)
road_axes = proto.road_axes

PROG = "simserver-recorder"
HISTORY_FILE = "history.parquet"
HOLDS_FILE = "holds.json"
DIAGNOSTICS_FILE = "diagnostics.parquet"
WHEELS = proto.WHEEL_NAMES
DEFAULT_FLUSH_ROWS = 10_000
STATE_INBOX = 1 << 15
"""Ring of received states: 32 s at 1 kHz before zenoh drops the oldest."""

VIEWER_START_S = 60.0
"""How long ``--rrd`` waits for ``simserver view`` to start writing."""

_TICK_OFFSET = proto.STATE_DTYPE.fields["tick"][1]

SEGMENTS_KEY = "simserver.recorder.segments"
"""File metadata key (both files' Parquet footer): a JSON list, one object per segment:
``segment``, ``first_tick``, ``rows``, and ``vehicle``, ``vehicle_path``, ``scene``,
``road`` as ``get_config`` reported them when the segment began (null if it did not
answer). Read it with :func:`read_segments`."""

# ----------------------------------------------------------------------------- columns


@dataclass(frozen=True)
class Column:
    """One column of the recorder's history file.

    Attributes
    ----------
    name : str
        Column name (a ``history.parquet`` name where it exists there).
    arrow_type : pyarrow.DataType
    unit : str
    description : str
    """

    name: str
    arrow_type: pa.DataType
    unit: str
    description: str


_F64 = pa.float64()
_ARROW_TYPES = {"<f8": _F64, "<u8": pa.uint64(), "<u4": pa.uint32(), "<u2": pa.uint16(),
                "u1": pa.uint8(), "i1": pa.int8()}


def _from_state(c: proto.StateColumn) -> Column:
    return Column(c.name, _ARROW_TYPES[c.dtype], c.unit, c.description)


ROAD_FRAME: tuple[Column, ...] = (
    Column("x_m", _F64, "m", "CG position along the road plane's e1 (road frame, from the "
           "world pose)"),
    Column("y_m", _F64, "m", "CG position along the road plane's e2 (road frame)"),
    Column("yaw_rad", _F64, "rad", "heading in the road plane, from e1 toward e2 (road frame)"),
    Column("roll_rad", _F64, "rad", "body roll relative to the road plane (left side up +)"),
    Column("pitch_rad", _F64, "rad", "body pitch relative to the road plane (nose down +)"),
)
"""History columns the recorder converts from the world pose (module docstring, Frames)."""

_HISTORY_FROM_STATE = tuple(_from_state(c) for c in proto.STATE_COLUMNS if c.history)
HISTORY_NAMED: tuple[Column, ...] = (
    _HISTORY_FROM_STATE[:1] + ROAD_FRAME + _HISTORY_FROM_STATE[1:])
"""Columns named as in the headless ``history.parquet``: ``time_s``, the road-frame pose,
then every state field the history has (``protocol.STATE_COLUMNS``, in the state's
order)."""
assert HISTORY_NAMED[0].name == "time_s"

STATE_ONLY: tuple[Column, ...] = (
    Column("segment", pa.int32(), "-", "0, then +1 at each reset or load (tick restarts)"),
    Column("recv_time_s", _F64, "s", "recorder's monotonic clock at receipt, from its start"),
    *(_from_state(c) for c in proto.STATE_COLUMNS if not c.history),
    Column("road_grade_pct", _F64, "%", "road grade used for the road-frame columns"),
    Column("road_cross_slope_pct", _F64, "%", "road cross slope used for the road-frame "
           "columns"),
    Column("cg_above_road_m", _F64, "m", "CG height above the road plane (along n; NaN on "
           "a terrain)"),
)
"""Columns the headless history does not have: the recorder's own, every other state
field (``protocol.STATE_COLUMNS``) and the road used."""

COLUMNS: tuple[Column, ...] = HISTORY_NAMED + STATE_ONLY

FRAME_NOTE = (
    "x_m, y_m, yaw_rad, roll_rad, pitch_rad: road-plane frame as in history.parquet, "
    "converted from the VehicleState's world pose with the road of ctl/get_config "
    "(road_grade_pct, road_cross_slope_pct per row; on a terrain the state's reference "
    "plane, with x_m, y_m NaN: its height is not on the wire); world_*: the VehicleState pose, "
    "world axes (ISO 8855 earth-fixed, z up)")
TIMING_NOTE = (
    "one row per VehicleState; pose, velocities, wheel spins and slip states at time_s; "
    "forces, accelerations, steer angles and input_* belong to the physics step that "
    "ended at the row's tick (history.parquet holds them one row earlier)")


def history_schema(metadata: dict[str, str]) -> pa.Schema:
    """Arrow schema of the recorder's history file, with unit/description metadata."""
    fields = [pa.field(c.name, c.arrow_type, nullable=False,
                       metadata={"unit": c.unit, "description": c.description})
              for c in COLUMNS]
    return pa.schema(fields, metadata=dict(sorted(metadata.items())))


def diagnostics_schema(metadata: dict[str, str]) -> pa.Schema:
    """Arrow schema of ``diagnostics.parquet``: ``recv_time_s`` then every field."""
    fields = [pa.field("recv_time_s", _F64, nullable=False,
                       metadata={"unit": "s", "description": "recorder clock at receipt"})]
    for f in proto.DIAGNOSTICS_FIELDS:
        if f.name in ("version", "reserved"):
            continue
        kind = f.dtype.lstrip("<")
        arrow = {"u1": pa.uint8(), "u2": pa.uint16(), "u4": pa.uint32(), "u8": pa.uint64(),
                 "f4": pa.float64(), "f8": pa.float64()}[kind]
        fields.append(pa.field(f.name, arrow, nullable=False,
                               metadata={"unit": f.unit, "description": f.description}))
    return pa.schema(fields, metadata=dict(sorted(metadata.items())))


def state_columns(rec: np.ndarray, grade_pct: np.ndarray, cross_slope_pct: np.ndarray,
                  on_terrain: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Every history-named and world column of decoded states (``STATE_DTYPE`` rows).

    ``grade_pct``, ``cross_slope_pct``: the road of each row; rows where ``on_terrain``
    is true use the state's reference plane instead (module docstring, Frames)."""
    x, y, z, yaw, pitch, roll = (rec[name].astype(np.float64)
                                 for name in proto.STATE_POSE_FIELDS)
    pos = np.stack([x, y, z], axis=-1)
    grade_pct = np.array(grade_pct, dtype=np.float64)
    cross_slope_pct = np.array(cross_slope_pct, dtype=np.float64)
    terrain = np.zeros(yaw.shape, dtype=bool) if on_terrain is None else on_terrain
    grade_pct[terrain], cross_slope_pct[terrain] = reference_plane_slopes(
        yaw[terrain], rec["ground_grade_pct"][terrain], rec["ground_cross_slope_pct"][terrain])
    road = world_to_road(pos, yaw, pitch, roll, grade_pct, cross_slope_pct)
    for name in ("x_m", "y_m", "cg_above_road_m"):  # the plane's height is not on the wire
        road[name][terrain] = np.nan
    cols: dict[str, np.ndarray] = {}
    for c in proto.STATE_COLUMNS:  # every state field, as the state table names it
        values = rec[c.field] if c.wheel is None else rec[c.field][:, c.wheel]
        cols[c.name] = values.astype(c.dtype)
    for name in ("x_m", "y_m", "yaw_rad", "roll_rad", "pitch_rad", "cg_above_road_m"):
        cols[name] = road[name]
    cols["road_grade_pct"] = np.asarray(grade_pct, dtype=np.float64)
    cols["road_cross_slope_pct"] = np.asarray(cross_slope_pct, dtype=np.float64)
    return cols


# ----------------------------------------------------------------------------- recorder


class StateBuffer:
    """Received states in a preallocated chunk, with per-row receive time, road, segment.

    Parameters
    ----------
    rows : int
        Chunk size; the owner flushes when :attr:`full`.
    """

    def __init__(self, rows: int) -> None:
        self.raw = np.zeros((rows, proto.STATE_SIZE), dtype=np.uint8)
        self.recv = np.zeros(rows)
        self.grade = np.zeros(rows)
        self.cross = np.zeros(rows)
        self.segment = np.zeros(rows, dtype=np.int32)
        self.on_terrain = np.zeros(rows, dtype=bool)
        self.n = 0

    @property
    def full(self) -> bool:
        """True when no row is left."""
        return self.n >= self.raw.shape[0]

    def add(self, payload: bytes, recv_s: float, road: tuple[float, float],
            segment: int, on_terrain: bool = False) -> None:
        """Append one state payload (``STATE_SIZE`` bytes, already checked); ``road``
        (grade, cross-slope %) is not used when ``on_terrain``."""
        i = self.n
        self.raw[i] = np.frombuffer(payload, dtype=np.uint8)
        self.recv[i] = recv_s
        self.grade[i], self.cross[i] = road
        self.segment[i] = segment
        self.on_terrain[i] = on_terrain
        self.n += 1

    def table(self, schema: pa.Schema) -> pa.Table:
        """The buffered rows as an Arrow table (then :meth:`clear`)."""
        n = self.n
        rec = self.raw[:n].view(proto.STATE_DTYPE).reshape(n)
        cols = state_columns(rec, self.grade[:n], self.cross[:n], self.on_terrain[:n])
        cols["recv_time_s"] = self.recv[:n].copy()
        cols["segment"] = self.segment[:n].copy()
        return pa.Table.from_arrays([pa.array(cols[f.name], type=f.type) for f in schema],
                                    schema=schema)

    def clear(self) -> None:
        """Forget the rows (the arrays are reused)."""
        self.n = 0


class Recorder:
    """Subscribes to state and diagnostics; writes Parquet row groups as chunks fill.

    Parameters
    ----------
    conn : Connection
        Checked connection.
    out_dir : Path
        Where ``history.parquet`` and ``diagnostics.parquet`` go (created).
    flush_rows : int
        Rows per row group.
    keep_paused : bool
        Keep every state (also the repeats of a frozen tick while paused).
    road_poll_s : float
        Seconds between ``get_config`` polls of the road.
    """

    def __init__(self, conn: Connection, out_dir: Path, flush_rows: int, keep_paused: bool,
                 road_poll_s: float) -> None:
        self.conn = conn
        self.out_dir = out_dir
        self.keep_paused = keep_paused
        self.road_poll_s = road_poll_s
        self.states = conn.ep.declare_state_inbox(capacity=STATE_INBOX)
        self.diags = conn.ep.declare_diag_inbox(capacity=256)
        self.presence = ServerPresence(conn.ep)
        self.buffer = StateBuffer(flush_rows)
        self.diag_rows: list[tuple[float, bytes]] = []
        cfg = conn.config  # checked by connect (check_server_config)
        self.state_every = int((cfg.get("server") or {}).get("state_every", 1)) or 1
        # states another publisher sent (no ACL): dropped and counted, never a row
        self.filter = state_filter(conn, PROG)
        self.bad_configs = 0  # get_config replies no server sends, ignored
        self.bad_diagnostics = 0  # Diagnostics no server sends, dropped
        self.road = self._road_of(cfg)
        self.on_terrain = self._on_terrain(cfg)
        self.segments: list[dict[str, Any]] = [self._segment_entry(0, cfg)]
        self.rows = 0
        self.diag_count = 0
        self.paused_repeats = 0
        self.missed = 0
        self.segment = 0
        self.last_tick: int | None = None
        self.first_tick: int | None = None
        self.t0 = time.monotonic()
        meta = {
            "simserver.recorder.keys": conn.ep.keys.base,
            "simserver.recorder.protocol_version": str(proto.PROTOCOL_VERSION),
            "simserver.recorder.frame": FRAME_NOTE,
            "simserver.recorder.timing": TIMING_NOTE,
            "simserver.columns": "history.parquet names (road frame) + state-only columns: "
                                 "see clients.recorder",
        }
        out_dir.mkdir(parents=True, exist_ok=True)
        self.schema = history_schema(meta)
        self.diag_schema = diagnostics_schema(meta)
        self.writer = pq.ParquetWriter(out_dir / HISTORY_FILE, self.schema,
                                       compression="zstd", use_dictionary=False)

    @staticmethod
    def _road_of(cfg: dict[str, Any]) -> tuple[float, float]:
        road = cfg.get("road") or {}
        return float(road.get("grade_pct", 0.0)), float(road.get("cross_slope_pct", 0.0))

    @staticmethod
    def _on_terrain(cfg: dict[str, Any]) -> bool:
        """Whether the scene runs on a terrain (``scene.terrain``; absent: the plane)."""
        return ((cfg.get("scene") or {}).get("terrain") or "plane") != "plane"

    @staticmethod
    def _segment_entry(segment: int, cfg: dict[str, Any] | None) -> dict[str, Any]:
        """The metadata of a segment that begins now (``cfg``: ``get_config``'s config)."""
        vehicle = (cfg or {}).get("vehicle") or {}
        return {"segment": segment, "first_tick": None, "rows": 0,
                "vehicle": vehicle.get("name"), "vehicle_path": vehicle.get("path"),
                "scene": ((cfg or {}).get("scene") or {}).get("path"),
                "road": (cfg or {}).get("road")}

    def _get_config(self) -> dict[str, Any] | None:
        """The server's config now, or None (no reply, or one no server sends: another
        queryable may answer on a network without access control; counted, warned)."""
        try:
            reply = self.conn.ep.request("get_config", timeout_s=1.0)
        except (TimeoutError, proto.ProtocolError):
            return None
        if not reply.get("ok"):
            return None
        try:
            return check_server_config(reply.get("config"))
        except proto.ProtocolError as exc:
            self.bad_configs += 1
            if self.bad_configs == 1 or self.bad_configs % 100 == 0:
                print(f"{PROG}: warning: ignored a malformed get_config reply ({exc}); "
                      f"{self.bad_configs} so far, the last good road is kept",
                      file=sys.stderr, flush=True)
            return None

    def refresh_road(self) -> None:
        """Ask the server for its road (``get_config``); keeps the old one on failure."""
        cfg = self._get_config()
        if cfg is not None:
            self.road = self._road_of(cfg)
            self.on_terrain = self._on_terrain(cfg)

    def new_segment(self) -> None:
        """A reset or load: the next segment, described by the server's config now."""
        self.segment += 1
        cfg = self._get_config()
        if cfg is not None:
            self.road = self._road_of(cfg)  # a load may have changed the road
            self.on_terrain = self._on_terrain(cfg)  # or the terrain
        self.segments.append(self._segment_entry(self.segment, cfg))

    def take(self, payload: bytes, tick: int, kind: str, recv_s: float) -> None:
        """File one state the filter took (:meth:`StateFilter.take`: ``kind`` is next,
        repeat or restart): dedupe frozen ticks, begin segments, count gaps."""
        last = self.last_tick
        if last is not None:
            if kind == "repeat" and not self.keep_paused:
                self.paused_repeats += 1
                return
            if kind == "restart":
                self.new_segment()
            elif tick > last + self.state_every:
                self.missed += (tick - last) // self.state_every - 1
        if self.first_tick is None:
            self.first_tick = tick
        entry = self.segments[-1]
        if entry["first_tick"] is None:
            entry["first_tick"] = tick
        entry["rows"] += 1
        self.last_tick = tick
        self.buffer.add(payload, recv_s, self.road, self.segment, self.on_terrain)
        self.rows += 1
        if self.buffer.full:
            self.flush()

    def flush(self) -> None:
        """Write the buffered rows as one row group."""
        if self.buffer.n:
            self.writer.write_table(self.buffer.table(self.schema))
            self.buffer.clear()

    def drain(self) -> int:
        """Take everything zenoh has delivered; returns the number of states."""
        now = time.monotonic() - self.t0
        payloads = self.states.drain_newest()
        for p, tick, kind in self.filter.take(payloads, now):
            self.take(p, tick, kind, now)
        diags = [d for d in self.diags.drain_newest() if len(d) == proto.DIAGNOSTICS_SIZE]
        if diags:
            raw = np.frombuffer(b"".join(diags), dtype=np.uint8).reshape(len(diags), -1)
            for d, fault in zip(diags, proto.invalid_fields(raw, "diagnostics").tolist(),
                                strict=True):
                if fault >= 0:  # no server sends it: never a row
                    self.bad_diagnostics += 1
                    if self.bad_diagnostics == 1:
                        print(f"{PROG}: warning: dropped a Diagnostics message with an "
                              f"invalid {proto.DIAGNOSTICS_FIELDS[fault].name}: another "
                              "publisher on the diagnostics key?", file=sys.stderr,
                              flush=True)
                    continue
                self.diag_rows.append((now, d))
                self.diag_count += 1
        return len(payloads)

    def close(self) -> None:
        """Flush and complete both files (with the per-segment metadata)."""
        self.flush()
        segments = {SEGMENTS_KEY: json.dumps(self.segments)}
        self.writer.add_key_value_metadata(segments)
        self.writer.close()
        n = len(self.diag_rows)
        rec = np.frombuffer(b"".join(d for _, d in self.diag_rows),
                            dtype=proto.DIAGNOSTICS_DTYPE, count=n)
        arrays = [pa.array(np.array([t for t, _ in self.diag_rows], dtype=np.float64))]
        for f in list(self.diag_schema)[1:]:
            arrays.append(pa.array(rec[f.name].astype(f.type.to_pandas_dtype()), type=f.type))
        with pq.ParquetWriter(self.out_dir / DIAGNOSTICS_FILE, self.diag_schema,
                              compression="zstd") as writer:
            writer.write_table(pa.Table.from_arrays(arrays, schema=self.diag_schema))
            writer.add_key_value_metadata(segments)

    def run(self, stop: StopFlag, duration_s: float | None, quiet: bool) -> str:
        """Record until a signal, the duration, or the server leaving; returns why."""
        next_report = 5.0
        next_road = self.road_poll_s
        reason = "stopped"
        while True:
            if stop.stopped:
                reason = f"stopped by {stop.signal_name}"
                break
            t = time.monotonic() - self.t0
            if duration_s is not None and t >= duration_s:
                reason = f"--duration {duration_s:g} s reached"
                break
            got = self.drain()
            if self.presence.gone():
                reason = "the server's liveliness token disappeared"
                break
            if t >= next_road:
                next_road = t + self.road_poll_s
                self.refresh_road()
            if not quiet and t >= next_report:
                next_report += 5.0
                print(f"{PROG}: {self.rows} rows, tick {self.last_tick}, segment "
                      f"{self.segment}, missed {self.missed}", flush=True)
            if not got:
                time.sleep(0.002)
        time.sleep(0.05)  # what zenoh has in flight still arrives
        self.drain()
        return reason


def _mm(value: float | None) -> str:
    return "-" if value is None else f"{1e3 * value:.4g} mm"


def _s(value: float | None) -> str:
    return "never" if value is None else f"{value:.2f} s"


def holds_report(out_dir: Path) -> tuple[dict[str, Any], list[str]]:
    """The recording's stops, holds and restarts (``simserver.analysis.holds``, as in a
    headless run's summary.json), per segment (time restarts at each reset or load), read
    back from the written ``history.parquet``; and one line per hold for the terminal."""
    table = pq.read_table(out_dir / HISTORY_FILE, columns=[*HOLD_COLUMNS, "segment"])
    cols = {name: table.column(name).to_numpy(zero_copy_only=False).astype(np.float64)
            for name in table.column_names}
    report: dict[str, Any] = {"segments": []}
    lines = []
    for segment in np.unique(cols["segment"]).astype(int).tolist():
        rows = cols["segment"] == segment
        section = holds_summary({name: cols[name][rows] for name in HOLD_COLUMNS})
        report["segments"].append({"segment": segment, **section})
        for h in section["holds"]:
            w0, w1 = h["creep_window_s"]
            line = (f"hold (segment {segment}) {h['start_s']:.2f}-{h['end_s']:.2f} s, "
                    f"released by {h['released_by']}: creep {_mm(h['creep_m'])} over "
                    f"{w0:.2f}-{w1:.2f} s, peak {1e3 * h['peak_speed_mps']:.3g} mm/s")
            if h["rollback_m"] is not None:
                jerk = h["peak_jerk_mps3"]
                line += (f"; restart: rollback {_mm(h['rollback_m'])}, 0.5 m/s in "
                         f"{_s(h['time_to_0p5_mps_s'])}, 2 m/s in {_s(h['time_to_2_mps_s'])}"
                         + ("" if jerk is None else f", peak jerk {jerk:.3g} m/s^3"))
            lines.append(line)
    return report, lines


def read_segments(path: str | Path) -> list[dict[str, Any]]:
    """The per-segment metadata of a recorder's Parquet file (``SEGMENTS_KEY``).

    Parameters
    ----------
    path : str or Path
        ``history.parquet`` or ``diagnostics.parquet`` of a recording.

    Returns
    -------
    list of dict
        One entry per segment, in order (see :data:`SEGMENTS_KEY`).

    Raises
    ------
    ValueError
        When the file has no segment metadata (not a recorder file, or an older one).
    """
    meta = pq.ParquetFile(path).metadata.metadata or {}
    raw = meta.get(SEGMENTS_KEY.encode())
    if raw is None:
        raise ValueError(f"{path}: no {SEGMENTS_KEY} metadata (not a recorder file?)")
    return json.loads(raw)


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``simserver-recorder`` (``python -m clients.recorder``)."""
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Record a live simserver car: OUT/history.parquet (one row per state, "
        "the headless runner's column names in the road-plane frame, plus world_* and "
        "state-only columns) and OUT/diagnostics.parquet. Ctrl-C or SIGTERM stops and "
        "writes everything received.",
        epilog="Exit codes: 0 recorded (stopped by a signal, --duration or the server "
        "leaving), 1 a file could not be written, 2 bad command line, 3 no server answered.",
    )
    parser.add_argument("--out", metavar="DIR", type=Path, required=True,
                        help="output directory (created; its two files are overwritten)")
    parser.add_argument("--duration", metavar="S", type=float, default=None,
                        help="stop after this many seconds of wall time")
    parser.add_argument("--keep-paused", action="store_true",
                        help="keep every state, also the repeats of a frozen tick while "
                        "the server is paused (default: one row per tick)")
    parser.add_argument("--flush-rows", metavar="N", type=int, default=DEFAULT_FLUSH_ROWS,
                        help=f"rows per Parquet row group (default {DEFAULT_FLUSH_ROWS})")
    parser.add_argument("--road-poll", metavar="S", type=float, default=1.0,
                        help="seconds between get_config polls of the road (default 1)")
    parser.add_argument("--rrd", metavar="FILE", type=Path, default=None,
                        help="also save a Rerun recording: runs 'simserver view --sink "
                        "save:FILE' beside the recorder (needs the server's vehicle files "
                        "on this machine)")
    parser.add_argument("--cars", metavar="all|ID,ID", default=None,
                        help="record several cars of a multi-car server into one long-form "
                        "table with a car_id column (the headless world history's form): "
                        "'all' (the cars served at start, by liveliness) or a list of ids "
                        "(default: only --vehicle-id, without car_id)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    add_connection_args(parser)
    return parser


def start_rrd_viewer(args: argparse.Namespace) -> subprocess.Popen:
    """Start ``simserver view --sink save:FILE`` for ``--rrd`` (its own process).

    Raises
    ------
    ClientError
        When the file name is not an ``.rrd`` or the viewer exits at once.
    """
    if args.rrd.suffix != ".rrd":
        raise ClientError(f"--rrd {args.rrd}: expected a .rrd file name")
    args.rrd.parent.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "simserver", "view", "--sink", f"save:{args.rrd}",
           "--prefix", args.prefix, "--vehicle-id", args.vehicle_id]
    if args.zenoh_config:
        cmd += ["--zenoh-config", args.zenoh_config]
    for endpoint in args.connect or ([] if args.zenoh_config else [DEFAULT_CONNECT]):
        cmd += ["--connect", endpoint]
    if args.rrd.exists():
        args.rrd.unlink()
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL)
    # Ready once it has written to the file: by then it handles SIGTERM (a signal during
    # its start-up, a few seconds of imports and compilation, would lose the file).
    deadline = time.monotonic() + VIEWER_START_S
    while not (args.rrd.exists() and args.rrd.stat().st_size > 0):
        if proc.poll() is not None:
            raise ClientError(f"--rrd: 'simserver view' exited (code {proc.returncode}) "
                              "before writing", EXIT_FAILED)
        if time.monotonic() > deadline:
            stop_rrd_viewer(proc)
            raise ClientError(f"--rrd: 'simserver view' wrote nothing to {args.rrd} within "
                              f"{VIEWER_START_S:g} s", EXIT_FAILED)
        time.sleep(0.05)
    return proc


def stop_rrd_viewer(proc: subprocess.Popen | None) -> None:
    """Stop the ``--rrd`` viewer (SIGTERM: it flushes and closes the file)."""
    if proc is None or proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _check_args(args: argparse.Namespace) -> None:
    if args.flush_rows < 1:
        raise ClientError(f"--flush-rows {args.flush_rows}: expected at least 1")
    if args.duration is not None and not args.duration > 0:
        raise ClientError(f"--duration {args.duration:g}: expected a positive number of s")
    if not args.road_poll > 0:
        raise ClientError(f"--road-poll {args.road_poll:g}: expected a positive number of s")


def _run(args: argparse.Namespace) -> int:
    _check_args(args)
    if args.cars is not None:
        if args.rrd is not None:
            raise ClientError("--rrd with --cars: run 'simserver view --sink save:FILE' "
                              "(it draws every car) beside the recorder")
        return _run_cars(args)
    with StopFlag() as stop:
        conn = connect(args, PROG)
        try:
            try:
                rec = Recorder(conn, args.out, args.flush_rows, args.keep_paused,
                               args.road_poll)
            except OSError as exc:
                raise ClientError(f"{args.out}: cannot write: {exc}", EXIT_FAILED) from None
            viewer = start_rrd_viewer(args) if args.rrd is not None else None
            print(f"{PROG}: recording {conn.where} to {args.out}/{HISTORY_FILE} and "
                  f"{DIAGNOSTICS_FILE}" + (f" and {args.rrd}" if viewer else "")
                  + " (Ctrl-C stops)", flush=True)
            try:
                reason = rec.run(stop, args.duration, args.quiet)
            finally:
                stop_rrd_viewer(viewer)
                try:
                    rec.close()
                except OSError as exc:
                    raise ClientError(f"{args.out}: cannot write: {exc}", EXIT_FAILED) \
                        from None
        finally:
            conn.close()
    span = "" if rec.last_tick is None else f", last tick {rec.last_tick}"
    print(f"{PROG}: {reason}: wrote {rec.rows} state rows{span} in {rec.segment + 1} "
          f"segment(s), {rec.diag_count} diagnostics; missed {rec.missed} states, "
          f"{rec.paused_repeats} paused repeats skipped, {rec.filter.rejected} bad payloads, "
          f"{rec.filter.out_of_order} out of order, {rec.bad_diagnostics} bad "
          f"diagnostics, {rec.bad_configs} bad get_config replies", flush=True)
    if rec.rows == 0:
        print(f"{PROG}: warning: no state was received", file=sys.stderr, flush=True)
        return EXIT_OK
    report, lines = holds_report(args.out)
    try:
        (args.out / HOLDS_FILE).write_text(json.dumps(report, indent=1) + "\n")
    except OSError as exc:
        raise ClientError(f"{args.out}: cannot write: {exc}", EXIT_FAILED) from None
    holds = sum(len(seg["holds"]) for seg in report["segments"])
    print(f"{PROG}: {holds} hold(s) (at rest below {1e3 * HOLD_SPEED_MPS:g} mm/s for "
          f"{HOLD_MIN_S:g} s or longer), in {args.out / HOLDS_FILE}", flush=True)
    for line in lines:
        print(f"{PROG}: {line}", flush=True)
    return EXIT_OK


# ------------------------------------------------------------------------ several cars
CARS_PARTS = ".cars"
"""Under OUT: one folder per car while recording (a single car's two files), merged into
OUT's long-form files when the recording ends, then removed."""


def parse_cars(text: str) -> list[str] | None:
    """``--cars``: None for ``all``, else the ids (each a valid vehicle id, no repeats).

    Raises
    ------
    ClientError
        An empty list, a repeated id or one that is no vehicle id.
    """
    if text.strip() == "all":
        return None
    ids = [c.strip() for c in text.split(",")]
    for car in ids:
        try:
            proto.vehicle_keys(proto.DEFAULT_PREFIX, car)
        except proto.ProtocolError as exc:
            raise ClientError(f"--cars {text!r}: {car!r} is no vehicle id ({exc})") from None
    if len(set(ids)) != len(ids):
        raise ClientError(f"--cars {text!r}: a car is named twice")
    return ids


def discover(args: argparse.Namespace, prog: str = PROG) -> list[str]:
    """The cars served under ``--prefix`` (their liveliness tokens, ``clients.world``),
    waited for up to ``--wait`` seconds."""
    from clients.world import discover_cars
    from simserver.adapters.zenoh_io import ZenohEndpoint, make_zenoh_config

    connect_to = args.connect
    if connect_to is None and args.zenoh_config is None:
        connect_to = [DEFAULT_CONNECT]
    cfg = make_zenoh_config(listen=[] if args.zenoh_config is None else None,
                            connect=connect_to, config_file=args.zenoh_config)
    deadline = time.monotonic() + max(0.0, args.wait)
    with ZenohEndpoint(cfg, prefix=args.prefix, vehicle=proto.DEFAULT_VEHICLE) as ep:
        while True:
            cars = discover_cars(ep, args.prefix, timeout_s=0.5)
            if cars or time.monotonic() >= deadline:
                break
            time.sleep(0.2)
    if not cars:
        raise ClientError(f"--cars all: no car's liveliness token under {args.prefix}/*/alive "
                          f"within {args.wait:g} s", EXIT_NO_SERVER)
    return cars


def merge_car_files(parts: dict[str, Path], out_dir: Path) -> None:
    """Merge each car's ``history.parquet`` and ``diagnostics.parquet`` (folders
    ``parts[id]``) into ``out_dir``'s in long form: ``car_id`` first
    (``protocol.WORLD_CAR_ID_COLUMN``, the history's), the cars' rows one car after the other in the
    given order; the per-car segment metadata as ``{id: segments}`` under
    :data:`SEGMENTS_KEY`."""
    CAR_ID_COLUMN = proto.WORLD_CAR_ID_COLUMN  # noqa: N806 - the history's own name

    for name in (HISTORY_FILE, DIAGNOSTICS_FILE):
        tables = {car: pq.read_table(folder / name) for car, folder in parts.items()}
        first = next(iter(tables.values()))
        meta = dict(first.schema.metadata or {})
        # the segments are in each file's footer (added at its close), not its schema
        meta[SEGMENTS_KEY.encode()] = json.dumps(
            {car: read_segments(folder / name) for car, folder in parts.items()}).encode()
        meta[b"simserver.recorder.keys"] = json.dumps(
            {car: (t.schema.metadata or {}).get(b"simserver.recorder.keys", b"").decode()
             for car, t in tables.items()}).encode()
        field = pa.field(CAR_ID_COLUMN, pa.string(), nullable=False,
                         metadata={"unit": "-", "description": "the car's id"})
        merged = pa.concat_tables([
            t.replace_schema_metadata(None).add_column(
                0, field, pa.array([car] * t.num_rows, type=pa.string()))
            for car, t in tables.items()]).replace_schema_metadata(meta)
        pq.write_table(merged, out_dir / name, compression="zstd",
                       use_dictionary=[CAR_ID_COLUMN])


def _run_cars(args: argparse.Namespace) -> int:
    """``--cars``: one connection and :class:`Recorder` per car, drained in one loop; a
    car whose liveliness token goes away (removed from the world) stops being recorded,
    the recording ends when every car has gone, or by a signal or ``--duration``."""
    import shutil

    ids = parse_cars(args.cars)
    parts_dir = args.out / CARS_PARTS
    with StopFlag() as stop:
        cars = discover(args) if ids is None else ids
        conns: dict[str, Connection] = {}
        recs: dict[str, Recorder] = {}
        try:
            for car in cars:
                conns[car] = connect(argparse.Namespace(**{**vars(args), "vehicle_id": car}),
                                     PROG)
                try:
                    recs[car] = Recorder(conns[car], parts_dir / car, args.flush_rows,
                                         args.keep_paused, args.road_poll)
                except OSError as exc:
                    raise ClientError(f"{args.out}: cannot write: {exc}", EXIT_FAILED) \
                        from None
            print(f"{PROG}: recording {', '.join(cars)} to {args.out}/{HISTORY_FILE} and "
                  f"{DIAGNOSTICS_FILE} (Ctrl-C stops)", flush=True)
            reason = _record_cars(recs, stop, args.duration, args.road_poll)
        finally:
            try:
                for rec in recs.values():
                    rec.close()
                if len(recs) == len(cars):
                    merge_car_files({c: parts_dir / c for c in cars}, args.out)
                    shutil.rmtree(parts_dir)
            except OSError as exc:
                raise ClientError(f"{args.out}: cannot write: {exc}", EXIT_FAILED) from None
            finally:
                for conn in conns.values():
                    conn.close()
    rows = ", ".join(f"{c} {r.rows}" for c, r in recs.items())
    print(f"{PROG}: {reason}: wrote state rows of {len(recs)} cars ({rows}); missed "
          f"{sum(r.missed for r in recs.values())} states", flush=True)
    return EXIT_OK


def _record_cars(recs: dict[str, Recorder], stop: StopFlag, duration_s: float | None,
                 road_poll_s: float) -> str:
    """The loop of :meth:`Recorder.run` over several cars; returns why it ended."""
    t0 = time.monotonic()
    next_road = road_poll_s
    active = dict(recs)
    while True:
        if stop.stopped:
            reason = f"stopped by {stop.signal_name}"
            break
        t = time.monotonic() - t0
        if duration_s is not None and t >= duration_s:
            reason = f"--duration {duration_s:g} s reached"
            break
        got = sum(rec.drain() for rec in active.values())
        for car in [c for c, rec in active.items() if rec.presence.gone()]:
            del active[car]  # removed from the world: what it sent is kept
        if not active:
            reason = "every car's liveliness token disappeared"
            break
        if t >= next_road:
            next_road = t + road_poll_s
            for rec in active.values():
                rec.refresh_road()
        if not got:
            time.sleep(0.002)
    time.sleep(0.05)  # what zenoh has in flight still arrives
    for rec in recs.values():
        rec.drain()
    return reason


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``simserver-recorder``; returns the exit code."""
    return client_main(PROG, build_parser, _run, argv)


if __name__ == "__main__":
    sys.exit(main())

