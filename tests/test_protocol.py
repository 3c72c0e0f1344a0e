"""The wire contract (simserver.wire.protocol): keys, payload layouts, validation, docs."""

from __future__ import annotations

import json
import math
import re
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from simserver.wire import protocol as P
from simserver.wire.protocol import ProtocolError

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "protocol.md"


def raise_field(field: str):
    """Context manager: a ProtocolError naming ``field`` (attribute and message)."""
    return pytest.raises(ProtocolError, match="^" + re.escape(field) + ":")


# ============================================================================ keys


def test_default_keys():
    k = P.vehicle_keys()
    assert (k.cmd, k.state, k.diag, k.alive) == (
        "simserver/car0/cmd",
        "simserver/car0/state",
        "simserver/car0/diag",
        "simserver/car0/alive",
    )
    assert k.ctl == {n: f"simserver/car0/ctl/{n}" for n in P.CONTROL_NAMES}
    assert set(P.CONTROL_NAMES) == {
        "reset", "pause", "resume", "step", "set_road", "load", "get_config"
    }
    assert k.ctl_wildcard == "simserver/car0/ctl/**"


def test_custom_prefix_and_vehicle():
    k = P.vehicle_keys("lab-1/sim.v2", "cockpit_3")
    assert k.cmd == "lab-1/sim.v2/cockpit_3/cmd"
    assert k.control("step") == "lab-1/sim.v2/cockpit_3/ctl/step"
    assert k.control_name("lab-1/sim.v2/cockpit_3/ctl/reset") == "reset"
    assert k.control_name("lab-1/sim.v2/cockpit_3/ctl/nope") is None
    assert k.control_name("lab-1/sim.v2/other/ctl/reset") is None
    with raise_field("control"):
        k.control("explode")


@pytest.mark.parametrize(
    ("vehicle", "needle"),
    [("", "non-empty"), ("a/b", "'/'"), ("car*", "'*'"), ("c$", "'\\$'"), ("c?", "'\\?'"),
     ("c#", "'#'"), ("car 0", "' '"), (None, "non-empty"), ("**", "'\\*'")],
)
def test_bad_vehicle_ids_rejected(vehicle, needle):
    with pytest.raises(ProtocolError, match=needle) as err:
        P.vehicle_keys(vehicle=vehicle)
    assert err.value.field == "vehicle"


@pytest.mark.parametrize("prefix", ["", "/a", "a/", "a//b", "a/*/b", "a/**", "x$y", "a?b", "a#"])
def test_bad_prefixes_rejected(prefix):
    with pytest.raises(ProtocolError) as err:
        P.vehicle_keys(prefix=prefix)
    assert err.value.field == "prefix"
    assert "prefix" in str(err.value)


def test_key_table_matches_keys():
    k = P.vehicle_keys("p", "v")
    table = {f"p/v/{s.suffix}" for s in P.KEY_SPECS}
    assert table == {k.cmd, k.state, k.state_decimated, k.diag, k.alive, *k.ctl.values()}


# ============================================================================ layouts


@pytest.mark.parametrize(
    ("fields", "dtype", "size"),
    [(P.COMMAND_FIELDS, P.COMMAND_DTYPE, 32), (P.STATE_FIELDS, P.STATE_DTYPE, 304),
     (P.DIAGNOSTICS_FIELDS, P.DIAGNOSTICS_DTYPE, 176)],
)
def test_layouts_packed_aligned_little_endian(fields, dtype, size):
    assert dtype.itemsize == size
    assert dtype.names == tuple(f.name for f in fields)
    assert dtype.names[0] == "version"
    end = 0
    for f in fields:
        sub, offset = dtype.fields[f.name][:2]
        base = sub.base if sub.subdtype else sub
        native_le = base.byteorder == "=" and sys.byteorder == "little"
        assert base.byteorder in ("<", "|") or native_le, f"{f.name}: not little-endian"
        assert offset == end, f"{f.name}: gap before it"
        assert offset % base.itemsize == 0, f"{f.name}: misaligned for C/Rust clients"
        end = offset + sub.itemsize
        assert f.unit and f.description
    assert end == size and size % 8 == 0


