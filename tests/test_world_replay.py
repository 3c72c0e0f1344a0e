"""A multi-car session replayed from every car's command log in one world, bit for bit
(issue 30 item 4), in-process: the real loop, slots, world desk and built-in driver on a
fake clock (the rig of tests/test_multicar_logic.py), every car's real command log, then
``simserver.server.world_replay.replay_world`` on the files.

The session has what a car's log alone cannot replay: a client's car driven into the
back of a car of the built-in driver (a contact: each car's motion depends on the
other's), a car stopped alone by a non-finite state and held while the others step, a
car added and one removed while the world runs, a world reset and a road change."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from test_multicar_logic import FLAT, WorldRig
from test_server_logic import ListControls, ListInbox, LocalRequest, RecordingPublisher

from simserver.adapters.validate import ConfigError
from simserver.core import layout as L
from simserver.server import cars_config
from simserver.server.command_log import CommandLog, replay_command_log
from simserver.server.live_drivers import LiveDrivers
from simserver.server.loop import SlotPorts
from simserver.server.world_replay import replay_world
from simserver.sim.scene import load_scene
from simserver.wire import protocol as proto

pytestmark = pytest.mark.timeout(300)

DRIVER = {"path": {"points": [[-50.0, 0.0], [2000.0, 0.0]]},
          "idm": {"v0_mps": 1.5, "T_s": 2.0, "s0_m": 1.0}}
CARS = [{"id": "a", "pose": {"x_m": 0.0, "y_m": 0.0, "yaw_rad": 0.0}},
        {"id": "b", "pose": {"x_m": 0.0, "y_m": 6.0, "yaw_rad": 0.0}},
        {"id": "t", "pose": {"x_m": 9.0, "y_m": 0.0, "yaw_rad": 0.0},
         "driven_by": "driver", "driver": DRIVER}]


@pytest.fixture(scope="module")
def flat_scene():
    return load_scene(FLAT)


def _drive_by_driver(rig: WorldRig, car_id: str, entry: dict) -> None:
    """Make ``car_id`` a car of the built-in driver, as ``fleet.make_cars`` and
    ``fleet.prepare_drivers`` do for ``driven_by: driver``."""
    spec, = cars_config.parse_cars(Path(FLAT), [entry])
    rig.slots[car_id].drive_by_driver()
    live = LiveDrivers()
    live.prepare(car_id, cars_config.driver_spec(spec, rig.scenes[car_id]),
                 rig.loop.world.model.terrain)
    rig.loop.live_drivers = live
    rig.loop.assemble_drivers()


def _world_session(flat_scene, tmp_path: Path) -> WorldRig:
    """The session (module docstring); every car's log closed as at a clean shutdown."""
    from simserver.server import fleet
    from simserver.server.world_desk import WorldDesk

    rig = WorldRig(flat_scene, CARS, tmp_path)
    rig.loop.world_message = fleet.WorldMessage(["a", "b", "t"], ["client", "client",
                                                                  "driver"], every=10,
                                                capacity=4)
    _drive_by_driver(rig, "t", CARS[2])
    controls = ListControls()

    def make_ports(cfg):
        rig.ports[cfg.vehicle_id] = SlotPorts(ListInbox(), ListControls(),
                                              RecordingPublisher())
        return rig.ports[cfg.vehicle_id]

    def added(slot):  # as SimServer._added: its log, then its start lines
        slot.command_log = CommandLog(tmp_path / f"{slot.keys.vehicle}.jsonl", {
            "scene": str(FLAT), "dt_s": rig.cfg.period_s, "step": 0})
        fleet.log_start(slot, cars_config.CarSpec(id=slot.keys.vehicle, where="",
                                                  vehicle=slot.sim.scene.vehicle.path))
        rig.slots[slot.keys.vehicle] = slot

    def removed(slot, ports):
        slot.command_log.close(slot.steps_total, slot.final_state)

    desk = WorldDesk(rig.loop, dataclasses.replace(rig.cfg, max_cars=4), controls,
                     make_ports, removed, on_added=added)
    rig.loop.world_desk = desk

    def ask(name, args=None):
        req = LocalRequest(name, json.dumps(args).encode() if args is not None else b"")
        controls.pending.append(req)
        for _ in range(500):
            rig.loop.tick()
            if req.body is not None:
                return req.answer
        raise AssertionError(f"{name}: no answer")

    try:
        _play(rig, ask)
    finally:
        desk.close()
    for cid, slot in rig.slots.items():
        if cid != "b":
            slot.command_log.close(slot.steps_total, slot.sim.x)
    return rig


