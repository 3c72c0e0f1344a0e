"""Client programs of the harness, each run as its own process (as a lab would run them)::

    python -m simserver.testing.roles driver --connect tcp/127.0.0.1:7447 --rate 1000 ...

- ``driver``: commands at ``--rate`` on absolute deadlines (a stop-and-go cycle, or a
  constant ``--profile throttle:X`` / ``brake:X``), ``seq`` from ``--seq-start``;
- ``flood``: commands far above 1 kHz, one batch per millisecond;
- ``recorder``: appends every state payload to ``--out`` and checks the ticks for gaps;
- ``joiner``: subscribes to the state, asks ``get_config``, leaves after ``--seconds``;
- ``slowsub``: subscribes through a tiny FIFO that it never reads;
- ``router``: a zenoh router on ``--listen``;
- ``multisub``: ``--sessions`` state subscribers, each its own zenoh session (link), each
  checking its ticks for gaps;
- ``churn``: ``--rate`` sessions a second join (subscribe to the state, ask
  ``get_config``) and leave ``--life`` seconds later.

Every role prints ``READY`` once its session is up and, when it ends (its duration is
over, or SIGTERM), one line ``RESULT {json}``. ``simserver.testing.RoleProcess`` starts
them.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import struct
import sys
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from simserver.testing import ROLES_MODULE, client_config
from simserver.wire import protocol as proto


def percentile(values: Sequence[float], q: float) -> float:
    """``q``-th percentile (NaN for no values)."""
    return float(np.percentile(np.asarray(values, dtype=float), q)) if len(values) else math.nan



class _Stop:
    """SIGTERM/SIGINT set a flag that the role's loop polls."""

    def __init__(self) -> None:
        self.stopped = False
        signal.signal(signal.SIGTERM, self._set)
        signal.signal(signal.SIGINT, self._set)

    def _set(self, *_: Any) -> None:
        self.stopped = True


def _role_endpoint(args: argparse.Namespace) -> Any:
    from simserver.adapters.zenoh_io import ZenohEndpoint

    cfg = client_config(args.connect, args.zenoh_config, args.mode)
    return ZenohEndpoint(cfg, prefix="simserver", vehicle=args.vehicle_id)


def _result(data: dict[str, Any]) -> None:
    print("RESULT " + json.dumps(data), flush=True)


def _profile_inputs(profile: str, t: float) -> dict[str, Any]:
    """Driver inputs of a profile at ``t`` seconds since the start."""
    if profile.startswith("throttle:"):
        return {"throttle": float(profile.split(":")[1])}
    if profile.startswith("brake:"):
        return {"brake": float(profile.split(":")[1])}
    # "cycle": 4 s throttle with a slow weave, 3 s braking to a stop, 2 s hold
    phase = t % 9.0
    if phase < 4.0:
        return {"throttle": 0.35, "steer": 0.15 * math.sin(2 * math.pi * t / 4.0)}
    return {"brake": 0.6}


def role_driver(args: argparse.Namespace) -> None:
    """Command at ``--rate`` on absolute deadlines for ``--seconds`` (or until SIGTERM)."""
    stop = _Stop()
    with _role_endpoint(args) as ep:
        pub = ep.declare_command_publisher()
        period = 1.0 / args.rate
        seq = args.seq_start - 1
        sent = late = 0
        t0 = time.monotonic()
        next_t = t0
        end = t0 + args.seconds if args.seconds > 0 else math.inf
        print("READY", flush=True)
        while not stop.stopped:
            now = time.monotonic()
            if now >= end:
                break
            if now < next_t:
                time.sleep(min(next_t - now, 0.01))
                continue
            seq += 1
            pub.put(proto.encode_command(seq=seq & 0xFFFFFFFF, gear=proto.Gear.D,
                                         sender_time_ns=time.monotonic_ns(),
                                         **_profile_inputs(args.profile, now - t0)))
            sent += 1
            next_t += period
            if now - next_t > 100 * period:  # a long stall: do not burst to catch up
                late += int((now - next_t) / period)
                next_t = now + period
        time.sleep(0.2)  # let the last puts leave before the session closes
    _result({"sent": sent, "first_seq": args.seq_start, "last_seq": seq,
             "seconds": round(time.monotonic() - t0, 3), "deadlines_dropped": late})


