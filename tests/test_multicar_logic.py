"""Several cars in one live server, in-process (issue 30 item 1): the real loop and slots
stepping the cars of one world on a fake clock, fed and read through list ports (the
fakes of tests/test_server_logic.py). Each car keeps its own commands, watchdog, state
and log; one compiled world step a tick for all; the world's controls act on every car;
the world message carries every car."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from test_server_logic import (
    FLAT,
    PAUSED,
    WATCHDOG,
    FakeClock,
    ListControls,
    ListInbox,
    LocalRequest,
    RecordingPublisher,
    load_server_config,
)

from simserver.core import layout as L
from simserver.server import cars_config, fleet
from simserver.server.command_log import CommandLog, replay_command_log
from simserver.server.loop import ServerLoop, SlotPorts
from simserver.server.slot import VehicleSlot
from simserver.sim.scene import load_scene
from simserver.sim.simulation import Simulation
from simserver.wire import protocol as proto

pytestmark = pytest.mark.timeout(300)

HATCH = Path(FLAT).parents[1] / "vehicles" / "mf_hatchback" / "vehicle.yaml"


@pytest.fixture(scope="module")
def flat_scene():
    return load_scene(FLAT)


class WorldRig:
    """A loop serving the cars of ``cars`` (a ``cars:`` list) on the flat scene."""

    def __init__(self, scene, cars, tmp_path: Path | None = None) -> None:
        self.clock = FakeClock()
        self.cfg = load_server_config()
        specs = cars_config.parse_cars(Path(FLAT), cars)
        self.scenes = cars_config.car_scenes(specs, scene)
        sims = fleet.build_world(self.scenes, self.cfg.period_s)
        self.loop = ServerLoop(self.cfg, clock=self.clock, sleep=self.clock.sleep, spin_ns=0)
        self.ports: dict[str, SlotPorts] = {}
        self.slots: dict[str, VehicleSlot] = {}
        for spec in specs:
            cfg = dataclasses.replace(self.cfg, vehicle_id=spec.id)
            log = None
            if tmp_path is not None:
                log = CommandLog(tmp_path / f"{spec.id}.jsonl",
                                 {"scene": str(FLAT), "dt_s": cfg.period_s, "step": 0})
            slot = VehicleSlot(cfg, sims[spec.id], log)
            if log is not None:
                fleet.log_start(slot, spec)
            if spec.driven_by == "keyframes":
                slot.drive_by_keyframes(cars_config.keyframe_table(spec, cfg.period_s))
            ports = SlotPorts(ListInbox(), ListControls(), RecordingPublisher())
            self.loop.add(slot, ports)
            self.slots[spec.id], self.ports[spec.id] = slot, ports
        self.world_payloads: list[bytes] = []
        self.loop.world_message = fleet.WorldMessage(
            [s.id for s in specs], [s.driven_by for s in specs],
            every=fleet.world_every(100.0, self.cfg.period_s))
        self.loop.publish_world = self.world_payloads.append
        self.loop.start()
        self.seq: dict[str, int] = {}

    def send(self, car: str, **fields) -> None:
        self.seq[car] = self.seq.get(car, 0) + 1
        self.ports[car].commands.pending.append(proto.encode_command(
            seq=self.seq[car], sender_time_ns=self.seq[car], **fields))

    def run(self, ticks: int = 1) -> None:
        for _ in range(ticks):
            self.loop.tick()

    def state(self, car: str) -> np.void:
        return self.ports[car].publisher.states[-1]

    def world_desk(self, cfg=None, closed: list | None = None, on_added=None):
        """The world's controls on list ports, as the server wires them (``WorldDesk``):
        a car added gets list ports (kept in ``ports``); a car removed is noted in
        ``closed``. Returns the desk (``close()`` it) and its control inbox; :meth:`ask`
        sends to it."""
        from simserver.server.world_desk import WorldDesk

        self.world_controls = ListControls()

        def make_ports(car_cfg):
            ports = SlotPorts(ListInbox(), ListControls(), RecordingPublisher())
            self.ports[car_cfg.vehicle_id] = ports
            return ports

        def removed(slot, ports):
            if closed is not None:
                closed.append(slot.keys.vehicle)

        desk = WorldDesk(self.loop, cfg or self.cfg, self.world_controls, make_ports,
                         removed, **({} if on_added is None else {"on_added": on_added}))
        self.loop.world_desk = desk
        return desk

    def answer(self, req: LocalRequest, ticks: int = 3000) -> dict:
        """Tick until ``req`` is answered (within ``ticks``); its answer."""
        for _ in range(ticks):
            self.loop.tick()
            if req.body is not None:
                return req.answer
        raise AssertionError(f"{req.name} not answered in {ticks} ticks")

    def ask(self, name: str, args: dict | None = None, ticks: int = 3000) -> dict:
        """A world control (:meth:`world_desk`), answered."""
        req = LocalRequest(name, json.dumps(args).encode() if args is not None else b"")
        self.world_controls.pending.append(req)
        return self.answer(req, ticks)

    def control(self, car: str, name: str, args: dict | None = None) -> dict:
        req = LocalRequest(name, json.dumps(args).encode() if args is not None else b"")
        self.ports[car].controls.pending.append(req)
        self.loop.tick()
        return req.answer


def test_each_car_its_own_commands_watchdog_and_state_one_world_step(flat_scene,
                                                                     monkeypatch):
    rig = WorldRig(flat_scene, [{"id": "car0"},
                                {"id": "car1", "vehicle": str(HATCH),
                                 "pose": {"x_m": 20.0, "y_m": 0.0}}])
    world = rig.loop.world
    assert world is rig.slots["car0"].sim.world is rig.slots["car1"].sim.world
    calls = []
    step = world.step
    monkeypatch.setattr(world, "step", lambda: (calls.append(1), step()))
    for _ in range(300):  # car1 driven, car0 left alone: its watchdog holds it
        rig.send("car1", throttle=0.6, gear=proto.Gear.D)
        rig.run()
    assert len(calls) == 300  # one world step a tick, not one per car
    s0, s1 = rig.state("car0"), rig.state("car1")
    assert s0["flags"] & WATCHDOG and not s1["flags"] & WATCHDOG
    assert s0["tick"] == s1["tick"] == 300
    assert s1["u_mps"] > 0.5 and s1["x_m"] > 20.0 and abs(s0["u_mps"]) < 1e-3
    assert s1["last_cmd_seq"] == 300 and s0["last_cmd_seq"] == 0
    assert rig.slots["car1"].counters["cmd_received"] == 300
    assert rig.slots["car0"].counters["cmd_received"] == 0
    # the world message: both cars, their newest published states
    w = proto.decode_world(rig.world_payloads[-1])
    assert w.ids == ("car0", "car1") and len(rig.world_payloads) == 30  # 100 Hz, 300 ticks
    for car in ("car0", "car1"):  # the states published in the world message's tick
        state = rig.ports[car].publisher.states[290]
        for name in ("x_m", "y_m", "z_m", "flags"):
            assert w.car(car)[name] == state[name]
        assert w.car(car)["u_mps"] == state["u_mps"]
        assert w.car(car)["yaw_rad"] == np.float32(state["yaw_rad"])
    assert w.car("car0")["flags"] & WATCHDOG and w.tick == 290


def test_each_car_matches_its_run_alone_bit_for_bit(flat_scene):
    """One world of two cars gives each car the bits of a single car's server stepping
    the same inputs (cars do not touch yet)."""
    rig = WorldRig(flat_scene, [{"id": "a"}, {"id": "b", "pose": {"x_m": 15.0, "y_m": 0.0}}])
    alone = {cid: Simulation(rig.scenes[cid], 0.001, car_id=cid) for cid in rig.scenes}
    for _k in range(200):
        rig.send("a", throttle=0.4, steer=0.2, gear=proto.Gear.D)
        rig.send("b", throttle=0.7, gear=proto.Gear.D)
        rig.run()
        for cid, sim in alone.items():
            sim.inputs[:] = rig.slots[cid].sim.inputs
            sim.step()
    for cid, sim in alone.items():
        assert np.array_equal(rig.slots[cid].sim.x, sim.x), cid


def test_world_controls_act_on_every_car_and_a_car_loads_its_vehicle_only(flat_scene):
    rig = WorldRig(flat_scene, [{"id": "a"}, {"id": "b", "pose": {"x_m": 15.0, "y_m": 0.0}}])
    rig.run(5)
    assert rig.control("b", "pause")["paused"] is True
    rig.run(5)
    assert rig.state("a")["flags"] & PAUSED and rig.state("b")["flags"] & PAUSED
    assert rig.state("a")["tick"] == rig.state("b")["tick"] == 6
    reply = rig.control("a", "step", {"n": 3})
    assert reply["until_tick"] == 9
    rig.run(5)
    assert rig.state("a")["tick"] == rig.state("b")["tick"] == 9
    assert rig.control("a", "resume")["paused"] is False
    road = rig.control("b", "set_road", {"grade_pct": 5.0})["road"]
    assert road["grade_pct"] == 5.0 and rig.slots["a"].sim.road["grade_pct"] == 5.0
    err = rig.control("a", "load", {"scene": str(FLAT)})
    assert not err["ok"] and err["field"] == "scene" and "vehicle only" in err["error"]
    rig.send("b", throttle=0.5, gear=proto.Gear.D)
    rig.run(50)
    reply = rig.control("b", "load", {"vehicle": str(HATCH)})
    assert reply["ok"], reply
    rig.run(2)
    b = rig.slots["b"]
    assert b.sim.scene.vehicle.path == HATCH.resolve()
    assert b.sim.road["grade_pct"] == 5.0  # the world's road, not the scene's
    assert rig.state("b")["x_m"] == pytest.approx(15.0, abs=0.05)  # its own start again
    assert rig.slots["a"].sim.scene.vehicle.path != HATCH.resolve()


def _keyframed_inputs(t_s: float) -> list[float]:
    """The inputs the table of ``test_a_keyframed_car_plays_its_table_and_ignores_commands``
    gives at time ``t_s``, written out from the keyframe rule (``simserver.sim.keyframes``):
    steer, throttle and brake linear between the keyframes naming them, their first value
    before the first, their last after the last; the parking brake and the gear switch at
    a keyframe's time, their defaults (0, D) before their first keyframe."""
    ramp = np.interp  # the linear rule: holds the end values outside the keyframes
    steer = ramp(t_s, [0.0, 0.1, 0.2], [0.0, 0.2, -0.1])
    throttle = ramp(t_s, [0.1, 0.2], [0.0, 1.0])
    brake = ramp(t_s, [0.0, 0.1], [0.6, 0.0])
    parking = 1.0 if 0.05 <= t_s < 0.25 else 0.0
    gear = proto.Gear.N if t_s < 0.05 else proto.Gear.D
    return [steer, throttle, brake, parking, float(gear)]