def test_gear_codes_match_core_layout():
    from simserver.core import layout as L

    assert (L.GEAR_P, L.GEAR_R, L.GEAR_N, L.GEAR_D) == tuple(int(g) for g in P.Gear)
    assert L.GEAR_NAMES == tuple(g.name for g in P.Gear)


# ============================================================================ commands


def test_command_round_trip():
    payload = P.encode_command(0.25, 0.5, 0.125, gear=P.Gear.R, parking_brake=True, seq=7,
                               sender_time_ns=123456789012345)
    assert len(payload) == P.COMMAND_SIZE == 32
    cmd = P.decode_command(payload)
    assert cmd == P.DriverCommand(seq=7, sender_time_ns=123456789012345, steer=0.25,
                                  throttle=0.5, brake=0.125, gear=1, parking_brake=True)
    # The same bytes through the numpy dtype (the documented layout).
    rec = np.frombuffer(payload, P.COMMAND_DTYPE)[0]
    assert rec["version"] == P.PROTOCOL_VERSION and rec["flags"] == 1 and rec["gear"] == 1
    assert rec["steer"] == np.float32(0.25)
    assert payload[:2] == P.PROTOCOL_VERSION.to_bytes(2, "little")  # little-endian version


def test_command_float32_rounding_and_bytes_like():
    payload = P.encode_command(0.1, 0.3, 0.7, seq=2**32 - 1, sender_time_ns=2**64 - 1)
    for buf in (payload, bytearray(payload), memoryview(payload)):
        cmd = P.decode_command(buf)
        assert cmd.steer == float(np.float32(0.1))
        assert cmd.seq == 2**32 - 1 and cmd.sender_time_ns == 2**64 - 1
        assert cmd.gear == P.Gear.D and not cmd.parking_brake and cmd.clamped == ()


def _raw_command(**over):
    vals = dict(version=P.PROTOCOL_VERSION, gear=3, flags=0, seq=1, sender_time_ns=2,
                steer=0.0, throttle=0.0, brake=0.0, reserved=0)
    vals.update(over)
    return struct.pack("<HBBIQfffI", *vals.values())


@pytest.mark.parametrize(
    ("payload", "field", "needle"),
    [
        (b"", "payload", "got 0"),
        (b"\x01\x00" * 13, "payload", "got 26"),
        (_raw_command()[:-1], "payload", "got 31"),
        (_raw_command() + b"\x00", "payload", "got 33"),
        (_raw_command()[:28], "payload", "got 28"),
        (bytes(1000), "payload", "got 1000"),
        (_raw_command(version=0), "version", "0 is not"),
        (_raw_command(version=P.PROTOCOL_VERSION + 1), "version",
         f"{P.PROTOCOL_VERSION + 1} is not"),
        (_raw_command(version=0xFFFF), "version", "65535"),
        (_raw_command(gear=4), "gear", "4 is not a gear"),
        (_raw_command(gear=255), "gear", "255"),
        (_raw_command(flags=0x02), "flags", "0x02"),
        (_raw_command(flags=0x81), "flags", "0x80"),
        (_raw_command(reserved=1), "reserved", "not zero"),
        (_raw_command(reserved=0x80000000), "reserved", "not zero"),
        (_raw_command(steer=math.nan), "steer", "not finite"),
        (_raw_command(steer=math.inf), "steer", "not finite"),
        (_raw_command(throttle=-math.inf), "throttle", "not finite"),
        (_raw_command(brake=math.nan), "brake", "not finite"),
        (_raw_command(steer=1.5), "steer", "outside"),
        (_raw_command(steer=-1.01), "steer", "outside"),
        (_raw_command(throttle=-0.5), "throttle", "outside"),
        (_raw_command(throttle=1.002), "throttle", "outside"),
        (_raw_command(brake=2.0), "brake", "outside"),
        (_raw_command(brake=3e38), "brake", "outside"),
    ],
)
def test_malformed_commands_rejected_naming_the_field(payload, field, needle):
    with pytest.raises(ProtocolError, match=needle) as err:
        P.decode_command(payload)
    assert err.value.field == field
    assert str(err.value).startswith(f"{field}:")


