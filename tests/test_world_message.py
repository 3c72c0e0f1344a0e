"""The world message (``{prefix}/world/state``, simserver.wire.protocol WorldState): layout,
round trip, rejection of malformed payloads, nothing non-finite published."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from simserver.wire import protocol as proto


def _car(car_id: str, x: float, driven_by: str = "client", **extra) -> dict:
    values = dict(id=car_id, driven_by=driven_by, x_m=x, y_m=-2.0, z_m=0.5, yaw_rad=0.25,
                  pitch_rad=-0.01, roll_rad=0.02, u_mps=12.5, v_mps=-0.1, flags=3)
    values.update(extra)
    return values


def test_layout_read_with_struct_not_numpy():
    """An independent decoder (struct, the documented offsets) reads what encode wrote."""
    payload = proto.encode_world(77, 1.25, [_car("car0", 1.5), _car("lead", 30.0,
                                                                   "keyframes")])
    assert len(payload) == 24 + 2 * 80
    version, n, reserved, tick, uptime = struct.unpack_from("<HHIQd", payload, 0)
    assert (version, n, reserved, tick, uptime) == (proto.PROTOCOL_VERSION, 2, 0, 77, 1.25)
    for k, (name, x, code) in enumerate((("car0", 1.5, 0), ("lead", 30.0, 1))):
        rec = struct.unpack_from("<32sddd5fHBB", payload, 24 + 80 * k)
        assert rec[0].rstrip(b"\0").decode() == name
        assert rec[1:4] == (x, -2.0, 0.5)
        assert rec[4] == pytest.approx(0.25) and rec[7] == 12.5
        assert rec[9:] == (3, code, 0)


def test_round_trip_and_lookup_by_id():
    w = proto.decode_world(proto.encode_world(5, 0.5, [_car("a", 1.0), _car("b.2", -4.0)]))
    assert w.ids == ("a", "b.2") and w.tick == 5
    assert w.car("b.2")["x_m"] == -4.0 and w.car("zz") is None
    empty = proto.decode_world(proto.encode_world(0, 0.0, []))
    assert empty.ids == () and empty.cars.size == 0


@pytest.mark.parametrize(("mutate", "field"), [
    (lambda b: b[:-1], "payload"),
    (lambda b: b[:10], "payload"),
    (lambda b: b + bytes(80), "payload"),
    (lambda b: b"\x09\x00" + b[2:], "version"),
    (lambda b: b[:4] + b"\x01" + b[5:], "reserved"),
    (lambda b: b[:24] + b"a*" + b[26:], "cars[0].id"),
    (lambda b: b[:24] + bytes(32) + b[56:], "cars[0].id"),
    (lambda b: b[:24 + 78] + b"\x07" + b[24 + 79:], "cars[0].driven_by"),
])
def test_malformed_payloads_are_named(mutate, field):
    good = proto.encode_world(1, 0.0, [_car("car0", 0.0)])
    with pytest.raises(proto.ProtocolError) as err:
        proto.decode_world(mutate(bytearray(good)))
    assert err.value.field == field


def test_a_non_finite_car_keeps_its_last_finite_values():
    buf = proto.WorldBuffer(4)
    buf.set_cars(["a", "b"], ["client", "client"])
    states = np.zeros(4, dtype=proto.STATE_DTYPE)
    states["x_m"][:2] = (1.0, 2.0)
    buf.fill_from(states)
    states["x_m"][:2] = (3.0, np.nan)
    states["u_mps"][0] = np.inf
    states["u_mps"][1] = 7.0
    buf.fill_from(states)
    w = proto.decode_world(buf.payload(2, 0.002))
    assert w.cars["x_m"].tolist() == [1.0, 2.0]  # both rows held a non-finite value
    states["u_mps"][0] = 4.0
    buf.fill_from(states)
    w = proto.decode_world(buf.payload(3, 0.003))
    assert w.cars["x_m"].tolist() == [3.0, 2.0] and w.cars["u_mps"].tolist() == [4.0, 0.0]


def test_world_keys_and_ids():
    keys = proto.world_keys("lab/sim")
    assert keys.state == "lab/sim/world/state" and keys.alive_all == "lab/sim/*/alive"
    with pytest.raises(proto.ProtocolError):
        proto.world_keys("bad*")
    with pytest.raises(proto.ProtocolError, match="longer than 32"):
        proto.car_id_field("x" * 33)
    with pytest.raises(ValueError, match="more than"):
        proto.WorldBuffer(1).set_cars(["a", "b"], ["client", "client"])