def test_a_keyframed_car_plays_its_table_and_ignores_commands(flat_scene, tmp_path):
    """A car ``driven_by: keyframes`` applies its file's inputs at every tick of the
    table, as the keyframe rule samples them (``_keyframed_inputs``): each keyframe's
    values at its time, the ramps between, the switches, and after the table's end
    (``duration_s``) its last row; the commands sent to it are counted, not applied.
    Checked on the inputs of every step (the car's input vector after each tick: the
    row applied over it) and on the published states (the inputs of the step that led
    to each); before, only the end values were."""
    frames = tmp_path / "go.yaml"
    frames.write_text("name: go\nduration_s: 0.3\ninputs:\n"
                      "  - {t: 0.0, gear: N, brake: 0.6, steer: 0.0}\n"
                      "  - {t: 0.05, gear: D, parking_brake: 1}\n"
                      "  - {t: 0.1, throttle: 0.0, brake: 0.0, steer: 0.2}\n"
                      "  - {t: 0.2, throttle: 1.0, steer: -0.1}\n"
                      "  - {t: 0.25, parking_brake: 0}\n")
    rig = WorldRig(flat_scene, [{"id": "a"}, {"id": "kf", "driven_by": "keyframes",
                                             "keyframes": str(frames),
                                             "pose": {"x_m": 15.0, "y_m": 0.0}}])
    kf = rig.slots["kf"]
    dt = rig.cfg.period_s
    applied = []
    for _ in range(700):
        rig.send("kf", brake=1.0, steer=-1.0, gear=proto.Gear.R)  # not applied
        rig.run()
        applied.append(kf.sim.inputs.copy())
    times = np.arange(700) * dt  # the step k starts at k dt (tick k)
    expected = np.array([_keyframed_inputs(t) for t in times])
    # every step: each keyframe's values at its time (t = 0, 50, 100, 200, 250 ms, where a
    # switch takes its new value), the ramps between (to rounding), the last row after
    # the table's end at 300 ms
    assert np.allclose(np.array(applied), expected, rtol=0.0, atol=1e-12), np.flatnonzero(
        np.abs(np.array(applied) - expected).max(axis=1) > 1e-12)[:5]
    for k, row in ((0, [0.0, 0.0, 0.6, 0.0, proto.Gear.N]), (50, [0.1, 0.0, 0.3, 1.0, 3.0]),
                   (100, [0.2, 0.0, 0.0, 1.0, 3.0]), (150, [0.05, 0.5, 0.0, 1.0, 3.0]),
                   (200, [-0.1, 1.0, 0.0, 1.0, 3.0]), (249, [-0.1, 1.0, 0.0, 1.0, 3.0]),
                   (250, [-0.1, 1.0, 0.0, 0.0, 3.0]), (699, [-0.1, 1.0, 0.0, 0.0, 3.0])):
        assert np.allclose(applied[k], row, rtol=0.0, atol=1e-12), (k, applied[k])
    # what a client sees: the state of tick n carries the inputs of the step n - 1 to n
    states = rig.ports["kf"].publisher.states
    assert len(states) == 70
    for st in states:
        want = expected[int(st["tick"]) - 1]
        got = [st["steer"], st["throttle"], st["brake"], st["parking_brake"], st["gear"]]
        assert np.allclose(got, want, rtol=0.0, atol=1e-6), (int(st["tick"]), got, want)
    s = rig.state("kf")
    assert s["throttle"] == 1.0 and s["gear"] == proto.Gear.D and s["brake"] == 0.0
    assert not s["flags"] & WATCHDOG and s["u_mps"] > 0.5
    assert kf.counters["cmd_rejected"] == 700
    w = proto.decode_world(rig.world_payloads[-1])
    assert proto.DRIVEN_BY_CODES[int(w.car("kf")["driven_by"])] == "keyframes"