@pytest.mark.parametrize("bad", ["x" * 32, None, 32, 1.0, ["a"] * 32, object()])
def test_non_bytes_rejected(bad):
    with raise_field("payload"):
        P.decode_command(bad)


@pytest.mark.parametrize(
    ("over", "expect", "clamped"),
    [
        ({"steer": 1.0000001}, {"steer": 1.0}, ("steer",)),
        ({"steer": -1.0005}, {"steer": -1.0}, ("steer",)),
        ({"throttle": -0.0009}, {"throttle": 0.0}, ("throttle",)),
        ({"brake": 1.0009, "throttle": 1.0001}, {"brake": 1.0, "throttle": 1.0},
         ("throttle", "brake")),
        ({"steer": -1.0, "throttle": 1.0, "brake": 0.0}, {"steer": -1.0}, ()),
        ({"throttle": -0.0}, {"throttle": 0.0}, ()),
    ],
)
def test_tiny_excursions_clamped_and_reported(over, expect, clamped):
    cmd = P.decode_command(_raw_command(**over))
    for name, value in expect.items():
        assert getattr(cmd, name) == value
    assert cmd.clamped == clamped


def test_encode_command_checks_by_default():
    with raise_field("steer"):
        P.encode_command(steer=2.0)
    with raise_field("gear"):
        P.encode_command(gear=7)
    with raise_field("seq"):
        P.encode_command(seq=-1)
    with raise_field("seq"):
        P.encode_command(seq=2**32)
    with raise_field("brake"):
        P.encode_command(brake=1e300)  # does not fit a float32 at all
    with raise_field("gear"):
        P.encode_command(gear=True)
    # check=False builds malformed payloads on purpose; decode still rejects them.
    bad = P.encode_command(steer=math.nan, check=False)
    with raise_field("steer"):
        P.decode_command(bad)
    with raise_field("version"):
        P.decode_command(P.encode_command(version=9, check=False))
    with raise_field("flags"):
        P.decode_command(P.encode_command(flags=0x40, check=False))


def test_seq_newer_wraps():
    assert P.seq_newer(1, 0)
    assert not P.seq_newer(0, 0)
    assert not P.seq_newer(0, 1)
    assert P.seq_newer(0, 2**32 - 1)
    assert P.seq_newer(5, 2**32 - 10)
    assert not P.seq_newer(2**32 - 10, 5)


# Fuzzing decode_command and validate_control (random bytes, hostile field values,
# random JSON): tests/test_fuzz.py, against an independent oracle of the field tables.


# ============================================================================ state, diag


def _random_values(fields, rng):
    out = {}
    for f in fields:
        if f.name in ("version", "reserved"):
            continue
        kind = f.dtype.lstrip("<")
        if kind.startswith("f"):
            v = rng.normal(size=f.count) * 100.0
        else:
            top = min(int(np.iinfo(np.dtype(f.dtype)).max), 2**31)
            hi = int(f.hi) if f.hi is not None else top
            v = rng.integers(0, hi + 1, size=f.count)
        out[f.name] = v if f.count > 1 else v[0].item()
    return out


