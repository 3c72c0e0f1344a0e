"""The wire contract of simserver: key expressions, binary payloads and control messages.

This module is the single definition of everything that crosses the network between the
server and its clients. It is pure Python and numpy (no zenoh), so that any client, test
or tool can import it without the transport. ``docs/protocol.md`` is generated from the
tables below (``python -m simserver.wire.protocol --write docs/protocol.md``) and a test fails
when the two drift apart.

Overview
--------
- Key expressions: :func:`vehicle_keys` builds every key of one vehicle from a prefix
  (default ``"simserver"``) and a vehicle id (default ``"car0"``).
- Binary payloads (little-endian, packed, naturally aligned): :data:`COMMAND_FIELDS`,
  :data:`STATE_FIELDS` and :data:`DIAGNOSTICS_FIELDS` are the field tables (type, unit,
  range, description); :data:`COMMAND_DTYPE`, :data:`STATE_DTYPE` and
  :data:`DIAGNOSTICS_DTYPE` are the numpy structured dtypes built from them.
- :data:`STATE_FIELDS` is also the one table of the published state: each row names its
  source in the server (``FieldSpec.source``) and its headless history column
  (``FieldSpec.history``). The recorder's columns (:data:`STATE_COLUMNS`), the server's
  fill and the viewer's inverse (``simserver.wire.state_schema``) and the docs derive from it.
- The frames of the wire (:func:`road_axes`, :func:`world_to_road`,
  :func:`ground_slopes_pct`, :func:`reference_plane_slopes`) for clients.
- Decoding a driver command (:func:`decode_command`) is the only gate between the network
  and the physics: it rejects or clamps as documented per field and raises
  :class:`ProtocolError` (and nothing else) on any malformed input.
- Control requests and replies are UTF-8 JSON objects; :func:`validate_control` checks a
  request against :data:`CONTROL_SPECS`.
"""

from __future__ import annotations

import enum
import json
import math
import re
import struct
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np

# ============================================================================ version

PROTOCOL_VERSION: Final[int] = 4  # 4: see the history in docs/protocol.md section 6
"""Carried in the first two bytes of every binary payload; bumped on any layout change."""

DEFAULT_PREFIX: Final[str] = "simserver"
DEFAULT_VEHICLE: Final[str] = "car0"

CLAMP_TOLERANCE: Final[float] = 1e-3
"""Normalised command inputs up to this far outside their range are clamped, not rejected."""

MAX_CONTROL_PAYLOAD_BYTES: Final[int] = 65536
"""Control requests larger than this are rejected before JSON parsing."""

COMMAND_RING_SLOTS: Final[int] = 256
"""Command payloads the server keeps between two ticks (its subscriber's receive ring):
when more arrive within one tick (a stalled loop), the oldest are dropped."""


class ProtocolError(ValueError):
    """A payload, key or argument that does not satisfy the contract.

    Parameters
    ----------
    field : str
        The offending field (``"steer"``, ``"pose.yaw_rad"``, ``"payload"``, ...). Always
        named in the message too.
    message : str
        What is wrong with it.
    """

    def __init__(self, field: str, message: str) -> None:
        self.field = field
        super().__init__(f"{field}: {message}")


# ============================================================================ keys

CONTROL_NAMES: Final[tuple[str, ...]] = (
    "reset",
    "pause",
    "resume",
    "step",
    "set_road",
    "load",
    "get_config",
)

_ID_CHUNK = re.compile(r"[A-Za-z0-9_.\-]+")
_WILDCARDS = "*$?#"


@dataclass(frozen=True)
class KeySpec:
    """One key expression of the contract (a row of the key table in docs/protocol.md)."""

    suffix: str
    direction: str
    payload: str
    encoding: str
    qos: str
    rate: str


ENCODING_COMMAND: Final[str] = "application/octet-stream;simserver.DriverCommand.v1"
ENCODING_STATE: Final[str] = "application/octet-stream;simserver.VehicleState.v1"
ENCODING_DIAGNOSTICS: Final[str] = "application/octet-stream;simserver.Diagnostics.v1"
ENCODING_CONTROL: Final[str] = "application/json"

STATE_DECIMATED_HZ: Final[int] = 100
"""Rate of the decimated state key ``state/100hz``: one of every
``states per second / STATE_DECIMATED_HZ`` states the server publishes (every 10th at
1 kHz). For
consumers that do not need every tick (the ROS 2 adapter at its default 100 Hz): they
receive and wake a tenth as often, and the 1 kHz key has one subscriber less (issue 19)."""

TRAFFIC_STATE_HZ: Final[int] = 100
"""Rate of the ``state`` key of a car that no client drives (a server's traffic, driven
by keyframes or the built-in driver; docs/protocol.md section 5.1)."""

KEY_SPECS: Final[tuple[KeySpec, ...]] = (
    KeySpec(
        "cmd",
        "client -> server (put)",
        "DriverCommand (binary)",
        ENCODING_COMMAND,
        "REAL_TIME, express, BLOCK",
        "any, up to 1 kHz; at least every watchdog period (default 200 ms)",
    ),
    KeySpec(
        "state",
        "server -> clients (put)",
        "VehicleState (binary)",
        ENCODING_STATE,
        "REAL_TIME, DROP (waits at most 50 us for a full link); not express",
        "every tick (1 kHz) by default; server-side decimation; a car no client drives "
        f"(traffic): {TRAFFIC_STATE_HZ} Hz",
    ),
    KeySpec(
        f"state/{STATE_DECIMATED_HZ}hz",
        "server -> clients (put)",
        "VehicleState (binary)",
        ENCODING_STATE,
        "REAL_TIME, DROP, not express (as `state`)",
        f"{STATE_DECIMATED_HZ} Hz: one of every (states per second / {STATE_DECIMATED_HZ}) "
        "states published, for consumers that need no more (the ROS 2 adapter)",
    ),
    KeySpec(
        "diag",
        "server -> clients (put)",
        "Diagnostics (binary)",
        ENCODING_DIAGNOSTICS,
        "DATA, DROP (waits at most 50 us for a full link)",
        "a few Hz (server config)",
    ),
    *(
        KeySpec(
            f"ctl/{name}",
            "client -> server (get / queryable)",
            f"JSON request `{name}` -> JSON reply",
            ENCODING_CONTROL,
            "default",
            "on demand; answered within about one tick",
        )
        for name in CONTROL_NAMES
    ),
    KeySpec(
        "alive",
        "server (liveliness token)",
        "none",
        "-",
        "-",
        "present while the server runs",
    ),
)


def validate_vehicle_id(vehicle: str) -> str:
    """Check a vehicle id: one non-empty key chunk of ``[A-Za-z0-9_.-]``.

    Parameters
    ----------
    vehicle : str
        The id, for example ``"car0"``.

    Returns
    -------
    str
        The id, unchanged.

    Raises
    ------
    ProtocolError
        With ``field == "vehicle"`` when the id is empty, contains ``/``, a wildcard
        (``* $ ? #``) or any other character outside the set above.
    """
    return _validate_chunk("vehicle", vehicle)


def validate_prefix(prefix: str) -> str:
    """Check a key prefix: one or more ``/``-separated chunks of ``[A-Za-z0-9_.-]``.

    Raises
    ------
    ProtocolError
        With ``field == "prefix"`` when the prefix is empty, starts or ends with ``/``,
        has an empty chunk, a wildcard (``* $ ? #``) or any other character outside the set.
    """
    if not isinstance(prefix, str) or not prefix:
        raise ProtocolError("prefix", f"must be a non-empty string, got {prefix!r}")
    for chunk in prefix.split("/"):
        if not chunk:
            raise ProtocolError(
                "prefix", f"{prefix!r} has an empty chunk (leading, trailing or double '/')"
            )
        _validate_chunk("prefix", chunk, whole=prefix)
    return prefix


def _validate_chunk(what: str, chunk: str, whole: str | None = None) -> str:
    shown = whole if whole is not None else chunk
    if not isinstance(chunk, str) or not chunk:
        raise ProtocolError(what, f"must be a non-empty string, got {chunk!r}")
    if _ID_CHUNK.fullmatch(chunk):
        return chunk
    for ch in chunk:
        if ch in _WILDCARDS:
            raise ProtocolError(
                what, f"{shown!r} contains {ch!r}: wildcards and '$ ? #' are not allowed"
            )
        if ch == "/":
            raise ProtocolError(what, f"{shown!r} contains '/': an id is one key chunk")
        if not _ID_CHUNK.fullmatch(ch):
            raise ProtocolError(
                what, f"{shown!r} contains {ch!r}: use letters, digits, '_', '-' or '.'"
            )
    raise ProtocolError(what, f"{shown!r} is not a valid key chunk")  # pragma: no cover


@dataclass(frozen=True)
class VehicleKeys:
    """Every key expression of one vehicle (built by :func:`vehicle_keys`).

    Attributes
    ----------
    prefix, vehicle : str
        The validated prefix and vehicle id.
    base : str
        ``"{prefix}/{vehicle}"``.
    cmd, state, diag, alive : str
        Driver commands in, state out, diagnostics out, liveliness token.
    state_decimated : str
        ``"{base}/state/100hz"``: the state at :data:`STATE_DECIMATED_HZ`.
    ctl : Mapping[str, str]
        Control name -> queryable key (``"{base}/ctl/{name}"``) for every
        :data:`CONTROL_NAMES`.
    ctl_wildcard : str
        ``"{base}/ctl/**"``: one queryable serving every control, and answering a query
        on any other key below ``ctl`` (``ctl``, ``ctl/reset/extra``) with an error
        instead of leaving it to time out.
    """

    prefix: str
    vehicle: str
    base: str
    cmd: str
    state: str
    diag: str
    alive: str
    ctl: Mapping[str, str]
    ctl_wildcard: str
    state_decimated: str

    def control(self, name: str) -> str:
        """Key of control ``name``; raises :class:`ProtocolError` for an unknown name."""
        try:
            return self.ctl[name]
        except KeyError:
            raise ProtocolError(
                "control", f"unknown control {name!r}; known: {', '.join(CONTROL_NAMES)}"
            ) from None

    def control_name(self, key: str) -> str | None:
        """The control named by a concrete key of this vehicle, or None if it is not one."""
        head = self.base + "/ctl/"
        if not key.startswith(head):
            return None
        name = key[len(head) :]
        return name if name in self.ctl else None


def vehicle_keys(prefix: str = DEFAULT_PREFIX, vehicle: str = DEFAULT_VEHICLE) -> VehicleKeys:
    """Build every key expression of one vehicle: the one place keys are made.

    Parameters
    ----------
    prefix : str, optional
        Key prefix, one or more chunks (``"simserver"``, ``"lab1/simserver"``).
    vehicle : str, optional
        Vehicle id, one chunk. Servers with different ids never see each other's traffic.

    Returns
    -------
    VehicleKeys

    Raises
    ------
    ProtocolError
        When the prefix or the id is invalid (see :func:`validate_prefix`,
        :func:`validate_vehicle_id`).
    """
    validate_prefix(prefix)
    validate_vehicle_id(vehicle)
    base = f"{prefix}/{vehicle}"
    return VehicleKeys(
        prefix=prefix,
        vehicle=vehicle,
        base=base,
        cmd=f"{base}/cmd",
        state=f"{base}/state",
        diag=f"{base}/diag",
        alive=f"{base}/alive",
        ctl={name: f"{base}/ctl/{name}" for name in CONTROL_NAMES},
        ctl_wildcard=f"{base}/ctl/**",
        state_decimated=f"{base}/state/{STATE_DECIMATED_HZ}hz",
    )


# ============================================================================ field tables


@dataclass(frozen=True)
class FieldSpec:
    """One field of a binary payload.

    Attributes
    ----------
    name : str
        Field name (numpy dtype field name).
    dtype : str
        Little-endian numpy type string (``"<u2"``, ``"<f4"``, ``"u1"``, ...).
    count : int
        1 for a scalar, 4 for a per-wheel array (FL, FR, RL, RR).
    unit : str
        SI unit, ``"1"`` for dimensionless, ``"-"`` for codes and counters.
    lo, hi : float or None
        Valid range (inclusive); None where any value of the type is valid.
    description : str
        Meaning and sign convention.
    rule : str
        What the receiver does with a value outside the range (commands only).
    source : str
        VehicleState only: where the server takes the value from (:data:`STATE_FIELDS`).
        ``"state:NAME"``, ``"output:NAME"`` or ``"input:NAME"``: the core's state, output
        or input slot named ``NAME`` in ``simserver.core.layout`` (its ``STATE_NAMES``,
        ``OUTPUT_NAMES``, ``INPUT_NAMES``; ``{w}`` stands for the wheel of a per-wheel
        field, ``fl fr rl rr``); ``"pose:NAME"``: the world pose the server computes each
        tick (``core.pose.world_pose``, slot ``POSE_<NAME>``); ``"server"``: computed by
        the server's vehicle slot (flags, counters, time, ...); empty for the constants
        ``version`` and ``reserved``.
    history : str or None
        VehicleState only: the column of the headless ``history.parquet``
        (docs/history_columns.md) that holds the same quantity, ``{w}`` for the wheel;
        None when the history has no such column. The recorder writes the field under
        this name (:func:`state_columns`).
    """

    name: str
    dtype: str
    count: int
    unit: str
    lo: float | None
    hi: float | None
    description: str
    rule: str = "-"
    source: str = ""
    history: str | None = None


_REJECT = "reject"
_CLAMP = f"NaN/inf: reject; within {CLAMP_TOLERANCE:g} outside: clamp; further: reject"