def test_each_cars_command_log_replays_bit_for_bit(flat_scene, tmp_path):
    rig = WorldRig(flat_scene, [{"id": "a", "pose": {"x_m": -5.0, "y_m": 1.0,
                                                     "yaw_rad": 0.2}},
                                {"id": "b", "vehicle": str(HATCH),
                                 "pose": {"x_m": 15.0, "y_m": 0.0}}], tmp_path)
    for k in range(300):
        rig.send("a", throttle=0.5, steer=0.1, gear=proto.Gear.D)
        if k < 150:
            rig.send("b", throttle=0.8, gear=proto.Gear.D)
        rig.run()
    assert rig.control("b", "reset")["ok"]
    assert rig.control("a", "set_road", {"grade_pct": -3.0})["ok"]
    rig.send("a", throttle=0.5, gear=proto.Gear.D)
    rig.run(100)
    assert rig.control("b", "load", {"vehicle": str(FLAT.parents[1] / "vehicles" /
                                                   "paper_sedan" / "vehicle.yaml")})["ok"]
    rig.run(100)
    for cid, slot in rig.slots.items():
        slot.command_log.close(slot.steps_total, slot.sim.x)
        replay = replay_command_log(tmp_path / f"{cid}.jsonl")
        assert replay.steps == slot.steps_total
        assert replay.final_state_matches, cid
        assert replay.final_state[L.X_M] != 0.0