def test_state_round_trip_and_record_path_agree():
    rng = np.random.default_rng(1)
    values = _random_values(P.STATE_FIELDS, rng)
    values["tick"] = 2**63 + 5
    values["flags"] = int(P.StateFlag.WATCHDOG | P.StateFlag.BRAKE_HOLD)
    payload = P.encode_state(**values)
    assert len(payload) == P.STATE_SIZE == 304
    rec = P.decode_state(payload)
    for f in P.STATE_FIELDS:
        if f.name in values:
            want = np.asarray(values[f.name]).astype(np.dtype(f.dtype))
            np.testing.assert_array_equal(rec[f.name], want, err_msg=f.name)
    assert rec["version"] == P.PROTOCOL_VERSION and not rec["reserved"].any()
    assert P.StateFlag(int(rec["flags"])) == P.StateFlag.WATCHDOG | P.StateFlag.BRAKE_HOLD
    # The in-place record path a 1 kHz loop would use gives the same bytes.
    fast = P.new_state_record()
    for name, v in values.items():
        fast[name] = v
    assert fast.tobytes() == payload
    d = P.record_to_dict(rec)
    assert len(d["fz_n"]) == 4 and isinstance(d["tick"], int)
    json.dumps(d)


def test_state_encode_errors_name_the_field():
    values = _random_values(P.STATE_FIELDS, np.random.default_rng(2))
    missing = dict(values)
    del missing["yaw_rate_radps"]
    with raise_field("yaw_rate_radps"):
        P.encode_state(**missing)
    with raise_field("speed_kph"):
        P.encode_state(**values, speed_kph=3.0)
    with raise_field("fz_n"):
        P.encode_state(**{**values, "fz_n": [1.0, 2.0, 3.0]})
    with raise_field("gear"):
        P.encode_state(**{**values, "gear": 300})
    with raise_field("tick"):
        P.encode_state(**{**values, "tick": -1})
    with raise_field("gear"):
        P.encode_state(**{**values, "gear": 0.5})
    with raise_field("damping_active"):
        P.encode_state(**{**values, "damping_active": [0.0, 1.0, math.nan, 0.0]})
    # The core keeps gears and flags in float64 arrays: integral floats are accepted.
    as_floats = {**values, "gear": 3.0, "damping_active": np.array([0.0, 1.0, 1.0, 0.0])}
    rec = P.decode_state(P.encode_state(**as_floats))
    assert rec["gear"] == 3 and rec["damping_active"].tolist() == [0, 1, 1, 0]


def test_state_and_diag_decode_errors():
    payload = P.encode_state(**_random_values(P.STATE_FIELDS, np.random.default_rng(3)))
    with raise_field("payload"):
        P.decode_state(payload[:-1])
    with raise_field("payload"):
        P.decode_state(payload + b"\0")
    with raise_field("version"):
        P.decode_state(b"\x07\x00" + payload[2:])
    with raise_field("payload"):
        P.decode_diagnostics(payload)
    with raise_field("payload"):
        P.decode_state(None)


def test_diagnostics_round_trip():
    values = _random_values(P.DIAGNOSTICS_FIELDS, np.random.default_rng(4))
    values["cmd_received"] = 2**64 - 1
    payload = P.encode_diagnostics(**values)
    assert len(payload) == P.DIAGNOSTICS_SIZE == 176
    rec = P.decode_diagnostics(payload)
    assert int(rec["cmd_received"]) == 2**64 - 1
    assert rec["lateness_p99_us"] == np.float32(values["lateness_p99_us"])
    with raise_field("cpu_percent"):
        P.encode_diagnostics(**{k: v for k, v in values.items() if k != "cpu_percent"})


# ============================================================================ controls


@pytest.mark.parametrize(
    ("name", "payload", "expect"),
    [
        ("reset", b"", {}),
        ("reset", None, {}),
        ("reset", b"{}", {}),
        ("reset", b'{"pose": {"x_m": 1, "y_m": -2.5, "yaw_rad": 0.5}}',
         {"pose": {"x_m": 1.0, "y_m": -2.5, "yaw_rad": 0.5}}),
        ("pause", b"  ", {}),
        ("resume", b"{}", {}),
        ("step", b"", {"n": 1}),
        ("step", b'{"n": 100000}', {"n": 100000}),
        ("set_road", b'{"grade_pct": 10}', {"grade_pct": 10.0}),
        ("set_road", b'{"cross_slope_pct": -3.5, "friction_scale": 0.3}',
         {"cross_slope_pct": -3.5, "friction_scale": 0.3}),
        ("load", '{"vehicle": "configs/vehicles/é/vehicle.yaml"}'.encode(),
         {"vehicle": "configs/vehicles/é/vehicle.yaml"}),
        ("load", b'{"scene": "s.yml", "vehicle": "/abs/v.yaml"}',
         {"scene": "s.yml", "vehicle": "/abs/v.yaml"}),
        ("get_config", b"", {}),
    ],
)
def test_valid_controls(name, payload, expect):
    assert P.validate_control(name, payload) == expect