COMMAND_FIELDS: Final[tuple[FieldSpec, ...]] = (
    FieldSpec("version", "<u2", 1, "-", PROTOCOL_VERSION, PROTOCOL_VERSION,
              "protocol version, must equal PROTOCOL_VERSION", _REJECT),
    FieldSpec("gear", "u1", 1, "-", 0, 3, "0 = P, 1 = R, 2 = N, 3 = D", _REJECT),
    FieldSpec("flags", "u1", 1, "-", None, None,
              "bit 0: parking (hand) brake applied; bits 1-7 must be 0",
              "unknown bit set: reject"),
    FieldSpec("seq", "<u4", 1, "-", None, None,
              "sender's sequence number, +1 per command (wraps at 2^32)", "-"),
    FieldSpec("sender_time_ns", "<u8", 1, "ns", None, None,
              "sender's clock (any epoch, opaque to the server; echoed in "
              "VehicleState.last_cmd_sender_time_ns)", "-"),
    FieldSpec("steer", "<f4", 1, "1", -1.0, 1.0,
              "normalised steering-wheel position, +1 = full left (ISO 8855: positive "
              "steer turns left)", _CLAMP),
    FieldSpec("throttle", "<f4", 1, "1", 0.0, 1.0, "accelerator pedal, 0 = released",
              _CLAMP),
    FieldSpec("brake", "<f4", 1, "1", 0.0, 1.0, "service brake pedal, 0 = released", _CLAMP),
    FieldSpec("reserved", "<u4", 1, "-", 0, 0,
              "zero (pads to 32 bytes, the size of the naturally aligned C struct)",
              "non-zero: reject"),
)

_POSE = "world frame, z up (ISO 8855 earth-fixed axes)"
_ATT = "body attitude R = Rz(yaw) Ry(pitch) Rx(roll), intrinsic z-y'-x''"
_WHEELS = "per wheel FL, FR, RL, RR"

STATE_FIELDS: Final[tuple[FieldSpec, ...]] = (
    FieldSpec("version", "<u2", 1, "-", PROTOCOL_VERSION, PROTOCOL_VERSION,
              "protocol version"),
    FieldSpec("flags", "<u2", 1, "-", None, None,
              "bit 0 watchdog engaged (no valid command: throttle off, brakes hold); "
              "bit 1 paused; bit 2 a brake holds a wheel at zero spin (the pedal, the "
              "parking brake or the park lock acting; not rolling resistance alone); "
              "bit 3 tick run late as part of a catch-up; bit 4 fault: the state went "
              "non-finite, the car was put at rest at the scene's start pose and paused "
              "until a reset or load; bit 5 the first state after skipped deadlines (a "
              "stall beyond the catch-up bound, see Diagnostics.skipped_ticks); bit 6 "
              "hill-start assist holds the brakes after the driver released the pedal "
              "(docs/model.md section 13); bits 7-15 are 0", source="server"),
    FieldSpec("last_cmd_seq", "<u4", 1, "-", None, None,
              "seq of the last command applied (0 before the first)", source="server"),
    FieldSpec("tick", "<u8", 1, "-", None, None,
              "physics ticks stepped since start or reset", source="server"),
    FieldSpec("last_cmd_sender_time_ns", "<u8", 1, "ns", None, None,
              "sender_time_ns of the last command applied (0 before the first)",
              source="server"),
    FieldSpec("sim_time_s", "<f8", 1, "s", 0.0, None, "simulated time = tick x period",
              source="server", history="time_s"),
    FieldSpec("x_m", "<f8", 1, "m", None, None, f"CG position, {_POSE}",
              source="pose:x_m", history="world_x_m"),
    FieldSpec("y_m", "<f8", 1, "m", None, None, f"CG position, {_POSE}",
              source="pose:y_m", history="world_y_m"),
    FieldSpec("z_m", "<f8", 1, "m", None, None, f"CG position, {_POSE}",
              source="pose:z_m", history="world_z_m"),
    FieldSpec("yaw_rad", "<f8", 1, "rad", None, None,
              f"heading from world x toward y, continuous (not wrapped); {_ATT}",
              source="pose:yaw_rad", history="world_yaw_rad"),
    FieldSpec("pitch_rad", "<f8", 1, "rad", None, None,
              f"pitch, positive = nose down; {_ATT}", source="pose:pitch_rad",
              history="world_pitch_rad"),
    FieldSpec("roll_rad", "<f8", 1, "rad", None, None,
              f"roll, positive = left side up; {_ATT}", source="pose:roll_rad",
              history="world_roll_rad"),
    FieldSpec("cmd_age_s", "<f4", 1, "s", -1.0, None,
              "wall time since the last valid command arrived; -1 before the first",
              source="server"),
    FieldSpec("u_mps", "<f4", 1, "m/s", None, None, "body longitudinal velocity (x forward)",
              source="state:u_mps", history="u_mps"),
    FieldSpec("v_mps", "<f4", 1, "m/s", None, None, "body lateral velocity (y left)",
              source="state:v_mps", history="v_mps"),
    # recorded under its own name: recordings have always called it w_mps
    FieldSpec("w_mps", "<f4", 1, "m/s", None, None, "body vertical velocity (z up)",
              source="state:heave_rate_mps"),
    FieldSpec("roll_rate_radps", "<f4", 1, "rad/s", None, None, "body roll rate (about x)",
              source="state:roll_rate_radps", history="roll_rate_radps"),
    FieldSpec("pitch_rate_radps", "<f4", 1, "rad/s", None, None, "body pitch rate (about y)",
              source="state:pitch_rate_radps", history="pitch_rate_radps"),
    FieldSpec("yaw_rate_radps", "<f4", 1, "rad/s", None, None, "body yaw rate (about z)",
              source="state:yaw_rate_radps", history="yaw_rate_radps"),
    FieldSpec("ax_mps2", "<f4", 1, "m/s^2", None, None, "CG acceleration along body x",
              source="output:ax_mps2", history="ax_mps2"),
    FieldSpec("ay_mps2", "<f4", 1, "m/s^2", None, None, "CG acceleration along body y",
              source="output:ay_mps2", history="ay_mps2"),
    FieldSpec("steer", "<f4", 1, "1", -1.0, 1.0,
              "applied steer (after clamping and watchdog)", source="input:steer",
              history="input_steer"),
    FieldSpec("throttle", "<f4", 1, "1", 0.0, 1.0, "applied throttle", source="input:throttle",
              history="input_throttle"),
    FieldSpec("brake", "<f4", 1, "1", 0.0, 1.0, "applied service brake", source="input:brake",
              history="input_brake"),
    FieldSpec("omega_radps", "<f4", 4, "rad/s", None, None,
              f"wheel spin rate, positive = rolling forward; {_WHEELS}",
              source="state:omega_{w}_radps", history="omega_{w}_radps"),
    FieldSpec("kappa_lag", "<f4", 4, "1", None, None,
              f"lagged longitudinal slip k' (SAE 950311 eq. 26), + when driving; {_WHEELS}",
              source="state:kappa_lag_{w}", history="kappa_lag_{w}"),
    FieldSpec("tan_alpha_lag", "<f4", 4, "1", None, None,
              f"lagged lateral slip tan a' (eq. 16), + when the hub slides left; {_WHEELS}",
              source="state:tan_alpha_lag_{w}", history="tan_alpha_lag_{w}"),
    FieldSpec("fx_n", "<f4", 4, "N", None, None,
              f"longitudinal tire force, wheel frame; {_WHEELS}",
              source="output:fx_{w}_n", history="fx_{w}_n"),
    FieldSpec("fy_n", "<f4", 4, "N", None, None, f"lateral tire force, wheel frame; {_WHEELS}",
              source="output:fy_{w}_n", history="fy_{w}_n"),
    FieldSpec("fz_n", "<f4", 4, "N", 0.0, None, f"normal load; {_WHEELS}",
              source="output:fz_{w}_n", history="fz_{w}_n"),
    FieldSpec("steer_rad", "<f4", 4, "rad", None, None,
              f"road-wheel steer angle, + = left; {_WHEELS}",
              source="output:steer_{w}_rad", history="steer_{w}_rad"),
    FieldSpec("mz_nm", "<f4", 4, "N m", None, None,
              f"tire aligning moment, + turns the wheel left (z up); {_WHEELS}",
              source="output:mz_{w}_nm", history="mz_{w}_nm"),
    FieldSpec("steering_wheel_angle_rad", "<f4", 1, "rad", None, None,
              "steering-wheel angle, + = left (steer x steering_wheel_max_rad)",
              source="state:steering_wheel_angle_rad", history="steering_wheel_angle_rad"),
    FieldSpec("steering_wheel_torque_nm", "<f4", 1, "N m", None, None,
              "torque the steering system applies to the driver's hands, + = toward the "
              "left; a force-feedback wheel produces it (docs/model.md section 12)",
              source="state:steering_wheel_torque_nm", history="steering_wheel_torque_nm"),
    FieldSpec("damping_active", "u1", 4, "-", 0, 1,
              f"low-speed auxiliary damping active (0/1); {_WHEELS}",
              source="state:damping_active_{w}", history="damping_active_{w}"),
    FieldSpec("brake_held", "u1", 4, "-", 0, 1,
              f"brake holds the wheel at zero spin (0/1); {_WHEELS}",
              source="server", history="wheel_held_{w}"),
    FieldSpec("parking_brake", "u1", 1, "-", 0, 1, "applied parking brake (0/1)",
              source="input:parking_brake", history="input_parking_brake"),
    FieldSpec("gear", "u1", 1, "-", 0, 3, "applied gear, 0 = P, 1 = R, 2 = N, 3 = D",
              source="input:gear", history="input_gear"),
    FieldSpec("wheel_contact", "u1", 4, "-", 0, 1,
              f"wheel touches the ground (carries load) (0/1); {_WHEELS}",
              source="state:in_contact_{w}", history="in_contact_{w}"),
    FieldSpec("gear_engaged", "i1", 1, "-", -1, 10,
              "gear engaged by the gearbox: 1 .. n forward, -1 reverse, 0 none (P, N); the "
              "simple powertrain: 1 in D, -1 in R", source="state:gear_engaged",
              history="gear_engaged"),
    FieldSpec("lockup_engaged", "u1", 1, "-", 0, 1,
              "torque converter's lock-up clutch closed (0/1; 0 on the simple powertrain)",
              source="state:lockup_engaged", history="lockup_engaged"),
    FieldSpec("ground_grade_pct", "<f4", 1, "%", None, None,
              "slope of the ground under the car along its heading, + = uphill ahead: the "
              "plane fitted under the four wheels (docs/model.md section 11; on the plane "
              "kind, the road)", source="server"),
    FieldSpec("ground_cross_slope_pct", "<f4", 1, "%", None, None,
              "slope of that plane across the heading, + = the left side higher",
              source="server"),
    FieldSpec("engine_speed_radps", "<f4", 1, "rad/s", 0.0, None,
              "engine speed (automatic powertrain; 0 on the simple powertrain, which has "
              "no engine)", source="state:engine_speed_radps", history="engine_speed_radps"),
    FieldSpec("contact_force_n", "<f4", 1, "N", 0.0, None,
              "magnitude of the contact force other cars' bodies put on this car over the "
              "last step, in the ground plane (docs/model.md section 16; 0 when touching "
              "none)", source="server"),
    FieldSpec("car_contact", "u1", 1, "-", 0, 1,
              "the car's body box overlapped another car's over the last step (0/1; "
              "docs/model.md section 16)", source="server"),
    FieldSpec("reserved", "u1", 7, "-", 0, 0, "zero (pads the payload to 304 bytes)"),
)

_WINDOW = "over the last window_ticks ticks"

DIAGNOSTICS_FIELDS: Final[tuple[FieldSpec, ...]] = (
    FieldSpec("version", "<u2", 1, "-", PROTOCOL_VERSION, PROTOCOL_VERSION,
              "protocol version"),
    FieldSpec("nonfinite_stops", "<u2", 1, "-", None, None,
              "times the state went non-finite and the car was stopped (flags bit 4; "
              "saturates at 65535)"),
    FieldSpec("window_ticks", "<u4", 1, "-", None, None,
              "ticks in the statistics window (the p50/p99/max fields)"),
    FieldSpec("tick", "<u8", 1, "-", None, None, "physics tick at publication"),
    FieldSpec("uptime_s", "<f8", 1, "s", 0.0, None, "wall time since the clock started"),
    FieldSpec("lateness_p50_us", "<f4", 1, "us", 0.0, None,
              f"median tick start lateness after its deadline, {_WINDOW}"),
    FieldSpec("lateness_p99_us", "<f4", 1, "us", 0.0, None, f"99th percentile, {_WINDOW}"),
    FieldSpec("lateness_max_us", "<f4", 1, "us", 0.0, None, f"maximum, {_WINDOW}"),
    FieldSpec("period_p50_us", "<f4", 1, "us", 0.0, None,
              f"median start-to-start tick period, {_WINDOW}"),
    FieldSpec("period_p99_us", "<f4", 1, "us", 0.0, None, f"99th percentile, {_WINDOW}"),
    FieldSpec("period_max_us", "<f4", 1, "us", 0.0, None, f"maximum, {_WINDOW}"),
    FieldSpec("period_min_us", "<f4", 1, "us", 0.0, None, f"minimum, {_WINDOW}"),
    FieldSpec("cpu_percent", "<f4", 1, "%", 0.0, None,
              "process CPU time / wall time since the last diagnostics (100 = one core)"),
    FieldSpec("overruns", "<u8", 1, "-", None, None,
              "ticks whose deadline had passed before the loop asked for them (since start)"),
    FieldSpec("skipped_ticks", "<u8", 1, "-", None, None,
              "deadlines dropped by the overrun policy (sim time lags wall time by "
              "skipped_ticks x period)"),
    FieldSpec("late_ticks", "<u8", 1, "-", None, None,
              "ticks started more than 1 ms after their deadline (since start)"),
    FieldSpec("cmd_received", "<u8", 1, "-", None, None, "command payloads received"),
    FieldSpec("cmd_rejected", "<u8", 1, "-", None, None,
              "commands rejected by decode_command (never applied)"),
    FieldSpec("cmd_clamped", "<u8", 1, "-", None, None,
              "commands applied with a value clamped into range"),
    FieldSpec("cmd_stale", "<u8", 1, "-", None, None,
              "valid commands not applied: older seq than one already applied, or "
              "superseded by a newer one in the same tick"),
    FieldSpec("state_published", "<u8", 1, "-", None, None, "VehicleState messages published"),
    FieldSpec("watchdog_trips", "<u8", 1, "-", None, None, "times the watchdog engaged"),
    FieldSpec("cmd_dropped", "<u8", 1, "-", None, None,
              "command payloads lost because the server's receive buffer was full (more "
              "than its capacity arrived between two ticks; the oldest are dropped)"),
    FieldSpec("ctl_received", "<u8", 1, "-", None, None, "control requests received"),
    FieldSpec("ctl_busy", "<u8", 1, "-", None, None,
              "control requests answered busy (that client's queue full, or a load "
              "still being prepared)"),
    FieldSpec("publish_slow", "<u8", 1, "-", None, None,
              "state publications that took longer than a quarter period (a congested "
              "link; the publication never waits for a subscriber, and runs beside the "
              "tick), or were dropped when 256 were waiting to go out"),
    FieldSpec("contact_events", "<u8", 1, "-", None, None,
              "contact events this car took part in since start: a pair of cars whose "
              "bodies start to touch (docs/model.md section 16), each also published on "
              "`{prefix}/world/collision`"),
    FieldSpec("contact_events_lost", "<u8", 1, "-", None, None,
              "contact events of the whole world the server did not read (its ring of "
              "64 overwritten between two ticks) and so did not count nor publish"),
)