def test_one_clock_a_car_reset_or_loaded_or_added_keeps_the_worlds_time(flat_scene,
                                                                         tmp_path):
    """The world has one clock (docs/protocol.md section 5.1): a car's own reset (at rest
    or at speed) or load keeps the world's time in its state (before, its TIME_S restarted
    at 0 while the other cars' went on), a car joining takes it, and the replay of the
    car's log alone restarts its clock where the live one stood (the log's reset names it)."""
    rig = WorldRig(flat_scene, [{"id": "a"}, {"id": "b", "pose": {"x_m": 15.0, "y_m": 0.0}}],
                   tmp_path)
    a, b = rig.slots["a"].sim, rig.slots["b"].sim
    rig.run(200)
    assert rig.control("b", "reset")["ok"]
    assert b.x[L.TIME_S] == a.x[L.TIME_S] > 0.19
    rig.run(50)
    req = LocalRequest("reset", json.dumps({"u_mps": 5.0}).encode())
    rig.ports["b"].controls.pending.append(req)
    for _ in range(100):  # the start at speed settles between ticks, then is swapped in
        rig.run()
        if req.body is not None:
            break
    assert req.answer["ok"]
    assert b.x[L.U_MPS] > 4.0 and b.x[L.TIME_S] == a.x[L.TIME_S]
    assert rig.control("b", "load", {"vehicle": str(HATCH)})["ok"]
    rig.run(5)
    assert b.x[L.TIME_S] == a.x[L.TIME_S]
    spec, = cars_config.parse_cars(Path(FLAT), [{"id": "c", "pose": {"x_m": 60.0,
                                                                      "y_m": 0.0}}])
    scene, table = cars_config.new_car(spec, flat_scene, 0.001,
                                       fleet.poses_now(list(rig.slots.values())))
    slot = fleet.join_world(dataclasses.replace(rig.cfg, vehicle_id="c"), scene, table,
                            rig.loop.world)
    assert slot.sim.x[L.TIME_S] == a.x[L.TIME_S]
    rig.loop.world.remove_car("c")  # joined the world only, not the loop's cars
    rig.run(10)
    slot_b = rig.slots["b"]
    slot_b.command_log.close(slot_b.steps_total, b.x)
    replay = replay_command_log(tmp_path / "b.jsonl")
    assert replay.final_state_matches
    assert replay.final_state[L.TIME_S] == b.x[L.TIME_S]


