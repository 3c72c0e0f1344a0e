"""The server's logic in-process: the real loop, slot and simulation on a fake clock.

No zenoh, no subprocess, no sleep: :class:`simserver.server.loop.ServerLoop` drives a
:class:`simserver.server.slot.VehicleSlot` stepping the real compiled simulation, with
the pacer on a :class:`FakeClock`, commands pushed into a list inbox, controls into a list
of requests, and states and diagnostics decoded by a recording publisher. The rules
checked are those of ``docs/protocol.md`` (2.1 commands, 2.2 state, 3 controls). The
end-to-end tests (``tests/test_server.py``) check the same server over zenoh.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable

import numpy as np
import pytest

from simserver.core import layout as L
from simserver.server.app import new_simulation
from simserver.server.command_log import CommandLog, read_command_log, replay_command_log
from simserver.server.config import DEFAULT_SERVER_CONFIG, REPO_CONFIGS
from simserver.server.config import load_server_config as _load_server_config
from simserver.server.loop import CONTROLS, ServerLoop, SlotPorts
from simserver.server.slot import VehicleSlot
from simserver.sim.scene import Scene, load_scene
from simserver.wire import protocol as proto

pytestmark = pytest.mark.timeout(120)

FLAT = REPO_CONFIGS / "scenes" / "flat_paper_sedan.yaml"
HILL = REPO_CONFIGS / "scenes" / "hill_10pct_paper_sedan.yaml"
MS = 1_000_000  # ns
WATCHDOG, PAUSED, CATCHUP = proto.StateFlag.WATCHDOG, proto.StateFlag.PAUSED, \
    proto.StateFlag.CATCHUP


def load_server_config(**overrides):
    return _load_server_config(DEFAULT_SERVER_CONFIG, viewer="off", **overrides)


# ---------------------------------------------------------------------- fakes of the ports
class FakeClock:
    """Integer nanoseconds; each read costs 1 us and ``sleep`` lands exactly on time."""

    def __init__(self, t0: int = 10_000 * MS) -> None:
        self.t = t0

    def __call__(self) -> int:
        self.t += 1_000
        return self.t

    def sleep(self, seconds: float) -> None:
        self.t += round(seconds * 1e9)

    def advance(self, ns: int) -> None:
        """Time passing outside the loop (a stall of the machine)."""
        self.t += ns


class ListInbox:
    """Command payloads pushed by the test, drained by the loop; like zenoh's ring, it
    keeps the newest ``capacity``."""

    def __init__(self, capacity: int = 256) -> None:
        self.pending: list[bytes] = []
        self.capacity = capacity

    def drain_newest(self) -> list[bytes]:
        out, self.pending = self.pending[-self.capacity:], []
        return out


class LocalRequest:
    """A control request answered in-process; answering twice fails the test."""

    def __init__(self, name: str, payload: bytes) -> None:
        self.name = name
        self.payload = payload
        self.body: bytes | None = None

    def reply(self, body: bytes) -> None:
        assert self.body is None, f"control {self.name!r} answered twice"
        self.body = body

    @property
    def answer(self) -> dict:
        assert self.body is not None, f"control {self.name!r} was not answered"
        return proto.decode_reply(self.body)


class ListControls:
    def __init__(self) -> None:
        self.pending: list[LocalRequest] = []
        self.received = 0
        self.busy = 0

    def poll(self, limit: int = 1 << 30) -> list[LocalRequest]:
        out, self.pending = self.pending[:limit], self.pending[limit:]
        self.received += len(out)
        return out


class RecordingPublisher:
    """Keeps every published state and diagnostics, decoded as a client would."""

    def __init__(self) -> None:
        self.states: list[np.void] = []
        self.diags: list[np.void] = []
        self.on_state: Callable[[], None] | None = None
        self.slow_publishes = 0

    def publish_state(self, payload: bytes) -> None:
        self.states.append(proto.decode_state(payload))
        if self.on_state is not None:
            self.on_state()

    def publish_diagnostics(self, payload: bytes) -> None:
        self.diags.append(proto.decode_diagnostics(payload))


# ---------------------------------------------------------------------- the rig
@pytest.fixture(scope="module")
def flat_scene() -> Scene:
    return load_scene(FLAT)


class Rig:
    """One loop serving one (or more) slots, fed and read by the test."""

    def __init__(self, scene: Scene, command_log: CommandLog | None = None,
                 **cfg_overrides) -> None:
        self.clock = FakeClock()
        self.cfg = load_server_config(**cfg_overrides)
        self.loop = ServerLoop(self.cfg, clock=self.clock, sleep=self.clock.sleep, spin_ns=0)
        self.slot, self.commands, self.controls, self.out = self.add(scene, self.cfg,
                                                                     command_log)
        self.loop.start()
        self.seq = 0

    def add(self, scene, cfg, command_log=None):
        slot = VehicleSlot(cfg, new_simulation(scene, cfg.period_s), command_log)
        ports = SlotPorts(ListInbox(), ListControls(), RecordingPublisher())
        self.loop.add(slot, ports)
        return slot, ports.commands, ports.controls, ports.publisher

    def send(self, seq: int | None = None, inbox: ListInbox | None = None, **fields) -> int:
        """Queue a command (the next seq by default) for the next tick."""
        if seq is None:
            self.seq += 1
            seq = self.seq
        fields.setdefault("sender_time_ns", 1000 + seq)
        (inbox or self.commands).pending.append(proto.encode_command(seq=seq, **fields))
        return seq

    def run(self, ticks: int = 1) -> np.void:
        """Run ``ticks`` ticks; the last published state."""
        for _ in range(ticks):
            self.loop.tick()
        return self.out.states[-1]

    def control(self, name: str, args: dict | None = None, payload: bytes | None = None,
                controls: ListControls | None = None) -> dict:
        """Send a control, run the tick that serves it, return the decoded reply."""
        if payload is None:
            payload = json.dumps(args).encode() if args is not None else b""
        req = LocalRequest(name, payload)
        (controls or self.controls).pending.append(req)
        self.loop.tick()
        return req.answer

    @property
    def counters(self) -> dict[str, int]:
        return self.slot.counters


@pytest.fixture
def rig(flat_scene) -> Rig:
    return Rig(flat_scene)


def approx32(value: float):
    """A float as it comes back through the state's float32 field."""
    return pytest.approx(float(np.float32(value)))


