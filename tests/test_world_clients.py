"""Seeing the other cars from a client (clients.world): the neighbours' geometry, and
the cars discovered and seen live."""

from __future__ import annotations

import math

import pytest

from clients import world as cw
from simserver.wire import protocol as proto


def _car(car_id: str, x: float, y: float = 0.0, yaw: float = 0.0, u: float = 0.0,
         v: float = 0.0) -> dict:
    return dict(id=car_id, driven_by="client", x_m=x, y_m=y, z_m=0.0, yaw_rad=yaw,
                pitch_rad=0.0, roll_rad=0.0, u_mps=u, v_mps=v, flags=0)


def _world(*cars: dict) -> proto.WorldState:
    return proto.decode_world(proto.encode_world(1, 0.001, list(cars)))


def test_nearest_ahead_and_behind_with_closing_speeds():
    w = _world(_car("me", 0.0, u=10.0), _car("far", 50.0, u=10.0), _car("lead", 20.0, u=8.0),
               _car("tail", -15.0, u=12.0), _car("beside", 5.0, y=3.5, u=0.0))
    ahead, behind = cw.neighbours(w, "me")
    assert ahead == cw.Neighbour("lead", 20.0, 2.0)  # 10 - 8: the gap shrinks by 2 m/s
    assert behind == cw.Neighbour("tail", 15.0, 2.0)  # 12 - 10
    assert "lead 20.0 m, closing +2.0 m/s" in cw.traffic_text(w, "me")


def test_heading_and_lateral_velocity_are_projected():
    yaw = math.radians(30.0)
    c, s = math.cos(yaw), math.sin(yaw)
    # a car 12 m ahead along a 30 degree heading, standing; me at 5 m/s, sliding 1 m/s left
    w = _world(_car("me", 0.0, yaw=yaw, u=5.0, v=1.0), _car("stop", 12 * c, 12 * s, yaw=1.0))
    ahead, behind = cw.neighbours(w, "me")
    assert behind is None
    assert ahead.id == "stop"
    assert ahead.distance_m == pytest.approx(12.0, abs=1e-5)  # f8 positions, f4 yaw
    assert ahead.closing_mps == pytest.approx(5.0, abs=1e-5)  # v is across the heading


def test_alone_or_absent():
    assert cw.neighbours(_world(_car("a", 0.0)), "a") == (None, None)
    assert cw.neighbours(_world(_car("a", 0.0), _car("b", 10.0)), "zz") == (None, None)
    assert cw.traffic_text(_world(_car("a", 0.0)), "a") == ""
    assert cw.traffic_text(None, "a") == ""


def test_alive_keys_to_car_ids():
    assert cw.car_of_alive_key("sim/car0/alive", "sim") == "car0"
    assert cw.car_of_alive_key("lab/sim/lead/alive", "lab/sim") == "lead"
    assert cw.car_of_alive_key("sim/car0/alive/abc123", "sim") is None
    assert cw.car_of_alive_key("other/car0/alive", "sim") is None