def test_a_car_added_and_one_removed_while_the_world_runs(flat_scene):
    rig = WorldRig(flat_scene, [{"id": "a"}, {"id": "b", "pose": {"x_m": 15.0, "y_m": 0.0}}])
    rig.loop.world_message = fleet.WorldMessage(["a", "b"], ["client", "client"], every=10,
                                                capacity=8)
    alone = Simulation(rig.scenes["a"], 0.001, car_id="a")
    for _ in range(100):
        rig.send("a", throttle=0.5, gear=proto.Gear.D)
        rig.run()
        alone.inputs[:] = rig.slots["a"].sim.inputs
        alone.step()
    # a third car, read and checked as the load worker would, joined between two ticks
    spec, = cars_config.parse_cars(Path(FLAT), [{"id": "c", "vehicle": str(HATCH),
                                           "pose": {"x_m": 40.0, "y_m": 0.0}}])
    slots = list(rig.slots.values())
    scene, table = cars_config.new_car(spec, flat_scene, 0.001, fleet.poses_now(slots))
    clash, = cars_config.parse_cars(Path(FLAT), [{"id": "d", "pose": {"x_m": 16.0, "y_m": 0.5}}])
    with pytest.raises(cars_config.ConfigError, match=r"\(d\): its start .* overlaps car 'b'"):
        cars_config.new_car(clash, flat_scene, 0.001, fleet.poses_now(slots))
    taken, = cars_config.parse_cars(Path(FLAT), [{"id": "b", "pose": {"x_m": 90.0, "y_m": 0.0}}])
    with pytest.raises(cars_config.ConfigError, match="has a car 'b' already"):
        cars_config.new_car(taken, flat_scene, 0.001, fleet.poses_now(slots))
    cfg = dataclasses.replace(rig.cfg, vehicle_id="c")
    slot = fleet.join_world(cfg, scene, table, rig.loop.world)
    ports = SlotPorts(ListInbox(), ListControls(), RecordingPublisher())
    rig.loop.add(slot, ports)
    rig.slots["c"], rig.ports["c"] = slot, ports
    assert rig.loop.world.ids == ["a", "b", "c"]
    # before its first state is published, the world message has the new car at its start
    # (not at zero: a client would draw it at the origin), the others where they are
    first = proto.decode_world(rig.loop.world_message.payload([None] * 3, 0, 0.0))
    assert first.ids == ("a", "b", "c")
    assert first.car("c")["x_m"] == pytest.approx(40.0, abs=0.05)
    assert first.car("b")["x_m"] == pytest.approx(15.0, abs=0.05)
    assert first.car("a")["x_m"] == pytest.approx(float(rig.slots["a"].sim.x[L.X_M]), abs=0.05)
    for _ in range(100):
        rig.send("a", throttle=0.5, gear=proto.Gear.D)
        rig.send("c", throttle=0.9, gear=proto.Gear.D)
        rig.run()
        alone.inputs[:] = rig.slots["a"].sim.inputs
        alone.step()
    assert rig.state("c")["u_mps"] > 0.2 and rig.state("c")["x_m"] > 40.0
    assert proto.decode_world(rig.world_payloads[-1]).ids == ("a", "b", "c")
    rig.loop.remove(rig.slots.pop("b"))
    assert rig.loop.world.ids == ["a", "c"]
    for _ in range(100):
        rig.send("a", throttle=0.5, gear=proto.Gear.D)
        rig.run()
        alone.inputs[:] = rig.slots["a"].sim.inputs
        alone.step()
    assert proto.decode_world(rig.world_payloads[-1]).ids == ("a", "c")
    assert np.array_equal(rig.slots["a"].sim.x, alone.x)  # unchanged by the others
    assert rig.state("a")["tick"] == 300