# ====================================================================== command arbitration
def test_the_newest_valid_command_of_a_tick_wins(rig):
    rig.run()
    for seq, throttle in ((1, 0.1), (3, 0.3), (2, 0.2)):
        rig.send(seq, throttle=throttle, gear=proto.Gear.D)
    state = rig.run()
    assert state["throttle"] == approx32(0.3)
    assert state["last_cmd_seq"] == 3 and state["last_cmd_sender_time_ns"] == 1003
    assert state["gear"] == proto.Gear.D
    assert rig.counters["cmd_received"] == 3
    assert rig.counters["cmd_stale"] == 2  # seq 1 superseded, seq 2 older than 3
    assert rig.counters["cmd_rejected"] == 0


def test_a_command_not_newer_than_the_last_applied_is_stale(rig):
    rig.send(10, throttle=0.5)
    rig.run()
    rig.send(10, throttle=0.9)
    rig.send(9, throttle=0.9)
    state = rig.run()
    assert state["throttle"] == approx32(0.5) and state["last_cmd_seq"] == 10
    assert rig.counters["cmd_stale"] == 2
    rig.send(11, throttle=0.7)
    assert rig.run()["throttle"] == approx32(0.7)


def test_sequence_numbers_wrap_around_at_2_to_the_32(rig):
    rig.send(0xFFFFFFFE, throttle=0.1)
    rig.send(0xFFFFFFFF, throttle=0.2)
    rig.send(0, throttle=0.3)
    rig.send(1, throttle=0.4)
    state = rig.run()
    assert state["last_cmd_seq"] == 1 and state["throttle"] == approx32(0.4)
    assert rig.counters["cmd_stale"] == 3
    # Half the sequence space ahead is not newer (RFC 1982): stale, not applied.
    rig.send(1 + 0x80000000, throttle=0.9)
    state = rig.run()
    assert state["last_cmd_seq"] == 1 and state["throttle"] == approx32(0.4)
    assert rig.counters["cmd_stale"] == 4


def test_invalid_commands_are_rejected_and_never_applied(rig, caplog):
    rig.send(1, throttle=0.25)
    rig.run()
    good = proto.encode_command(seq=2, throttle=0.9)
    wrong_version = (proto.PROTOCOL_VERSION + 1).to_bytes(2, "little") + good[2:]
    rig.commands.pending += [good[:-1], wrong_version, b""]
    with caplog.at_level(logging.WARNING, logger="simserver.server"):
        state = rig.run()
    assert state["throttle"] == approx32(0.25) and state["last_cmd_seq"] == 1
    assert rig.counters["cmd_rejected"] == 3 and rig.counters["cmd_received"] == 4
    # Logged at a bounded rate: one line for the burst, on the fake clock's time.
    assert sum("rejected command" in r.getMessage() for r in caplog.records) == 1


def test_slightly_out_of_range_inputs_are_clamped_and_applied(rig):
    rig.send(1, throttle=1.0005, steer=-1.0004)
    state = rig.run()
    assert state["throttle"] == 1.0 and state["steer"] == -1.0
    assert rig.counters["cmd_clamped"] == 1 and rig.counters["cmd_rejected"] == 0


# ====================================================================== watchdog
def test_the_watchdog_holds_the_car_until_the_first_command(rig):
    state = rig.run(3)
    assert state["flags"] & WATCHDOG
    assert state["throttle"] == 0.0 and state["brake"] == approx32(rig.cfg.watchdog_brake)
    assert state["cmd_age_s"] == -1.0 and state["last_cmd_seq"] == 0
    assert rig.counters["watchdog_trips"] == 0  # engaged from the start, not a trip
    rig.send(throttle=0.4, brake=0.0, gear=proto.Gear.D)
    state = rig.run()
    assert not state["flags"] & WATCHDOG
    assert state["throttle"] == approx32(0.4) and state["brake"] == 0.0
    assert state["cmd_age_s"] == 0.0


def test_the_watchdog_engages_after_its_timeout_and_releases_on_resumed_commands(rig, caplog):
    timeout_ticks = round(rig.cfg.watchdog_s / rig.cfg.period_s)  # 200
    rig.run()
    rig.send(seq=500, steer=0.2, throttle=0.6, gear=proto.Gear.D)
    rig.run()
    state = rig.run(timeout_ticks)  # exactly the timeout since the command: still driving
    assert not state["flags"] & WATCHDOG and state["throttle"] == approx32(0.6)
    assert state["cmd_age_s"] == approx32(rig.cfg.watchdog_s)
    speed_before = state["u_mps"]
    assert speed_before > 0.1
    with caplog.at_level(logging.INFO, logger="simserver.server"):
        caplog.clear()
        state = rig.run()  # one tick more: engaged
        assert state["flags"] & WATCHDOG
        assert rig.counters["watchdog_trips"] == 1
        # Throttle off, the watchdog's brake; the driver's steer and gear are kept.
        assert state["throttle"] == 0.0 and state["brake"] == approx32(rig.cfg.watchdog_brake)
        assert state["steer"] == approx32(0.2) and state["gear"] == proto.Gear.D
        # last_cmd_seq stays the last command applied (docs/protocol.md 2.2: 0 only
        # before the first), though the arbitration forgot it
        assert state["last_cmd_seq"] == 500
        held = rig.run(1500)
        assert held["flags"] & WATCHDOG and rig.counters["watchdog_trips"] == 1
        assert abs(held["u_mps"]) < 0.01 < speed_before  # the car is stopped and held
        # The last seq is forgotten: a restarted client counting from 1 is heard.
        rig.send(seq=1, throttle=0.3, gear=proto.Gear.D)
        state = rig.run()
    assert not state["flags"] & WATCHDOG
    assert state["last_cmd_seq"] == 1 and state["throttle"] == approx32(0.3)
    assert state["brake"] == 0.0
    messages = [r.getMessage() for r in caplog.records]
    assert messages.count("watchdog: no valid command for 200 ms, holding the car") == 1
    assert messages.count("watchdog released: commands resumed") == 1