@pytest.mark.parametrize(
    ("name", "payload", "field", "needle"),
    [
        ("explode", b"", "control", "unknown control"),
        ("step", b"{", "request", "not valid JSON"),
        ("step", b"\xff\xfe", "request", "not UTF-8"),
        ("step", b"[1]", "request", "JSON object"),
        ("step", b'"n"', "request", "JSON object"),
        ("step", b'{"n": NaN}', "request", "NaN"),
        ("set_road", b'{"grade_pct": Infinity}', "request", "Infinity"),
        ("set_road", b'{"grade_pct": -Infinity}', "request", "Infinity"),
        ("step", b'{"n": 0}', "n", "outside"),
        ("step", b'{"n": 100001}', "n", "outside"),
        ("step", b'{"n": 2.5}', "n", "integer"),
        ("step", b'{"n": 2.0}', "n", "integer"),
        ("step", b'{"n": "5"}', "n", "integer"),
        ("step", b'{"n": true}', "n", "integer"),
        ("step", b'{"n": 1, "m": 2}', "m", "not an argument"),
        ("pause", b'{"now": true}', "now", "not an argument"),
        ("reset", b'{"pose": {"x_m": 1, "y_m": 2}}', "pose.yaw_rad", "required"),
        ("reset", b'{"pose": [1, 2, 3]}', "pose", "JSON object"),
        ("reset", b'{"pose": {"x_m": 1, "y_m": 2, "yaw_rad": 9}}', "pose.yaw_rad", "outside"),
        ("reset", b'{"pose": {"x_m": 1e300, "y_m": 2, "yaw_rad": 0}}', "pose.x_m", "outside"),
        ("reset", b'{"pose": {"x_m": 1, "y_m": 2, "yaw_rad": 0, "z": 1}}', "pose.z",
         "not an argument"),
        ("reset", b'{"pose": {"x_m": null, "y_m": 2, "yaw_rad": 0}}', "pose.x_m", "number"),
        ("set_road", b"{}", "request", "at least one"),
        ("set_road", b'{"grade_pct": 61}', "grade_pct", "outside"),
        ("set_road", b'{"friction_scale": 0}', "friction_scale", "outside"),
        ("set_road", b'{"cross_slope_pct": "steep"}', "cross_slope_pct", "number"),
        ("set_road", b'{"grade_pct": 1e999}', "grade_pct", "not finite"),
        ("load", b"{}", "request", "at least one"),
        ("load", b'{"vehicle": "v.json"}', "vehicle", "yaml"),
        ("load", b'{"vehicle": ""}', "vehicle", "non-empty"),
        ("load", b'{"scene": "a\\u0000b.yaml"}', "scene", "control characters"),
        ("load", b'{"scene": 3}', "scene", "string"),
        ("load", json.dumps({"scene": "a" * 2000 + ".yaml"}).encode(), "scene", "longer"),
        ("step", b" " * (P.MAX_CONTROL_PAYLOAD_BYTES + 1), "request", "exceeds"),
        ("step", b"[" * 100000 + b"]" * 100000, "request", "exceeds"),
        ("step", b"[" * 20000 + b"]" * 20000, "request", "JSON"),
    ],
)
def test_bad_controls_rejected_naming_the_field(name, payload, field, needle):
    with pytest.raises(ProtocolError, match=needle) as err:
        P.validate_control(name, payload)
    assert err.value.field == field
    assert field in str(err.value)