def test_world_controls_add_and_remove_cars_between_ticks(flat_scene):
    rig = WorldRig(flat_scene, [{"id": "a"}, {"id": "b", "pose": {"x_m": 15.0, "y_m": 0.0}}])
    rig.loop.world_message = fleet.WorldMessage(["a", "b"], ["client", "client"], every=10,
                                                capacity=4)
    closed = []
    desk = rig.world_desk(dataclasses.replace(rig.cfg, max_cars=3), closed)
    ask = rig.ask

    try:
        bad = ask("add_car", {"id": "c", "pose": {"x_m": 15.5, "y_m": 0.0, "yaw_rad": 0.0}})
        assert not bad["ok"] and bad["field"] == "pose" and "overlaps car 'b'" in bad["error"]
        assert not ask("add_car", {"id": "world"})["ok"]
        assert ask("add_car", {"id": "b"})["field"] == "id"
        nofile = ask("add_car", {"id": "c", "vehicle": "no_such_vehicle.yaml"})
        assert nofile["field"] == "vehicle" and "no such file" in nofile["error"]
        # a driver block: with driven_by driver only, and checked as a cars: entry's,
        # the error naming the car and the block's key
        at = {"x_m": 40.0, "y_m": 0.0, "yaw_rad": 0.0}
        block = {"path": {"points": [[0.0, 0.0], [500.0, 0.0]]}}
        missing = ask("add_car", {"id": "c", "pose": at, "driven_by": "driver"})
        assert missing["field"] == "driver" and missing["error"].startswith(
            "driver: car 'c' is driven by the driver and needs a driver block"), missing
        stray = ask("add_car", {"id": "c", "pose": at, "driver": block})
        assert stray["field"] == "driver" and "only a car driven_by driver" in stray["error"]
        for driver, field, error in (
                ({**block, "idm": {"T_s": -1.0}}, "driver.idm.T_s",
                 "add_car (c): key 'driver.idm.T_s': -1 is outside"),
                ({**block, "bogus": 1}, "driver", "add_car (c) (driver): unknown key 'bogus'"),
                ({"path": {"road": "1"}}, "driver.path",
                 "add_car (c) (driver.path): missing key 'lane'")):
            bad = ask("add_car", {"id": "c", "pose": at, "driven_by": "driver",
                                  "driver": driver})
            assert bad["field"] == field and bad["error"].startswith(error), bad
        assert ask("add_car", {"id": "c", "driven_by": "robot"})["field"] == "driven_by"
        lane = {"road": "1", "s": 10.0, "lane": -1}
        both = ask("add_car", {"id": "c", "pose": at, "start": lane})
        assert both["field"] == "start" and "pose or start, not both" in both["error"]
        flat = ask("add_car", {"id": "c", "start": lane})  # a start by lane: OpenDRIVE only
        assert flat["field"] == "start" and flat["error"].startswith(
            "add_car (c): key 'start': a start by road, s and lane needs an OpenDRIVE"), flat
        # nothing changed: no car, no ports made
        assert rig.loop.world.ids == ["a", "b"] and set(rig.ports) == {"a", "b"}
        ok = ask("add_car", {"id": "c", "vehicle": str(HATCH),
                             "pose": {"x_m": 40.0, "y_m": 0.0, "yaw_rad": 0.0}})
        assert ok == {"ok": True, "car": "c", "cars": ["a", "b", "c"]}, ok
        assert set(rig.ports) == {"a", "b", "c"} and rig.loop.world.ids == ["a", "b", "c"]
        full = ask("add_car", {"id": "d", "pose": {"x_m": 80.0, "y_m": 0.0, "yaw_rad": 0.0}})
        assert full["field"] == "id" and "max_cars (3)" in full["error"]
        for _ in range(300):
            rig.ports["c"].commands.pending.append(proto.encode_command(
                seq=_ + 1, throttle=0.8, gear=proto.Gear.D))
            rig.run()
        c = rig.ports["c"].publisher.states[-1]
        assert c["x_m"] > 40.0 and c["u_mps"] > 0.5
        assert ask("remove_car", {"id": "b"}) == {"ok": True, "car": "b", "cars": ["a", "c"]}
        rig.run(20)
        assert proto.decode_world(rig.world_payloads[-1]).ids == ("a", "c")
        assert ask("remove_car", {"id": "zz"})["field"] == "id"
        config = ask("get_config")
        assert config["cars"] == [{"id": "a", "driven_by": "client"},
                                  {"id": "c", "driven_by": "client"}]
        # the whole world back to its starts, in one tick
        assert ask("reset") == {"ok": True, "cars": ["a", "c"]}
        rig.run()
        a, c = rig.ports["a"].publisher.states[-1], rig.ports["c"].publisher.states[-1]
        assert a["tick"] == c["tick"] == 1
        assert a["x_m"] == pytest.approx(0.0, abs=1e-3) and c["x_m"] == pytest.approx(
            40.0, abs=1e-3) and abs(c["u_mps"]) < 0.01  # one step from rest
    finally:
        desk.close()
    assert closed == ["b"]



