"""The live server as a real subprocess, driven by a separate zenoh client on loopback.

Explicit endpoints on free loopback ports, multicast scouting off (the defaults of
``make_zenoh_config``). Timing is never asserted here: the benchmarks measure it.
"""

from __future__ import annotations

import math
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from simserver import protocol as proto
from simserver.adapters.zenoh_io import ZenohEndpoint, make_zenoh_config
from tests.conftest import CONFIGS, REPO

pytestmark = pytest.mark.timeout(300)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServerProcess:
    """``simserver serve`` in a subprocess, stopped with SIGTERM."""

    def __init__(self, tmp: Path, vehicle_id: str = "car0", scene: str = "flat_paper_sedan",
                 command_log: bool = False) -> None:
        self.port = free_port()
        self.vehicle_id = vehicle_id
        self.log_path = tmp / f"{vehicle_id}_commands.jsonl" if command_log else None
        args = [sys.executable, "-m", "simserver", "serve", "--vehicle-id", vehicle_id,
                "--viewer", "off",
                "--listen", f"tcp/127.0.0.1:{self.port}",
                "--scene", str(CONFIGS / "scenes" / f"{scene}.yaml")]
        if self.log_path:
            args += ["--command-log", str(self.log_path)]
        self.proc = subprocess.Popen(args, cwd=REPO, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True)
        deadline = time.monotonic() + 120
        self.output: list[str] = []
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline()
            if not line:
                raise RuntimeError("server exited early:\n" + "".join(self.output))
            self.output.append(line)
            if "ready on" in line:
                return
        raise RuntimeError("server did not become ready")

    def stop(self) -> str:
        self.proc.terminate()
        out, _ = self.proc.communicate(timeout=30)
        self.output.append(out)
        return "".join(self.output)