def _play(rig: WorldRig, ask) -> None:
    # a drives into the back of t (the driver's car, 9 m ahead at 1.5 m/s); b beside
    touched = 0
    for k in range(4000):
        rig.send("a", throttle=0.6 if not touched else 0.0, brake=0.0 if not touched
                 else 0.5, gear=proto.Gear.D)
        rig.send("b", throttle=0.3, steer=0.02 * math.sin(k / 300.0), gear=proto.Gear.D)
        rig.run()
        if not touched and rig.loop.world.contact_count() > 0:
            touched = k
        if touched and k > touched + 600:
            break
    assert touched, "a never touched t"
    rig.after_contact = {cid: (slot.steps_total, slot.sim.x.copy())
                         for cid, slot in rig.slots.items()}
    # b stopped alone by a non-finite state (held at its start while the others step),
    # then the world resumed
    rig.slots["b"].sim.x[L.U_MPS] = math.nan
    for _ in range(120):
        rig.send("a", throttle=0.2, gear=proto.Gear.D)
        rig.run()
    assert rig.slots["b"].counters["nonfinite_stops"] == 1
    assert rig.control("a", "resume")["ok"]
    # a car added while the world runs, one removed, the road changed, the world reset
    assert ask("add_car", {"id": "c", "pose": {"x_m": -30.0, "y_m": 0.0, "yaw_rad": 0.0}})["ok"]
    for _ in range(300):
        rig.send("a", throttle=0.3, gear=proto.Gear.D)
        rig.send("b", throttle=0.4, gear=proto.Gear.D)
        rig.send("c", throttle=0.8, steer=0.05, gear=proto.Gear.D)
        rig.run()
    assert rig.control("a", "set_road", {"grade_pct": 2.0})["ok"]
    for _ in range(200):
        rig.send("a", throttle=0.4, gear=proto.Gear.D)
        rig.send("b", throttle=0.4, gear=proto.Gear.D)
        rig.send("c", throttle=0.5, gear=proto.Gear.D)
        rig.run()
    assert ask("remove_car", {"id": "b"})["ok"]
    rig.before_reset = {cid: (slot.steps_total, slot.sim.x.copy())
                        for cid, slot in rig.slots.items() if cid != "b"}
    assert ask("reset")["ok"]
    for _ in range(300):
        rig.send("a", throttle=0.7, gear=proto.Gear.D)
        rig.send("c", throttle=0.2, gear=proto.Gear.D)
        rig.run()


def test_a_multicar_session_with_contact_replays_bit_for_bit(flat_scene, tmp_path):
    rig = _world_session(flat_scene, tmp_path)
    live_contacts = rig.loop.world.contact_count()
    logs = [tmp_path / f"{cid}.jsonl" for cid in ("a", "b", "t", "c")]
    replay = replay_world(logs, record=True)
    for cid, car in replay.cars.items():
        assert car.final_state_matches, cid
    assert replay.cars["b"].left_at is not None and replay.cars["c"].joined_at > 0
    assert replay.cars["a"].steps == rig.slots["a"].steps_total
    assert replay.cars["b"].steps < replay.cars["a"].steps  # held while the world stepped
    assert replay.contact_events == live_contacts >= 1
    # the driver's car moved under its driver, the contact pushed it
    assert replay.cars["t"].final_state[L.X_M] != 9.0
    # after the contact: the world replay's states are the live ones; each car's log
    # replayed alone is not (the contact is the other car's too; the final states match
    # alone only because the world's reset wiped the contact's effect)
    for cid in ("a", "t"):
        steps, x = rig.after_contact[cid]
        assert np.array_equal(replay.cars[cid].states[steps - 1], x), cid
        alone = replay_command_log(tmp_path / f"{cid}.jsonl")
        assert not np.array_equal(alone.states[steps - 1], x), cid
    steps, x = rig.after_contact["b"]  # b did not touch: alone or in the world, the same
    assert np.array_equal(replay.cars["b"].states[steps - 1], x)
    # before the world's reset (which wipes what came before from the final states): the
    # road changed for every car at the world step it did live (b's log, which says it
    # too at its own step, lags the world's by the steps b was held)
    for cid, (steps, x) in rig.before_reset.items():
        assert np.array_equal(replay.cars[cid].states[steps - 1], x), cid


def test_a_world_replay_names_the_file_of_a_bad_set_of_logs(flat_scene, tmp_path):
    rig = WorldRig(flat_scene, CARS[:2], tmp_path)
    for _ in range(50):
        rig.send("a", throttle=0.5, gear=proto.Gear.D)
        rig.run()
    for slot in rig.slots.values():
        slot.command_log.close(slot.steps_total, slot.sim.x)
    with pytest.raises(ConfigError, match=r"a\.jsonl:2: the world started with car\(s\) b: "
                                          "give their command logs too"):
        replay_world([tmp_path / "a.jsonl"])
    with pytest.raises(ConfigError, match=r"a\.jsonl: car 'a' is the car of .*a\.jsonl too"):
        replay_world([tmp_path / "a.jsonl", tmp_path / "b.jsonl", tmp_path / "a.jsonl"])
    single = tmp_path / "single.jsonl"
    log = CommandLog(single, {"scene": str(FLAT), "dt_s": 0.001, "step": 0})
    log.close(0, np.zeros(L.N_STATE))
    with pytest.raises(ConfigError, match=r"single\.jsonl:2: not the log of a car of a "
                                          "world of several"):
        replay_world([single, tmp_path / "a.jsonl"])
    assert replay_world([tmp_path / "a.jsonl", tmp_path / "b.jsonl"]).all_match