def role_flood(args: argparse.Namespace) -> None:
    """Commands at ``--rate`` (far above 1 kHz), sent in one batch per millisecond."""
    stop = _Stop()
    with _role_endpoint(args) as ep:
        pub = ep.declare_command_publisher()
        per_ms = max(1, int(round(args.rate / 1000.0)))
        seq = args.seq_start - 1
        sent = 0
        print("READY", flush=True)
        t0 = time.monotonic()
        next_t = t0
        end = t0 + args.seconds
        # a valid command, its seq patched in place (encoding each one would cap the rate)
        template = bytearray(proto.encode_command(brake=0.3, gear=proto.Gear.D))
        seq_offset = proto.COMMAND_DTYPE.fields["seq"][1]
        put, pack_into = pub.put, struct.Struct("<I").pack_into
        while not stop.stopped and time.monotonic() < end:
            for _ in range(per_ms):
                seq += 1
                pack_into(template, seq_offset, seq & 0xFFFFFFFF)
                put(bytes(template))
            sent += per_ms
            next_t += 0.001
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        elapsed = time.monotonic() - t0
        time.sleep(0.3)
    _result({"sent": sent, "seconds": round(elapsed, 3),
             "rate_hz": round(sent / elapsed, 1), "last_seq": seq})


def role_recorder(args: argparse.Namespace) -> None:
    """Record every state to ``--out`` (raw payloads) and check the ticks for gaps."""
    stop = _Stop()
    with _role_endpoint(args) as ep:
        states = ep.declare_state_inbox(capacity=1 << 16)
        diag = ep.declare_diag_inbox(capacity=256)
        n = gaps = missing = resets = watchdog = 0
        ages: list[float] = []
        last_tick: int | None = None
        diags = 0
        out = open(args.out, "wb") if args.out else None
        print("READY", flush=True)
        end = time.monotonic() + args.seconds if args.seconds > 0 else math.inf
        try:
            while not stop.stopped and time.monotonic() < end:
                payloads = states.drain_newest()
                for payload in payloads:
                    st = proto.decode_state(payload)
                    tick = int(st["tick"])
                    if last_tick is not None:
                        if tick > last_tick + 1:
                            gaps += 1
                            missing += tick - last_tick - 1
                        elif tick < last_tick:
                            resets += 1
                    last_tick = tick
                    if st["flags"] & proto.StateFlag.WATCHDOG:
                        watchdog += 1
                    elif st["cmd_age_s"] >= 0:
                        ages.append(float(st["cmd_age_s"]))
                    n += 1
                    if out is not None:
                        out.write(payload)
                diags += len(diag.drain_newest())
                time.sleep(0.005)
        finally:
            if out is not None:
                out.close()
    _result({"states": n, "gaps": gaps, "missing_ticks": missing, "resets": resets,
             "watchdog_states": watchdog, "diagnostics": diags,
             "cmd_age_p50_ms": round(1e3 * percentile(ages, 50), 3),
             "cmd_age_p99_ms": round(1e3 * percentile(ages, 99), 3),
             "cmd_age_max_ms": round(1e3 * max(ages), 3) if ages else None})


def role_joiner(args: argparse.Namespace) -> None:
    """Connect, subscribe to the state, ask ``get_config``, leave after ``--seconds``."""
    stop = _Stop()
    with _role_endpoint(args) as ep:
        states = ep.declare_state_inbox(capacity=1 << 13)
        print("READY", flush=True)
        try:
            config_ok = bool(ep.request("get_config", timeout_s=2.0)["ok"])
        except (TimeoutError, ValueError):
            config_ok = False
        n = 0
        end = time.monotonic() + args.seconds
        while not stop.stopped and time.monotonic() < end:
            n += len(states.drain_newest())
            time.sleep(0.01)
    _result({"states": n, "config_ok": config_ok})


def role_slowsub(args: argparse.Namespace) -> None:
    """Subscribe to the state through a tiny FIFO that is never drained; sleep."""
    import zenoh

    stop = _Stop()
    with _role_endpoint(args) as ep:
        sub = ep.session.declare_subscriber(ep.keys.state,
                                            zenoh.handlers.FifoChannel(args.capacity))
        print("READY", flush=True)
        end = time.monotonic() + args.seconds if args.seconds > 0 else math.inf
        while not stop.stopped and time.monotonic() < end:
            time.sleep(0.05)  # never reads: the FIFO fills and blocks zenoh's receiver
        sub.undeclare()
    _result({"slept": True})


def role_router(args: argparse.Namespace) -> None:
    """A zenoh router (this Python process) on ``--listen``: clients and servers meet here."""
    import zenoh

    from simserver.adapters.zenoh_io import make_zenoh_config

    stop = _Stop()
    cfg = make_zenoh_config(listen=args.listen, connect=args.connect or [],
                            config_file=args.zenoh_config, mode="router")
    with zenoh.open(cfg):
        print("READY", flush=True)
        end = time.monotonic() + args.seconds if args.seconds > 0 else math.inf
        while not stop.stopped and time.monotonic() < end:
            time.sleep(0.05)
    _result({"routed": True})


