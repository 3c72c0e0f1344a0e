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

from simserver.testing import (
    Client,
    OutputProcess,
    ServerProcess,
    client_command,
    client_env,
    wait_until,
)
from simserver.wire import protocol as proto


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


def test_invalid_fields_names_the_first_bad_field_alike_for_one_payload_and_a_batch():
    """The check runs in plain Python for a few payloads and in numpy for a batch: both
    name the same field, from the tables' ranges (``protocol.STATE_FIELDS``)."""
    changes = [{}, {"x_m": np.nan}, {"fz_n": -1.0}, {"flags": 0x80}, {"gear": 7},
               {"u_mps": np.inf}, {"steer": -1.5}, {"version": 1}, {"cmd_age_s": -2.0},
               {"sim_time_s": -np.inf}, {"engine_speed_radps": np.nan},
               {"last_cmd_seq": 2**32 - 1}]
    payloads = [_state(5, **c) for c in changes] * 2
    raw = np.frombuffer(b"".join(payloads), dtype=np.uint8).reshape(len(payloads), -1)
    batch = proto.invalid_fields(raw, "state")  # numpy
    one = [int(proto.invalid_fields(raw[k:k + 1], "state")[0]) for k in range(len(raw))]
    assert batch.tolist() == one
    names = [None if i < 0 else proto.STATE_FIELDS[i].name for i in one[:len(changes)]]
    assert names == [None, "x_m", "fz_n", "flags", "gear", "u_mps", "steer", "version",
                     "cmd_age_s", "sim_time_s", "engine_speed_radps", None]


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


class RecorderUnderAttack:
    """A real server, the real recorder as a subprocess and a hostile zenoh session in
    this process (a :class:`Client`, whose session also publishes and answers)."""

    def __init__(self, tmp_path) -> None:
        self.server = ServerProcess(vehicle_id="trust34", scene="flat_paper_sedan")
        self.out = tmp_path / "rec"
        self.rec = OutputProcess(client_command("recorder", "--out", str(self.out),
                                                "--quiet", "--road-poll", "0.1",
                                                *self.server.client_args()),
                                 ready="recording", env=client_env())
        assert self.rec.wait_ready(60.0), self.rec.text()
        self.probe = Client(self.server)
        self.session = self.probe.ep.session
        self.keys = self.probe.ep.keys
        self.sent = 0
        self._fake_pub = self.session.declare_publisher(self.keys.state)
        self._rng = np.random.default_rng(34)

    def fake_states(self, n: int) -> None:
        """``n`` fake states at about 1 kHz, a quarter each: NaN/inf pose, -inf speed,
        finite with a tick before the server's, finite far ahead of it."""
        for _ in range(n):
            state = self.probe.poll()
            real = int(state["tick"]) if state is not None else 0
            kind = self.sent % 4
            if kind == 0:
                payload = _state(real, x_m=np.nan, yaw_rad=np.inf)
            elif kind == 1:
                payload = _state(real + 1, u_mps=-np.inf)
            elif kind == 2:
                payload = _state(int(self._rng.integers(0, max(1, real - 100))))
            else:
                payload = _state(real + 10**9 + int(self._rng.integers(0, 10**6)))
            self._fake_pub.put(payload)
            self.sent += 1
            time.sleep(0.001)

    def finish(self) -> tuple[str, dict]:
        """Stop the recorder with Ctrl-C (it must still run); its output and the
        history's columns."""
        assert self.rec.alive(), "the recorder died:\n" + self.rec.text()
        assert self.rec.stop(signal.SIGINT, timeout_s=30.0) == 0, self.rec.text()
        text = self.rec.text()
        assert "Traceback" not in text, text
        return text, pq.read_table(self.out / "history.parquet").to_pydict()

    def close(self) -> None:
        self.probe.close()
        self.rec.kill()
        self.server.stop()


def _last_counts(text: str) -> dict[str, int]:
    # the recorder's last counters line (its holds lines and file names may follow it)
    last = [line for line in text.strip().splitlines() if " bad payloads" in line][-1]
    return {w: int(last.split(f" {w}")[0].rsplit(" ", 1)[1])
            for w in ("bad payloads", "out of order", "bad get_config")}


def test_the_recorder_drops_fake_states_and_keeps_only_the_real_segments(tmp_path):
    """Before (default config, no ACL): a second client's fake states put NaN/inf rows
    and hundreds of segments into history.parquet without a warning. Now: no NaN row,
    only the real reset begins a segment, every drop counted and warned."""
    attack = RecorderUnderAttack(tmp_path)
    try:
        attack.fake_states(600)
        assert attack.probe.request("reset", timeout_s=10.0)["ok"]  # the one real segment
        attack.fake_states(600)
        attack.probe.wait_state(lambda s: int(s["tick"]) > 300, timeout_s=20.0)
        text, cols = attack.finish()
    finally:
        attack.close()
    nonfinite = {name: int((~np.isfinite(np.asarray(v))).sum()) for name, v in cols.items()
                 if np.asarray(v).dtype.kind == "f"}
    segment = np.asarray(cols["segment"])
    tick = np.asarray(cols["tick"], dtype=np.int64)
    rows_with_nan = int(np.column_stack([~np.isfinite(np.asarray(v)) for name, v in
                                         cols.items() if name in nonfinite]).any(1).sum())
    assert rows_with_nan == 0 and segment.max() == 1, (
        f"{rows_with_nan} rows with NaN/inf of {tick.size}, {segment.max() + 1} segments "
        f"for one reset; per column {({k: v for k, v in nonfinite.items() if v})}")
    for s in (0, 1):
        assert (np.diff(tick[segment == s]) >= 0).all()
    assert tick.max() < 10**8
    counts = _last_counts(text)
    assert counts["bad payloads"] >= 250 and counts["out of order"] >= 250, text[-2000:]
    assert "warning: dropped" in text
    print(f"\n[recorder] {attack.sent} fake states sent: {tick.size} rows, 0 with NaN, "
          f"2 segments; counted {counts}")


def test_the_recorder_survives_a_hostile_get_config_reply(tmp_path):
    """Before: a hostile ``get_config`` reply after the start crashed the recorder
    (``AttributeError`` in ``_road_of`` / ``_on_terrain``). Now it is ignored with a
    counted warning and the last good road is kept."""
    attack = RecorderUnderAttack(tmp_path)
    try:
        def answer(query: zenoh.Query) -> None:
            query.reply(query.key_expr, HOSTILE_CONFIG)

        hostile = attack.session.declare_queryable(attack.keys.control("get_config"), answer)
        wait_until(lambda: "malformed get_config" in attack.rec.text()
                   or not attack.rec.alive(), timeout_s=20.0, interval_s=0.05,
                   what="the recorder to meet the hostile get_config reply")
        hostile.undeclare()
        text, cols = attack.finish()
    finally:
        attack.close()
    counts = _last_counts(text)
    assert counts["bad get_config"] >= 1, text[-2000:]
    assert np.isfinite(np.asarray(cols["road_grade_pct"])).all()
    print(f"\n[recorder] hostile get_config: {counts['bad get_config']} replies ignored, "
          f"{len(cols['tick'])} rows")
