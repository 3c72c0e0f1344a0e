"""Every car a client can see: discovery by liveliness, the world message, the neighbours.

A server may serve several cars in one world (docs/protocol.md section 5.1). A client finds
them without asking the server anything:

- :func:`discover_cars` lists the cars served now (their liveliness tokens,
  ``{prefix}/*/alive``); :class:`CarsWatch` follows cars appearing and going;
- :class:`WorldWatch` keeps the newest WorldState (``{prefix}/world/state``: every car's
  id, pose and speed), never blocking;
- :func:`neighbours` picks the nearest car ahead and behind a car, with the distance and
  the closing speed, for a driver's display (``simserver-player``'s progress line).

``python -m clients.world`` prints the cars a server has, and what its world message
says of them, once a second (or once, with ``--once``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass

from clients.common import (
    EXIT_FAILED,
    EXIT_OK,
    ClientError,
    StopFlag,
    add_connection_args,
    client_main,
    connect,
)
from simserver.adapters.zenoh_io import AliveWatch, Inbox, ZenohEndpoint
from simserver.wire import protocol as proto

PROG = "simserver-world"

LANE_HALF_WIDTH_M = 2.5
"""A car counts as ahead or behind when its CG is within this much of the line through the
car's CG along its heading: about one lane (3.5 m) and a half's half-width, so that the car
in the next lane is not taken for the one ahead."""


def car_of_alive_key(key: str, prefix: str) -> str | None:
    """The car id of a liveliness token's key ``{prefix}/{id}/alive``, else None (the
    per-session tokens ``.../alive/<zid>`` are not cars)."""
    head = prefix + "/"
    if not key.startswith(head) or not key.endswith("/alive"):
        return None
    car = key[len(head):-len("/alive")]
    return car if car and "/" not in car else None


def discover_cars(ep: ZenohEndpoint, prefix: str, timeout_s: float = 1.0) -> list[str]:
    """The ids of the cars served under ``prefix`` now (sorted): their liveliness tokens."""
    keys = ep.alive_tokens(proto.world_keys(prefix).alive_all, timeout_s=timeout_s)
    return sorted({c for k in keys if (c := car_of_alive_key(k, prefix)) is not None})


class CarsWatch:
    """The cars present, kept up to date from a liveliness subscriber (cars added to and
    removed from a running world, servers starting and stopping)."""

    def __init__(self, ep: ZenohEndpoint, prefix: str) -> None:
        self.prefix = prefix
        self._watch: AliveWatch = ep.declare_alive_watch(proto.world_keys(prefix).alive_all)
        self.cars: set[str] = set()

    def poll(self) -> set[str]:
        """The cars present after the changes received since the last call."""
        for key, appeared in self._watch.poll():
            car = car_of_alive_key(key, self.prefix)
            if car is not None:
                (self.cars.add if appeared else self.cars.discard)(car)
        return self.cars


class WorldWatch:
    """The newest world message (``{prefix}/world/state``), read without blocking;
    payloads that do not decode are counted in ``rejected``, never raised."""

    def __init__(self, ep: ZenohEndpoint, prefix: str, capacity: int = 16) -> None:
        self._inbox: Inbox = ep.declare_inbox(proto.world_keys(prefix).state, capacity)
        self.world: proto.WorldState | None = None
        self.received = 0
        self.rejected = 0

    def poll(self) -> proto.WorldState | None:
        """The newest valid world message received so far (None before the first)."""
        for payload in reversed(self._inbox.drain_newest()):
            self.received += 1
            try:
                self.world = proto.decode_world(payload)
                break
            except proto.ProtocolError:
                self.rejected += 1
        return self.world


@dataclass(frozen=True)
class Neighbour:
    """Another car seen from one car: its id, the distance between the CGs along the car's
    heading (m, > 0), and the closing speed (m/s, > 0 when the gap shrinks)."""

    id: str
    distance_m: float
    closing_mps: float

    def text(self) -> str:
        return f"{self.id} {self.distance_m:.1f} m, closing {self.closing_mps:+.1f} m/s"


def neighbours(world: proto.WorldState, me: str,
               lane_half_width_m: float = LANE_HALF_WIDTH_M
               ) -> tuple[Neighbour | None, Neighbour | None]:
    """The nearest car ahead and behind car ``me`` (None where there is none; both None if
    ``me`` is not in the world): cars whose CG is within ``lane_half_width_m`` of the line
    along ``me``'s heading, in the horizontal plane; the closing speed is the rate at which
    the distance shrinks, from both cars' velocities projected on that heading."""
    mine = world.car(me)
    if mine is None:
        return None, None
    yaw = float(mine["yaw_rad"])
    c, s = math.cos(yaw), math.sin(yaw)
    my_speed = _along(mine, c, s)
    ahead: Neighbour | None = None
    behind: Neighbour | None = None
    for k, car_id in enumerate(world.ids):
        if car_id == me:
            continue
        other = world.cars[k]
        dx = float(other["x_m"]) - float(mine["x_m"])
        dy = float(other["y_m"]) - float(mine["y_m"])
        along, across = dx * c + dy * s, -dx * s + dy * c
        if abs(across) > lane_half_width_m or along == 0.0:
            continue
        their_speed = _along(other, c, s)
        if along > 0.0 and (ahead is None or along < ahead.distance_m):
            ahead = Neighbour(car_id, along, my_speed - their_speed)
        elif along < 0.0 and (behind is None or -along < behind.distance_m):
            behind = Neighbour(car_id, -along, their_speed - my_speed)
    return ahead, behind


