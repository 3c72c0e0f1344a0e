"""The clients trust no one they cannot (issue 34 item 4): on a network without access
control anyone may publish on a car's state key or answer its ``get_config``. The
recorder and every client drop states no server sends (non-finite, out of range, out of
the server's order) and ``get_config`` replies no server sends, with a counted warning:
never a crash, never a NaN row, never a segment that did not happen.

The live tests run a real server, the real recorder as a subprocess and a real hostile
zenoh session on loopback in the test process.
"""

from __future__ import annotations

import json
import signal
import time

import numpy as np
import pyarrow.parquet as pq
import pytest
import zenoh

from simserver import protocol as proto
from simserver.testing import (
    Client,
    OutputProcess,
    ServerProcess,
    client_command,
    client_env,
    wait_until,
)


def _state(tick: int, **values: float) -> bytes:
    rec = proto.new_state_record()
    rec["tick"] = tick
    rec["sim_time_s"] = tick * 1e-3
    rec["fz_n"][:] = 3000.0
    for name, value in values.items():
        rec[name] = value
    return rec.tobytes()


# ============================================================================ in-process
def test_the_state_filter_drops_invalid_and_out_of_order_states_and_follows_a_reset():
    from clients.common import StateFilter

    f = StateFilter(period_s=1e-3, state_every=1, out=None)
    t = 100.0
    taken = f.take([_state(k) for k in range(1, 11)], t)
    assert [k for _, k, _ in taken] == list(range(1, 11))
    assert [kind for _, _, kind in taken] == ["restart"] + ["next"] * 9
    # non-finite, out of range, an undefined flag bit: dropped, counted
    bad = [_state(11, x_m=np.nan), _state(11, u_mps=np.inf), _state(11, steer=3.0),
           _state(11, flags=0x80), _state(11, version=2), b"short"]
    assert f.take(bad, t + 0.001) == [] and f.rejected == 6
    # interleaved with the server's run: an old tick, one far ahead of the wall clock
    t += 0.002
    mixed = [_state(11), _state(3), _state(12), _state(10**12), _state(13), _state(4)]
    assert [k for _, k, _ in f.take(mixed, t)] == [11, 12, 13]
    for k in range(14, 300):  # the server goes on; the candidates stop and are dropped
        t += 0.001
        f.take([_state(k)], t)
    assert f.out_of_order == 3 and f.last_tick == 299
    # the same tick again: a repeat (paused)
    assert [kind for _, _, kind in f.take([_state(299)], t)] == ["repeat"]
    # a reset: the tick restarts; followed once the old run is silent
    got: list[tuple[bytes, int, str]] = []
    for k in range(1, 200):
        t += 0.001
        got += f.take([_state(k), _state(10**9 + 7 * k)], t)  # with random-ish fakes
    assert got and got[0][1:] == (1, "restart")
    assert [k for _, k, _ in got] == list(range(1, 200))
    assert f.out_of_order > 3


def test_a_malformed_get_config_is_refused_naming_the_member():
    from clients.common import check_server_config

    good = {"server": {"period_s": 0.001, "state_every": 1}, "road": {"grade_pct": 2.0},
            "scene": {"path": "scenes/x.yaml", "terrain": "plane"}, "vehicle": {"name": "v"}}
    assert check_server_config(good) is good
    for bad, member in [([], "config"), ({"road": [1]}, "config.road"),
                        ({"road": {"grade_pct": "steep"}}, "config.road.grade_pct"),
                        ({"road": {"grade_pct": 1e308}}, "config.road.grade_pct"),
                        ({"scene": ["x"]}, "config.scene"),
                        ({"scene": {"terrain": 7}}, "config.scene.terrain"),
                        ({"vehicle": 7}, "config.vehicle"),
                        ({"server": {"state_every": 0}}, "config.server.state_every"),
                        ({"server": {"period_s": float("nan")}}, "config.server.period_s")]:
        with pytest.raises(proto.ProtocolError) as err:
            check_server_config(bad)
        assert err.value.field == member, (bad, err.value)