_STRUCT_CODES = {"u1": "B", "i1": "b", "u2": "H", "u4": "I", "u8": "Q", "f4": "f", "f8": "d"}


def _make_dtype(fields: Sequence[FieldSpec]) -> np.dtype:
    return np.dtype(
        [(f.name, f.dtype, (f.count,)) if f.count > 1 else (f.name, f.dtype) for f in fields]
    )


def _struct_format(fields: Sequence[FieldSpec]) -> str:
    parts = []
    for f in fields:
        code = _STRUCT_CODES[f.dtype.lstrip("<")]
        parts.append(f"{f.count}{code}" if f.count > 1 else code)
    return "<" + "".join(parts)


COMMAND_DTYPE: Final[np.dtype] = _make_dtype(COMMAND_FIELDS)
STATE_DTYPE: Final[np.dtype] = _make_dtype(STATE_FIELDS)
DIAGNOSTICS_DTYPE: Final[np.dtype] = _make_dtype(DIAGNOSTICS_FIELDS)

_COMMAND_STRUCT = struct.Struct(_struct_format(COMMAND_FIELDS))
_STATE_STRUCT = struct.Struct(_struct_format(STATE_FIELDS))
_DIAGNOSTICS_STRUCT = struct.Struct(_struct_format(DIAGNOSTICS_FIELDS))

COMMAND_SIZE: Final[int] = COMMAND_DTYPE.itemsize
STATE_SIZE: Final[int] = STATE_DTYPE.itemsize
DIAGNOSTICS_SIZE: Final[int] = DIAGNOSTICS_DTYPE.itemsize

assert _COMMAND_STRUCT.size == COMMAND_SIZE == 32
assert _STATE_STRUCT.size == STATE_SIZE == 304
assert _DIAGNOSTICS_STRUCT.size == DIAGNOSTICS_SIZE == 176


# ============================================================================ state schema
# STATE_FIELDS is the one table of the published state: each row gives a field's layout,
# where the server takes it from (``source``) and the headless history column that holds
# the same quantity (``history``). Everything else is derived from it: the server's fill
# (simserver.wire.state_schema, used by the vehicle slot), the viewer's inverse (the same
# module), the recorder's columns and mapping (:data:`STATE_COLUMNS`) and the state table
# of docs/protocol.md. Adding a field is one row here plus the version bump.

WHEEL_NAMES: Final[tuple[str, ...]] = ("fl", "fr", "rl", "rr")
"""The order of a per-wheel field's values, and what ``{w}`` stands for in its names."""

_WHEEL_LONG = {"fl": "front-left", "fr": "front-right", "rl": "rear-left", "rr": "rear-right"}

STATE_SOURCE_KINDS: Final[tuple[str, ...]] = ("state", "output", "input", "pose", "server")
"""The kinds of ``FieldSpec.source`` (its text before the ``:``)."""

STEP_SOURCE_KINDS: Final[tuple[str, ...]] = ("output", "input")
"""Sources that belong to the physics step that ended at the state's tick (section 2.4)."""


def state_source(f: FieldSpec) -> tuple[str, str]:
    """``(kind, name)`` of a state field's source: ``("state", "omega_{w}_radps")``,
    ``("server", "")``; ``("", "")`` for the constants ``version`` and ``reserved``."""
    kind, _, name = f.source.partition(":")
    return kind, name


@dataclass(frozen=True)
class StateColumn:
    """One column a recorder writes from the state (one per wheel of a per-wheel field).

    Attributes
    ----------
    name : str
        Column name: the field's ``history`` column (the wheel filled in; the world pose's
        is ``world_<field>``, the history's ``x_m`` being on the road plane), else the
        field's own name.
    field : str
        The VehicleState field it is read from.
    wheel : int or None
        Index into that field's values (FL, FR, RL, RR), None for a scalar field.
    dtype : str
        numpy type of the column: float64 for history columns (as the history) and
        floats, the field's own integer type for the other integers (ticks, flags, ...).
    unit : str
        The field's unit (``"1"`` for a dimensionless history column, as the history).
    description : str
    history : bool
        True when the headless ``history.parquet`` has this column (same name, meaning).
    """

    name: str
    field: str
    wheel: int | None
    dtype: str
    unit: str
    description: str
    history: bool


def _column_of(f: FieldSpec, wheel: int | None) -> StateColumn:
    kind, _ = state_source(f)
    w = WHEEL_NAMES[wheel] if wheel is not None else None
    text = f.description.removesuffix(f"; {_WHEELS}")
    if w is not None:
        text = f"{_WHEEL_LONG[w]}: {text}"
    if kind in STEP_SOURCE_KINDS:
        text += " (of the step that ended at the state's tick)"
    if f.history is not None:
        return StateColumn(f.history.format(w=w), f.name, wheel, "<f8",
                           "1" if f.unit == "-" else f.unit, text, True)
    name = f.name
    if w is not None:
        name = f"{name}_{w}"
    dtype = "<f8" if f.dtype.lstrip("<")[0] == "f" else f.dtype
    return StateColumn(name, f.name, wheel, dtype, f.unit, text, False)


def state_columns() -> tuple[StateColumn, ...]:
    """The columns of a recording of VehicleStates, derived from :data:`STATE_FIELDS` in
    its order (``version`` and ``reserved`` left out): what ``simserver-recorder`` writes
    besides the road-plane pose it converts and its own bookkeeping."""
    cols: list[StateColumn] = []
    for f in STATE_FIELDS:
        if not f.source:
            continue
        if f.count == 1:
            cols.append(_column_of(f, None))
        else:
            cols.extend(_column_of(f, i) for i in range(f.count))
    return tuple(cols)


def _check_state_table() -> None:
    """The table's own rules, checked on import (a wrong row is found before any use)."""
    seen: set[str] = set()
    for f in STATE_FIELDS:
        kind, name = state_source(f)
        if f.name in ("version", "reserved"):
            assert not f.source and f.history is None, f.name
            continue
        assert kind in STATE_SOURCE_KINDS, f"{f.name}: source {f.source!r}"
        assert (kind == "server") == (not name), f"{f.name}: source {f.source!r}"
        per_wheel = f.count == len(WHEEL_NAMES)
        assert f.count == 1 or per_wheel, f.name
        for text in (name, f.history or ""):
            if text:
                assert ("{w}" in text) == per_wheel, f"{f.name}: {text!r} and count {f.count}"
        # the history's x_m, y_m, yaw_rad are on the road plane; its world pose is world_*
        assert kind != "pose" or f.history == f"world_{name}", f"{f.name}: {f.history!r}"
    for c in state_columns():
        assert c.name not in seen, f"two state columns named {c.name!r}"
        seen.add(c.name)


_check_state_table()

STATE_COLUMNS: Final[tuple[StateColumn, ...]] = state_columns()
"""Every column of a recording of VehicleStates (:func:`state_columns`)."""

STATE_POSE_FIELDS: Final[tuple[str, ...]] = tuple(
    f.name for f in STATE_FIELDS if state_source(f)[0] == "pose")
"""The world pose's fields, in the table's order: x, y, z of the CG, yaw, pitch, roll."""
assert [n.split("_")[0] for n in STATE_POSE_FIELDS] == ["x", "y", "z", "yaw", "pitch", "roll"]


def check_state_reads(reader: str, names: Sequence[str]) -> tuple[str, ...]:
    """The state fields a client reads, checked against :data:`STATE_FIELDS` once (at its
    import), so that a field renamed or removed from the table fails there, naming the
    reader, and not at the first message.

    Raises
    ------
    ProtocolError
        Naming the first field the state does not have.
    """
    for name in names:
        if name not in STATE_DTYPE.names:
            raise ProtocolError(name, f"{reader} reads it, but the VehicleState has no such "
                                      "field (protocol.STATE_FIELDS)")
    return tuple(names)


# ============================================================================ frames
# The frames of section 2.4 of docs/protocol.md, for clients (the recorder): the road plane
# of ``set_road`` and a terrain's reference plane, from what the wire carries. The server
# computes the same in its compiled core (core.road, core.pose; tests check one against
# the other).


