"""The hill queue live (issue 30, acceptance: the hill queue as a shipped scene a person can
drive): a real server process on ``configs/server/hill_queue_15pct.yaml`` (car0 driven by
a client, car1 by the built-in driver), this test process as the person's client on
loopback driving car0 through its command key, and car1 read from its own state key.

On the 15 % grade car0 is held with the brake; car1 pulls away from rest 40 m below,
stops 1.0 m behind car0's rear bumper (the IDM's s0) and holds; commands sent to car1 are
not applied; car0 drives off (throttle against the brake, then the brake released: under
1 mm of rollback) and car1 follows it up the hill at the IDM's 2 s time gap.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from simserver.testing import Client, ServerProcess, wait_until
from simserver.wire import protocol as proto

pytestmark = pytest.mark.timeout(420)

REPO = Path(__file__).resolve().parents[1]
HILL_QUEUE = REPO / "configs" / "server" / "hill_queue_15pct.yaml"
GRADE = 0.15
ALONG_SLOPE = math.sqrt(1.0 + GRADE**2)  # world x -> distance along the road plane


def _lengths() -> tuple[float, float]:
    """CG to front and to rear bumper of the paper sedan (both cars): its body's box, the
    contact stage's and the built-in driver's (``core.contact.body_box``)."""
    from simserver.adapters.config import load_vehicle
    from simserver.core.contact import body_box

    vp = load_vehicle(REPO / "configs" / "vehicles" / "paper_sedan" / "vehicle.yaml").vp
    front_m, rear_m, _ = body_box(vp)
    return front_m, rear_m


class Queue:
    """The two cars' states as received (car0 at 1 kHz, car1 at the traffic rate), the
    bumper gap where both have a state of the same simulated millisecond."""

    def __init__(self, car0: Client, car1: Client) -> None:
        self.car0, self.car1 = car0, car1
        self.front_m, self.rear_m = _lengths()
        self.by_ms: dict[int, np.void] = {}
        self.pairs: list[tuple[float, float, float, float]] = []  # t, gap, u1, x1 (along)

    def drain(self) -> None:
        for st in self.car0.drain_states():
            self.by_ms[round(float(st["sim_time_s"]) * 1000)] = st
        for st in self.car1.drain_states():
            lead = self.by_ms.get(round(float(st["sim_time_s"]) * 1000))
            if lead is not None:
                gap = ((float(lead["x_m"]) - float(st["x_m"])) * ALONG_SLOPE
                       - self.rear_m - self.front_m)
                self.pairs.append((float(st["sim_time_s"]), gap, float(st["u_mps"]),
                                   float(st["x_m"]) * ALONG_SLOPE))

    def drive(self, seconds: float | None = None, until=None, timeout_s: float = 60.0,
              **cmd) -> None:
        """Command car0 ``cmd`` at 200 Hz for ``seconds`` of simulated time, or until
        ``until(self)``."""
        t0 = self.sim_time()

        def step() -> bool:
            self.car0.send(**cmd)
            self.drain()
            if until is not None:
                return until(self)
            return self.sim_time() - t0 >= seconds

        wait_until(step, timeout_s=timeout_s, interval_s=0.005, what=f"car0 driving {cmd}")

    def sim_time(self) -> float:
        return float(self.car0.last["sim_time_s"]) if self.car0.last is not None else 0.0

    def since(self, t: float) -> np.ndarray:
        rows = np.array(self.pairs)
        return rows[rows[:, 0] >= t]


def _held_behind(q: Queue) -> bool:
    """car1 stopped 1.0 m behind car0 for the last second."""
    rows = np.array(q.pairs) if q.pairs else np.zeros((0, 4))
    if not len(rows) or rows[-1, 0] < 1.0:
        return False
    last = rows[rows[:, 0] >= rows[-1, 0] - 1.0]
    return bool(len(last) > 50 and np.all(np.abs(last[:, 2]) < 0.01)
                and np.all(np.abs(last[:, 1] - 1.0) < 0.05))


def test_hill_queue_live_stops_1_m_behind_holds_and_follows(tmp_path):
    hold = {"brake": 0.6, "throttle": 0.0, "gear": proto.Gear.D}
    config = tmp_path / "server.yaml"  # the shipped scene, with command logs
    config.write_text(HILL_QUEUE.read_text().replace("../", f"{HILL_QUEUE.parent}/../")
                      + f"command_log: {tmp_path / 'run.jsonl'}\n")
    with ServerProcess(config=config, scene=None) as server, \
            Client(server, vehicle_id="car0", keep_history=False) as car0, \
            Client(server, vehicle_id="car1", keep_history=False) as car1:
        q = Queue(car0, car1)
        wait_until(lambda: (car0.send(**hold), q.drain(), car0.last)[2] is not None,
                   timeout_s=30, what="car0's first state")
        start_t = q.sim_time()
        # car0 held braked; car1 comes up behind it and stops 1.0 m short
        q.drive(until=_held_behind, timeout_s=120, **hold)
        t_stop = q.pairs[-1][0]
        # the hold: 3 s more, while a client commands car1 full throttle (not applied)
        x0_hold = float(car0.last["x_m"]) * ALONG_SLOPE
        for _ in range(3):
            car1.send(throttle=1.0, brake=0.0, gear=proto.Gear.D)
            q.drive(1.0, **hold)
        held = q.since(t_stop)
        assert np.ptp(held[:, 3]) < 1e-3, np.ptp(held[:, 3])  # car1 creeps < 1 mm
        assert held[:, 1].min() >= 0.99 and held[:, 1].max() <= 1.05, held[:, 1]
        assert abs(float(car0.last["x_m"]) * ALONG_SLOPE - x0_hold) < 1e-3
        diag = car1.wait_diagnostics(lambda d: d["cmd_rejected"] >= 3, timeout_s=10)
        assert diag["cmd_rejected"] >= 3
        # car0 drives off: throttle against the brake, then the brake released
        t_off = q.sim_time()
        x_release = float(car0.last["x_m"]) * ALONG_SLOPE
        low = [x_release]
        car0_track = lambda qq: low.append(float(qq.car0.last["x_m"]) * ALONG_SLOPE)  # noqa: E731
        q.drive(0.5, brake=0.6, throttle=0.45, gear=proto.Gear.D)
        car0_track(q)
        q.drive(5.0, until=lambda qq: (car0_track(qq), qq.sim_time() - t_off >= 5.5)[1],
                brake=0.0, throttle=0.45, gear=proto.Gear.D)
        rollback_m = x_release - min(low)
        assert rollback_m < 1e-3, rollback_m
        # ... and car1 follows: 25 s after the drive-off its time gap is the IDM's 2 s
        q.drive(until=lambda qq: qq.sim_time() - t_off >= 28.0, timeout_s=90,
                brake=0.0, throttle=0.31, gear=proto.Gear.D)
    assert server.returncode == 0, server.text()
    # each car's command log replays it bit for bit: car1's holds the driver's inputs
    from simserver.server.command_log import replay_command_log

    for car in ("car0", "car1"):
        assert replay_command_log(tmp_path / f"run.{car}.jsonl").final_state_matches, car
    rows = q.since(start_t)
    assert rows[:, 1].min() >= 0.99, rows[:, 1].min()  # never closer than 0.99 m
    after = q.since(t_off)
    assert after[0, 3] - after[:, 3].min() < 1e-3  # car1's own drive-off: no rollback
    assert after[-1, 3] - after[0, 3] > 30.0, after[-1, 3] - after[0, 3]
    late = q.since(t_off + 25.0)
    time_gap = (late[:, 1] - 1.0) / late[:, 2]
    # the lead still gathers speed, so the follower's gap runs a little behind the closed
    # form's (the headless test's 5 %, tests/test_driver.py); a live client's pedal
    # timing is a few ms off the scenario's: 10 %
    assert np.abs(time_gap / 2.0 - 1.0).max() < 0.10, (time_gap.min(), time_gap.max())
    print(f"hill queue live: held gap {held[:, 1].min():.4f}-{held[:, 1].max():.4f} m, "
          f"car1 creep {np.ptp(held[:, 3]) * 1e3:.4f} mm, car0 rollback "
          f"{rollback_m * 1e3:.4f} mm, min gap {rows[:, 1].min():.4f} m, time gap "
          f"{time_gap.min():.3f}-{time_gap.max():.3f} s")