def role_multisub(args: argparse.Namespace) -> None:
    """``--sessions`` subscribers of the state, one zenoh session each; gaps per session."""
    stop = _Stop()
    tick_at = proto.STATE_DTYPE.fields["tick"][1]
    unpack = struct.Struct("<Q").unpack_from
    eps = [_role_endpoint(args) for _ in range(args.sessions)]
    inboxes = [ep.declare_state_inbox(capacity=1 << 16) for ep in eps]
    states = [0] * len(eps)
    missing = [0] * len(eps)
    last: list[int | None] = [None] * len(eps)
    print("READY", flush=True)
    end = time.monotonic() + args.seconds if args.seconds > 0 else math.inf
    try:
        while not stop.stopped and time.monotonic() < end:
            for i, inbox in enumerate(inboxes):
                for payload in inbox.drain_newest():
                    tick = unpack(payload, tick_at)[0]
                    if last[i] is not None and tick > last[i] + 1:
                        missing[i] += tick - last[i] - 1
                    last[i] = tick
                    states[i] += 1
            time.sleep(0.005)
    finally:
        for ep in eps:
            ep.close()
    _result({"sessions": len(eps), "states_min": min(states), "states_max": max(states),
             "missing_ticks": missing, "missing_total": sum(missing)})


def role_churn(args: argparse.Namespace) -> None:
    """Sessions joining at ``--rate`` per second, each leaving after ``--life`` seconds."""
    stop = _Stop()
    period = 1.0 / args.rate
    alive: list[tuple[float, Any, Any]] = []
    joined = config_ok = 0
    print("READY", flush=True)
    t0 = time.monotonic()
    next_t = t0
    end = t0 + args.seconds if args.seconds > 0 else math.inf
    while not stop.stopped and time.monotonic() < end:
        now = time.monotonic()
        while alive and alive[0][0] <= now:
            alive.pop(0)[1].close()
        if now >= next_t:
            ep = _role_endpoint(args)
            inbox = ep.declare_state_inbox(capacity=1 << 12)
            try:
                config_ok += bool(ep.request("get_config", timeout_s=1.0)["ok"])
            except (TimeoutError, ValueError):
                pass
            alive.append((time.monotonic() + args.life, ep, inbox))
            joined += 1
            next_t += period
        else:
            for _, _, inbox in alive:
                inbox.drain_newest()
            time.sleep(min(0.005, max(0.0, next_t - now)))
    for _, ep, _ in alive:
        ep.close()
    _result({"joined": joined, "config_ok": config_ok,
             "seconds": round(time.monotonic() - t0, 3)})


ROLES = {"driver": role_driver, "flood": role_flood, "recorder": role_recorder,
         "joiner": role_joiner, "slowsub": role_slowsub, "router": role_router,
         "multisub": role_multisub, "churn": role_churn}


def role_main(argv: Sequence[str]) -> int:
    """``NAME ...``: run one client role (see the module docstring)."""
    parser = argparse.ArgumentParser(prog=f"python -m {ROLES_MODULE}")
    parser.add_argument("name", choices=sorted(ROLES))
    parser.add_argument("--connect", action="append", default=None)
    parser.add_argument("--listen", action="append", default=None, help="router: endpoints")
    parser.add_argument("--vehicle-id", default="car0")
    parser.add_argument("--zenoh-config", default=None, help="client-side zenoh JSON5 file")
    parser.add_argument("--mode", default="client")
    parser.add_argument("--seconds", type=float, default=0.0, help="0: until SIGTERM")
    parser.add_argument("--rate", type=float, default=1000.0, help="commands per second")
    parser.add_argument("--seq-start", type=int, default=1)
    parser.add_argument("--profile", default="cycle", help="cycle | throttle:X | brake:X")
    parser.add_argument("--out", default=None, help="recorder: file of raw state payloads")
    parser.add_argument("--capacity", type=int, default=1, help="slowsub: FIFO capacity")
    parser.add_argument("--sessions", type=int, default=20, help="multisub: sessions")
    parser.add_argument("--life", type=float, default=1.0, help="churn: session lifetime, s")
    args = parser.parse_args(argv)
    if args.name != "router" and not args.connect:
        parser.error(f"role {args.name} needs --connect")
    ROLES[args.name](args)
    return 0


if __name__ == "__main__":
    raise SystemExit(role_main(sys.argv[1:]))