@pytest.mark.parametrize(("scene_name", "where"), [
    ("hill_15pct_paper_sedan", {"pose": {"x_m": 40.0, "y_m": 0.0, "yaw_rad": 0.0}}),
    ("curves_elevation_paper_sedan", {"start": {"road": "1", "s": 60.0, "lane": -1}}),
    ("flat_mf_hatchback", {"pose": {"x_m": 40.0, "y_m": 0.0, "yaw_rad": 0.0}}),
    ("curves_elevation_paper_sedan", {"start": {"road": "1", "s": 60.0, "lane": -1},
                                      "driven_by": "driver",
                                      "driver": {"path": {"road": "1", "lane": -1},
                                                 "idm": {"v0_mps": 10.0}}}),
], ids=["hill", "opendrive_lane", "other_vehicle", "driver_on_a_lane"])
def test_a_car_added_after_a_live_load_is_made_on_the_loaded_scene(flat_scene, scene_name,
                                                                    where):
    """A world of one car that loaded another scene while running (its own ``load``), then
    ``add_car``: the new car is made on the world's scene now, the loaded one, as a car of
    that scene alone at the same place would be, bit for bit: its road, its OpenDRIVE
    lanes for a start by lane and for a driver's lane path (sampled on its terrain), its
    vehicle as the default, and its command log naming it.
    Before, the new car was made on the server config's scene: the flat road's scene on
    the 15 % grade, a start by lane refused ("needs an OpenDRIVE" terrain), the paper sedan
    where the world's scene drives the hatchback."""
    loaded = Path(FLAT).parent / f"{scene_name}.yaml"
    rig = WorldRig(flat_scene, [{"id": "a"}])
    rig.loop.world_message = fleet.WorldMessage(["a"], ["client"], every=10, capacity=2)
    desk = rig.world_desk()
    try:
        load = LocalRequest("load", json.dumps({"scene": str(loaded)}).encode())
        rig.ports["a"].controls.pending.append(load)
        assert rig.answer(load)["ok"], load.answer
        added = rig.ask("add_car", {"id": "c", **where})
        assert added == {"ok": True, "car": "c", "cars": ["a", "c"]}, added
        slot = next(s for s, _ in rig.loop.slots if s.keys.vehicle == "c")
        scene = load_scene(loaded)
        spec, = cars_config.parse_cars(loaded, [{"id": "c", **where}])
        alone, _ = cars_config.new_car(spec, scene, rig.cfg.period_s, {})
        expected = Simulation(alone, rig.cfg.period_s, car_id="c").x
        got = slot.sim.x.copy()
        got[L.TIME_S] = expected[L.TIME_S]  # it took the world's clock (one clock)
        assert np.array_equal(got, expected), np.flatnonzero(got != expected)
        assert slot.sim.scene.road == scene.road
        assert slot.sim.scene.vehicle.name == scene.vehicle.name
        assert slot.scene_path == loaded  # what its log's header and load line name
        if "driver" in where:  # its lane path: the loaded scene's road, sampled on its
            from simserver.server.live_drivers import sample_path  # terrain

            assert slot.driven_by == "driver"
            block = cars_config.driver_spec(spec, scene)
            assert np.array_equal(rig.loop.live_drivers.rows["c"],
                                  sample_path(block, scene.terrain))
    finally:
        desk.close()


