"""``simserver-player``: play a scenario's input keyframes live, in real time.

The scenario file is the headless runner's (``configs/scenarios/*.yaml``); its name,
duration and keyframes are read by :mod:`simserver.sim.keyframes`, the keyframe parser and
sampler of ``simserver run-scenario`` (the file format, not the server, and without the
compiled core). The channels are sampled by the same function as the headless input
table (:func:`simserver.sim.keyframes.sample_keyframes`: steer, throttle and brake linear
between their keyframes, gear and parking brake switching at theirs) and sent as
DriverCommands at a steady rate (``--rate``, default 1000 Hz, on absolute deadlines of
this process's monotonic clock). The rest of the file (vehicle, road, initial state) is
the server's to validate, when ``--load`` asks it to load the file as its scene.

With ``--load`` (the usual way to compare with a headless run) the player first pauses
the server, asks it to ``load`` the scenario file as its scene (vehicle, road, initial
state: the live run starts where the headless one does, at tick 0), sends the t = 0
inputs for ``--preroll`` seconds while paused (so the server's watchdog has let go
before the first step), then resumes the server and starts its own clock. The live run
then lags the headless time line by the resume round trip and the command transit: a
tick or two, which a comparison removes by aligning on an input event.

It prints its progress once a second (its time, the server's simulated time, speed,
applied brake and gear; with other cars in the server's world, the nearest car ahead and
behind with the distance and closing speed, from the world message: ``clients.world``)
and exits when the maneuver ends (``duration_s`` of the scenario, or ``--duration``); the
server's watchdog then holds the car unless ``--pause-at-end`` freezes it where the maneuver ended.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from clients.common import (
    EXIT_FAILED,
    EXIT_OK,
    ClientError,
    Connection,
    RatePacer,
    ServerPresence,
    StopFlag,
    add_connection_args,
    add_rate_arg,
    check_rate,
    client_main,
    connect,
    gear_name,
    state_filter,
)
from clients.world import WorldWatch, traffic_text
from simserver.adapters.validate import ConfigError
from simserver.sim.keyframes import load_keyframe_file, sample_keyframes
from simserver.wire import protocol as proto

PROG = "simserver-player"
DEFAULT_RATE_HZ = 1000.0
DEFAULT_PREROLL_S = 0.3


@dataclass(frozen=True)
class InputTrack:
    """Keyframes sampled on a regular time grid.

    Attributes
    ----------
    rate_hz : float
        Samples per second.
    time_s : ndarray
        ``k / rate_hz``.
    steer, throttle, brake : ndarray
        Normalised inputs (float64).
    parking_brake : ndarray of bool
    gear : ndarray of int
        :class:`simserver.wire.protocol.Gear` codes.
    """

    rate_hz: float
    time_s: np.ndarray
    steer: np.ndarray
    throttle: np.ndarray
    brake: np.ndarray
    parking_brake: np.ndarray
    gear: np.ndarray

    def __len__(self) -> int:
        return int(self.time_s.size)

    def command(self, k: int, seq: int, sender_time_ns: int) -> bytes:
        """Encoded DriverCommand of sample ``k``."""
        return proto.encode_command(
            float(self.steer[k]), float(self.throttle[k]), float(self.brake[k]),
            gear=int(self.gear[k]), parking_brake=bool(self.parking_brake[k]), seq=seq,
            sender_time_ns=sender_time_ns)


def make_track(keyframes: Sequence[Mapping[str, Any]], duration_s: float,
               rate_hz: float) -> InputTrack:
    """Sample keyframes from 0 to ``duration_s`` inclusive at ``rate_hz``."""
    n = int(math.floor(duration_s * rate_hz + 1e-9)) + 1
    times = np.arange(n) / rate_hz
    ch = sample_keyframes(keyframes, times)
    return InputTrack(rate_hz=rate_hz, time_s=times, steer=np.clip(ch["steer"], -1.0, 1.0),
                      throttle=np.clip(ch["throttle"], 0.0, 1.0),
                      brake=np.clip(ch["brake"], 0.0, 1.0),
                      parking_brake=ch["parking_brake"] > 0.5,
                      gear=ch["gear"].round().astype(np.int64))


def load_track(path: Path, rate_hz: float, duration_s: float | None) -> tuple[InputTrack,
                                                                             str]:
    """Parse a scenario file's keyframes; returns the track and the scenario name.

    Raises
    ------
    ClientError
        When the file's name, duration or keyframes are invalid (the message names the
        file and key).
    """
    try:
        scenario = load_keyframe_file(path)
    except ConfigError as exc:  # names the file and the key
        raise ClientError(str(exc)) from None
    end = scenario.duration_s if duration_s is None else duration_s
    return make_track(scenario.keyframes, end, rate_hz), scenario.name


class Progress:
    """Reads the newest state (for the progress line) without blocking."""

    def __init__(self, conn: Connection) -> None:
        self.inbox = conn.ep.declare_state_inbox(capacity=64)
        self.filter = state_filter(conn, PROG)  # only the server's states, others counted
        self.state: np.void | None = None
        self.world = WorldWatch(conn.ep, conn.ep.keys.prefix)  # the other cars, if any
        self.vehicle = conn.ep.keys.vehicle

    def traffic(self) -> str:
        """The nearest cars ahead and behind (``clients.world.traffic_text``), or ""."""
        return traffic_text(self.world.poll(), self.vehicle)

    def poll(self) -> np.void | None:
        """The newest valid state received so far."""
        state = self.filter.newest(self.inbox.drain_newest(), time.monotonic())
        if state is not None:
            self.state = state
        return self.state


def _request(conn: Connection, name: str, args: dict[str, Any] | None = None,
             timeout_s: float = 5.0) -> dict[str, Any]:
    try:
        reply = conn.ep.request(name, args, timeout_s=timeout_s)
    except TimeoutError as exc:
        raise ClientError(f"{name}: {exc}", EXIT_FAILED) from None
    except proto.ProtocolError as exc:
        raise ClientError(f"{name}: {exc}") from None
    if not reply.get("ok"):
        raise ClientError(f"the server refused {name}: {reply.get('error')}", EXIT_FAILED)
    return reply


def play(conn: Connection, track: InputTrack, stop: StopFlag, *, load: str | None,
         reset: bool, preroll_s: float, pause_at_end: bool, quiet: bool) -> int:
    """Play a track against the connected server; returns the exit code.

    Parameters
    ----------
    conn : Connection
    track : InputTrack
    stop : StopFlag
    load : str or None
        Scene path to ``load`` first (paused), or None to play on the running server.
    reset : bool
        ``reset`` the server to its scene's start first (ignored with ``load``).
    preroll_s : float
        Seconds of t = 0 commands sent while paused before resuming (with ``load``).
    pause_at_end : bool
        Pause the server when the track ends.
    quiet : bool
        No progress lines.
    """
    pub = conn.ep.declare_command_publisher()
    progress = Progress(conn)
    presence = ServerPresence(conn.ep)
    seq = 0

    def send(k: int) -> None:
        nonlocal seq
        seq = (seq + 1) & 0xFFFFFFFF
        pub.put(track.command(k, seq, time.monotonic_ns()))

    if load is not None:
        _request(conn, "pause")
        reply = _request(conn, "load", {"scene": load}, timeout_s=30.0)
        print(f"{PROG}: loaded {reply.get('scene')} (vehicle {reply.get('vehicle')}), paused "
              "at tick 0", flush=True)
        pacer = RatePacer(min(track.rate_hz, 500.0))
        pacer.start()
        while pacer.wait() < preroll_s:
            send(0)
        _request(conn, "resume")
    elif reset:
        _request(conn, "reset")
    pacer = RatePacer(track.rate_hz)
    t0 = pacer.start()
    send(0)
    n = len(track)
    end_s = float(track.time_s[-1])
    next_print = 0.0
    sent = 1
    last_k = 0
    next_alive = 0.25
    while not stop.stopped:
        t = pacer.wait()
        k = min(n - 1, int(t * track.rate_hz + 1e-9))
        send(k)
        sent += 1
        last_k = k
        if t >= next_alive:
            next_alive = t + 0.25
            if presence.gone():
                raise ClientError(f"the server went away at t {t:.3f} s (its liveliness "
                                  f"token is gone: {conn.where})", EXIT_FAILED)
        if t >= next_print and not quiet:
            next_print += 1.0
            s = progress.poll()
            server = "-" if s is None else (
                f"{float(s['sim_time_s']):7.3f} s, u {float(s['u_mps']):+7.3f} m/s, brake "
                f"{float(s['brake']):.3f}, gear {gear_name(int(s['gear']))}")
            traffic = progress.traffic()
            print(f"{PROG}: t {min(t, end_s):7.3f} / {end_s:.3f} s | server {server}"
                  + (f" | {traffic}" if traffic else ""), flush=True)
        if k >= n - 1 and t >= end_s:
            break
    elapsed = time.monotonic() - t0
    if pause_at_end and not stop.stopped:
        _request(conn, "pause")
    s = progress.poll()
    final = "" if s is None else (f"; server at {float(s['sim_time_s']):.3f} s, u "
                                  f"{float(s['u_mps']):+.4f} m/s")
    how = f"stopped by {stop.signal_name}" if stop.stopped else "done"
    print(f"{PROG}: {how}: {sent} commands over {elapsed:.3f} s up to t "
          f"{float(track.time_s[last_k]):.3f} s; {pacer.late} late, {pacer.skipped} skipped "
          f"sends{final}", flush=True)
    return EXIT_OK


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``simserver-player`` (``python -m clients.player``)."""
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Play the input keyframes of a scenario YAML (configs/scenarios/*.yaml, "
        "the headless runner's format) against a live simserver in real time.",
        epilog="Exit codes: 0 played to the end (or stopped by Ctrl-C/SIGTERM), 1 the "
        "server refused a control or stopped answering, 2 bad command line or scenario, "
        "3 no server answered.",
    )
    parser.add_argument("scenario", type=Path, help="scenario YAML")
    add_rate_arg(parser, DEFAULT_RATE_HZ)
    parser.add_argument("--duration", metavar="S", type=float, default=None,
                        help="play this long (default the scenario's duration_s)")
    parser.add_argument("--load", action="store_true",
                        help="first load the scenario as the server's scene (paused), so the "
                        "live run starts where the headless one does, then resume")
    parser.add_argument("--server-path", metavar="PATH", default=None,
                        help="the scenario's path as the server sees it, for --load "
                        "(default: this file's absolute path; the server may restrict "
                        "loads to its config directories)")
    parser.add_argument("--preroll", metavar="S", type=float, default=DEFAULT_PREROLL_S,
                        help="with --load: seconds of t = 0 commands while paused, so the "
                        f"watchdog has let go at the start (default {DEFAULT_PREROLL_S:g})")
    parser.add_argument("--reset", action="store_true",
                        help="without --load: reset the server to its scene's start first")
    parser.add_argument("--pause-at-end", action="store_true",
                        help="pause the server when the maneuver ends (else its watchdog "
                        "takes over 200 ms after the last command)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    add_connection_args(parser)
    return parser


def _run(args: argparse.Namespace) -> int:
    check_rate(args.rate)
    if args.duration is not None and not 0.0 < args.duration <= 1e6:
        raise ClientError(f"--duration {args.duration:g}: expected a positive number of s")
    if not 0.0 <= args.preroll <= 10.0:
        raise ClientError(f"--preroll {args.preroll:g}: expected 0 to 10 s")
    if not args.scenario.is_file():
        raise ClientError(f"{args.scenario}: no such scenario file")
    track, name = load_track(args.scenario, args.rate, args.duration)
    load = None
    if args.load:
        load = args.server_path or str(args.scenario.resolve())
    with StopFlag() as stop:
        conn = connect(args, PROG)
        try:
            print(f"{PROG}: playing {name} ({len(track)} samples at {args.rate:g} Hz, "
                  f"{float(track.time_s[-1]):.3f} s) on {conn.where}", flush=True)
            return play(conn, track, stop, load=load, reset=args.reset,
                        preroll_s=args.preroll, pause_at_end=args.pause_at_end,
                        quiet=args.quiet)
        finally:
            conn.close()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``simserver-player``; returns the exit code."""
    return client_main(PROG, build_parser, _run, argv)


if __name__ == "__main__":
    sys.exit(main())