def test_encode_control_and_replies():
    assert P.encode_control("pause") == b""
    assert json.loads(P.encode_control("step", {"n": 3})) == {"n": 3}
    with raise_field("n"):
        P.encode_control("step", {"n": -3})
    ok = P.decode_reply(P.reply_ok(tick=5, paused=True))
    assert ok == {"ok": True, "tick": 5, "paused": True}
    err = P.decode_reply(P.reply_error(ProtocolError("n", "too big")))
    assert err == {"ok": False, "error": "n: too big", "field": "n"}
    assert P.decode_reply(P.reply_error("busy")) == {"ok": False, "error": "busy"}
    for bad in (b"", b"[]", b'{"ok": 1}', b'{"ok": false}', b"\xff"):
        with raise_field("reply"):
            P.decode_reply(bad)


# ============================================================================ docs


def test_doc_tables_match_protocol():
    text = DOC.read_text(encoding="utf-8")
    assert P.update_doc(text) == text, (
        "docs/protocol.md drifted from simserver/wire/protocol.py: run "
        "python -m simserver.wire.protocol --write docs/protocol.md"
    )
    for section in P.doc_sections():
        assert f"<!-- BEGIN GENERATED: {section} -->" in text


def test_doc_check_detects_drift(tmp_path):
    text = DOC.read_text(encoding="utf-8")
    drifted = text.replace("| 16 | `steer` | f32 |", "| 16 | `steer` | f64 |", 1)
    assert drifted != text
    assert P.update_doc(drifted) != drifted
    path = tmp_path / "protocol.md"
    path.write_text(drifted, encoding="utf-8")
    run = [sys.executable, "-m", "simserver.wire.protocol", str(path)]
    env = {"PYTHONPATH": str(REPO)}
    res = subprocess.run(run, capture_output=True, text=True, cwd=REPO, env=env, timeout=60)
    assert res.returncode == 1 and "out of date" in res.stderr
    subprocess.run([*run, "--write"], check=True, cwd=REPO, env=env, timeout=60)
    assert path.read_text(encoding="utf-8") == text
    with pytest.raises(ValueError, match="missing"):
        P.update_doc("no sections here")


# ------------------------------------------------------------------ issue 14, item 7
def test_a_key_given_twice_is_rejected_naming_it():
    with raise_field("friction_scale"):
        P.validate_control("set_road", b'{"friction_scale": 1e6, "friction_scale": 1.0}')
    with raise_field("x_m"):
        P.validate_control("reset", b'{"pose": {"x_m": 1, "x_m": 2, "y_m": 0, "yaw_rad": 0}}')


def test_the_documented_yaw_bound_is_accepted_at_both_ends():
    for yaw in (6.28319, -6.28319, 2 * math.pi):
        args = P.validate_control("reset", json.dumps(
            {"pose": {"x_m": 0, "y_m": 0, "yaw_rad": yaw}}).encode())
        assert args["pose"]["yaw_rad"] == yaw
    with raise_field("pose.yaw_rad"):
        P.validate_control("reset", b'{"pose": {"x_m": 0, "y_m": 0, "yaw_rad": 6.2832}}')
    assert "[-6.28319, 6.28319]" in P.controls_markdown()


@pytest.mark.parametrize("key", ["k" * 60_000, "\ud800", "a\x00b\u2028"])
def test_error_replies_never_echo_huge_keys_or_lone_surrogates(key):
    try:
        P.validate_control("pause", json.dumps({key: 1}).encode())
    except P.ProtocolError as exc:
        body = P.reply_error(exc)
    else:
        raise AssertionError("an unknown key was accepted")
    assert len(body) < 1500
    text = body.decode("utf-8", errors="strict")
    assert "\\ud800" not in text.replace("\\\\ud800", "")  # no JSON surrogate escape
    reply = json.loads(text)
    reply["error"].encode("utf-8")  # strict: no lone surrogate
    assert all(ch.isprintable() for ch in reply["error"] + reply["field"])
    assert len(reply["field"]) <= P.MAX_REPLY_FIELD_CHARS