def _along(car: object, c: float, s: float) -> float:
    """A car's horizontal velocity projected on the unit vector ``(c, s)``."""
    yaw = float(car["yaw_rad"])
    u, v = float(car["u_mps"]), float(car["v_mps"])
    vx, vy = u * math.cos(yaw) - v * math.sin(yaw), u * math.sin(yaw) + v * math.cos(yaw)
    return vx * c + vy * s


def traffic_text(world: proto.WorldState | None, me: str) -> str:
    """``ahead ID D m, closing V m/s; behind ...`` for a progress line ("" with no other
    car in the world)."""
    if world is None or len(world.ids) < 2:
        return ""
    ahead, behind = neighbours(world, me)
    return (f"ahead {ahead.text() if ahead else '-'}; "
            f"behind {behind.text() if behind else '-'}")


# ------------------------------------------------------------------ the command line
def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m clients.world``."""
    parser = argparse.ArgumentParser(
        prog=PROG, description="List the cars a simserver serves and print its world "
        "message (every car's pose and speed) once a second, as JSON lines.")
    parser.add_argument("--once", action="store_true",
                        help="print one line when a world message has arrived, then exit")
    parser.add_argument("--seconds", type=float, default=None,
                        help="stop after this long (default: until Ctrl-C)")
    add_connection_args(parser)
    return parser


def _line(cars: Sequence[str], world: proto.WorldState | None) -> str:
    out: dict[str, object] = {"cars": list(cars)}
    if world is not None:
        out["tick"] = world.tick
        out["world"] = {car_id: {"x_m": round(float(world.cars[k]["x_m"]), 3),
                                 "y_m": round(float(world.cars[k]["y_m"]), 3),
                                 "u_mps": round(float(world.cars[k]["u_mps"]), 3),
                                 "driven_by": proto.DRIVEN_BY_CODES[
                                     int(world.cars[k]["driven_by"])]}
                        for k, car_id in enumerate(world.ids)}
    return json.dumps(out)


def _run(args: argparse.Namespace) -> int:
    with StopFlag() as stop:
        conn = connect(args, PROG)  # the vehicle given (default car0) must be served
        try:
            ep = conn.ep
            cars = CarsWatch(ep, args.prefix)
            watch = WorldWatch(ep, args.prefix)
            t0 = time.monotonic()
            next_print = t0
            while not stop.stopped:
                now = time.monotonic()
                world = watch.poll()
                present = sorted(cars.poll())
                if args.once and world is not None:
                    print(_line(present, world), flush=True)
                    return EXIT_OK
                if not args.once and now >= next_print:
                    next_print += 1.0
                    print(_line(present, world), flush=True)
                if args.seconds is not None and now - t0 >= args.seconds:
                    if args.once:
                        raise ClientError(f"no world message within {args.seconds:g} s",
                                          EXIT_FAILED)
                    break
                time.sleep(0.01)
            return EXIT_OK
        finally:
            conn.close()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m clients.world``; returns the exit code."""
    return client_main(PROG, build_parser, _run, argv)


if __name__ == "__main__":
    sys.exit(main())