def test_a_car_added_after_a_live_set_road_replays_on_the_worlds_road(flat_scene, tmp_path):
    """A live ``set_road`` changes the road under every car; a car added afterwards
    (``add_car``) stands on the world's road, so its command log names that road after
    its start (``fleet.log_start``): the replay of its log alone, and the world's replay
    of every log, give its live bits. Before, its log named only the scene (its file's
    road, 0 %): its replay alone drove up a flat road the live car climbed at 8 %."""
    from simserver.server.world_replay import replay_world

    rig = WorldRig(flat_scene, [{"id": "a"}], tmp_path)
    rig.loop.world_message = fleet.WorldMessage(["a"], ["client"], every=10, capacity=2)

    def added(slot):  # as the server's (SimServer._added): its log, then its start lines
        slot.command_log = CommandLog(tmp_path / f"{slot.keys.vehicle}.jsonl", {
            "scene": str(slot.scene_path), "dt_s": rig.cfg.period_s, "step": 0})
        fleet.log_start(slot, cars_config.CarSpec(id=slot.keys.vehicle, where="",
                                                  vehicle=slot.sim.scene.vehicle.path))

    desk = rig.world_desk(on_added=added)
    try:
        rig.run(50)
        assert rig.control("a", "set_road", {"grade_pct": 8.0})["road"]["grade_pct"] == 8.0
        rig.run(50)
        add = rig.ask("add_car", {"id": "c", "pose": {"x_m": 40.0, "y_m": 0.0, "yaw_rad": 0.0}})
        assert add == {"ok": True, "car": "c", "cars": ["a", "c"]}, add
        c = next(s for s, _ in rig.loop.slots if s.keys.vehicle == "c")
        assert c.sim.road["grade_pct"] == 8.0  # the world's road, live
        for k in range(400):
            rig.send("a", brake=0.8, gear=proto.Gear.D)
            rig.ports["c"].commands.pending.append(proto.encode_command(
                seq=k + 1, throttle=0.7, gear=proto.Gear.D))
            rig.run()
        assert c.sim.x[L.X_M] > 40.2
    finally:
        desk.close()
    for slot, _ in rig.loop.slots:
        slot.command_log.close(slot.steps_total, slot.sim.x.copy())
    alone = replay_command_log(tmp_path / "c.jsonl")
    assert alone.steps == c.steps_total
    assert alone.final_state_matches, (alone.final_state[L.X_M], c.sim.x[L.X_M])
    world = replay_world([tmp_path / "a.jsonl", tmp_path / "c.jsonl"])
    assert world.all_match
