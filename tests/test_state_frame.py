"""The states of a live world's cars filled in one go (simserver.server.state_frame): the
same bytes as each car's own field-by-field fill (``VehicleSlot.fill_state``), for every
car, on a terrain (the pose from the reference plane under the wheels) and on an inclined
plane (the pose from the road plane), driven, steered, braked, with the built-in driver's
cars among them; and the loop that uses it publishes the same states as each car filling
its own."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from simserver.core import layout as L
from simserver.core.contact import CC_ACTIVE, CC_FORCE_X_N, CC_FORCE_Y_N
from simserver.server import fleet
from simserver.server.config import REPO_CONFIGS, load_server_config
from simserver.server.state_frame import GROUPS, StateFrame
from simserver.sim.scene import load_scene
from simserver.wire import protocol as proto
from simserver.wire.state_schema import FILL

pytestmark = pytest.mark.timeout(600)

CARS = {
    "crest_curve_paper_sedan": [
        {"id": "car0", "start": {"road": "0", "s": 150.0, "lane": -1}},
        {"id": "car1", "start": {"road": "0", "s": 200.0, "lane": 1},
         "vehicle": str(REPO_CONFIGS / "vehicles" / "mf_hatchback" / "vehicle.yaml")},
        {"id": "t2", "start": {"road": "0", "s": 120.0, "lane": -1}, "driven_by": "driver",
         "driver": {"path": {"road": "0", "lane": -1}, "idm": {"v0_mps": 12.0}}}],
    "hill_10pct_paper_sedan": [
        {"id": "car0", "pose": {"x_m": 40.0, "y_m": 0.0, "yaw_rad": 0.0}},
        {"id": "car1", "pose": {"x_m": 0.0, "y_m": 6.0, "yaw_rad": 0.3}},
        {"id": "t2", "pose": {"x_m": 10.0, "y_m": 0.0, "yaw_rad": 0.0}, "driven_by": "driver",
         "driver": {"path": {"points": [[-50.0, 0.0], [2000.0, 0.0]]}}}],
}


def _cars(tmp_path: Path, scene: str) -> tuple[object, list]:
    path = tmp_path / f"{scene}.yaml"
    path.write_text(json.dumps({"scene": str(REPO_CONFIGS / "scenes" / f"{scene}.yaml"),
                                "viewer": "off", "cars": CARS[scene]}))
    cfg = load_server_config(path)
    return cfg, fleet.make_cars(cfg, load_scene(cfg.scene))


def test_every_copied_field_has_its_bytes_once():
    """The groups' byte indices cover every copied field's bytes exactly once."""
    fields = proto.STATE_DTYPE.fields
    want = sorted(b for f, _, _ in FILL for b in range(
        fields[f][1], fields[f][1] + fields[f][0].itemsize))
    got = sorted(int(b) for g in GROUPS for b in g.byte_index)
    assert got == want


@pytest.mark.parametrize("scene", list(CARS))
def test_frame_bytes_are_each_cars_own_fill(tmp_path, scene):
    cfg, served = _cars(tmp_path, scene)
    slots = [car.slot for car in served]
    world = slots[0].sim.world
    assert list(world.ids) == [s.keys.vehicle for s in slots]
    live = fleet.prepare_drivers(served)
    drivers = live.assemble(world)
    from simserver.core.driver import drive

    frame = StateFrame()
    frame.bind(slots)
    own = [proto.new_state_record() for _ in slots]
    compared = 0
    contacts = world.data.contacts.car
    seen_flags, not_finite, touched, held_patterns = 0, 0, 0, set()
    for k in range(2200):
        for j, slot in enumerate(slots[:2]):  # the clients' inputs
            inputs = slot.sim.inputs
            # driven, then braked to rest, then held by the parking brake alone (car0)
            # or by gear P's park lock (car1)
            inputs[L.IN_GEAR] = L.GEAR_P if j == 1 and k >= 1800 else L.GEAR_D
            inputs[L.IN_THROTTLE] = 0.5 if k < 1000 else 0.0
            inputs[L.IN_BRAKE] = 0.0 if k < 1000 or k >= 1800 else 0.7
            inputs[L.IN_PARKING_BRAKE] = 1.0 if j == 0 and k >= 1700 else 0.0
            inputs[L.IN_STEER] = 0.2 * math.sin(k * 0.004 + j)
        drive(world.model, world.data, drivers)
        for slot in slots:
            slot.advance(step=False)
        world.step()
        if k % 7:
            continue
        rows = np.arange(len(slots), dtype=np.int64)[k % 2::2] if k % 3 else \
            np.arange(len(slots), dtype=np.int64)  # some cars publish, or all
        # the rules' other inputs, set on the rows the fill reads and put back after:
        # a car-to-car contact (the step's contact output), the hill-hold assist's
        # state, and a contact force that is not finite (the state is then not published)
        saved = contacts.copy(), world.data.x.copy()
        c_touch = k // 7 % len(slots)
        if k % 5 == 0:
            contacts[c_touch, CC_ACTIVE] = 1.0
            contacts[c_touch, CC_FORCE_X_N] = 812.5 + k
            contacts[c_touch, CC_FORCE_Y_N] = -97.25
        if k % 11 == 0:
            world.data.x[c_touch, L.HILL_HOLD_ACTIVE] = 1.0
        if k % 13 == 0:
            contacts[c_touch, CC_FORCE_Y_N] = math.inf
        frame.fill(world, rows)
        for c in rows:
            slot = slots[c]
            view = slot.record
            got = slot.fill_state(1_000_000 * k, k % 3 == 0, frame, c)
            slot.record = own[c]  # the car's own record, filled field by field
            want = slot.fill_state(1_000_000 * k, k % 3 == 0)
            assert bool(frame.pose_ok[c]) is slot._pose_finite(), (scene, k, c)
            slot.record = view
            assert got == want, (scene, k, slot.keys.vehicle, [
                name for name in proto.STATE_DTYPE.names
                if np.frombuffer(got, proto.STATE_DTYPE)[name].tobytes()
                != np.frombuffer(want, proto.STATE_DTYPE)[name].tobytes()])
            rec = np.frombuffer(got, proto.STATE_DTYPE)[0]
            seen_flags |= int(rec["flags"])
            not_finite += not frame.pose_ok[c]
            touched += int(rec["car_contact"])
            held_patterns.add(tuple(int(v) for v in rec["brake_held"]))
            compared += 1
        contacts[:], world.data.x[:] = saved
    assert compared >= 2 * len(range(0, 2200, 7))
    # the comparison saw every rule at work: wheels held by the pedal and by the parking
    # brake alone (the rear ones), the hill-hold flag, a contact, and a state whose
    # contact force is not finite
    assert {(1, 1, 1, 1), (0, 0, 1, 1)} <= held_patterns, held_patterns
    assert seen_flags & proto.StateFlag.BRAKE_HOLD and seen_flags & proto.StateFlag.HILL_HOLD
    assert touched > 0 and not_finite > 0
    speeds = np.frombuffer(got, proto.STATE_DTYPE)["u_mps"]
    assert speeds[0] > 1.0  # the last car moved: the comparison saw a driven world


def test_the_loop_publishes_what_each_car_filling_its_own_publishes(tmp_path):
    """The live loop's states with the frame and without it (``state_frame`` off: each
    car fills its own, as before the frame), over a world's ticks with commands."""
    from benchmarks.state_wire_digest import _Clock, _Controls, _Inbox
    from simserver.server.loop import ServerLoop, SlotPorts

    published: dict[bool, list[bytes]] = {}
    for use_frame in (True, False):
        cfg, served = _cars(tmp_path, "crest_curve_paper_sedan")
        clock = _Clock()
        loop = ServerLoop(cfg, clock=clock, sleep=clock.sleep, spin_ns=0)
        loop.live_drivers = fleet.prepare_drivers(served)
        out: list[bytes] = []

        class Pub:
            slow_publishes = 0

            def publish_state(self, payload: bytes, out=out) -> None:
                out.append(payload)

            def publish_diagnostics(self, payload: bytes) -> None:
                pass

        inboxes = {}
        for car in served:
            inboxes[car.slot.keys.vehicle] = _Inbox()
            loop.add(car.slot, SlotPorts(inboxes[car.slot.keys.vehicle], _Controls(), Pub()))
        assert (loop.state_frame is not None) is True
        if not use_frame:
            loop.state_frame = None
            for car in served:
                car.slot.record = car.slot.record.copy()
        loop.world_message = fleet.world_message_for(served, dataclasses.replace(cfg))
        loop.publish_world = out.append
        loop.start()
        for k in range(600):
            inboxes["car0"].pending.append(proto.encode_command(
                seq=k + 1, sender_time_ns=k, gear=proto.Gear.D, throttle=0.4,
                steer=0.1 * math.sin(k * 0.01)))
            loop.tick()
        published[use_frame] = out
    assert len(published[True]) > 600
    assert published[True] == published[False]
