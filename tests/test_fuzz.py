"""Hostile input: fuzzing the command decoder and every control, in process and live.

In process (hypothesis), more than 10 000 payloads in total in the long form (``-m slow`` or
``SIMSERVER_SLOW=1``), a fifth of each generator's count in the default suite (the same
generators and checks, and every explicit ``@example``):

- ``decode_command`` on random bytes, on structured commands with hostile field values
  (every float class, boundary values, unknown gears, flags, versions, reserved bits),
  and on valid commands mutated byte by byte (flips, truncation, extension). Only
  ``ProtocolError`` may escape; an accepted command is finite and in range, and agrees
  with an independent oracle written from the field table (accept or reject, clamping);
- ``validate_control`` on random bytes, random JSON (huge integers, NaN, lone
  surrogates, deep nesting), structure-aware requests built from ``CONTROL_SPECS`` with
  hostile values, and valid requests mutated character by character. Only
  ``ProtocolError`` may escape; accepted arguments are of their kind, finite, in range,
  and a path is a UTF-8 encodable ``.yaml`` string.

Live: a running ``simserver serve`` gets more than 10 000 seeded payloads (random bytes
and mutated commands on ``cmd``, random and structure-aware JSON on every control key,
plus unknown and wildcard keys). Afterwards it is alive, ticking, its state is finite,
every query got exactly one reply (an error naming the field the local validator names),
and its diagnostics counted every command: received == sent, rejected and clamped
exactly as ``decode_command`` predicts for each payload.
"""

from __future__ import annotations

import json
import math
import random
import struct
import time
from collections import Counter
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from simserver.testing import CONFIGS, Client, ServerProcess, state_is_finite
from simserver.wire import protocol as proto
from simserver.wire.protocol import (
    CLAMP_TOLERANCE,
    COMMAND_DTYPE,
    COMMAND_SIZE,
    CONTROL_NAMES,
    CONTROL_SPECS,
    ProtocolError,
    decode_command,
    validate_control,
)
from tests.conftest import slow_enabled

pytestmark = pytest.mark.timeout(600)

PAYLOADS_TRIED: Counter[str] = Counter()
"""Payloads fed to the decoders by each test of this module (printed at its end)."""