# ============================================================================ live
HOSTILE_CONFIG = json.dumps({"ok": True, "protocol_version": proto.PROTOCOL_VERSION,
                             "config": {"road": {"grade_pct": "steep"}, "scene": ["x"],
                                        "vehicle": 7}}).encode()


def test_the_recorder_drops_fake_states_and_survives_a_hostile_get_config(tmp_path):
    """Before (default config, no ACL): a second client's fake states put NaN/inf rows and
    hundreds of segments into history.parquet without a warning, and a hostile
    ``get_config`` reply after the start crashed the recorder (``AttributeError`` in
    ``_road_of`` / ``_on_terrain``). Now: no NaN row, only the real reset begins a
    segment, every drop counted, the recording completes."""
    server = ServerProcess(vehicle_id="trust34", scene="flat_paper_sedan")
    out = tmp_path / "rec"
    rec = OutputProcess(client_command("recorder", "--out", str(out), "--quiet",
                                       "--road-poll", "0.1", *server.client_args()),
                        ready="recording", env=client_env())
    try:
        assert rec.wait_ready(60.0), rec.text()
        with Client(server) as probe:
            keys = probe.ep.keys
            session = probe.ep.session
            fake_pub = session.declare_publisher(keys.state)

            def answer(query: zenoh.Query) -> None:
                query.reply(query.key_expr, HOSTILE_CONFIG)

            hostile = session.declare_queryable(keys.control("get_config"), answer)
            rng = np.random.default_rng(34)
            sent = 0

            def attack(n: int) -> None:
                nonlocal sent
                for _ in range(n):
                    real = int(probe.poll()["tick"]) if probe.poll() is not None else 0
                    kind = sent % 4
                    if kind == 0:
                        payload = _state(real, x_m=np.nan, yaw_rad=np.inf)
                    elif kind == 1:
                        payload = _state(real + 1, u_mps=-np.inf)
                    elif kind == 2:  # finite, but a tick out of the server's order
                        payload = _state(int(rng.integers(0, max(1, real - 100))))
                    else:  # finite, far ahead of the server
                        payload = _state(real + 10**9 + int(rng.integers(0, 10**6)))
                    fake_pub.put(payload)
                    sent += 1
                    time.sleep(0.001)

            attack(600)
            assert probe.request("reset")["ok"]  # the one real new segment
            attack(600)
            wait_until(lambda: "malformed get_config" in rec.text(), timeout_s=20.0,
                       what="the recorder to meet the hostile get_config reply",
                       interval_s=0.05)
            hostile.undeclare()
            probe.wait_state(lambda s: int(s["tick"]) > 500, timeout_s=20.0)
        assert rec.alive(), rec.text()
        assert rec.stop(signal.SIGINT, timeout_s=30.0) == 0, rec.text()
    finally:
        rec.kill()
        server.stop()
    text = rec.text()
    assert "Traceback" not in text, text
    table = pq.read_table(out / "history.parquet")
    cols = table.to_pydict()
    for name in table.column_names:
        values = np.asarray(cols[name])
        if values.dtype.kind == "f":
            assert np.isfinite(values).all(), f"non-finite {name} rows"
    segment = np.asarray(cols["segment"])
    tick = np.asarray(cols["tick"], dtype=np.int64)
    assert segment.max() == 1, f"{segment.max() + 1} segments for one reset"
    for s in (0, 1):
        assert (np.diff(tick[segment == s]) >= 0).all()
    assert tick.max() < 10**8
    last = text.strip().splitlines()[-1]
    counts = {w: int(last.split(f" {w}")[0].rsplit(" ", 1)[1])
              for w in ("bad payloads", "out of order", "bad get_config")}
    assert counts["bad payloads"] >= 250, last
    assert counts["out of order"] >= 250, last
    assert counts["bad get_config"] >= 1, last
    assert "warning: dropped" in text
    print(f"\n[recorder] {sent} fake states sent: {table.num_rows} rows, 2 segments, "
          f"finite; {last}")