class Client:
    """A zenoh client of the protocol, as a driver program would be."""

    def __init__(self, server: ServerProcess) -> None:
        cfg = make_zenoh_config(listen=[], connect=[f"tcp/127.0.0.1:{server.port}"])
        self.ep = ZenohEndpoint(cfg, prefix="simserver", vehicle=server.vehicle_id)
        self.pub = self.ep.declare_command_publisher()
        self.states = self.ep.declare_state_inbox(capacity=4096)
        self.diag = self.ep.declare_diag_inbox()
        self.seq = 0
        self.last: np.ndarray | None = None
        self.history: list[np.ndarray] = []

    def send(self, **kw) -> None:
        self.seq += 1
        self.pub.put(proto.encode_command(seq=self.seq, **kw))

    def drive(self, seconds: float, rate_hz: float = 200.0, **kw) -> np.ndarray:
        """Command at ``rate_hz`` for ``seconds``; returns the newest state."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.send(**kw)
            self.poll()
            time.sleep(1.0 / rate_hz)
        return self.poll()

    def poll(self) -> np.ndarray:
        for payload in self.states.drain_newest():
            self.last = proto.decode_state(payload)
            self.history.append(self.last)
        return self.last

    def wait_state(self, timeout: float = 10.0) -> np.ndarray:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            before = len(self.history)
            self.poll()
            if len(self.history) > before:
                return self.last
            time.sleep(0.005)
        raise TimeoutError("no state received")

    def diagnostics(self, timeout: float = 5.0) -> np.ndarray:
        self.diag.drain_newest()
        payload = self.diag.wait_newest(timeout)
        assert payload is not None, "no diagnostics"
        return proto.decode_diagnostics(payload)

    def close(self) -> None:
        self.ep.close()


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("server")
    server = ServerProcess(tmp, command_log=True)
    client = Client(server)
    yield server, client
    client.close()
    server.stop()


def test_liveliness_config_and_first_state(served):
    server, client = served
    assert client.ep.alive_tokens() == ["simserver/car0/alive"]
    reply = client.ep.request("get_config")
    assert reply["ok"] and reply["protocol_version"] == proto.PROTOCOL_VERSION
    assert reply["config"]["vehicle"]["name"] == "paper_sedan"
    state = client.wait_state()
    # no command yet: the watchdog holds the car
    assert state["flags"] & proto.StateFlag.WATCHDOG
    assert state["cmd_age_s"] == -1.0


def test_throttle_moves_brake_stops_holds_on_10_percent_and_restarts(served):
    _, client = served
    assert client.ep.request("reset")["ok"]
    state = client.drive(2.0, throttle=0.4, gear=proto.Gear.D)
    assert not state["flags"] & proto.StateFlag.WATCHDOG
    assert state["u_mps"] > 2.0  # it moves
    state = client.drive(3.0, brake=0.7, gear=proto.Gear.D)
    assert abs(state["u_mps"]) < 0.01  # it stops
    assert client.ep.request("set_road", {"grade_pct": 10.0})["ok"]
    client.drive(1.0, brake=0.7, gear=proto.Gear.D)  # settle on the slope
    held = client.drive(0.1, brake=0.7, gear=proto.Gear.D)
    later = client.drive(2.0, brake=0.7, gear=proto.Gear.D)
    creep = math.hypot(later["x_m"] - held["x_m"], later["y_m"] - held["y_m"])
    assert creep < 1e-3  # holds on 10 % (no creep over 2 s)
    assert later["flags"] & proto.StateFlag.BRAKE_HOLD
    state = client.drive(3.0, throttle=0.5, gear=proto.Gear.D)
    assert state["u_mps"] > 2.0  # and drives off uphill
    assert state["z_m"] > later["z_m"] + 0.2
    assert client.ep.request("set_road", {"grade_pct": 0.0})["ok"]


def test_reset_pause_step_resume(served):
    _, client = served
    reply = client.ep.request("reset", {"pose": {"x_m": 5.0, "y_m": -2.0, "yaw_rad": 1.0}})
    assert reply["ok"] and reply["tick"] == 0
    state = client.drive(0.2, brake=0.5)
    assert abs(state["x_m"] - 5.0) < 1e-3 and abs(state["yaw_rad"] - 1.0) < 1e-3
    reply = client.ep.request("pause")
    assert reply["ok"] and reply["paused"]
    time.sleep(0.2)
    client.poll()
    frozen = client.wait_state()
    assert frozen["flags"] & proto.StateFlag.PAUSED
    time.sleep(0.3)
    assert client.wait_state()["tick"] == frozen["tick"]  # nothing steps while paused
    reply = client.ep.request("step", {"n": 50})
    assert reply["ok"] and reply["until_tick"] == reply["tick"] + 50
    time.sleep(0.5)
    client.poll()
    assert client.wait_state()["tick"] == reply["until_tick"]
    assert client.ep.request("resume")["ok"]
    time.sleep(0.3)
    assert client.wait_state()["tick"] > reply["until_tick"] + 100
    # step while running is an error that changes nothing
    reply = client.ep.request("step", {"n": 5})
    assert not reply["ok"] and reply["field"] == "n"


def test_bad_control_arguments_change_nothing(served):
    _, client = served
    road = client.ep.request("get_config")["config"]["road"]
    for name, payload in [
        ("set_road", b'{"grade_pct": 500}'), ("set_road", b'{"grade_pct": NaN}'),
        ("set_road", b'{"bogus": 1}'), ("set_road", b"not json"), ("step", b'{"n": 0}'),
        ("reset", b'{"pose": {"x_m": 1}}'), ("load", b'{"scene": "/etc/passwd.yaml"}'),
        ("load", b'{"vehicle": "../../../../etc/x.yaml"}'),
    ]:
        reply = client.ep.request(name, payload=payload)
        assert not reply["ok"] and reply["error"], (name, payload)
    assert client.ep.request("get_config")["config"]["road"] == road


MALFORMED = {
    "short": b"\x01\x00\x03",
    "long": proto.encode_command(throttle=0.1) + b"\x00",
    "version": proto.encode_command(throttle=0.1, version=9, check=False),
    "nan": proto.encode_command(throttle=float("nan"), check=False),
    "inf": proto.encode_command(steer=float("inf"), check=False),
    "range": proto.encode_command(throttle=7.0, check=False),
    "gear": proto.encode_command(gear=9, check=False),
    "flags": proto.encode_command(flags=0x80, check=False),
    "empty": b"",
}


def test_malformed_commands_are_rejected_counted_and_harmless(served):
    _, client = served
    assert client.ep.request("reset")["ok"]
    client.drive(0.5, brake=0.3)
    before = client.diagnostics()
    for _ in range(20):
        for payload in MALFORMED.values():
            client.pub.put(payload)
        # valid commands keep flowing too, so the watchdog stays off
        client.send(brake=0.3)
        time.sleep(0.01)
    time.sleep(0.3)
    after = client.diagnostics()
    rejected = int(after["cmd_rejected"]) - int(before["cmd_rejected"])
    assert rejected == 20 * len(MALFORMED)
    state = client.drive(0.3, brake=0.3)
    values = [state[name] for name in state.dtype.names]
    assert all(np.all(np.isfinite(v)) for v in values)
    assert abs(state["u_mps"]) < 0.01 and state["throttle"] == 0.0


def test_watchdog_engages_and_releases(served):
    _, client = served
    assert client.ep.request("reset")["ok"]
    state = client.drive(1.0, throttle=0.3)
    assert not state["flags"] & proto.StateFlag.WATCHDOG and state["throttle"] > 0.29
    time.sleep(0.5)  # the client goes silent for more than 200 ms
    client.poll()
    state = client.wait_state()
    assert state["flags"] & proto.StateFlag.WATCHDOG
    assert state["throttle"] == 0.0 and state["brake"] >= 0.6 - 1e-6
    state = client.drive(0.3, throttle=0.3)
    assert not state["flags"] & proto.StateFlag.WATCHDOG and state["throttle"] > 0.29


def test_two_servers_are_isolated(tmp_path):
    a = ServerProcess(tmp_path, vehicle_id="car_a")
    b = ServerProcess(tmp_path, vehicle_id="car_b")
    try:
        ca, cb = Client(a), Client(b)
        # client a also connects to b's endpoint: it sees both networks' traffic
        cfg = make_zenoh_config(listen=[], connect=[f"tcp/127.0.0.1:{a.port}",
                                                    f"tcp/127.0.0.1:{b.port}"])
        both = ZenohEndpoint(cfg, prefix="simserver", vehicle="car_a")
        pub_a = both.declare_command_publisher()
        seq = 0
        end = time.monotonic() + 2.0
        while time.monotonic() < end:
            seq += 1
            pub_a.put(proto.encode_command(throttle=0.5, seq=seq))
            cb.send(brake=0.5)
            ca.poll()
            cb.poll()
            time.sleep(0.005)
        sa, sb = ca.wait_state(), cb.wait_state()
        assert sa["u_mps"] > 1.0 and sa["throttle"] > 0.49
        assert abs(sb["u_mps"]) < 1e-3 and sb["throttle"] == 0.0
        both.close()
        ca.close()
        cb.close()
    finally:
        a.stop()
        b.stop()


def test_liveliness_disappears_when_the_server_stops(tmp_path):
    server = ServerProcess(tmp_path, vehicle_id="car_gone")
    client = Client(server)
    watch = client.ep.declare_alive_watch()
    assert client.ep.alive_tokens() == ["simserver/car_gone/alive"]
    out = server.stop()
    assert "stopped" in out  # clean shutdown with final statistics
    end = time.monotonic() + 10
    events: list = []
    while time.monotonic() < end and not any(not alive for _, alive in events):
        events += watch.poll()
        time.sleep(0.05)
    assert ("simserver/car_gone/alive", False) in events
    client.close()


def test_replay_reproduces_the_live_run_bit_for_bit(served):
    """Stop the module's server, replay its command log, compare every published state."""
    server, client = served
    client.poll()
    ticks = [int(s["tick"]) for s in client.history]
    # the states published since the last reset (the tick restarts at 0 on a reset)
    start = max((i for i in range(1, len(ticks)) if ticks[i] < ticks[i - 1]), default=0)
    live = {int(s["tick"]): s for s in client.history[start:]}
    out = server.stop()
    assert "stopped" in out
    proc = subprocess.run([sys.executable, "-m", "simserver", "replay", str(server.log_path)],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "identical" in proc.stdout
    # and the published states (after the last reset) match the replayed ones field by field
    from simserver.core import layout as L
    from simserver.server import read_command_log, replay_command_log

    rep = replay_command_log(server.log_path)
    entries = read_command_log(server.log_path)
    last_reset = max((e["step"] for e in entries if "reset" in e), default=0)
    compared = 0
    for tick, state in live.items():
        n = last_reset + tick - 1  # state published at tick T is the one after T steps
        if tick < 1 or n >= rep.steps or state["flags"] & proto.StateFlag.PAUSED:
            continue
        x = rep.states[n]
        assert state["u_mps"] == np.float32(x[L.U_MPS])
        assert state["yaw_rate_radps"] == np.float32(x[L.YAW_RATE_RADPS])
        assert np.array_equal(state["omega_radps"], x[L.OMEGA0:L.OMEGA0 + 4].astype(np.float32))
        assert np.array_equal(state["kappa_lag"], x[L.KAPPA0:L.KAPPA0 + 4].astype(np.float32))
        compared += 1
    assert compared > 200


def test_replay_rejects_a_broken_log(tmp_path):
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"simserver_command_log": 1, "scene": "x.yaml", "dt_s": 0.001}\n{oops\n')
    proc = subprocess.run([sys.executable, "-m", "simserver", "replay", str(bad)], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "bad.jsonl:2" in proc.stderr


def test_load_another_scene_and_vehicle(tmp_path):
    server = ServerProcess(tmp_path, vehicle_id="car_load")
    client = Client(server)
    try:
        reply = client.ep.request(
            "load", {"scene": str(CONFIGS / "scenes" / "hill_10pct_paper_sedan.yaml"),
                     "vehicle": str(CONFIGS / "vehicles" / "mf_hatchback" / "vehicle.yaml")})
        assert reply["ok"], reply
        config = client.ep.request("get_config")["config"]
        assert config["vehicle"]["name"] == "mf_hatchback"
        assert config["road"]["grade_pct"] == 10.0
        state = client.drive(1.0, brake=0.6, gear=proto.Gear.D)
        assert abs(state["u_mps"]) < 0.01 and state["pitch_rad"] < -0.05  # nose up the hill
        # a scenario file is a scene too: the live run starts where the headless one does
        reply = client.ep.request("load", {"scene": str(
            CONFIGS / "scenarios" / "e2_stop_downslope_paper_damping.yaml")})
        assert reply["ok"], reply
        state = client.drive(0.2, gear=proto.Gear.N)
        assert state["u_mps"] > 24.0
    finally:
        client.close()
        server.stop()