def test_the_watchdog_timeout_comes_from_the_config(flat_scene):
    rig = Rig(flat_scene, watchdog_s=0.05, watchdog_brake=0.9)
    rig.run()
    rig.send(throttle=0.5)
    rig.run(51)
    assert not rig.out.states[-1]["flags"] & WATCHDOG
    state = rig.run()
    assert state["flags"] & WATCHDOG and state["brake"] == approx32(0.9)


# ====================================================================== pause and step
def test_pause_freezes_the_physics_and_the_tick_and_resume_continues(rig):
    rig.send(throttle=0.8, gear=proto.Gear.D)
    rig.run(50)
    reply = rig.control("pause")
    tick = rig.slot.tick
    assert reply == {"ok": True, "tick": tick, "paused": True}
    x = rig.slot.sim.x.copy()
    for _ in range(5):  # the driver keeps sending: still no step
        rig.send(throttle=0.8, gear=proto.Gear.D)
        state = rig.run()
        assert state["flags"] & PAUSED and state["tick"] == tick
    np.testing.assert_array_equal(rig.slot.sim.x, x)
    assert rig.control("pause")["paused"] is True  # idempotent
    reply = rig.control("resume")  # served after its tick's (paused) step phase
    assert reply == {"ok": True, "tick": tick, "paused": False}
    state = rig.run(3)
    assert not state["flags"] & PAUSED and state["tick"] == tick + 3


def test_step_runs_n_ticks_while_paused_then_stays_paused(rig):
    rig.run(10)
    rig.control("pause")
    tick = rig.slot.tick
    reply = rig.control("step", {"n": 3})
    assert reply == {"ok": True, "tick": tick, "until_tick": tick + 3}
    reply = rig.control("step")  # n defaults to 1; pending steps add up
    assert reply == {"ok": True, "tick": tick + 1, "until_tick": tick + 4}
    states = [rig.run() for _ in range(6)]
    assert [int(s["tick"]) for s in states] == [tick + 2, tick + 3, tick + 4, tick + 4,
                                               tick + 4, tick + 4]
    assert all(s["flags"] & PAUSED for s in states)
    assert rig.slot.steps_total == tick + 4


def test_pause_drops_pending_steps(rig):
    rig.control("pause")
    tick = rig.slot.tick
    rig.control("step", {"n": 100})
    rig.control("pause")
    assert rig.run(5)["tick"] == tick + 1  # the one step run in the second pause's tick


def test_step_is_refused_unless_paused(rig):
    rig.run(3)
    reply = rig.control("step", {"n": 2})
    assert reply == {"ok": False, "error": "step: the server is not paused (pause first)",
                     "field": "step"}
    # no n sent: the error names no argument that was not sent (it never named one)
    assert rig.control("step")["field"] == "step"
    assert rig.slot.steps_to_run == 0
    reply = rig.control("step", {"n": 0})  # validated against the protocol's range first
    assert reply["ok"] is False and reply["field"] == "n" and "outside [1, 100000]" in \
        reply["error"]


# ====================================================================== other controls
def test_reset_goes_back_to_the_scene_or_to_a_pose_at_rest(rig):
    rig.send(throttle=0.8, gear=proto.Gear.D)
    rig.run(300)
    assert rig.slot.sim.x[L.U_MPS] > 0.1
    reply = rig.control("reset")
    assert reply == {"ok": True, "tick": 0, "pose": {"x_m": 0.0, "y_m": 0.0, "yaw_rad": 0.0}}
    assert rig.slot.tick == 0 and rig.slot.sim.x[L.U_MPS] == 0.0
    state = rig.run()
    assert state["tick"] == 1 and state["sim_time_s"] == pytest.approx(0.001)
    pose = {"x_m": 12.5, "y_m": -3.0, "yaw_rad": 1.0}
    reply = rig.control("reset", {"pose": pose})
    assert reply == {"ok": True, "tick": 0, "pose": pose}
    assert rig.slot.sim.x[L.X_M] == 12.5 and rig.slot.sim.x[L.U_MPS] == 0.0
    # Counters are kept across a reset.
    assert rig.counters["cmd_received"] == 1


