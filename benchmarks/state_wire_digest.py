"""Digest of the published VehicleState bytes, to compare two trees bit for bit.

The real vehicle slot (``VehicleSlot.fill_state``, the bytes the loop publishes) on the
real simulation, 3000 ticks on the flat, the 10 % hill and the hills height map, driven,
steered and braked, with catch-up ticks and a moving command clock; one SHA-256 per scene.
Run it with ``PYTHONPATH`` at each tree and compare the lines::

    PYTHONPATH=/path/to/before python -m benchmarks.state_wire_digest
    PYTHONPATH=/path/to/after  python -m benchmarks.state_wire_digest

(issue 29 item 5: the state table changed how the state is filled, not its bytes.)

``world_digests`` does the same for the live loop's several cars in one world
(``ServerLoop`` on a fake clock, list ports as ``tests/test_server_logic.py``'s): 4 cars
on the crest-curve road and on a 10 % plane, two driven by commands, two by the built-in
driver; one SHA-256 per world of every state each car published and of the world
messages (issue 30: the states of a world's cars are filled in one go, not their bytes).
"""

from __future__ import annotations

import hashlib
import math

SCENES = ("flat_paper_sedan", "hill_10pct_paper_sedan", "hills_paper_sedan")
TICKS = 3000
WORLDS = {"crest_curve_paper_sedan": [  # road "0", lanes -1 (along s) and 1 (against)
    {"id": "car0", "start": {"road": "0", "s": 150.0, "lane": -1}},
    {"id": "car1", "start": {"road": "0", "s": 200.0, "lane": 1}},
    {"id": "t2", "start": {"road": "0", "s": 120.0, "lane": -1}, "driven_by": "driver",
     "driver": {"path": {"road": "0", "lane": -1}, "idm": {"v0_mps": 12.0}}},
    {"id": "t3", "start": {"road": "0", "s": 240.0, "lane": 1}, "driven_by": "driver",
     "driver": {"path": {"road": "0", "lane": 1}, "idm": {"v0_mps": 12.0}}}],
    "hill_10pct_paper_sedan": [
    {"id": "car0", "pose": {"x_m": 40.0, "y_m": 0.0, "yaw_rad": 0.0}},
    {"id": "car1", "pose": {"x_m": 0.0, "y_m": 6.0, "yaw_rad": 0.3}},
    {"id": "t2", "pose": {"x_m": 10.0, "y_m": 0.0, "yaw_rad": 0.0}, "driven_by": "driver",
     "driver": {"path": {"points": [[-50.0, 0.0], [2000.0, 0.0]]},
                "idm": {"v0_mps": 12.0, "s0_m": 2.0}}},
    {"id": "t3", "pose": {"x_m": -20.0, "y_m": 0.0, "yaw_rad": 0.0}, "driven_by": "driver",
     "driver": {"path": {"points": [[-50.0, 0.0], [2000.0, 0.0]]},
                "idm": {"v0_mps": 12.0, "s0_m": 2.0}}}]}


def digests(ticks: int = TICKS) -> dict[str, str]:
    """Scene name -> SHA-256 of the concatenated state payloads of ``ticks`` ticks."""
    from simserver.core import layout as L
    from simserver.server.app import new_simulation
    from simserver.server.config import DEFAULT_SERVER_CONFIG, REPO_CONFIGS, load_server_config
    from simserver.server.slot import VehicleSlot
    from simserver.sim.scene import load_scene

    cfg = load_server_config(DEFAULT_SERVER_CONFIG, viewer="off")
    out = {}
    for name in SCENES:
        scene = load_scene(REPO_CONFIGS / "scenes" / f"{name}.yaml")
        slot = VehicleSlot(cfg, new_simulation(scene, cfg.period_s))
        h = hashlib.sha256()
        for k in range(ticks):
            inputs = slot.sim.inputs
            inputs[L.IN_GEAR] = L.GEAR_D
            inputs[L.IN_THROTTLE] = 0.6 if k < 2 * ticks // 3 else 0.0
            inputs[L.IN_BRAKE] = 0.0 if k < 2 * ticks // 3 else 0.8
            inputs[L.IN_STEER] = 0.3 * math.sin(k * 0.003)
            slot.advance()
            h.update(slot.fill_state(1_000_000 * k, k % 7 == 0))
        out[name] = h.hexdigest()
    return out


class _Inbox:
    capacity = 256

    def __init__(self) -> None:
        self.pending: list[bytes] = []

    def drain_newest(self) -> list[bytes]:
        out, self.pending = self.pending, []
        return out


class _Controls:
    received = busy = 0

    def poll(self, limit: int) -> list:
        return []


class _Publisher:
    slow_publishes = 0

    def __init__(self, h) -> None:
        self.h = h

    def publish_state(self, payload: bytes) -> None:
        self.h.update(payload)

    def publish_diagnostics(self, payload: bytes) -> None:
        """Not digested: they carry the process's CPU time."""


class _Clock:
    def __init__(self) -> None:
        self.t = 10_000_000_000

    def __call__(self) -> int:
        self.t += 1_000
        return self.t

    def sleep(self, seconds: float) -> None:
        self.t += round(seconds * 1e9)


def world_digests(ticks: int = TICKS) -> dict[str, str]:
    """World scene name -> SHA-256 of every state its cars published and of its world
    messages over ``ticks`` ticks of the live loop (``WORLDS``)."""
    import dataclasses
    import hashlib
    import json
    import tempfile
    from pathlib import Path

    from simserver.server import fleet
    from simserver.server.config import REPO_CONFIGS, load_server_config
    from simserver.server.loop import ServerLoop, SlotPorts
    from simserver.sim.scene import load_scene
    from simserver.wire import protocol as proto

    out = {}
    for name, cars in WORLDS.items():
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "world.yaml"
            scene_path = REPO_CONFIGS / "scenes" / f"{name}.yaml"
            path.write_text(json.dumps({"scene": str(scene_path), "viewer": "off",
                                        "cars": cars}))
            cfg = load_server_config(path)
            served = fleet.make_cars(cfg, load_scene(cfg.scene))
        clock = _Clock()
        loop = ServerLoop(cfg, clock=clock, sleep=clock.sleep, spin_ns=0)
        loop.live_drivers = fleet.prepare_drivers(served)
        h = hashlib.sha256()
        ports = {}
        for car in served:
            ports[car.slot.keys.vehicle] = SlotPorts(_Inbox(), _Controls(), _Publisher(h))
            loop.add(car.slot, ports[car.slot.keys.vehicle])
        loop.world_message = fleet.world_message_for(served, dataclasses.replace(
            cfg, world_hz=100.0))
        loop.publish_world = h.update
        loop.start()
        for k in range(ticks):
            for j, car in enumerate(("car0", "car1")):
                if k % (5 + j) == 0:
                    ports[car].commands.pending.append(proto.encode_command(
                        seq=k + 1, sender_time_ns=k, gear=proto.Gear.D,
                        throttle=0.5 if k < 2 * ticks // 3 else 0.0,
                        brake=0.0 if k < 2 * ticks // 3 else 0.7,
                        steer=0.2 * math.sin(k * 0.004 + j)))
            loop.tick()
        out[name] = h.hexdigest()
    return out


if __name__ == "__main__":
    for scene, digest in digests().items():
        print(scene, digest)
    for scene, digest in world_digests().items():
        print("world", scene, digest)