IN_PROCESS_EXAMPLES_LONG = {
    "command_random_bytes": 2000, "command_structured": 2500, "command_mutated": 2000,
    "control_random_bytes": 1000, "control_random_json": 1500, "control_structured": 1200,
    "control_mutated": 1000,
}
"""Generated examples per in-process test in the long form (docs/reliability.md quotes
their total)."""
SHORT_FORM_DIVISOR = 5
"""The default suite runs a fifth of each count (the issue 33 suite budget; the in-process
fuzzing took 45 s of CPU, a fifth 7.6 s); ``-m slow`` / ``SIMSERVER_SLOW=1`` runs them all."""
IN_PROCESS_EXAMPLES = (IN_PROCESS_EXAMPLES_LONG if slow_enabled(None) else
                       {k: n // SHORT_FORM_DIVISOR for k, n in IN_PROCESS_EXAMPLES_LONG.items()})
LIVE_COMMANDS = 7000
LIVE_QUERIES = 3000

FUZZ_SETTINGS = {"deadline": None, "suppress_health_check": [HealthCheck.too_slow,
                                                             HealthCheck.filter_too_much]}


@pytest.fixture(scope="module", autouse=True)
def report_payload_counts() -> Iterator[None]:
    """Print how many payloads each test tried (docs/reliability.md quotes the total)."""
    yield
    if PAYLOADS_TRIED:
        total = sum(PAYLOADS_TRIED.values())
        print(f"\n[fuzz] payloads tried: {dict(PAYLOADS_TRIED)}; total {total}")


# ============================================================================ oracles


UNIT_RANGES = {"steer": (-1.0, 1.0), "throttle": (0.0, 1.0), "brake": (0.0, 1.0)}


def command_oracle(payload: bytes) -> tuple[bool, dict[str, float], set[str]]:
    """Independent reading of the DriverCommand table: (accepted, values, clamped)."""
    if len(payload) != COMMAND_SIZE:
        return False, {}, set()
    rec = np.frombuffer(payload, dtype=COMMAND_DTYPE)[0]
    if int(rec["version"]) != proto.PROTOCOL_VERSION or int(rec["gear"]) > 3:
        return False, {}, set()
    if int(rec["flags"]) & ~1 or int(rec["reserved"]) != 0:
        return False, {}, set()
    values, clamped = {}, set()
    for name, (lo, hi) in UNIT_RANGES.items():
        v = float(rec[name])
        if not math.isfinite(v) or v < lo - CLAMP_TOLERANCE or v > hi + CLAMP_TOLERANCE:
            return False, {}, set()
        if v < lo or v > hi:
            clamped.add(name)
            v = min(max(v, lo), hi)
        values[name] = v
    return True, values, clamped


def check_command(payload: bytes) -> None:
    """decode_command raises only ProtocolError and agrees with the oracle."""
    accepted, values, clamped = command_oracle(payload)
    try:
        cmd = decode_command(payload)
    except ProtocolError as exc:
        assert not accepted, f"rejected a valid command ({exc}): {payload.hex()}"
        assert exc.field in ("payload", "version", "gear", "flags", "reserved", "steer",
                             "throttle", "brake"), exc
        assert str(exc).startswith(f"{exc.field}: "), exc  # the field is named first
        return
    assert accepted, f"accepted an invalid command: {payload.hex()}"
    for name, value in values.items():
        got = getattr(cmd, name)
        assert math.isfinite(got) and got == value, (name, got, value)
    assert -1.0 <= cmd.steer <= 1.0 and 0.0 <= cmd.throttle <= 1.0 and 0.0 <= cmd.brake <= 1.0
    assert 0 <= int(cmd.gear) <= 3 and 0 <= cmd.seq < 2**32
    assert set(cmd.clamped) == clamped


def check_control_args(name: str, args: dict[str, Any]) -> None:
    """Properties of arguments that validate_control accepted."""
    spec = CONTROL_SPECS[name]

    def check(specs: tuple, obj: dict, where: str) -> None:
        known = {s.name: s for s in specs}
        assert set(obj) <= set(known), (where, obj)
        for s in specs:
            if s.name not in obj:
                assert not s.required, (where, s.name)
                continue
            v = obj[s.name]
            if s.kind == "number":
                assert type(v) is float and math.isfinite(v) and s.lo <= v <= s.hi, (s.name, v)
            elif s.kind == "integer":
                assert type(v) is int and s.lo <= v <= s.hi, (s.name, v)
            elif s.kind == "path":
                assert isinstance(v, str) and v.endswith((".yaml", ".yml")), v
                v.encode("utf-8")  # a lone surrogate would reach open()/stat() and raise
                assert not any(ord(c) < 32 or ord(c) == 127 for c in v)
            else:
                assert isinstance(v, dict)
                check(s.children, v, f"{where}{s.name}.")

    check(spec.args, args, "")
    if spec.at_least_one:
        assert args, name
    for key in spec.defaults:
        assert key in args
    # accepted arguments, sent again, are accepted identically
    assert validate_control(name, json.dumps(args).encode()) == args


def check_control(name: str, payload: bytes) -> bool:
    """validate_control raises only ProtocolError; True if accepted."""
    try:
        args = validate_control(name, payload)
    except ProtocolError as exc:
        assert str(exc).startswith(f"{exc.field}: "), exc  # the field is named first
        return False
    check_control_args(name, args)
    return True


# ============================================================================ strategies


FLOAT_EDGES = [0.0, -0.0, 1.0, -1.0, 0.5, 1.0 + 5e-4, -1.0 - 5e-4, 1.001, -1.001, 1.0011,
               -1.0011, 1e-45, -1e-45, 3.4e38, -3.4e38, math.nan, math.inf, -math.inf,
               1e-3, -1e-3, -9e-4, 2.0, 1e30]

lone_surrogates = st.text(st.characters(min_codepoint=0xD800, max_codepoint=0xDFFF),
                          min_size=1, max_size=2)
huge_ints = st.one_of(st.integers(min_value=10**308, max_value=10**400),
                      st.integers(min_value=-(10**400), max_value=-(10**308)))
json_scalars = st.one_of(
    st.none(), st.booleans(), st.integers(), huge_ints,
    st.floats(allow_nan=True, allow_infinity=True), st.sampled_from(FLOAT_EDGES),
    st.text(max_size=20), lone_surrogates,
)
json_values = st.recursive(
    json_scalars,
    lambda children: st.one_of(st.lists(children, max_size=4),
                               st.dictionaries(st.text(max_size=12), children, max_size=4)),
    max_leaves=12,
)


def value_for(spec: proto.ArgSpec) -> st.SearchStrategy:
    """Hostile and valid values for one argument of a control."""
    if spec.kind == "number":
        lo, hi = spec.lo, spec.hi
        return st.one_of(
            st.floats(lo, hi), st.floats(lo - 10, hi + 10, allow_nan=False),
            st.sampled_from([lo, hi, lo - 1e-9, hi + 1e-9, 0.0, math.nan, math.inf]),
            st.integers(int(lo) - 2, int(hi) + 2), huge_ints, json_scalars, json_values)
    if spec.kind == "integer":
        return st.one_of(st.integers(spec.lo - 2, spec.hi + 2),
                         st.sampled_from([1.0, 2.5, True, "3", spec.hi + 1]), huge_ints,
                         json_scalars)
    if spec.kind == "path":
        return st.one_of(
            st.text(max_size=40).map(lambda s: s + ".yaml"),
            lone_surrogates.map(lambda s: f"scenes/{s}.yaml"),
            st.sampled_from(["/etc/passwd.yaml", "../../../../etc/x.yaml", "x.yml", "",
                             "a\x00b.yaml", "a\nb.yaml", "x" * 1030 + ".yaml", ".yaml",
                             "scenes/flat_paper_sedan.yaml", "/proc/self/environ.yaml"]),
            json_scalars)
    return st.one_of(
        st.fixed_dictionaries({}, optional={c.name: value_for(c) for c in spec.children}),
        st.fixed_dictionaries({c.name: value_for(c) for c in spec.children}),
        json_values)


def request_for(name: str) -> st.SearchStrategy:
    """Structure-aware request objects for control ``name`` (maybe with a stray key)."""
    spec = CONTROL_SPECS[name]
    base = st.fixed_dictionaries({}, optional={a.name: value_for(a) for a in spec.args})
    extra = st.dictionaries(st.sampled_from(["bogus", "N", "pose ", "grade", "__proto__"]),
                            json_scalars, max_size=1)
    return st.builds(lambda a, b, mix: {**a, **b} if mix else a, base, extra,
                     st.booleans())


def command_bytes(version: int = proto.PROTOCOL_VERSION, gear: int = 3, flags: int = 0,
                  seq: int = 1, sender: int = 0, steer: float = 0.0, throttle: float = 0.0,
                  brake: float = 0.0, reserved: int = 0) -> bytes:
    """A DriverCommand with any field values (no validation)."""
    rec = np.zeros((), dtype=COMMAND_DTYPE)
    for key, value in (("version", version), ("gear", gear), ("flags", flags), ("seq", seq),
                       ("sender_time_ns", sender), ("reserved", reserved)):
        rec[key] = value
    with np.errstate(over="ignore", invalid="ignore"):
        rec["steer"], rec["throttle"], rec["brake"] = steer, throttle, brake
    return rec.tobytes()


unit_floats = st.one_of(st.floats(width=32, allow_nan=True, allow_infinity=True),
                        st.floats(float(np.float32(-1.0015)), float(np.float32(1.0015)),
                                  width=32), st.sampled_from(FLOAT_EDGES))
structured_commands = st.builds(
    command_bytes,
    version=st.one_of(st.just(proto.PROTOCOL_VERSION), st.integers(0, 0xFFFF)),
    gear=st.one_of(st.integers(0, 3), st.integers(0, 255)),
    flags=st.one_of(st.sampled_from([0, 1]), st.integers(0, 255)),
    seq=st.integers(0, 2**32 - 1), sender=st.integers(0, 2**64 - 1),
    steer=unit_floats, throttle=unit_floats, brake=unit_floats,
    reserved=st.one_of(st.just(0), st.integers(0, 2**32 - 1)),
)
valid_commands = st.builds(
    command_bytes, gear=st.integers(0, 3), flags=st.integers(0, 1),
    seq=st.integers(0, 2**32 - 1), steer=st.floats(-1, 1, width=32),
    throttle=st.floats(0, 1, width=32), brake=st.floats(0, 1, width=32))


def mutate(data: bytes, edits: list[tuple[int, int, int]]) -> bytes:
    """Apply ``(kind, position, value)`` edits: 0 flip bits, 1 set byte, 2 delete, 3 insert,
    4 truncate, 5 extend."""
    buf = bytearray(data)
    for kind, pos, value in edits:
        i = pos % (len(buf) + 1)
        if kind == 0 and buf:
            buf[i % len(buf)] ^= value or 1
        elif kind == 1 and buf:
            buf[i % len(buf)] = value
        elif kind == 2 and buf:
            del buf[i % len(buf)]
        elif kind == 3:
            buf.insert(i, value)
        elif kind == 4:
            del buf[i:]
        elif kind == 5:
            buf.extend(bytes([value]) * (1 + pos % 8))
    return bytes(buf)


edits = st.lists(st.tuples(st.integers(0, 5), st.integers(0, 1 << 16), st.integers(0, 255)),
                 min_size=1, max_size=4)


# ============================================================================ in process: commands


@pytest.mark.slow  # the long form: every count of IN_PROCESS_EXAMPLES_LONG
@settings(max_examples=IN_PROCESS_EXAMPLES["command_random_bytes"], **FUZZ_SETTINGS)
@given(st.one_of(st.binary(max_size=80), st.binary(min_size=COMMAND_SIZE,
                                                   max_size=COMMAND_SIZE)))
def test_decode_command_random_bytes(payload):
    PAYLOADS_TRIED["command_random_bytes"] += 1
    check_command(payload)


@pytest.mark.slow  # the long form: every count of IN_PROCESS_EXAMPLES_LONG
@settings(max_examples=IN_PROCESS_EXAMPLES["command_structured"], **FUZZ_SETTINGS)
@given(structured_commands)
@example(command_bytes(steer=1.0 + 5e-4))  # clamped
@example(command_bytes(throttle=-5e-4, brake=1.0009))  # clamped twice
@example(command_bytes(steer=math.nan))
@example(command_bytes(gear=4))
def test_decode_command_structured(payload):
    PAYLOADS_TRIED["command_structured"] += 1
    check_command(payload)


@pytest.mark.slow  # the long form: every count of IN_PROCESS_EXAMPLES_LONG
@settings(max_examples=IN_PROCESS_EXAMPLES["command_mutated"], **FUZZ_SETTINGS)
@given(valid_commands, edits)
def test_decode_command_mutated_valid_commands(payload, changes):
    PAYLOADS_TRIED["command_mutated"] += 1
    check_command(payload)  # the unmutated one is accepted ...
    assert command_oracle(payload)[0]
    check_command(mutate(payload, changes))  # ... and its mutants handled


def test_decode_command_odd_buffer_types():
    """bytearray, memoryview and non-buffers: accepted alike or ProtocolError."""
    good = command_bytes(throttle=0.5)
    assert decode_command(bytearray(good)).throttle == 0.5
    assert decode_command(memoryview(good)).throttle == 0.5
    for bad in (None, 5, "x" * 32, [0] * 32, memoryview(good)[::2], object()):
        with pytest.raises(ProtocolError):
            decode_command(bad)  # type: ignore[arg-type]


# ============================================================================ in process: controls


control_names = st.one_of(st.sampled_from(CONTROL_NAMES),
                          st.sampled_from(["", "Reset", "reset/", "*", "shutdown"]))


@pytest.mark.slow  # the long form: every count of IN_PROCESS_EXAMPLES_LONG
@settings(max_examples=IN_PROCESS_EXAMPLES["control_random_bytes"], **FUZZ_SETTINGS)
@given(control_names, st.binary(max_size=200))
def test_validate_control_random_bytes(name, payload):
    PAYLOADS_TRIED["control_random_bytes"] += 1
    if name not in CONTROL_SPECS:
        with pytest.raises(ProtocolError):
            validate_control(name, payload)
        return
    check_control(name, payload)


@pytest.mark.slow  # the long form: every count of IN_PROCESS_EXAMPLES_LONG
@settings(max_examples=IN_PROCESS_EXAMPLES["control_random_json"], **FUZZ_SETTINGS)
@given(st.sampled_from(CONTROL_NAMES), json_values)
@example("set_road", {"grade_pct": 10**400})  # an integer too large for a float
@example("reset", {"pose": {"x_m": -(10**309), "y_m": 0, "yaw_rad": 0}})
@example("load", {"scene": "\ud800.yaml"})  # a lone surrogate in a path
def test_validate_control_random_json(name, obj):
    PAYLOADS_TRIED["control_random_json"] += 1
    check_control(name, json.dumps(obj).encode())


@pytest.mark.slow  # the long form: every count of IN_PROCESS_EXAMPLES_LONG
@settings(max_examples=IN_PROCESS_EXAMPLES["control_structured"], **FUZZ_SETTINGS)
@given(st.sampled_from(CONTROL_NAMES).flatmap(
    lambda n: st.tuples(st.just(n), request_for(n))))
def test_validate_control_structured(case):
    name, obj = case
    PAYLOADS_TRIED["control_structured"] += 1
    check_control(name, json.dumps(obj).encode())


def _valid_request(name: str, rnd: random.Random) -> dict[str, Any]:
    """A valid request for ``name`` (random values in range)."""
    if name == "reset":
        return {"pose": {"x_m": rnd.uniform(-50, 50), "y_m": rnd.uniform(-50, 50),
                         "yaw_rad": rnd.uniform(-3, 3)}} if rnd.random() < 0.5 else {}
    if name == "step":
        return {"n": rnd.randint(1, 20)}
    if name == "set_road":
        return {"grade_pct": round(rnd.uniform(-12, 12), 2),
                "friction_scale": round(rnd.uniform(0.5, 1.0), 2)}
    if name == "load":
        return {"scene": rnd.choice(["scenes/nope.yaml", "../nope.yml", "/nope.yaml"])}
    return {}


@pytest.mark.slow  # the long form: every count of IN_PROCESS_EXAMPLES_LONG
@settings(max_examples=IN_PROCESS_EXAMPLES["control_mutated"], **FUZZ_SETTINGS)
@given(st.sampled_from(CONTROL_NAMES), st.integers(0, 2**32), edits)
def test_validate_control_mutated_valid_requests(name, seed, changes):
    PAYLOADS_TRIED["control_mutated"] += 1
    payload = json.dumps(_valid_request(name, random.Random(seed))).encode()
    assert check_control(name, payload)
    check_control(name, mutate(payload, changes))


def test_validate_control_size_and_depth_limits():
    for name in CONTROL_NAMES:
        for payload in (b"[" * 100_000, b"[" * 60_000 + b"]" * 60_000,
                        b'{"a":' * 10_000 + b"1" + b"}" * 10_000,
                        b" " * (proto.MAX_CONTROL_PAYLOAD_BYTES + 1), b"\xff\xfe{}"):
            with pytest.raises(ProtocolError):
                validate_control(name, payload)


# ============================================================================ live


def _random_json(rnd: random.Random, depth: int = 0) -> Any:
    """A random JSON value (python's random; seeded)."""
    r = rnd.random()
    if depth > 3 or r < 0.5:
        return rnd.choice([
            None, True, False, rnd.randint(-10, 10), rnd.randint(-2**70, 2**70),
            rnd.uniform(-1e6, 1e6), rnd.choice(FLOAT_EDGES), 10**rnd.randint(300, 420),
            "".join(rnd.choice("abc.yaml/\\\x00\n\u00e9") for _ in range(rnd.randint(0, 12))),
            chr(rnd.randint(0xD800, 0xDFFF)) + ".yaml",
        ])
    if r < 0.75:
        return [_random_json(rnd, depth + 1) for _ in range(rnd.randint(0, 4))]
    keys = ["pose", "x_m", "y_m", "yaw_rad", "n", "grade_pct", "cross_slope_pct",
            "friction_scale", "vehicle", "scene", "bogus", ""]
    return {rnd.choice(keys): _random_json(rnd, depth + 1) for _ in range(rnd.randint(0, 4))}


def _structured_request(name: str, rnd: random.Random) -> dict[str, Any]:
    """Known argument names with random (often hostile) values."""
    spec = CONTROL_SPECS[name]
    out: dict[str, Any] = {}
    for a in spec.args:
        if rnd.random() < 0.6:
            if a.kind == "object":
                out[a.name] = {c.name: _random_json(rnd, 2) if rnd.random() < 0.3
                               else rnd.uniform(-7, 7) for c in a.children
                               if rnd.random() < 0.9}
            elif a.kind == "number":
                out[a.name] = rnd.choice([rnd.uniform(a.lo - 5, a.hi + 5), a.lo, a.hi,
                                          _random_json(rnd, 3)])
            elif a.kind == "integer":
                out[a.name] = rnd.choice([rnd.randint(a.lo - 2, a.hi + 2), 1.5, "7",
                                          _random_json(rnd, 3)])
            else:
                out[a.name] = rnd.choice(["scenes/x.yaml", "../../etc/passwd.yaml",
                                          _random_json(rnd, 3),
                                          "s\ud83a.yaml", "x" * 1100 + ".yaml"])
    if rnd.random() < 0.1:
        out[rnd.choice(["bogus", "N"])] = 1
    return out


def live_command_payloads(rnd: random.Random, n: int) -> list[bytes]:
    """Seeded random bytes, mutated valid commands and hostile structured commands."""
    out = []
    seq = 0
    for i in range(n):
        seq += 1
        r = i % 3
        if r == 0:
            size = COMMAND_SIZE if rnd.random() < 0.3 else rnd.randint(0, 64)
            out.append(rnd.randbytes(size))
        elif r == 1:
            valid = command_bytes(gear=rnd.randint(0, 3), flags=rnd.randint(0, 1), seq=seq,
                                  steer=rnd.uniform(-1, 1), throttle=rnd.uniform(0, 0.3),
                                  brake=rnd.uniform(0, 1))
            changes = [(rnd.randint(0, 5), rnd.randint(0, 64), rnd.randint(0, 255))
                       for _ in range(rnd.randint(0, 3))]
            out.append(mutate(valid, changes))
        else:
            pick = lambda: rnd.choice(FLOAT_EDGES + [rnd.uniform(-1.01, 1.01)])  # noqa: E731
            out.append(command_bytes(
                version=rnd.choice([1, 1, 1, 0, 2, 0xFFFF]), gear=rnd.choice([0, 1, 2, 3, 4]),
                flags=rnd.choice([0, 1, 2, 0x80]), seq=seq, steer=pick(),
                throttle=pick(), brake=pick(), reserved=rnd.choice([0, 0, 0, 1])))
    return out


def live_control_requests(rnd: random.Random, n: int) -> list[tuple[str, bytes]]:
    """Seeded (control suffix, payload) pairs for every control key and a few odd keys."""
    out: list[tuple[str, bytes]] = []
    names = list(CONTROL_NAMES)
    for i in range(n):
        r = rnd.random()
        name = names[i % len(names)] if r < 0.97 else rnd.choice(["nope", "*", "RESET"])
        kind = i % 4
        if kind == 0:
            payload = rnd.randbytes(rnd.randint(0, 120))
        elif kind == 1:
            payload = json.dumps(_random_json(rnd)).encode()
        elif kind == 2:
            payload = json.dumps(_structured_request(name if name in CONTROL_SPECS else "reset",
                                                     rnd)).encode()
        else:
            valid = json.dumps(_valid_request(name, rnd)).encode()
            changes = [(rnd.randint(0, 5), rnd.randint(0, 200), rnd.randint(32, 126))
                       for _ in range(rnd.randint(0, 2))]
            payload = mutate(valid, changes)
        out.append((name, payload))
    # a few real loads, so the load path runs under fuzz too
    hill = str(CONFIGS / "scenes" / "hill_10pct_paper_sedan.yaml")
    flat = str(CONFIGS / "scenes" / "flat_paper_sedan.yaml")
    out[n // 3] = ("load", json.dumps({"scene": hill}).encode())
    out[2 * n // 3] = ("load", json.dumps({"scene": flat}).encode())
    return out


def expected_command_counts(payloads: list[bytes]) -> tuple[int, int]:
    """(rejected, clamped) as the server must count them."""
    rejected = clamped = 0
    for p in payloads:
        try:
            cmd = decode_command(p)
        except ProtocolError:
            rejected += 1
        else:
            clamped += bool(cmd.clamped)
    return rejected, clamped


def _send_queries(probe: Client, requests: list[tuple[str, bytes]],
                  in_flight: int = 8) -> list[tuple[str, bytes, list[dict]]]:
    """Send every query (at most ``in_flight`` outstanding); each one's decoded replies."""
    import zenoh

    session = probe.ep.session
    base = probe.ep.keys.base
    pending: list[tuple[str, bytes, Any]] = []
    done: list[tuple[str, bytes, list[dict]]] = []

    def collect(entry: tuple[str, bytes, Any]) -> None:
        name, payload, handler = entry
        replies = []
        for reply in handler:  # ends when the query is finalised (or times out)
            result = reply.ok if reply.ok is not None else reply.err
            raw = result.payload.to_bytes()
            try:
                replies.append(proto.decode_reply(raw))
            except ProtocolError:  # zenoh's own error (a timeout): not the server's
                replies.append({"ok": False, "not_json": raw[:100]})
        done.append((name, payload, replies))

    for name, payload in requests:
        key = f"{base}/ctl/{name}"
        pending.append((name, payload, session.get(
            key, payload=payload, encoding=zenoh.Encoding(proto.ENCODING_CONTROL),
            timeout=20.0)))
        if len(pending) >= in_flight:
            collect(pending.pop(0))
    while pending:
        collect(pending.pop(0))
    return done


def test_live_server_survives_10000_fuzzed_payloads(tmp_path):
    rnd = random.Random(20261123)
    commands = live_command_payloads(rnd, LIVE_COMMANDS)
    requests = live_control_requests(rnd, LIVE_QUERIES)
    exp_rejected, exp_clamped = expected_command_counts(commands)
    with ServerProcess(log_level="WARNING") as server, Client(server) as probe:
        probe.fresh_state()
        d0 = probe.diagnostics()
        t0 = time.monotonic()
        # commands: about one per millisecond (never in bursts), so the server's 256-deep
        # ring cannot overflow unless the server alone stalls for a quarter of a second:
        # every payload must be counted
        for payload in commands:
            probe.pub.put(payload)
            time.sleep(0.001)  # the subject: a paced stream, about one command a tick
        t_cmd = time.monotonic() - t0
        results = _send_queries(probe, requests)
        t_all = time.monotonic() - t0
        unanswered = [(n, p[:80], replies) for n, p, replies in results
                      if len(replies) != 1 or "not_json" in replies[0]]
        if unanswered:
            pytest.fail(f"{len(unanswered)} queries without exactly one server reply, first "
                        f"{unanswered[:3]}; {server.crash_report()}")
        assert server.alive(), server.text()[-3000:]
        # leave the car in a known state, then check it still ticks and is finite
        for name, args in (("resume", None), ("reset", None),
                           ("set_road", {"grade_pct": 0.0, "cross_slope_pct": 0.0,
                                         "friction_scale": 1.0})):
            assert probe.request(name, args, timeout_s=10.0)["ok"], name
        d1 = probe.wait_diagnostics(
            lambda d: int(d["cmd_received"] - d0["cmd_received"]) >= len(commands),
            what=f"the {len(commands)} commands counted")
        a = probe.fresh_state()
        b = probe.wait_state(lambda s: int(s["tick"]) > int(a["tick"]) + 500, timeout_s=10.0,
                             what="500 more ticks")
        assert int(b["tick"]) > int(a["tick"]) + 500  # ticking
        assert state_is_finite(a) and state_is_finite(b)
        assert server.alive()

    received = int(d1["cmd_received"] - d0["cmd_received"])
    rejected = int(d1["cmd_rejected"] - d0["cmd_rejected"])
    clamped = int(d1["cmd_clamped"] - d0["cmd_clamped"])
    # every command counted: received == sent, and rejected/clamped exactly as predicted
    assert received == len(commands)
    assert rejected == exp_rejected and clamped == exp_clamped
    # every query got exactly one reply; errors name the field the validator names
    outcomes = Counter()
    for name, payload, replies in results:
        assert len(replies) == 1, (name, payload[:100], replies)
        reply = replies[0]
        if name not in CONTROL_SPECS:
            assert not reply["ok"] and reply["field"] == "control"
            outcomes["unknown control"] += 1
            continue
        try:
            validate_control(name, payload)
        except ProtocolError as exc:
            assert not reply["ok"] and reply["field"] == exc.field, (name, payload, reply)
            outcomes["rejected"] += 1
        else:
            outcomes["ok" if reply["ok"] else "valid, refused by the server"] += 1
    PAYLOADS_TRIED["live_commands"] += len(commands)
    PAYLOADS_TRIED["live_queries"] += len(results)
    print(f"\n[live fuzz] {len(commands)} commands in {t_cmd:.1f} s: received {received}, "
          f"rejected {rejected}, clamped {clamped} (as predicted); {len(results)} queries, "
          f"all answered once: {dict(outcomes)}; {t_all:.1f} s in all; late ticks "
          f"{int(d1['late_ticks'] - d0['late_ticks'])}, skipped "
          f"{int(d1['skipped_ticks'] - d0['skipped_ticks'])} over "
          f"{float(d1['uptime_s'] - d0['uptime_s']):.1f} s")


def test_command_oracle_agrees_on_known_cases():
    """The oracle itself: a few hand-checked payloads."""
    assert command_oracle(command_bytes(throttle=0.5))[0]
    assert command_oracle(command_bytes(steer=-1.0005))[2] == {"steer"}
    assert not command_oracle(command_bytes(steer=-1.0015))[0]
    assert not command_oracle(command_bytes(version=proto.PROTOCOL_VERSION + 1))[0]
    assert not command_oracle(command_bytes(flags=2))[0]
    assert not command_oracle(command_bytes(reserved=1))[0]
    assert not command_oracle(command_bytes()[:-1])[0]
    assert struct.unpack_from("<H", command_bytes())[0] == proto.PROTOCOL_VERSION