def ground_slopes_pct(grade_pct: float, cross_slope_pct: float,
                      yaw_rad: float) -> tuple[float, float]:
    """The state's ``ground_grade_pct``, ``ground_cross_slope_pct``: the slopes along and
    across the heading ``yaw_rad`` of a plane rising ``grade_pct`` % along world x and
    ``cross_slope_pct`` % along world y (+ = uphill ahead, + = the left side higher).

    A plane ``Z = (g X + c Y) / 100`` rises ``g cos(yaw) + c sin(yaw)`` per cent along the
    horizontal heading and ``-g sin(yaw) + c cos(yaw)`` to its left."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return grade_pct * c + cross_slope_pct * s, -grade_pct * s + cross_slope_pct * c




def road_axes(grade_pct: np.ndarray, cross_slope_pct: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit vectors ``e1``, ``e2``, ``n`` of the road plane in world axes, per row.

    Parameters
    ----------
    grade_pct, cross_slope_pct : ndarray
        The plane rises ``grade_pct`` % along world x and ``cross_slope_pct`` % along y.

    Returns
    -------
    e1, e2, n : ndarray
        ``(rows, 3)`` each: ``e1`` above world x, ``n`` the upward normal, ``e2 = n x e1``.
    """
    sx = np.asarray(grade_pct, dtype=np.float64) / 100.0
    sy = np.asarray(cross_slope_pct, dtype=np.float64) / 100.0
    one = np.ones_like(sx)
    e1 = np.stack([one, np.zeros_like(sx), sx], axis=-1)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    n = np.stack([-sx, -sy, one], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    e2 = np.cross(n, e1)
    e2 /= np.linalg.norm(e2, axis=-1, keepdims=True)
    return e1, e2, n


def world_to_road(pos: np.ndarray, yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray,
                  grade_pct: np.ndarray, cross_slope_pct: np.ndarray) -> dict[str, np.ndarray]:
    """Road-plane coordinates and body angles from the world pose (vectorised).

    Parameters
    ----------
    pos : ndarray
        ``(rows, 3)`` CG positions, world axes.
    yaw, pitch, roll : ndarray
        World body attitude, ``R = Rz(yaw) Ry(pitch) Rx(roll)``.
    grade_pct, cross_slope_pct : ndarray
        The road plane of each row.

    Returns
    -------
    dict of str to ndarray
        ``x_m``, ``y_m`` (along ``e1``, ``e2``), ``cg_above_road_m`` (along ``n``),
        ``yaw_rad`` (heading in the plane from ``e1`` toward ``e2``, continuous with the
        world yaw), ``pitch_rad`` and ``roll_rad`` relative to the plane.
    """
    e1, e2, n = road_axes(grade_pct, cross_slope_pct)
    cz, sz = np.cos(yaw), np.sin(yaw)
    cy, sy = np.cos(pitch), np.sin(pitch)
    cx, sx = np.cos(roll), np.sin(roll)
    bx = np.stack([cz * cy, sz * cy, -sy], axis=-1)
    by = np.stack([cz * sy * sx - sz * cx, sz * sy * sx + cz * cx, cy * sx], axis=-1)
    bz = np.stack([cz * sy * cx + sz * sx, sz * sy * cx - cz * sx, cy * cx], axis=-1)

    def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.einsum("ij,ij->i", a, b)

    wrapped = np.arctan2(dot(bx, e2), dot(bx, e1))
    diff = (wrapped - yaw + np.pi) % (2.0 * np.pi) - np.pi
    return {
        "x_m": dot(pos, e1),
        "y_m": dot(pos, e2),
        "cg_above_road_m": dot(pos, n),
        "yaw_rad": yaw + diff,
        "pitch_rad": np.arcsin(np.clip(-dot(bx, n), -1.0, 1.0)),
        "roll_rad": np.arctan2(dot(by, n), dot(bz, n)),
    }


def reference_plane_slopes(yaw: np.ndarray, ground_grade_pct: np.ndarray,
                           ground_cross_slope_pct: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray]:
    """A terrain's reference plane under the car, ``(grade_pct, cross_slope_pct)`` along
    world x and y, from the state's slopes along and across the world heading ``yaw``
    (:func:`ground_slopes_pct` turned back)."""
    c, s = np.cos(yaw), np.sin(yaw)
    along = np.asarray(ground_grade_pct, dtype=np.float64)
    across = np.asarray(ground_cross_slope_pct, dtype=np.float64)
    return along * c - across * s, along * s + across * c


# ============================================================================ commands


class Gear(enum.IntEnum):
    """Gear selector codes (as ``core.layout.GEAR_*``)."""

    P = 0
    R = 1
    N = 2
    D = 3


CMD_FLAG_PARKING_BRAKE: Final[int] = 0x01
CMD_FLAGS_KNOWN: Final[int] = CMD_FLAG_PARKING_BRAKE


class StateFlag(enum.IntFlag):
    """Bits of ``VehicleState.flags``."""

    WATCHDOG = 0x01
    PAUSED = 0x02
    BRAKE_HOLD = 0x04
    CATCHUP = 0x08
    FAULT = 0x10
    SKIPPED = 0x20  # the first state after deadlines were skipped (a stall: SIGSTOP, ...)
    HILL_HOLD = 0x40  # hill-start assist holds the brakes (docs/model.md section 13)


@dataclass(frozen=True, slots=True)
class DriverCommand:
    """A validated driver command, ready to apply (names as CARLA's VehicleControl).

    Attributes
    ----------
    seq : int
        Sender's sequence number (u32).
    sender_time_ns : int
        Sender's timestamp (u64, the sender's clock).
    steer : float
        [-1, 1], +1 = full left.
    throttle, brake : float
        [0, 1].
    gear : int
        A :class:`Gear` code.
    parking_brake : bool
        Hand brake applied.
    clamped : tuple of str
        Names of the fields that were clamped into range (empty almost always).
    """

    seq: int
    sender_time_ns: int
    steer: float
    throttle: float
    brake: float
    gear: int
    parking_brake: bool
    clamped: tuple[str, ...] = ()


_CMD_STEER = COMMAND_FIELDS[5]
_CMD_THROTTLE = COMMAND_FIELDS[6]
_CMD_BRAKE = COMMAND_FIELDS[7]


def _unit_value(spec: FieldSpec, value: float) -> tuple[float, bool]:
    """Validate a normalised float: returns (value within range, was clamped)."""
    if not math.isfinite(value):
        raise ProtocolError(spec.name, f"{value!r} is not finite: rejected")
    lo, hi = spec.lo, spec.hi
    if lo <= value <= hi:
        return value, False
    if lo - CLAMP_TOLERANCE <= value <= hi + CLAMP_TOLERANCE:
        return (lo if value < lo else hi), True
    raise ProtocolError(
        spec.name,
        f"{value!r} is outside [{lo:g}, {hi:g}] by more than the clamp tolerance "
        f"{CLAMP_TOLERANCE:g}: rejected",
    )


def decode_command(payload: bytes | bytearray | memoryview) -> DriverCommand:
    """Decode and validate one DriverCommand payload.

    Parameters
    ----------
    payload : bytes-like
        Exactly :data:`COMMAND_SIZE` bytes (``zenoh.ZBytes`` must be converted with
        ``to_bytes()`` first).

    Returns
    -------
    DriverCommand
        Finite values within their ranges; ``clamped`` lists any field clamped.

    Raises
    ------
    ProtocolError
        Naming the field: wrong type or size (``payload``), wrong ``version``, unknown
        ``gear``, unknown ``flags`` bits, non-zero ``reserved``, a non-finite or
        out-of-range ``steer``, ``throttle`` or ``brake``. No other exception escapes,
        whatever the input.
    """
    try:
        size = len(payload)
        version, gear, flags, seq, sender_time_ns, steer, throttle, brake, reserved = (
            _COMMAND_STRUCT.unpack(payload)
            if size == COMMAND_SIZE
            else (None,) * 9
        )
    except (TypeError, struct.error, BufferError, ValueError) as exc:
        raise ProtocolError("payload", f"not a {COMMAND_SIZE}-byte buffer ({exc})") from None
    if version is None:
        raise ProtocolError(
            "payload", f"DriverCommand is {COMMAND_SIZE} bytes, got {size}: rejected"
        )
    if version != PROTOCOL_VERSION:
        raise ProtocolError(
            "version", f"{version} is not the supported version {PROTOCOL_VERSION}: rejected"
        )
    if gear > 3:
        raise ProtocolError("gear", f"{gear} is not a gear (0 P, 1 R, 2 N, 3 D): rejected")
    if flags & ~CMD_FLAGS_KNOWN:
        raise ProtocolError(
            "flags", f"unknown bits 0x{flags & ~CMD_FLAGS_KNOWN:02x} set: rejected"
        )
    if reserved:
        raise ProtocolError("reserved", f"0x{reserved:08x} is not zero: rejected")
    steer, c_steer = _unit_value(_CMD_STEER, steer)
    throttle, c_throttle = _unit_value(_CMD_THROTTLE, throttle)
    brake, c_brake = _unit_value(_CMD_BRAKE, brake)
    clamped: tuple[str, ...] = ()
    if c_steer or c_throttle or c_brake:
        clamped = tuple(
            name
            for name, c in (("steer", c_steer), ("throttle", c_throttle), ("brake", c_brake))
            if c
        )
    return DriverCommand(
        seq=seq,
        sender_time_ns=sender_time_ns,
        steer=steer,
        throttle=throttle,
        brake=brake,
        gear=gear,
        parking_brake=bool(flags & CMD_FLAG_PARKING_BRAKE),
        clamped=clamped,
    )


def _check_int(name: str, value: Any, bits: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ProtocolError(name, f"must be an integer, got {value!r}")
    if not 0 <= int(value) < (1 << bits):
        raise ProtocolError(name, f"{value} does not fit in u{bits}")
    return int(value)


def encode_command(
    steer: float = 0.0,
    throttle: float = 0.0,
    brake: float = 0.0,
    *,
    gear: int = Gear.D,
    parking_brake: bool = False,
    seq: int = 0,
    sender_time_ns: int | None = None,
    flags: int | None = None,
    version: int = PROTOCOL_VERSION,
    check: bool = True,
) -> bytes:
    """Encode a DriverCommand payload.

    Parameters
    ----------
    steer, throttle, brake : float
        Normalised inputs (see :data:`COMMAND_FIELDS`).
    gear : int, optional
        A :class:`Gear` code (default D).
    parking_brake : bool, optional
        Sets flags bit 0.
    seq : int, optional
        Sequence number (u32); increment it by one per command.
    sender_time_ns : int, optional
        Sender timestamp (u64); default ``time.monotonic_ns()``.
    flags : int, optional
        Raw flags byte, overriding ``parking_brake`` (for tests of malformed input).
    version : int, optional
        Protocol version to write (for tests of malformed input).
    check : bool, optional
        If True (default) the payload must pass :func:`decode_command`; False builds
        malformed payloads for tests.

    Returns
    -------
    bytes
        :data:`COMMAND_SIZE` bytes.

    Raises
    ------
    ProtocolError
        When a value does not fit its wire type, or (with ``check``) would be rejected.
    """
    if sender_time_ns is None:
        sender_time_ns = time.monotonic_ns()
    if flags is None:
        flags = CMD_FLAG_PARKING_BRAKE if parking_brake else 0
    values = (
        _check_int("version", version, 16),
        _check_int("gear", gear, 8),
        _check_int("flags", flags, 8),
        _check_int("seq", seq, 32),
        _check_int("sender_time_ns", sender_time_ns, 64),
    )
    floats = []
    for name, v in (("steer", steer), ("throttle", throttle), ("brake", brake)):
        try:
            floats.append(struct.unpack("<f", struct.pack("<f", v))[0])
        except (struct.error, OverflowError, TypeError) as exc:
            raise ProtocolError(name, f"{v!r} is not representable as float32 ({exc})") from None
    payload = _COMMAND_STRUCT.pack(*values, *floats, 0)
    if check:
        decode_command(payload)
    return payload


def seq_newer(seq: int, last: int) -> bool:
    """True if u32 sequence number ``seq`` is newer than ``last`` (RFC 1982 arithmetic).

    Differences in (0, 2^31) count as newer, so the 49-day wrap of a 1 kHz counter is
    handled.
    """
    diff = (seq - last) & 0xFFFFFFFF
    return 0 < diff < 0x80000000


# ============================================================================ state, diagnostics


def _pack(kind: str, fields: Sequence[FieldSpec], st: struct.Struct, values: Mapping) -> bytes:
    if len(values) > len(fields) or not values.keys() <= _FIELD_NAMES[id(fields)]:
        unknown = sorted(set(values) - _FIELD_NAMES[id(fields)])
        raise ProtocolError(unknown[0] if unknown else kind, f"is not a {kind} field")
    args: list[Any] = []
    for f in fields:
        v = values.get(f.name, _MISSING)
        if v is _MISSING:
            if f.name == "version":
                v = PROTOCOL_VERSION
            elif f.name == "reserved":
                v = [0] * f.count if f.count > 1 else 0
            else:
                raise ProtocolError(f.name, f"missing from the {kind}")
        if f.count > 1:
            try:
                seq = v.tolist() if isinstance(v, np.ndarray) and v.ndim == 1 else (
                    np.asarray(v).reshape(-1).tolist())
            except Exception as exc:  # noqa: BLE001 - any array-like failure is a field error
                raise ProtocolError(f.name, f"not an array of {f.count}: {exc}") from None
            if len(seq) != f.count:
                raise ProtocolError(f.name, f"needs {f.count} values, got {len(seq)}")
        else:
            seq = [v.item() if isinstance(v, np.generic) else v]
        if f.dtype[-2] == "u":
            # Integer fields accept integral floats (the core keeps flags and gears in
            # float64 arrays); anything else is an error, never a silent truncation.
            for i, x in enumerate(seq):
                if isinstance(x, float):
                    if not x.is_integer():
                        raise ProtocolError(f.name, f"{x!r} is not an integer")
                    seq[i] = int(x)
        args.extend(seq)
    try:
        return st.pack(*args)
    except (struct.error, OverflowError, TypeError):
        pass
    # Locate the field that did not pack, for the message.
    i = 0
    for f in fields:
        one = struct.Struct(_struct_format([f]))
        try:
            one.pack(*args[i : i + f.count])
        except (struct.error, OverflowError, TypeError) as exc:
            raise ProtocolError(f.name, f"does not fit {f.dtype} x {f.count}: {exc}") from None
        i += f.count
    raise ProtocolError(kind, "could not be packed")  # pragma: no cover


_MISSING = object()
_FIELD_NAMES = {
    id(fields): frozenset(f.name for f in fields)
    for fields in (COMMAND_FIELDS, STATE_FIELDS, DIAGNOSTICS_FIELDS)
}


def _unpack(kind: str, dtype: np.dtype, payload: bytes | bytearray | memoryview) -> np.void:
    try:
        size = len(payload)
    except TypeError:
        raise ProtocolError("payload", f"expected bytes, got {type(payload).__name__}") from None
    if size != dtype.itemsize:
        raise ProtocolError("payload", f"{kind} is {dtype.itemsize} bytes, got {size}")
    try:
        rec = np.frombuffer(payload, dtype=dtype, count=1)[0]
    except (TypeError, ValueError, BufferError) as exc:
        raise ProtocolError("payload", f"not a {kind} buffer ({exc})") from None
    if rec["version"] != PROTOCOL_VERSION:
        raise ProtocolError(
            "version", f"{int(rec['version'])} is not the supported version {PROTOCOL_VERSION}"
        )
    return rec


def encode_state(**values: Any) -> bytes:
    """Encode a VehicleState payload from plain values and arrays.

    Every field of :data:`STATE_FIELDS` is required except ``version`` and ``reserved``;
    per-wheel fields take any array-like of 4 (FL, FR, RL, RR). Costs about 10-20 us; a
    1 kHz loop may instead fill :func:`new_state_record` in place and send
    ``record.tobytes()`` (same bytes).

    Raises
    ------
    ProtocolError
        Naming a missing, unknown or unrepresentable field.
    """
    return _pack("VehicleState", STATE_FIELDS, _STATE_STRUCT, values)


def decode_state(payload: bytes | bytearray | memoryview) -> np.void:
    """Decode a VehicleState payload into a numpy record (``rec["x_m"]``, ``rec["fz_n"]``).

    Raises
    ------
    ProtocolError
        Wrong size (``payload``) or ``version``.
    """
    return _unpack("VehicleState", STATE_DTYPE, payload)


_STATE_FLAG_BITS = sum(int(f) for f in StateFlag)


def _payload_checks(fields: tuple[FieldSpec, ...], dtype: np.dtype
                    ) -> list[tuple[np.ndarray, str, np.ndarray, np.ndarray, np.ndarray]]:
    """Per element type of a field table: the byte offsets of its elements, the type,
    each element's field index and its lower and upper bound (from the table)."""
    groups: dict[str, list[tuple[int, int, float, float]]] = {}
    for index, spec in enumerate(fields):
        offset = dtype.fields[spec.name][1]
        size = np.dtype(spec.dtype).itemsize
        lo = -np.inf if spec.lo is None else spec.lo
        hi = np.inf if spec.hi is None else spec.hi
        for k in range(spec.count):
            groups.setdefault(spec.dtype, []).append((offset + k * size, index, lo, hi))
    checks = []
    for kind, elements in groups.items():
        if kind != "<u2" and np.dtype(kind).kind != "f" and \
                all(np.isinf(e[2]) and np.isinf(e[3]) for e in elements):
            continue  # any value of the type is valid (counters, stamps)
        size = np.dtype(kind).itemsize
        starts = np.array([e[0] for e in elements])
        byte_index = (starts[:, None] + np.arange(size)).ravel()
        lo = np.array([e[2] for e in elements])
        hi = np.array([e[3] for e in elements])
        if np.dtype(kind).kind == "f":  # finite bounds: a NaN or an infinity fails them
            big = float(np.finfo(kind).max)
            lo, hi = np.maximum(lo, -big), np.minimum(hi, big)
        checks.append((byte_index, kind, np.array([e[1] for e in elements]), lo, hi))
    return checks


_PAYLOAD_CHECKS = {"state": (STATE_FIELDS, _payload_checks(STATE_FIELDS, STATE_DTYPE)),
                   "diagnostics": (DIAGNOSTICS_FIELDS,
                                   _payload_checks(DIAGNOSTICS_FIELDS, DIAGNOSTICS_DTYPE))}


def invalid_fields(payloads: np.ndarray, kind: str = "state") -> np.ndarray:
    """Which received payloads no server sends, and why (a receiver's first check).

    ``payloads`` is an ``(n, size)`` ``uint8`` array of VehicleState (``kind`` "state")
    or Diagnostics ("diagnostics") payloads. For each: the index in the field table
    (:data:`STATE_FIELDS`, :data:`DIAGNOSTICS_FIELDS`) of its first field that is
    non-finite, outside the field's range (the table's ``lo``, ``hi``: the version among
    them) or, for a state's ``flags``, sets a bit :class:`StateFlag` does not define; -1
    when every field is valid. The server never publishes such a payload
    (docs/reliability.md), so a receiver drops it: it came from someone else. A few
    numpy operations per call, whatever ``n``.
    """
    fields, checks = _PAYLOAD_CHECKS[kind]
    n = payloads.shape[0]
    if n <= 8:  # a few payloads (a client's poll): plain Python is faster than numpy
        layout, bounds = _PAYLOAD_BOUNDS[kind]
        return np.array([_first_invalid(layout.unpack(row.tobytes()), bounds, kind)
                         for row in payloads], dtype=np.int64)
    ok = np.ones(n, dtype=bool)  # the common case first: every payload valid
    for byte_index, dtype, _, lo, hi in checks:
        values = np.ascontiguousarray(payloads[:, byte_index]).view(dtype)
        ok &= ((values >= lo) & (values <= hi)).all(axis=1)  # NaN and inf fail both
        if dtype == "<u2" and kind == "state":  # the flags: no undefined bit
            ok &= values[:, _FLAGS_COLUMN] | _STATE_FLAG_BITS == _STATE_FLAG_BITS
    if ok.all():
        return np.full(n, -1, dtype=np.int64)
    none = len(fields)
    first = np.full(n, none, dtype=np.int64)
    for byte_index, dtype, field_index, lo, hi in checks:
        values = np.ascontiguousarray(payloads[:, byte_index]).view(dtype)
        bad = ~((values >= lo) & (values <= hi))
        if dtype == "<u2" and kind == "state":  # the flags: no undefined bit
            bad |= (field_index == _FLAGS_INDEX) & \
                ((values | _STATE_FLAG_BITS) != _STATE_FLAG_BITS)
        np.minimum(first, np.where(bad, field_index, none).min(axis=1), out=first)
    first[first == none] = -1
    return first


_FLAGS_INDEX = next(i for i, f in enumerate(STATE_FIELDS) if f.name == "flags")


def _element_bounds(fields: tuple[FieldSpec, ...]) -> list[tuple[int, float, float]]:
    """(field index, lo, hi) of every element of a payload, in ``struct`` order (the
    bounds of floats finite, so a NaN or an infinity fails them)."""
    out = []
    for index, spec in enumerate(fields):
        lo = -math.inf if spec.lo is None else float(spec.lo)
        hi = math.inf if spec.hi is None else float(spec.hi)
        if np.dtype(spec.dtype).kind == "f":
            big = float(np.finfo(spec.dtype).max)
            lo, hi = max(lo, -big), min(hi, big)
        out += [(index, lo, hi)] * spec.count
    return out


def _first_invalid(values: tuple, bounds: list[tuple[int, float, float]], kind: str) -> int:
    for value, (index, lo, hi) in zip(values, bounds, strict=True):
        if not lo <= value <= hi:
            return index
    if kind == "state" and values[_FLAGS_ELEMENT] | _STATE_FLAG_BITS != _STATE_FLAG_BITS:
        return _FLAGS_INDEX
    return -1


_FLAGS_ELEMENT = sum(f.count for f in STATE_FIELDS[:_FLAGS_INDEX])
_PAYLOAD_BOUNDS = {"state": (_STATE_STRUCT, _element_bounds(STATE_FIELDS)),
                   "diagnostics": (_DIAGNOSTICS_STRUCT, _element_bounds(DIAGNOSTICS_FIELDS))}
_FLAGS_COLUMN = next(list(c[2]).index(_FLAGS_INDEX) for c in _PAYLOAD_CHECKS["state"][1]
                     if c[1] == "<u2")


def new_state_record() -> np.ndarray:
    """A zeroed 0-d VehicleState record with ``version`` set, to fill in place per tick.

    ``rec["x_m"] = ...; rec["fz_n"][:] = ...; payload = rec.tobytes()``. A numba kernel can
    also fill it (structured arrays are supported in nopython mode).
    """
    rec = np.zeros((), dtype=STATE_DTYPE)
    rec["version"] = PROTOCOL_VERSION
    return rec


def encode_diagnostics(**values: Any) -> bytes:
    """Encode a Diagnostics payload; every field but ``version``/``reserved`` is required.

    Raises
    ------
    ProtocolError
        Naming a missing, unknown or unrepresentable field.
    """
    return _pack("Diagnostics", DIAGNOSTICS_FIELDS, _DIAGNOSTICS_STRUCT, values)


def decode_diagnostics(payload: bytes | bytearray | memoryview) -> np.void:
    """Decode a Diagnostics payload into a numpy record.

    Raises
    ------
    ProtocolError
        Wrong size (``payload``) or ``version``.
    """
    return _unpack("Diagnostics", DIAGNOSTICS_DTYPE, payload)


def record_to_dict(rec: np.void | np.ndarray) -> dict[str, Any]:
    """Plain Python values of a decoded record (arrays become lists), e.g. for JSON logs."""
    return {name: rec[name].tolist() for name in rec.dtype.names}


# ============================================================================ controls


@dataclass(frozen=True)
class ArgSpec:
    """One argument of a control request.

    Attributes
    ----------
    name : str
        JSON key.
    kind : str
        ``"number"`` (int or float, finite), ``"integer"``, ``"path"`` (a YAML file path
        string), ``"name"`` (a short printable string: an id), ``"choice"`` (one of
        ``choices``), ``"object"`` (with ``children``) or ``"block"`` (a JSON object
        whose members the server checks with the parser of the config block it stands
        for, as that block's YAML: a car's ``driver:``; here only its form, an object).
    required : bool
        Must be present.
    unit : str
        Unit of a number.
    lo, hi : float or None
        Inclusive range of a number or integer.
    description : str
        Meaning.
    children : tuple of ArgSpec
        Members of an object (all required unless marked otherwise).
    choices : tuple of str
        The values a ``"choice"`` may take.
    """

    name: str
    kind: str
    required: bool
    unit: str
    lo: float | None
    hi: float | None
    description: str
    children: tuple[ArgSpec, ...] = ()
    choices: tuple[str, ...] = ()


@dataclass(frozen=True)
class ControlSpec:
    """A control queryable: its arguments and the fields of a successful reply."""

    name: str
    description: str
    args: tuple[ArgSpec, ...] = ()
    at_least_one: bool = False
    reply: str = ""
    defaults: Mapping[str, Any] = field(default_factory=dict)


LANE_ARGS: Final[tuple[ArgSpec, ...]] = (
    ArgSpec("road", "name", True, "", None, None, "road id, as written in the .xodr file"),
    ArgSpec("s", "number", True, "m", 0.0, 1e6, "distance along the road's reference line"),
    ArgSpec("lane", "integer", True, "", -1000, 1000,
            "lane id: negative right of the reference line, positive left, not 0"),
)
"""A place by road, s and lane of an OpenDRIVE terrain (a car's ``reset`` ``lane``, the
world's ``add_car`` ``start``)."""

_MAX_PATH = 1024
_MAX_NAME = 100
YAW_BOUND_RAD: Final[float] = 6.28319
"""The ``reset`` yaw bound: 2 pi rounded up to the digits the docs show, so that the
documented bound itself is accepted (both ends inclusive)."""
MAX_REPLY_FIELD_CHARS: Final[int] = 100
"""Longest ``field`` in an error reply (a key of the request may be 60 000 characters)."""
MAX_REPLY_ERROR_CHARS: Final[int] = 1000
"""Longest ``error`` in an error reply."""

CONTROL_SPECS: Final[Mapping[str, ControlSpec]] = {
    spec.name: spec
    for spec in (
        ControlSpec(
            "reset",
            "Reset the vehicle to the scene's initial state, to `pose` at rest, or at rest "
            "on a lane of the scene's OpenDRIVE road (`lane`: on the lane's centre, heading "
            "along its direction of travel; an error names `lane.road`, `lane.s` or "
            "`lane.lane` when the road has no such place); `pose` and `lane` not both. With "
            "`u_mps`, driving straight on at that speed (from `pose`, `lane` or the scene's "
            "initial pose), the wheels spinning at u / R and the slip states and the "
            "powertrain relaxed to their steady values at that speed, so that a session "
            "starts on the move without a transient. Tick and sim time restart at 0; "
            "counters are kept. The reset is applied when ready: at rest in the tick that "
            "serves it; with `u_mps` (or a scene with `initial.relaxed`) the settling (up "
            "to 2000 model steps below 2.3 m/s, about 230 at 20 m/s) runs 50 steps a tick "
            "beside the running car, which drives on meanwhile, so it is applied and "
            "answered 1-40 ticks later (under 40 ms at 1 kHz); no tick is made late. The "
            "state swapped in is computed from the inputs of the tick that served the "
            "request. One reset or load at a time: another meanwhile is answered busy.",
            (
                ArgSpec("pose", "object", False, "", None, None,
                        "pose on the road plane, at rest",
                        (
                            ArgSpec("x_m", "number", True, "m", -1e6, 1e6, "position x"),
                            ArgSpec("y_m", "number", True, "m", -1e6, 1e6, "position y"),
                            ArgSpec("yaw_rad", "number", True, "rad", -YAW_BOUND_RAD,
                                    YAW_BOUND_RAD, "heading, + = left of world x"),
                        )),
                ArgSpec("lane", "object", False, "", None, None,
                        "start by road, s and lane on an OpenDRIVE terrain, at rest (the "
                        "`start:` keys of a scene, docs/configuration.md)", LANE_ARGS),
                ArgSpec("u_mps", "number", False, "m/s", -30.0, 80.0,
                        "initial speed along the heading (negative: reversing)"),
            ),
            reply='"tick": 0 (the state swapped in; the next state published is tick 1), '
                  '"pose": {"x_m": number, "y_m": number, "yaw_rad": number} (where it '
                  'starts), with u_mps: "u_mps": number (its speed, as set)',
        ),
        ControlSpec("pause", "Stop stepping the physics; state is still published with "
                    "flags bit 1 set. Idempotent.", reply='"tick": int, "paused": true'),
        ControlSpec("resume", "Resume stepping at the wall-clock rate from the current tick. "
                    "Sim time does not advance while paused and the paused time is not "
                    "caught up. Idempotent.",
                    reply='"tick": int, "paused": false'),
        ControlSpec(
            "step",
            "While paused: step `n` ticks, one per period at the normal rate, then stay "
            "paused. Replies at once (before the steps run). Error if not paused.",
            (ArgSpec("n", "integer", False, "ticks", 1, 100000, "ticks to step (default 1)"),),
            reply='"tick": int (now), "until_tick": int (tick after the n steps)',
            defaults={"n": 1},
        ),
        ControlSpec(
            "set_road",
            "Change the road plane and friction; omitted members keep their value. Takes "
            "effect on the next tick.",
            (
                ArgSpec("grade_pct", "number", False, "%", -60.0, 60.0,
                        "grade: the road rises grade_pct m per 100 m along world x"),
                ArgSpec("cross_slope_pct", "number", False, "%", -30.0, 30.0,
                        "cross slope: the road rises cross_slope_pct m per 100 m along world y"),
                ArgSpec("friction_scale", "number", False, "1", 0.05, 2.0,
                        "road friction scale (1 = the surface the tires were measured on)"),
            ),
            at_least_one=True,
            reply='"road": {"grade_pct": number, "cross_slope_pct": number, '
            '"friction_scale": number} (all three, after the change)',
        ),
        ControlSpec(
            "load",
            "Load another vehicle and/or scene YAML (a relative path is looked up in the "
            "server's working directory first, then in its config directories, to which "
            "it may restrict them; the error lists where it looked). The server reads "
            "only regular files in its config directories, and so must be every file "
            "they refer to. The files are read off the tick (in a worker process; the "
            "physics runs on meanwhile; big arrays such as a terrain's grids come back "
            "through shared memory, mapped without a copy) and the result swapped in "
            "between two ticks in a few pieces of well under a millisecond each (mapped, "
            "built, settled like a `reset` with speed if the scene starts relaxed, "
            "committed), then reset; the reply comes then. One load or reset at a time: "
            "another meanwhile is answered busy. "
            "An error's `field` is the argument whose files are at fault.",
            (
                ArgSpec("vehicle", "path", False, "", None, None, "vehicle YAML path"),
                ArgSpec("scene", "path", False, "", None, None,
                        "scene YAML (or OpenSCENARIO .xosc) path"),
            ),
            at_least_one=True,
            reply='"vehicle": string, "scene": string (the active paths, relative to the '
            'server\'s config directory holding them)',
        ),
        ControlSpec(
            "get_config",
            "Return the active configuration (file paths relative to the server's config "
            "directory holding them: never an absolute server path).",
            reply='"protocol_version": integer (PROTOCOL_VERSION), "config": object (server, '
            'vehicle, scene, road, keys, ros2: the ROS 2 adapter the server runs, `null` if '
            'none: "state" running, restarting or stopped, "restarts", "last_exit_code", '
            '"pid", and while restarting "restart_in_s"; docs/ros2.md)',
        ),
    )
}
assert tuple(CONTROL_SPECS) == CONTROL_NAMES


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not allowed (JSON numbers must be finite)")


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """An object's members; a key given twice is an error (which one would count?)."""
    obj: dict[str, Any] = {}
    for key, value in pairs:
        if key in obj:
            raise ProtocolError(_printable(key, MAX_REPLY_FIELD_CHARS),
                                "is given twice in one object")
        obj[key] = value
    return obj


def _printable(text: str, limit: int) -> str:
    """``text`` safe to send back: lone surrogates and control characters escaped
    (strict JSON parsers reject a lone surrogate), cut to ``limit`` characters."""
    text = text.encode("utf-8", "backslashreplace").decode("utf-8")
    text = "".join(ch if ch.isprintable() else ch.encode("unicode_escape").decode("ascii")
                   for ch in text)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _check_arg(spec: ArgSpec, value: Any, path: str) -> Any:
    if spec.kind == "number":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ProtocolError(path, f"must be a number, got {value!r}")
        try:
            value = float(value)
        except OverflowError:
            raise ProtocolError(path, "is too large to be a number") from None
        if not math.isfinite(value):
            raise ProtocolError(path, f"{value!r} is not finite")
        if not spec.lo <= value <= spec.hi:
            raise ProtocolError(path, f"{value!r} is outside [{_num(spec.lo)}, {_num(spec.hi)}]")
        return value
    if spec.kind == "integer":
        if isinstance(value, bool) or not isinstance(value, int):
            raise ProtocolError(path, f"must be an integer, got {value!r}")
        if not spec.lo <= value <= spec.hi:
            raise ProtocolError(path, f"{value} is outside [{_num(spec.lo)}, {_num(spec.hi)}]")
        return value
    if spec.kind == "path":
        if not isinstance(value, str) or not value:
            raise ProtocolError(path, f"must be a non-empty string, got {value!r}")
        if len(value) > _MAX_PATH:
            raise ProtocolError(path, f"is longer than {_MAX_PATH} characters")
        if any(ord(ch) < 32 or ord(ch) == 127 for ch in value):
            raise ProtocolError(path, "contains control characters")
        try:
            value.encode("utf-8")
        except UnicodeEncodeError:
            raise ProtocolError(path, "is not valid Unicode (a lone surrogate)") from None
        suffixes = _path_suffixes(spec)
        if not value.endswith(suffixes):
            raise ProtocolError(path, f"{value!r} is not a {'/'.join(suffixes)} file")
        return value
    if spec.kind == "name":
        if not isinstance(value, str) or not value:
            raise ProtocolError(path, f"must be a non-empty string, got {type(value).__name__}")
        if len(value) > _MAX_NAME or not value.isprintable():
            raise ProtocolError(path, f"must be at most {_MAX_NAME} printable characters")
        return value
    if spec.kind == "choice":
        if not isinstance(value, str) or value not in spec.choices:
            raise ProtocolError(path, f"must be one of {', '.join(spec.choices)}, got "
                                      f"{_printable(repr(value), _MAX_NAME)}")
        return value
    if spec.kind == "object":
        return _check_object(spec.children, value, path, at_least_one=False)
    if spec.kind == "block":  # its members: the server's parser of that block
        if not isinstance(value, dict):
            raise ProtocolError(path, f"must be a JSON object, got {type(value).__name__}")
        return value
    raise AssertionError(spec.kind)  # pragma: no cover


def _check_object(
    specs: Sequence[ArgSpec], obj: Any, path: str, *, at_least_one: bool
) -> dict[str, Any]:
    where = path or "request"
    if not isinstance(obj, dict):
        raise ProtocolError(where, f"must be a JSON object, got {type(obj).__name__}")
    known = {s.name: s for s in specs}
    for key in obj:
        if key not in known:
            full = f"{path}.{key}" if path else str(key)
            allowed = ", ".join(known) or "none"
            raise ProtocolError(full, f"is not an argument here (allowed: {allowed})")
    out: dict[str, Any] = {}
    for s in specs:
        full = f"{path}.{s.name}" if path else s.name
        if s.name in obj:
            out[s.name] = _check_arg(s, obj[s.name], full)
        elif s.required:
            raise ProtocolError(full, "is required")
    if at_least_one and not out:
        raise ProtocolError(where, f"give at least one of: {', '.join(known)}")
    return out


SCENE_SUFFIXES: Final[tuple[str, ...]] = (".yaml", ".yml", ".xosc")
"""A ``scene`` argument's file kinds: a scene or scenario YAML, or an OpenSCENARIO file (its
ego's start: docs/openscenario.md); any other ``path`` argument is a YAML file."""


def _path_suffixes(spec: ArgSpec) -> tuple[str, ...]:
    return SCENE_SUFFIXES if spec.name == "scene" else (".yaml", ".yml")


def validate_control(name: str, payload: bytes | bytearray | memoryview | None,
                     specs: Mapping[str, ControlSpec] | None = None) -> dict:
    """Validate a control request and return its arguments, defaults filled in.

    Parameters
    ----------
    name : str
        One of :data:`CONTROL_NAMES`.
    payload : bytes-like or None
        UTF-8 JSON object; empty or None means ``{}``.

    Returns
    -------
    dict
        Validated arguments: numbers as float, integers as int, defaults added.

    Raises
    ------
    ProtocolError
        Naming the field (``"n"``, ``"pose.yaw_rad"``, ...), or ``"control"`` for an
        unknown control, ``"request"`` for a payload that is not a UTF-8 JSON object.
    """
    specs = CONTROL_SPECS if specs is None else specs
    spec = specs.get(name)
    if spec is None:
        raise ProtocolError(
            "control", f"unknown control {name!r}; known: {', '.join(specs)}"
        )
    if payload is None:
        payload = b""
    try:
        raw = bytes(payload)
    except TypeError:
        raise ProtocolError("request", f"expected bytes, got {type(payload).__name__}") from None
    if len(raw) > MAX_CONTROL_PAYLOAD_BYTES:
        raise ProtocolError("request", f"{len(raw)} bytes exceeds {MAX_CONTROL_PAYLOAD_BYTES}")
    if raw.strip() == b"":
        obj: Any = {}
    else:
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ProtocolError("request", f"is not UTF-8 ({exc.reason})") from None
        try:
            obj = json.loads(text, parse_constant=_reject_constant,
                             object_pairs_hook=_unique_keys)
        except ProtocolError:
            raise
        except RecursionError:
            raise ProtocolError("request", "JSON nested too deeply") from None
        except ValueError as exc:
            raise ProtocolError("request", f"is not valid JSON ({exc})") from None
    args = _check_object(spec.args, obj, "", at_least_one=spec.at_least_one)
    for key, default in spec.defaults.items():
        args.setdefault(key, default)
    return args


def encode_control(name: str, args: Mapping[str, Any] | None = None,
                   specs: Mapping[str, ControlSpec] | None = None) -> bytes:
    """Encode a control request (client side); validated with :func:`validate_control`.

    Raises
    ------
    ProtocolError
        When the server would reject the request.
    """
    payload = json.dumps(dict(args or {}), allow_nan=False).encode() if args else b""
    validate_control(name, payload, specs)
    return payload


def reply_ok(**data: Any) -> bytes:
    """A success reply: ``{"ok": true, ...data}`` as UTF-8 JSON."""
    return json.dumps({"ok": True, **data}, allow_nan=False).encode()


def reply_error(error: str | ProtocolError, field: str | None = None) -> bytes:
    """A failure reply: ``{"ok": false, "error": "...", "field": "..."}`` as UTF-8 JSON.

    ``field`` is taken from a :class:`ProtocolError` when not given. Both are made
    printable and cut (:data:`MAX_REPLY_ERROR_CHARS`, :data:`MAX_REPLY_FIELD_CHARS`): a
    request's huge key or lone surrogate is never echoed back as such.
    """
    if field is None and isinstance(error, ProtocolError):
        field = error.field
    body: dict[str, Any] = {"ok": False, "error": _printable(str(error), MAX_REPLY_ERROR_CHARS)}
    if field is not None:
        body["field"] = _printable(field, MAX_REPLY_FIELD_CHARS)
    return json.dumps(body).encode()


def decode_reply(payload: bytes | bytearray | memoryview) -> dict[str, Any]:
    """Parse a control reply; it must be a JSON object with a boolean ``ok``.

    Raises
    ------
    ProtocolError
        When the reply is not such an object (``field == "reply"``).
    """
    try:
        obj = json.loads(bytes(payload).decode("utf-8"))
    except (TypeError, ValueError) as exc:
        raise ProtocolError("reply", f"is not UTF-8 JSON ({exc})") from None
    if not isinstance(obj, dict) or not isinstance(obj.get("ok"), bool):
        raise ProtocolError("reply", f"has no boolean 'ok': {obj!r}"[:200])
    if not obj["ok"] and not isinstance(obj.get("error"), str):
        raise ProtocolError("reply", "an error reply has no 'error' string")
    return obj


# ============================================================================ the world
# Several cars in one server (issue 30): each car keeps every key above under its own id;
# the world's own keys live under ``{prefix}/world`` (so no car may take the id ``world``),
# and one compact message carries every car's id, pose and speed for a client that wants
# to see the others (a HUD's nearest car ahead, a viewer drawing the traffic) without
# subscribing to N full states.

WORLD_KEY: Final[str] = "world"
"""The key chunk of the world's keys, ``{prefix}/world/...``: reserved, not a vehicle id."""

WORLD_ID_BYTES: Final[int] = 32
"""Bytes of a car's id in the world message (UTF-8, NUL-padded): the longest id a server
with several cars accepts."""

WORLD_HZ_DEFAULT: Final[float] = 100.0
WORLD_CAR_ID_COLUMN: Final[str] = "car_id"
"""The column naming the car in a table of several cars' rows (the headless world history,
``adapters.history``; the recorder's ``--cars``)."""
"""Default rate of ``{prefix}/world/state`` (server config ``world_hz``). Not 1 kHz: a
client that needs a car's every tick subscribes to that car's ``state`` (1 kHz, the full
state); the world message is for seeing the traffic (a HUD, a viewer, a driver model's
gap to the car ahead), for which 100 Hz moves a car at 30 m/s by 0.3 m between messages,
at a tenth of the publishing cost in the tick."""

ENCODING_WORLD: Final[str] = "application/octet-stream;simserver.WorldState.v1"
ENCODING_COLLISION: Final[str] = "application/octet-stream;simserver.Collision.v1"
ENCODING_STORYBOARD: Final[str] = "application/json;simserver.Storyboard.v1"
"""A storyboard element's state change of a served OpenSCENARIO scenario (one JSON object:
``t_s``, ``kind``, ``name``, ``from``, ``to`` and, when a trigger caused it, ``cause``:
the storyboard trace line of docs/openscenario.md)."""

DRIVEN_BY_CODES: Final[tuple[str, ...]] = ("client", "keyframes", "driver")
"""``WorldState`` cars' ``driven_by`` code -> who drives the car (``simserver.server.fleet``)."""

ADD_CAR_DRIVEN_BY: Final[tuple[str, ...]] = ("client", "driver")
"""Who may drive a car added by ``add_car`` (of :data:`DRIVEN_BY_CODES`; keyframed cars come
from the server config's ``cars:`` only)."""

WORLD_CONTROL_NAMES: Final[tuple[str, ...]] = ("add_car", "remove_car", "reset", "get_config")
"""The world's controls (:data:`WORLD_CONTROL_SPECS`)."""

WORLD_KEY_SPECS: Final[tuple[KeySpec, ...]] = (
    KeySpec(
        "state",
        "server -> clients (put)",
        "WorldState (binary): a header and one record per car",
        ENCODING_WORLD,
        "DATA, DROP, not express",
        f"`world_hz` of the server config (default {WORLD_HZ_DEFAULT:g} Hz); also with one car",
    ),
    KeySpec(
        "collision",
        "server -> clients (put)",
        "Collision (binary): two cars' bodies started to touch",
        ENCODING_COLLISION,
        "DATA, DROP, not express",
        "once per contact event (read from the world's ring after the step that made it)",
    ),
    KeySpec(
        "storyboard",
        "server -> clients (put)",
        "Storyboard (JSON): a storyboard element's state change (`serve --scenario`, "
        "docs/openscenario.md)",
        ENCODING_STORYBOARD,
        "DATA, BLOCK, reliable",
        "once per state change (the scenario's worker thread, never the tick)",
    ),
    *(
        KeySpec(f"ctl/{name}", "client -> server (get / queryable)",
                f"JSON request `{name}` -> JSON reply", ENCODING_CONTROL, "default",
                "on demand")
        for name in WORLD_CONTROL_NAMES
    ),
)


@dataclass(frozen=True)
class WorldKeys:
    """The world's key expressions (built by :func:`world_keys`)."""

    prefix: str
    base: str  # "{prefix}/world"
    state: str  # the WorldState messages
    collision: str  # the Collision messages
    storyboard: str  # a served scenario's storyboard state changes (JSON)
    alive_all: str  # "{prefix}/*/alive": every car's liveliness token (discovery)
    ctl: Mapping[str, str]  # world control name -> queryable key "{base}/ctl/{name}"
    ctl_wildcard: str  # "{base}/ctl/**"

    def control(self, name: str) -> str:
        """Key of world control ``name`` (:class:`ProtocolError` for an unknown one)."""
        try:
            return self.ctl[name]
        except KeyError:
            raise ProtocolError("control", f"unknown world control {name!r}; known: "
                                           f"{', '.join(WORLD_CONTROL_NAMES)}") from None

    def control_name(self, key: str) -> str | None:
        """The world control named by a concrete key, or None."""
        head = self.base + "/ctl/"
        name = key[len(head):] if key.startswith(head) else None
        return name if name in self.ctl else None


def world_keys(prefix: str = DEFAULT_PREFIX) -> WorldKeys:
    """The world's keys under ``prefix`` (:class:`ProtocolError` for a bad prefix)."""
    validate_prefix(prefix)
    base = f"{prefix}/{WORLD_KEY}"
    return WorldKeys(prefix=prefix, base=base, state=f"{base}/state",
                     collision=f"{base}/collision", storyboard=f"{base}/storyboard",
                     alive_all=f"{prefix}/*/alive",
                     ctl={name: f"{base}/ctl/{name}" for name in WORLD_CONTROL_NAMES},
                     ctl_wildcard=f"{base}/ctl/**")


_WORLD_POSE = ArgSpec("pose", "object", False, "", None, None,
                      "its start pose at rest (default the scene's), on the road plane or "
                      "the terrain's horizontal axes", (
                          ArgSpec("x_m", "number", True, "m", -1e6, 1e6, "position x"),
                          ArgSpec("y_m", "number", True, "m", -1e6, 1e6, "position y"),
                          ArgSpec("yaw_rad", "number", True, "rad", -YAW_BOUND_RAD,
                                  YAW_BOUND_RAD, "heading, + = left of world x")))

WORLD_CONTROL_SPECS: Final[Mapping[str, ControlSpec]] = {
    spec.name: spec
    for spec in (
        ControlSpec(
            "add_car",
            "Add a car to the running world, driven by a client or by the built-in driver "
            "(`driven_by`): its keys `{prefix}/{id}/...` with their own command inbox, "
            "watchdog, liveliness token and controls, as a car of the server config's "
            "`cars:` list. Its files are read and its `driver` block checked and its path "
            "sampled off the tick (the load worker); it joins between two ticks (a driven "
            "car's driver with it, the other drivers' states kept); answered when it is "
            "served (its liveliness token declared). Errors name the car and the argument "
            "(`start.s`, `driver.path`, `driver.idm.T_s`, ...): an id taken, a start "
            "overlapping a car where that car is now or off the road, a driver path that "
            "leaves the road, "
            "more cars than `max_cars`, a vehicle file outside the config directories; "
            "nothing changes then.",
            (
                ArgSpec("id", "name", True, "", None, None,
                        f"the car's id: one key chunk, at most {WORLD_ID_BYTES} characters, "
                        f"not `{WORLD_KEY}`"),
                ArgSpec("vehicle", "path", False, "", None, None,
                        "vehicle YAML (default the world scene's), as `load`'s"),
                _WORLD_POSE,
                ArgSpec("start", "object", False, "", None, None,
                        "its start at rest by road, s and lane of the world's OpenDRIVE "
                        "terrain (a `cars:` entry's `start:`), instead of `pose`",
                        LANE_ARGS),
                ArgSpec("driven_by", "choice", False, "", None, None,
                        "who drives it (default `client`): a client over zenoh, or the "
                        "built-in driver (docs/model.md section 15), which then needs "
                        "`driver`", choices=ADD_CAR_DRIVEN_BY),
                ArgSpec("driver", "block", False, "", None, None,
                        "with `driven_by: driver` only: the built-in driver's block, as a "
                        "`cars:` entry's `driver:` (path or OpenDRIVE lane, speed profile, "
                        "idm, stop_s_m, go_t_s; docs/configuration.md, `driver:` of a "
                        "scenario's car)"),
            ),
            reply='"car": id, "cars": [ids]',
            defaults={"driven_by": "client"},
        ),
        ControlSpec(
            "remove_car",
            "Take a car out of the running world between two ticks: its keys stop being "
            "served and its liveliness token goes; the other cars go on with their bits. "
            "The last car cannot be removed.",
            (ArgSpec("id", "name", True, "", None, None, "the car's id"),),
            reply='"car": id, "cars": [ids]',
        ),
        ControlSpec(
            "reset",
            "Every car back to its start, at rest, all in the same tick (each car's own "
            "`reset` without arguments: its tick restarts at 0, its log has the line), and "
            "the world's one clock (every state's `time_s`) back to 0; a car's own `reset` "
            "or `load` keeps the world's time. The "
            "cars' start states are made one car a tick beside the running world, then "
            "swapped in together; answered then (within about one tick per car).",
            reply='"cars": [ids]',
        ),
        ControlSpec(
            "get_config",
            "The world: its cars in the order of the world message, who drives each, "
            "`max_cars` and `world_hz`.",
            reply='"cars": [{"id": ..., "driven_by": ...}], "max_cars": n, "world_hz": hz',
        ),
    )
}
"""The world's controls (``{prefix}/world/ctl/{name}``, docs/protocol.md section 5.1)."""
assert tuple(WORLD_CONTROL_SPECS) == WORLD_CONTROL_NAMES


WORLD_HEADER_FIELDS: Final[tuple[FieldSpec, ...]] = (
    FieldSpec("version", "<u2", 1, "-", PROTOCOL_VERSION, PROTOCOL_VERSION,
              "protocol version"),
    FieldSpec("n_cars", "<u2", 1, "-", 0, 65535,
              "car records that follow the header (the payload is 24 + 80 n_cars bytes)"),
    FieldSpec("reserved", "<u4", 1, "-", 0, 0, "zero"),
    FieldSpec("tick", "<u8", 1, "-", None, None,
              "the world's tick: ticks of the server's clock since it started (a car's "
              "own VehicleState.tick restarts at its reset or load)"),
    FieldSpec("uptime_s", "<f8", 1, "s", 0.0, None, "wall time since the clock started"),
)

def _state_copy(name: str, dtype: str) -> FieldSpec:
    """A world car field copied from the VehicleState field ``name`` (its unit and meaning;
    ``dtype`` may be narrower)."""
    f = next(f for f in STATE_FIELDS if f.name == name)
    return FieldSpec(name, dtype, 1, f.unit, f.lo, f.hi, f"as VehicleState: {f.description}")


WORLD_CAR_FIELDS: Final[tuple[FieldSpec, ...]] = (
    FieldSpec("id", "u1", WORLD_ID_BYTES, "-", None, None,
              "the car's vehicle id, UTF-8, padded with NUL bytes (its keys: "
              "`{prefix}/{id}/...`)"),
    *(_state_copy(name, dtype) for name, dtype in (
        ("x_m", "<f8"), ("y_m", "<f8"), ("z_m", "<f8"), ("yaw_rad", "<f4"),
        ("pitch_rad", "<f4"), ("roll_rad", "<f4"), ("u_mps", "<f4"), ("v_mps", "<f4"),
        ("flags", "<u2"))),
    FieldSpec("driven_by", "u1", 1, "-", 0, len(DRIVEN_BY_CODES) - 1,
              "who drives it: " + ", ".join(f"{k} = {name}"
                                             for k, name in enumerate(DRIVEN_BY_CODES))),
    FieldSpec("reserved", "u1", 1, "-", 0, 0, "zero"),
)
"""One car of the world message; the values are those of the car's newest VehicleState
published (the same bits, ``yaw``/``pitch``/``roll`` narrowed to f32)."""

WORLD_HEADER_DTYPE: Final[np.dtype] = _make_dtype(WORLD_HEADER_FIELDS)
WORLD_CAR_DTYPE: Final[np.dtype] = _make_dtype(WORLD_CAR_FIELDS)
WORLD_HEADER_SIZE: Final[int] = WORLD_HEADER_DTYPE.itemsize
WORLD_CAR_SIZE: Final[int] = WORLD_CAR_DTYPE.itemsize
assert WORLD_HEADER_SIZE == 24 and WORLD_CAR_SIZE == 80  # 8-byte aligned records
WORLD_STATE_COPIED: Final[tuple[str, ...]] = tuple(
    f.name for f in WORLD_CAR_FIELDS if f.name not in ("id", "driven_by", "reserved"))
"""The car fields copied from the car's VehicleState record, by name."""


def car_id_field(car_id: str) -> np.ndarray:
    """A car id as the world message's ``id`` field (``ProtocolError`` if too long)."""
    raw = validate_vehicle_id(car_id).encode()
    if len(raw) > WORLD_ID_BYTES:
        raise ProtocolError("vehicle", f"{car_id!r} is longer than {WORLD_ID_BYTES} bytes, "
                                       "the world message's id field")
    out = np.zeros(WORLD_ID_BYTES, dtype=np.uint8)
    out[:len(raw)] = np.frombuffer(raw, dtype=np.uint8)
    return out


class WorldBuffer:
    """The world message of up to ``capacity`` cars, filled in place (the server's tick:
    no allocation but the bytes it publishes)."""

    def __init__(self, capacity: int) -> None:
        self.buffer = np.zeros(WORLD_HEADER_SIZE + capacity * WORLD_CAR_SIZE, dtype=np.uint8)
        self.header = self.buffer[:WORLD_HEADER_SIZE].view(WORLD_HEADER_DTYPE)[0:1]
        self.cars = self.buffer[WORLD_HEADER_SIZE:].view(WORLD_CAR_DTYPE)
        self.header["version"] = PROTOCOL_VERSION
        self.n_cars = 0

    def set_cars(self, ids: Sequence[str], driven_by: Sequence[str]) -> None:
        """The cars of the message, in order (between ticks: when the world changes)."""
        if len(ids) > self.cars.size:
            raise ValueError(f"{len(ids)} cars, more than this buffer's {self.cars.size}")
        self.cars[:] = 0
        for k, (car_id, who) in enumerate(zip(ids, driven_by, strict=True)):
            self.cars["id"][k] = car_id_field(car_id)
            self.cars["driven_by"][k] = DRIVEN_BY_CODES.index(who)
        self.n_cars = len(ids)
        self.header["n_cars"] = self.n_cars

    def fill_from(self, states: np.ndarray) -> None:
        """The cars' poses and speeds from their VehicleState records ``states`` (the
        first ``n_cars`` rows, in the cars' order), a few vectorised copies; a car whose
        record is not finite keeps the values it had (nothing non-finite is published)."""
        n = self.n_cars
        rows = states[:n]
        ok = np.ones(n, dtype=bool)
        for name in WORLD_STATE_COPIED:
            if rows.dtype[name].kind == "f":
                ok &= np.isfinite(rows[name])
        cars = self.cars[:n]
        for name in WORLD_STATE_COPIED:
            column = cars[name]
            column[ok] = rows[name][ok]

    def payload(self, tick: int, uptime_s: float) -> bytes:
        """The message's bytes, with the header's ``tick`` and ``uptime_s``."""
        self.header["tick"] = tick
        self.header["uptime_s"] = uptime_s
        return self.buffer[:WORLD_HEADER_SIZE + self.n_cars * WORLD_CAR_SIZE].tobytes()


COLLISION_FIELDS: Final[tuple[FieldSpec, ...]] = (
    FieldSpec("version", "<u2", 1, "-", PROTOCOL_VERSION, PROTOCOL_VERSION,
              "protocol version"),
    FieldSpec("reserved", "<u2", 1, "-", 0, 0, "zero"),
    FieldSpec("lost", "<u4", 1, "-", None, None,
              "contact events the server did not read before this one, since it started "
              "(the world's ring of 64 overwritten between two ticks; as "
              "Diagnostics.contact_events_lost)"),
    FieldSpec("seq", "<u8", 1, "-", 1, None,
              "the event's number in the world, 1, 2, ... (a gap of lost events is "
              "counted in `lost`; restarts at 1 when the world is rebuilt)"),
    FieldSpec("tick", "<u8", 1, "-", None, None,
              "the world's tick (as WorldState.tick) when the server read the event: the "
              "tick of the step the bodies met"),
    FieldSpec("sim_time_s", "<f8", 1, "s", 0.0, None,
              "car_a's simulated time at the start of the step the bodies met (its "
              "VehicleState.sim_time_s clock)"),
    FieldSpec("closing_speed_mps", "<f8", 1, "m/s", 0.0, None,
              "how fast the contact point closed along the contact normal as they met"),
    FieldSpec("x_m", "<f8", 1, "m", None, None,
              "the contact point: road plane axes on the plane terrain, the horizontal "
              "world axes on a height map (docs/model.md section 16)"),
    FieldSpec("y_m", "<f8", 1, "m", None, None, "the contact point, as x_m"),
    FieldSpec("car_a", "u1", WORLD_ID_BYTES, "-", None, None,
              "one car's vehicle id, UTF-8, padded with NUL bytes (as WorldState's `id`)"),
    FieldSpec("car_b", "u1", WORLD_ID_BYTES, "-", None, None, "the other car's id"),
)
"""A contact event: two cars' bodies started to touch (``{prefix}/world/collision``)."""

COLLISION_DTYPE: Final[np.dtype] = _make_dtype(COLLISION_FIELDS)
COLLISION_SIZE: Final[int] = COLLISION_DTYPE.itemsize
assert COLLISION_SIZE == 120  # 8-byte aligned


def encode_collision(*, seq: int, tick: int, sim_time_s: float, car_a: str, car_b: str,
                     closing_speed_mps: float, x_m: float, y_m: float,
                     lost: int = 0) -> bytes:
    """A Collision message (``ProtocolError`` naming the field for a non-finite value or
    an id too long): nothing non-finite is published."""
    rec = np.zeros((), dtype=COLLISION_DTYPE)
    rec["version"] = PROTOCOL_VERSION
    for name, value in (("sim_time_s", sim_time_s), ("closing_speed_mps", closing_speed_mps),
                        ("x_m", x_m), ("y_m", y_m)):
        if not math.isfinite(value):
            raise ProtocolError(name, f"{value} is not finite")
        rec[name] = value
    rec["seq"], rec["tick"], rec["lost"] = seq, tick, min(int(lost), 0xFFFFFFFF)
    rec["car_a"], rec["car_b"] = car_id_field(car_a), car_id_field(car_b)
    return rec.tobytes()


def decode_collision(payload: bytes | bytearray | memoryview) -> dict[str, Any]:
    """A Collision message as a dict (the ids as text); ``ProtocolError`` for a payload of
    the wrong size or version."""
    if len(payload) != COLLISION_SIZE:
        raise ProtocolError("payload", f"Collision is {COLLISION_SIZE} bytes, got "
                                       f"{len(payload)}")
    rec = np.frombuffer(bytes(payload), dtype=COLLISION_DTYPE)[0]
    if rec["version"] != PROTOCOL_VERSION:
        raise ProtocolError("version", f"{int(rec['version'])} is not the supported version "
                                       f"{PROTOCOL_VERSION}")
    out: dict[str, Any] = {f.name: rec[f.name].item() for f in COLLISION_FIELDS
                           if f.count == 1}
    for name in ("car_a", "car_b"):
        out[name] = bytes(rec[name]).rstrip(b"\0").decode()
    return out


@dataclass(frozen=True)
class WorldState:
    """A decoded world message: the header's ``tick`` and ``uptime_s``, the cars' records
    (``cars["x_m"]``, ...) and their ids as text."""

    tick: int
    uptime_s: float
    ids: tuple[str, ...]
    cars: np.ndarray  # WORLD_CAR_DTYPE[n_cars]

    def car(self, car_id: str) -> np.void | None:
        """The record of car ``car_id``, or None if the world has no such car."""
        return self.cars[self.ids.index(car_id)] if car_id in self.ids else None


def encode_world(tick: int, uptime_s: float, cars: Sequence[Mapping[str, Any]]) -> bytes:
    """A world message from plain values (tools, tests): each car a mapping with ``id``,
    ``driven_by`` (a name of :data:`DRIVEN_BY_CODES`) and every copied field."""
    buf = WorldBuffer(len(cars))
    buf.set_cars([c["id"] for c in cars], [c["driven_by"] for c in cars])
    states = np.zeros(len(cars), dtype=STATE_DTYPE)
    for k, c in enumerate(cars):
        for name in WORLD_STATE_COPIED:
            states[name][k] = c[name]
    buf.fill_from(states)
    return buf.payload(tick, uptime_s)


def decode_world(payload: bytes | bytearray | memoryview) -> WorldState:
    """Decode a WorldState payload.

    Raises
    ------
    ProtocolError
        A size that is not 24 + 80 n_cars bytes for the header's ``n_cars``, another
        ``version``, a non-zero reserved field, an id that is not a vehicle id, or a
        ``driven_by`` code out of range.
    """
    try:
        raw = np.frombuffer(payload, dtype=np.uint8)
    except (TypeError, ValueError, BufferError):
        raise ProtocolError("payload", f"expected bytes, got {type(payload).__name__}") from None
    if raw.size < WORLD_HEADER_SIZE:
        raise ProtocolError("payload", f"WorldState is at least {WORLD_HEADER_SIZE} bytes, "
                                       f"got {raw.size}")
    header = raw[:WORLD_HEADER_SIZE].view(WORLD_HEADER_DTYPE)[0]
    if header["version"] != PROTOCOL_VERSION:
        raise ProtocolError("version", f"{int(header['version'])} is not the supported "
                                       f"version {PROTOCOL_VERSION}")
    n = int(header["n_cars"])
    if raw.size != WORLD_HEADER_SIZE + n * WORLD_CAR_SIZE:
        raise ProtocolError("payload", f"WorldState of {n} cars is "
                                       f"{WORLD_HEADER_SIZE + n * WORLD_CAR_SIZE} bytes, got "
                                       f"{raw.size}")
    if header["reserved"] != 0:
        raise ProtocolError("reserved", "must be zero")
    cars = raw[WORLD_HEADER_SIZE:].copy().view(WORLD_CAR_DTYPE)
    ids = []
    for k in range(n):
        text = bytes(cars[k]["id"]).rstrip(b"\0")
        try:
            ids.append(validate_vehicle_id(text.decode("ascii")))
        except (UnicodeDecodeError, ProtocolError):
            raise ProtocolError(f"cars[{k}].id", f"not a vehicle id: {text!r}") from None
        if cars[k]["driven_by"] >= len(DRIVEN_BY_CODES) or cars[k]["reserved"] != 0:
            raise ProtocolError(f"cars[{k}].driven_by", "unknown code or reserved not zero")
    return WorldState(tick=int(header["tick"]), uptime_s=float(header["uptime_s"]),
                      ids=tuple(ids), cars=cars)


# ============================================================================ docs


def _num(x: float) -> str:
    """Format a range bound: integers in full, other numbers with up to 6 digits."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:.6g}"


def _range_text(f: FieldSpec) -> str:
    if f.name == "version":
        return f"= {PROTOCOL_VERSION}"
    if f.lo is None and f.hi is None:
        return "any" if f.dtype.lstrip("<").startswith("f") else "all"
    lo = "-inf" if f.lo is None else _num(f.lo)
    hi = "+inf" if f.hi is None else _num(f.hi)
    if f.lo == f.hi:
        return f"= {lo}"
    return f"[{lo}, {hi}]"


_TYPE_NAMES = {"u1": "u8", "i1": "i8", "u2": "u16", "u4": "u32", "u8": "u64", "f4": "f32",
               "f8": "f64"}


def _source_text(f: FieldSpec) -> str:
    kind, name = state_source(f)
    return f"{kind} `{name}`" if name else (kind or "-")


def _recorded_text(f: FieldSpec) -> str:
    if not f.source:
        return "-"
    if f.history is not None:
        return f"`{f.history}` (history)"
    return f"`{f.name}_{{w}}`" if f.count > 1 else f"`{f.name}`"


def fields_markdown(fields: Sequence[FieldSpec], *, with_rule: bool = False,
                    with_source: bool = False) -> str:
    """Markdown table of a payload: offset, field, type, unit, range (and decode rule; or
    a state field's source and the column it is recorded as)."""
    dt = _make_dtype(fields)
    head = "| offset | field | type | unit | range | description |"
    sep = "|---:|---|---|---|---|---|"
    if with_rule:
        head += " on decode |"
        sep += "---|"
    if with_source:
        head += " source | recorded as |"
        sep += "---|---|"
    rows = [head, sep]
    for f in fields:
        t = _TYPE_NAMES[f.dtype.lstrip("<")]
        if f.count > 1:
            t = f"{t}[{f.count}]"
        row = (f"| {dt.fields[f.name][1]} | `{f.name}` | {t} | {f.unit} | {_range_text(f)} "
               f"| {f.description} |")
        if with_rule:
            row += f" {f.rule} |"
        if with_source:
            row += f" {_source_text(f)} | {_recorded_text(f)} |"
        rows.append(row)
    rows.append(f"\nTotal: **{dt.itemsize} bytes**, little-endian, no padding between fields.")
    return "\n".join(rows)


def keys_markdown() -> str:
    """Markdown table of every key expression of a vehicle."""
    rows = [
        "| key | direction | payload | encoding | QoS | rate |",
        "|---|---|---|---|---|---|",
    ]
    for k in KEY_SPECS:
        rows.append(
            f"| `{{prefix}}/{{vehicle}}/{k.suffix}` | {k.direction} | {k.payload} "
            f"| `{k.encoding}` | {k.qos} | {k.rate} |"
        )
    return "\n".join(rows)


def world_keys_markdown() -> str:
    """Markdown table of the world's key expressions."""
    rows = ["| key | direction | payload | encoding | QoS | rate |",
            "|---|---|---|---|---|---|"]
    for k in WORLD_KEY_SPECS:
        rows.append(f"| `{{prefix}}/{WORLD_KEY}/{k.suffix}` | {k.direction} | {k.payload} "
                    f"| `{k.encoding}` | {k.qos} | {k.rate} |")
    return "\n".join(rows)


def _arg_rows(args: Sequence[ArgSpec], prefix: str = "") -> list[str]:
    rows = []
    for a in args:
        name = f"{prefix}{a.name}"
        if a.kind in ("number", "integer"):
            rng = f"[{_num(a.lo)}, {_num(a.hi)}]"
        elif a.kind == "path":
            rng = f"string ending {'/'.join(_path_suffixes(a))}, at most {_MAX_PATH} chars"
        elif a.kind == "name":
            rng = f"string, at most {_MAX_NAME} printable chars"
        elif a.kind == "choice":
            rng = "one of " + ", ".join(f"`{c}`" for c in a.choices)
        elif a.kind == "block":
            rng = "object (checked by the server, as the YAML block)"
        else:
            rng = "object"
        req = "required" if a.required else "optional"
        rows.append(f"| `{name}` | {a.kind} | {req} | {a.unit or '-'} | {rng} | {a.description} |")
        rows.extend(_arg_rows(a.children, prefix=f"{name}."))
    return rows


def controls_markdown(specs: Mapping[str, ControlSpec] | None = None,
                      key: str = "ctl") -> str:
    """Markdown description of every control (of ``specs``, default the car's):
    arguments and reply fields."""
    out = []
    for spec in (CONTROL_SPECS if specs is None else specs).values():
        out.append(f"#### `{key}/{spec.name}`\n\n{spec.description}\n")
        if spec.args:
            extra = " At least one argument is required." if spec.at_least_one else ""
            out.append(f"Arguments (unknown keys are rejected).{extra}\n")
            out.append("| argument | type | presence | unit | range | description |")
            out.append("|---|---|---|---|---|---|")
            out.extend(_arg_rows(spec.args))
            out.append("")
        else:
            out.append("Arguments: none (empty payload or `{}`).\n")
        out.append(f'Reply on success: `{{"ok": true, {spec.reply}}}`\n')
    return "\n".join(out).rstrip() + "\n"


def constants_markdown() -> str:
    """Markdown list of the protocol constants."""
    return "\n".join(
        [
            f"- `PROTOCOL_VERSION` = {PROTOCOL_VERSION}",
            f"- DriverCommand: {COMMAND_SIZE} bytes; VehicleState: {STATE_SIZE} bytes; "
            f"Diagnostics: {DIAGNOSTICS_SIZE} bytes",
            f"- clamp tolerance for normalised inputs: {CLAMP_TOLERANCE:g}",
            f"- largest control request: {MAX_CONTROL_PAYLOAD_BYTES} bytes",
            f"- command receive ring: the server keeps the last {COMMAND_RING_SLOTS} "
            f"commands (`COMMAND_RING_SLOTS`) that arrived since its previous tick",
            f"- default prefix `{DEFAULT_PREFIX}`, default vehicle id `{DEFAULT_VEHICLE}`",
            f"- WorldState: {WORLD_HEADER_SIZE} + {WORLD_CAR_SIZE} bytes per car; a car id "
            f"at most {WORLD_ID_BYTES} bytes; `{WORLD_KEY}` is no vehicle id",
            f"- Collision: {COLLISION_SIZE} bytes",
        ]
    )


def doc_sections() -> dict[str, str]:
    """The generated sections of docs/protocol.md, by marker name."""
    return {
        "constants": constants_markdown(),
        "keys": keys_markdown(),
        "command": fields_markdown(COMMAND_FIELDS, with_rule=True),
        "state": fields_markdown(STATE_FIELDS, with_source=True),
        "diagnostics": fields_markdown(DIAGNOSTICS_FIELDS),
        "controls": controls_markdown(),
        "world_keys": world_keys_markdown(),
        "world_header": fields_markdown(WORLD_HEADER_FIELDS),
        "world_car": fields_markdown(WORLD_CAR_FIELDS),
        "collision": fields_markdown(COLLISION_FIELDS),
        "world_controls": controls_markdown(WORLD_CONTROL_SPECS, f"{WORLD_KEY}/ctl"),
    }


_SECTION = re.compile(
    r"(<!-- BEGIN GENERATED: (?P<name>[a-z_]+) -->\n)(?P<body>.*?)(<!-- END GENERATED -->)",
    re.DOTALL,
)


def update_doc(text: str) -> str:
    """Return ``text`` with every generated section replaced by the current tables.

    Raises
    ------
    ValueError
        When a section marker names no known section or a section is missing.
    """
    sections = doc_sections()
    seen = set()

    def sub(m: re.Match) -> str:
        name = m.group("name")
        if name not in sections:
            raise ValueError(f"unknown generated section {name!r}")
        seen.add(name)
        return f"{m.group(1)}{sections[name].rstrip()}\n{m.group(4)}"

    new = _SECTION.sub(sub, text)
    missing = set(sections) - seen
    if missing:
        raise ValueError(f"sections missing from the document: {sorted(missing)}")
    return new


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m simserver.wire.protocol [--check|--write] PATH``: check or regenerate a doc."""
    import argparse

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("path")
    parser.add_argument("--write", action="store_true", help="rewrite the generated sections")
    args = parser.parse_args(argv)
    with open(args.path, encoding="utf-8") as fh:
        text = fh.read()
    new = update_doc(text)
    if args.write:
        if new != text:
            with open(args.path, "w", encoding="utf-8") as fh:
                fh.write(new)
        return 0
    if new != text:
        print(f"{args.path} is out of date: run python -m simserver.wire.protocol --write "
              f"{args.path}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