def test_a_reset_at_speed_settles_between_ticks_and_equals_a_reset_in_one_go(flat_scene):
    """Issue 17: the settling of a start at speed (2000 steps at 1 m/s) runs
    SETTLE_STEPS_PER_TICK steps per tick beside the running car, which keeps its ticks and
    its commands; the state swapped in is the one a reset in place gives, to the bit."""
    from simserver.core.start import settle_steps
    from simserver.server.loop import SETTLE_STEPS_PER_TICK

    rig = Rig(flat_scene)
    rig.send(throttle=0.3, gear=proto.Gear.D, steer=0.02)
    rig.run(50)
    reference = new_simulation(flat_scene, rig.cfg.period_s)  # the same car, reset in place
    reference.inputs[:] = rig.slot.sim.inputs
    reference.reset(None, 1.0)
    req = LocalRequest("reset", b'{"u_mps": 1.0}')
    rig.controls.pending.append(req)
    rig.run()
    ticks_needed = -(-settle_steps(rig.slot.sim.model, 1.0) // SETTLE_STEPS_PER_TICK)
    assert ticks_needed > 10 and req.body is None  # not answered within its first tick
    before = int(rig.run()["tick"])
    busy = rig.control("reset", {"u_mps": 5.0})  # one start at a time, counted busy
    assert busy["ok"] is False and "busy" in busy["error"] and busy["field"] == "reset"
    ticks = 3  # the request's tick, before's and busy's
    while req.body is None and ticks < 2 * ticks_needed:  # the car runs on, commands apply
        rig.send(throttle=0.3, gear=proto.Gear.D, steer=0.02)
        state = rig.run()
        ticks += 1
        assert int(state["tick"]) == before + ticks - 2
        assert rig.slot.arbiter.last_applied_seq == rig.seq
    assert ticks == ticks_needed  # answered in the tick of its last piece
    assert req.answer == {"ok": True, "tick": 0, "u_mps": 1.0,
                          "pose": {"x_m": 0.0, "y_m": 0.0, "yaw_rad": 0.0}}
    assert rig.slot.tick == 0  # swapped in after that tick's step: the next one is tick 1
    assert np.array_equal(rig.slot.sim.x, reference.x)
    assert np.array_equal(rig.slot.sim.out, reference.out)


def test_a_bad_reset_changes_nothing(rig):
    rig.run(20)
    reply = rig.control("reset", {"pose": {"x_m": 1.0, "y_m": 0.0, "yaw_rad": 7.0}})
    assert reply["ok"] is False and reply["field"] == "pose.yaw_rad"
    reply = rig.control("reset", {"pose": {"x_m": 1.0}})
    assert reply["ok"] is False and reply["field"] == "pose.y_m"
    assert rig.slot.tick == 22 and rig.slot.sim.x[L.X_M] == 0.0


def test_set_road_changes_the_given_members_only(rig):
    reply = rig.control("set_road", {"grade_pct": 10})
    road = {"grade_pct": 10.0, "cross_slope_pct": 0.0, "friction_scale": 1.0}
    assert reply == {"ok": True, "road": road}
    assert rig.slot.sim.road == road
    reply = rig.control("set_road", {"friction_scale": 0.5, "cross_slope_pct": -2})
    road = {"grade_pct": 10.0, "cross_slope_pct": -2.0, "friction_scale": 0.5}
    assert reply == {"ok": True, "road": road} and rig.slot.sim.road == road
    # The parked car on the 10 % grade, no driver: the watchdog's brake holds it.
    assert abs(rig.run(500)["u_mps"]) < 1e-3


def test_a_bad_set_road_changes_nothing(rig):
    before = dict(rig.slot.sim.road)
    for args, field in (({"friction_scale": 5.0}, "friction_scale"),
                        ({"grade_pct": 10, "camber": 1}, "camber"), ({}, "request")):
        reply = rig.control("set_road", args)
        assert reply["ok"] is False and reply["field"] == field, reply
        assert reply["error"].startswith(f"{field}:")
    assert rig.control("set_road", payload=b'{"grade_pct": NaN}')["field"] == "request"
    assert rig.slot.sim.road == before


def test_get_config_reports_the_active_configuration(rig):
    rig.control("set_road", {"grade_pct": 3})
    reply = rig.control("get_config")
    assert reply["ok"] is True and reply["protocol_version"] == proto.PROTOCOL_VERSION
    config = reply["config"]
    assert set(config) == {"server", "vehicle", "scene", "road", "keys", "ros2", "load_worker"}
    assert config["ros2"] is None  # no ROS 2 adapter (tests/test_ros2.py: one that runs)
    assert config["load_worker"] is None  # loads run inline here (tests/test_server.py: a
    # live server's worker)
    assert config["server"]["watchdog_s"] == 0.2 and config["server"]["period_s"] == 0.001
    # paths relative to the config folder holding them: no absolute server path is shown
    assert config["scene"]["path"] == "scenes/flat_paper_sedan.yaml"
    assert config["server"]["path"] == "server/default.yaml"
    assert config["road"]["grade_pct"] == 3.0
    assert config["vehicle"]["name"] == rig.slot.sim.scene.vehicle.name
    assert config["keys"] == {"cmd": "simserver/car0/cmd", "state": "simserver/car0/state",
                              "diag": "simserver/car0/diag", "alive": "simserver/car0/alive"}


def test_load_swaps_the_scene_and_resets(rig):
    rig.send(throttle=0.5, gear=proto.Gear.D)
    rig.run(100)
    sim = rig.slot.sim
    # Relative to the server config's folder (configs/server), as before.
    reply = rig.control("load", {"scene": "../scenes/hill_10pct_paper_sedan.yaml"})
    assert reply == {"ok": True, "scene": "scenes/hill_10pct_paper_sedan.yaml",
                     "vehicle": "vehicles/paper_sedan/vehicle.yaml"}
    assert sim.scene.vehicle.path == REPO_CONFIGS / "vehicles/paper_sedan/vehicle.yaml"
    assert sim.road["grade_pct"] == 10.0 and rig.slot.scene_path == HILL
    assert rig.slot.tick == 0 and sim.x[L.U_MPS] == 0.0
    after = [rig.run() for _ in range(3)]
    assert rig.loop.pacer.skipped_ticks == 0
    assert [int(s["tick"]) for s in after] == [1, 2, 3]
    assert rig.control("get_config")["config"]["scene"]["path"] == \
        "scenes/hill_10pct_paper_sedan.yaml"


def test_load_paths_are_relative_to_the_working_directory_then_the_config_folders(
        rig, monkeypatch):
    monkeypatch.chdir(REPO_CONFIGS.parent)  # the repository root, as a user runs it
    reply = rig.control("load", {"scene": "configs/scenes/hill_10pct_paper_sedan.yaml"})
    # replies show paths relative to the config folder (docs/security.md)
    assert reply["ok"] is True and reply["scene"] == "scenes/hill_10pct_paper_sedan.yaml", reply
    assert rig.slot.scene_path == HILL
    reply = rig.control("load", {"scene": "scenes/flat_paper_sedan.yaml"})  # configs/
    assert reply["ok"] is True and reply["scene"] == "scenes/flat_paper_sedan.yaml", reply
    assert rig.slot.scene_path == FLAT
    reply = rig.control("load", {"scene": "scenes/nowhere.yaml"})
    assert reply["ok"] is False and reply["field"] == "scene"
    # the error lists every place it looked, the working directory first, each shown
    # relative to the config folder or the working directory (no absolute server paths)
    assert rig.cfg.config_dirs == [REPO_CONFIGS] and rig.cfg.path.parent == REPO_CONFIGS / "server"
    assert reply["error"] == "scene: scenes/nowhere.yaml: no such file; looked in " \
                             "scenes/nowhere.yaml, scenes/nowhere.yaml, server/scenes/nowhere.yaml"
    assert str(REPO_CONFIGS.parent) not in reply["error"]


class HeldPreparer:
    """A worker the test finishes by hand: the job is seen, its result set later."""

    def __init__(self) -> None:
        self.jobs: list[tuple] = []
        self.restarts = 0

    def submit(self, fn, *args):
        from concurrent.futures import Future

        future = Future()
        self.jobs.append((fn, args, future))
        return future

    def restart(self) -> None:
        self.restarts += 1

    def finish(self) -> None:
        fn, args, future = self.jobs.pop(0)
        future.set_result(fn(*args))


def test_load_is_prepared_off_the_tick_and_applied_between_two_ticks(flat_scene):
    rig = Rig(flat_scene)
    held = rig.loop.preparer = HeldPreparer()
    rig.send(throttle=0.5, gear=proto.Gear.D)
    rig.run(10)
    req = LocalRequest("load", b'{"scene": "../scenes/hill_10pct_paper_sedan.yaml"}')
    rig.controls.pending.append(req)
    rig.run()
    assert req.body is None and len(held.jobs) == 1  # handed over, not read in the tick
    # meanwhile the car runs on, and another load is answered busy (counted)
    ticks = [int(rig.run()["tick"]) for _ in range(5)]
    assert ticks == list(range(ticks[0], ticks[0] + 5)) and rig.slot.sim.road["grade_pct"] == 0
    busy = rig.control("load", {"scene": "../scenes/flat_paper_sedan.yaml"})
    assert busy["ok"] is False and busy["field"] == "load" and "busy" in busy["error"]
    bad = rig.control("load", {"N": 1})  # bad arguments are named first, busy or not
    assert bad["ok"] is False and bad["field"] == "N"
    assert rig.control("get_config")["ok"] is True  # quick controls are still served
    held.finish()
    # applied in pieces, one a tick after that tick's step: the result mapped, the model
    # and start state built, committed (simserver.server.loop: each well under a tick)
    before = int(rig.run()["tick"])
    assert int(rig.run()["tick"]) == before + 1 and req.body is None
    assert rig.slot.sim.road["grade_pct"] == 0  # not yet swapped in
    rig.run()
    assert req.answer["ok"] is True and req.answer["scene"] == "scenes/hill_10pct_paper_sedan.yaml"
    assert rig.slot.sim.road["grade_pct"] == 10.0 and rig.slot.tick == 0
    assert rig.run()["tick"] == 1
    rig.run(int(1 / (rig.cfg.diag_hz * rig.cfg.period_s)))
    assert int(rig.out.diags[-1]["ctl_busy"]) == 1


def test_a_load_that_never_finishes_is_answered_and_its_worker_restarted(flat_scene):
    rig = Rig(flat_scene)
    held = rig.loop.preparer = HeldPreparer()
    req = LocalRequest("load", b'{"scene": "../scenes/hill_10pct_paper_sedan.yaml"}')
    rig.controls.pending.append(req)
    rig.run()
    rig.run(int(rig.loop.job_timeout_ns / MS) - 5)
    assert req.body is None
    rig.run(10)
    assert req.answer["ok"] is False and "not prepared within" in req.answer["error"]
    assert held.restarts == 1 and rig.slot.scene_path == FLAT
    assert rig.control("get_config")["ok"] is True


def test_a_load_that_fails_changes_nothing(flat_scene, tmp_path):
    bad = tmp_path / "bad_scene.yaml"
    bad.write_text("road: {grade_pct: 5.0}\n")  # no vehicle
    rig = Rig(flat_scene, config_dirs=[str(REPO_CONFIGS), str(tmp_path)])
    rig.run(5)
    cases = [
        ({"scene": "/etc/simserver.yaml"}, "scene", "outside the server's config directories"),
        ({"scene": "scenes/no_such_scene.yaml"}, "scene", "no such file"),
        ({"vehicle": "vehicles/none.yml"}, "vehicle", "no such file"),
        ({"scene": str(bad)}, "scene", "scene: bad_scene.yaml: missing key 'vehicle'"),
        ({"scene": "scenes/flat.txt"}, "scene", "not a .yaml/.yml/.xosc file"),
        ({}, "request", "give at least one of"),
    ]
    for args, field, text in cases:
        reply = rig.control("load", args)
        assert reply["ok"] is False and reply["field"] == field, reply
        assert text in reply["error"], reply
    assert rig.slot.scene_path == FLAT and rig.slot.tick == 5 + len(cases)
    assert rig.slot.sim.scene is flat_scene


def test_load_confines_nested_files_and_quotes_nothing_of_them(flat_scene, tmp_path):
    """Issue 14 item 5: a scene inside the config folders whose ``vehicle`` (or a vehicle
    whose subsystem or tire file) lies outside them, or is no regular file, is refused
    without the file being read; no reply shows an absolute server path."""
    inside = tmp_path / "configs"
    inside.mkdir()
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    secret = outside / "secret.yaml"
    secret.write_text("name: SECRET-LINE\n")
    fifo = inside / "fifo.yaml"
    os.mkfifo(fifo)
    sedan = REPO_CONFIGS / "vehicles" / "paper_sedan"
    vehicle = (sedan / "vehicle.yaml").read_text()
    (inside / "vehicle_out.yaml").write_text(vehicle.replace("chassis.yaml", str(secret)))
    for name, target in (("proc", "/proc/self/status"), ("out", str(secret)),
                         ("fifo", "fifo.yaml"), ("nested", "vehicle_out.yaml")):
        (inside / f"scene_{name}.yaml").write_text(f"vehicle: {target}\n")
    rig = Rig(flat_scene, config_dirs=[str(inside)])
    for name, text in (("proc", "key 'vehicle': refers to a file outside"),
                       ("out", "key 'vehicle': refers to a file outside"),
                       ("fifo", "key 'vehicle': " + "fifo.yaml: not a regular file"),
                       ("nested", "key 'chassis': refers to a file outside")):
        reply = rig.control("load", {"scene": str(inside / f"scene_{name}.yaml")})
        assert reply["ok"] is False and reply["field"] == "scene", reply
        assert text in reply["error"], reply
        assert "SECRET" not in reply["error"] and "State:" not in reply["error"], reply
        assert str(tmp_path) not in reply["error"] and str(REPO_CONFIGS) not in reply["error"]
    reply = rig.control("load", {"scene": str(secret)})
    assert reply["field"] == "scene" and str(tmp_path) not in reply["error"], reply
    assert rig.slot.sim.scene is flat_scene


def test_unknown_controls_and_bad_requests_get_an_error_naming_the_field(rig):
    reply = rig.control("explode")
    assert reply["ok"] is False and reply["field"] == "control"
    assert rig.control("pause", payload=b"[1, 2]")["field"] == "request"
    assert rig.control("pause", payload=b"\xff")["field"] == "request"
    assert rig.control("pause", {"now": True})["field"] == "now"
    assert rig.slot.paused is False


def test_a_failing_handler_is_answered_and_the_loop_goes_on(rig, monkeypatch, caplog):
    def broken(**road):
        raise RuntimeError("bug")

    monkeypatch.setattr(rig.slot.sim, "set_road", broken)
    with caplog.at_level(logging.ERROR, logger="simserver.server"):
        reply = rig.control("set_road", {"grade_pct": 1})
    assert reply == {"ok": False, "error": "set_road: internal error (RuntimeError)",
                     "field": "set_road"}
    assert any("control set_road failed" in r.getMessage() for r in caplog.records)
    tick = rig.slot.tick
    assert rig.run(3)["tick"] == tick + 3


def test_a_validator_bug_is_answered_as_a_bad_request(rig, monkeypatch):
    def broken(name, payload):
        raise OverflowError("int too large")

    monkeypatch.setattr(proto, "validate_control", broken)
    reply = rig.control("set_road", {"grade_pct": 1})
    assert reply == {"ok": False, "error": "request: could not be validated (OverflowError)",
                     "field": "request"}
    assert rig.slot.sim.road["grade_pct"] == 0.0


def test_the_control_table_serves_every_control_of_the_protocol():
    assert tuple(CONTROLS) == proto.CONTROL_NAMES
    # the one control that reads files runs off the tick
    assert [n for n, c in CONTROLS.items() if c.job is not None] == ["load"]


def test_several_controls_in_one_tick_are_each_answered_in_order(rig):
    reqs = [LocalRequest("pause", b""), LocalRequest("step", b'{"n": 2}'),
            LocalRequest("get_config", b"")]
    rig.controls.pending += reqs
    rig.run()
    assert [r.answer["ok"] for r in reqs] == [True, True, True]
    assert reqs[1].answer["until_tick"] == reqs[0].answer["tick"] + 2


# ====================================================================== publishing
def test_state_and_diagnostics_rates_and_counters(flat_scene):
    rig = Rig(flat_scene, state_every=3, diag_hz=100)  # diagnostics every 10 ticks
    rig.send(throttle=0.2)
    rig.commands.pending.append(b"junk")
    rig.run(30)
    assert [int(s["tick"]) for s in rig.out.states] == list(range(1, 31, 3))
    assert rig.counters["state_published"] == 10
    assert [int(d["tick"]) for d in rig.out.diags] == [1, 11, 21]
    last = rig.out.diags[-1]
    assert last["cmd_received"] == 2 and last["cmd_rejected"] == 1
    assert last["state_published"] == 7
    assert last["uptime_s"] == pytest.approx(0.020, abs=1e-4)
    assert last["window_ticks"] == 21


def test_late_ticks_are_flagged_as_catch_up(rig):
    rig.run(5)
    rig.clock.advance(3 * MS + MS // 2)  # the machine stalled 3.5 ms
    flags = [int(rig.run()["flags"]) & CATCHUP for _ in range(6)]
    assert flags == [CATCHUP] * 3 + [0] * 3  # 2.5 periods behind, then back on time
    assert rig.loop.pacer.skipped_ticks == 0


def test_the_first_state_after_skipped_deadlines_is_flagged(rig):
    rig.run(5)
    rig.clock.advance(2000 * MS)  # SIGSTOP for 2 s: far beyond max_catchup_ticks
    states = [rig.run() for _ in range(3)]
    assert rig.loop.pacer.skipped_ticks > 1000
    skipped = [bool(int(s["flags"]) & proto.StateFlag.SKIPPED) for s in states]
    assert skipped == [True, False, False]


def test_the_brake_hold_flag_means_a_brake_holds(flat_scene):
    """At rest on the flat with brake 0 and the parking brake off nothing holds the car
    but rolling resistance: no flag. With the pedal, or the parking brake (rear wheels
    only): flagged."""
    rig = Rig(flat_scene)

    def hold(ticks: int, **command) -> np.void:  # a driver holding its inputs
        for _ in range(ticks):
            rig.send(**command)
            state = rig.run()
        return state

    state = hold(300, gear=proto.Gear.D, brake=0.0)
    assert abs(state["u_mps"]) < 1e-3 and state["brake"] == 0.0
    assert not int(state["flags"]) & (proto.StateFlag.BRAKE_HOLD | WATCHDOG)
    assert list(state["brake_held"]) == [0, 0, 0, 0]
    state = hold(50, gear=proto.Gear.D, brake=0.5)
    assert int(state["flags"]) & proto.StateFlag.BRAKE_HOLD
    assert list(state["brake_held"]) == [1, 1, 1, 1]
    state = hold(50, gear=proto.Gear.N, parking_brake=True)
    assert int(state["flags"]) & proto.StateFlag.BRAKE_HOLD
    assert list(state["brake_held"]) == [0, 0, 1, 1]


def test_reset_forgets_the_last_seq(rig):
    """docs/protocol.md 2.1: the server forgets the last seq on ctl/reset, so a restarted
    client may count from 1 again at once."""
    rig.send(seq=900, throttle=0.2, gear=proto.Gear.D)
    rig.run()
    assert rig.control("reset")["ok"] is True
    rig.send(seq=1, throttle=0.6, gear=proto.Gear.D)
    state = rig.run()
    assert state["last_cmd_seq"] == 1 and state["throttle"] == approx32(0.6)
    assert rig.counters["cmd_stale"] == 0


def test_commands_overwritten_in_a_full_buffer_are_counted(flat_scene):
    rig = Rig(flat_scene)
    rig.commands.capacity = 8
    rig.send(seq=1, throttle=0.1)
    rig.run()
    for seq in range(2, 22):  # 20 arrive between two ticks: 12 overwritten
        rig.send(seq=seq, throttle=0.2)
    state = rig.run()
    assert state["last_cmd_seq"] == 21
    assert rig.counters["cmd_dropped"] == 12 and rig.counters["cmd_received"] == 9
    rig.send(seq=30, throttle=0.3)  # a gap without a full buffer is the sender's own
    rig.run()
    assert rig.counters["cmd_dropped"] == 12


def test_control_requests_are_served_a_few_per_tick(rig):
    reqs = [LocalRequest("get_config", b"") for _ in range(10)]
    rig.controls.pending += reqs
    rig.run()
    assert sum(r.body is not None for r in reqs) == rig.loop.controls_per_tick
    rig.run(3)
    assert all(r.answer["ok"] for r in reqs)


def test_a_non_finite_state_is_reset(rig, caplog):
    rig.run(5)
    rig.slot.sim.x[L.U_MPS] = np.nan
    with caplog.at_level(logging.ERROR, logger="simserver.server"):
        rig.run()
    assert np.isfinite(rig.slot.sim.x).all()
    assert any("non-finite state at tick" in r.getMessage() for r in caplog.records)


# ====================================================================== command log
def test_the_command_log_replays_the_live_run_bit_for_bit(flat_scene, tmp_path):
    path = tmp_path / "commands.jsonl"
    log = CommandLog(path, {"scene": str(FLAT), "dt_s": 0.001, "step": 0})
    rig = Rig(flat_scene, command_log=log)
    rig.run(10)
    for _ in range(200):  # the same command repeated: one inputs line
        rig.send(throttle=0.7, steer=0.1, gear=proto.Gear.D)
        rig.run()
    rig.control("set_road", {"grade_pct": 4})
    rig.send(throttle=0.0, brake=0.3, gear=proto.Gear.D)
    rig.run(50)
    rig.control("reset", {"pose": {"x_m": 5.0, "y_m": 1.0, "yaw_rad": 0.5}})
    rig.control("pause")
    rig.run(20)
    rig.control("step", {"n": 5})
    rig.run(10)
    rig.control("resume")
    rig.control("load", {"scene": "../scenes/hill_10pct_paper_sedan.yaml"})
    rig.run(30)
    log.close(rig.slot.steps_total, rig.slot.sim.x)
    entries = read_command_log(path)
    kinds = [next(k for k in e if k != "step") for e in entries[1:]]
    assert kinds == ["inputs", "inputs", "set_road", "inputs", "reset", "load", "end"]
    assert entries[-2]["load"] == {"scene": str(HILL), "vehicle": None}
    assert entries[1]["step"] == 0 and entries[1]["inputs"][L.IN_BRAKE] == 0.6  # watchdog
    replay = replay_command_log(path)
    assert replay.steps == rig.slot.steps_total
    np.testing.assert_array_equal(replay.final_state, rig.slot.sim.x)
    np.testing.assert_array_equal(replay.logged_final_state, rig.slot.sim.x)


# ====================================================================== several slots
def test_one_loop_serves_several_vehicles_apart(flat_scene):
    rig = Rig(flat_scene)
    car1_cfg = load_server_config(vehicle_id="car1")
    car1, inbox1, controls1, out1 = rig.add(flat_scene, car1_cfg)
    rig.send(seq=7, throttle=0.5, gear=proto.Gear.D)
    rig.send(seq=3, throttle=0.2, gear=proto.Gear.R, inbox=inbox1)
    rig.send(seq=4, throttle=0.3, gear=proto.Gear.R, inbox=inbox1)
    rig.run()
    assert rig.control("pause", controls=controls1)["paused"] is True
    rig.run(10)
    car0_state, car1_state = rig.out.states[-1], out1.states[-1]
    assert car0_state["last_cmd_seq"] == 7 and car0_state["throttle"] == approx32(0.5)
    assert car1_state["last_cmd_seq"] == 4 and car1_state["throttle"] == approx32(0.3)
    assert car0_state["gear"] == proto.Gear.D and car1_state["gear"] == proto.Gear.R
    assert car1_state["flags"] & PAUSED and not car0_state["flags"] & PAUSED
    assert car0_state["tick"] == 12 and car1_state["tick"] == 2
    assert rig.counters["cmd_received"] == 1 and rig.counters["cmd_stale"] == 0
    assert car1.counters["cmd_received"] == 2 and car1.counters["cmd_stale"] == 1
    config = rig.control("get_config", controls=controls1)["config"]
    assert config["keys"]["cmd"] == "simserver/car1/cmd"
    final = rig.loop.final_stats()
    assert set(final["vehicles"]) == {"car0", "car1"}
    assert final["vehicles"]["car1"]["ticks"] == 2


# ====================================================================== the loop
def test_run_ticks_until_stopped_and_reports_the_stopped_line_fields(rig):
    def stop_after_25():
        if len(rig.out.states) == 25:
            rig.loop.stop()

    rig.out.on_state = stop_after_25
    rig.loop.running = True
    rig.loop.run()
    final = rig.loop.final_stats()
    assert final["ticks"] == 25 and final["steps_total"] == 25
    assert list(final) == ["ticks", "steps_total", "uptime_s", "lateness_p50_us",
                           "lateness_p99_us", "lateness_max_us", "overruns",
                           "skipped_ticks", "late_ticks", "cmd_received", "cmd_rejected",
                           "cmd_clamped", "cmd_stale", "state_published", "watchdog_trips",
                          "nonfinite_stops", "cmd_dropped", "ctl_received", "ctl_busy",
                          "publish_slow", "contact_events", "contact_events_lost"]


def test_the_logic_needs_no_wall_clock(rig, monkeypatch):
    """Everything the loop reads comes from the injected clock: time.* is never called."""
    import time

    def forbidden(*_):
        raise AssertionError("the loop read the wall clock")

    for name in ("monotonic", "perf_counter", "perf_counter_ns", "monotonic_ns", "sleep"):
        monkeypatch.setattr(time, name, forbidden)
    rig.commands.pending.append(b"junk")  # the rate-limited warning too
    rig.send(throttle=0.1)
    rig.run(250)


def test_slots_keep_their_own_keys(flat_scene):
    cfg = load_server_config(prefix="lab1/simserver", vehicle_id="cockpit-a")
    slot = VehicleSlot(cfg, new_simulation(flat_scene, cfg.period_s))
    assert slot.keys.base == "lab1/simserver/cockpit-a"



# ====================================================================== non-finite states
MF_SCENE = REPO_CONFIGS / "scenes" / "flat_mf_hatchback.yaml"


def test_a_non_finite_state_is_never_published_and_stops_the_car(caplog, tmp_path):
    """Issue 14 item 3 live: a tire whose friction scale overflows (LMUX = 1e300, now
    refused by the .tir check, so put in past it) made 3 001 of 3 002 published states NaN
    and logged 1 000 lines a second. Now: checked before publishing, the car stopped at
    rest at the scene's start and paused, flags bit 4 and ``nonfinite_stops``, one log line
    per episode; a reset starts a new episode."""
    from simserver.core.tire_layout import TP_MODEL_BASE
    from simserver.core.tire_mf61 import P_LMUX

    scene = load_scene(MF_SCENE)
    log_path = tmp_path / "cmd.jsonl"
    rig = Rig(scene, command_log=CommandLog(log_path, {"scene": str(MF_SCENE),
                                                       "dt_s": 0.001, "step": 0}))
    rig.slot.sim.tp[:, TP_MODEL_BASE + P_LMUX] = 1e300
    caplog.set_level(logging.ERROR, logger="simserver.server")
    for _ in range(300):
        rig.send(throttle=1.0, gear=proto.Gear.D)
        rig.run()
    states = rig.out.states
    assert len(states) == 300
    for state in states:
        for name in state.dtype.names:
            assert np.isfinite(state[name]).all(), (int(state["tick"]), name)
    faulted = [s for s in states if int(s["flags"]) & proto.StateFlag.FAULT]
    assert faulted, "the overflowing tire never went non-finite: the test tests nothing"
    first = faulted[0]
    assert int(first["flags"]) & PAUSED and first["u_mps"] == 0.0 and first["x_m"] == 0.0
    assert rig.slot.paused and rig.counters["nonfinite_stops"] == 1
    assert all(int(s["flags"]) & proto.StateFlag.FAULT for s in states[len(states) -
                                                                       len(faulted):])
    errors = [r for r in caplog.records if "non-finite state" in r.getMessage()]
    assert len(errors) == 1
    # resumed into the same fault: stopped again, counted, not logged again
    rig.control("resume")
    rig.run(rig.loop.diag_every)  # up to the next diagnostics
    assert rig.counters["nonfinite_stops"] == 2 and rig.slot.paused
    assert len([r for r in caplog.records if "non-finite state" in r.getMessage()]) == 1
    assert rig.loop.slots[0][1].publisher.diags[-1]["nonfinite_stops"] == 2
    # a reset is a new episode: flag cleared
    rig.slot.sim.tp[:, TP_MODEL_BASE + P_LMUX] = 1.0
    rig.control("reset")
    rig.control("resume")
    assert not int(rig.run(5)["flags"]) & proto.StateFlag.FAULT


CHILD_AT_IDLE = r"""
import os, signal, sys
os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
def on_term(*_):
    print(os.sched_getscheduler(0), flush=True)  # the policy its handler ran under
    sys.exit(0)
signal.signal(signal.SIGTERM, on_term)
print("ready", flush=True)
signal.pause()
"""


def test_a_child_at_idle_priority_is_stopped_at_normal_priority():
    """The viewer and the ROS 2 adapter run at idle CPU priority: on a busy machine one
    gets next to no CPU to run its SIGTERM handler (the README's server took 30 s to stop),
    so the server puts its threads back to normal priority before it terminates it."""
    import subprocess
    import sys

    from simserver.server.app import SimServer

    child = subprocess.Popen([sys.executable, "-c", CHILD_AT_IDLE], stdout=subprocess.PIPE,
                             text=True)
    try:
        assert child.stdout.readline().strip() == "ready"
        assert os.sched_getscheduler(child.pid) == os.SCHED_IDLE
        SimServer._stop_viewer(child)
        assert child.returncode == 0  # stopped by its handler, not killed
        assert int(child.stdout.readline()) == os.SCHED_OTHER
    finally:
        if child.poll() is None:
            child.kill()
        child.wait()
