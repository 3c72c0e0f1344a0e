"""Container health check: is a simserver publishing vehicle states?

The image's ``HEALTHCHECK`` runs::

    python /usr/local/lib/simserver/healthcheck.py

It opens a zenoh session in client mode to ``SIMSERVER_HEALTH_CONNECT`` (default
``tcp/127.0.0.1:7447``, the container's own server), waits up to ``--timeout`` seconds for a
VehicleState on ``SIMSERVER_HEALTH_KEY`` (default ``**/state``: any prefix, any vehicle id),
decodes it, prints the vehicle's tick and exits 0; exit 1 if none arrives (the server is not
up yet, has stopped ticking, or listens elsewhere). It only subscribes: it sends no command,
so it never takes the car from a driver.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"
"""The endpoint checked unless ``SIMSERVER_HEALTH_CONNECT`` or ``--connect`` says otherwise."""

DEFAULT_KEY = "**/state"
"""The state key expression checked: every vehicle of every prefix."""


def check(connect: str, key: str, timeout_s: float) -> dict[str, float] | None:
    """The first state received within ``timeout_s`` (tick and simulated time), or None."""
    import zenoh

    from simserver.adapters.zenoh_io import make_zenoh_config
    from simserver.wire import protocol as proto

    cfg = make_zenoh_config(listen=[], connect=[connect], mode="client")
    with zenoh.open(cfg) as session:
        sub = session.declare_subscriber(key, zenoh.handlers.RingChannel(4))
        deadline = time.monotonic() + timeout_s
        try:
            while time.monotonic() < deadline:
                sample = sub.try_recv()
                if sample is None:
                    time.sleep(0.01)
                    continue
                try:
                    state = proto.decode_state(sample.payload.to_bytes())
                except proto.ProtocolError:
                    continue
                return {"tick": int(state["tick"]), "sim_time_s": float(state["sim_time_s"])}
        finally:
            sub.undeclare()
    return None


def main(argv: list[str] | None = None) -> int:
    """Exit 0 if a state arrives in time, 1 otherwise (Docker's healthy / unhealthy)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connect", default=os.environ.get("SIMSERVER_HEALTH_CONNECT",
                                                            DEFAULT_CONNECT))
    parser.add_argument("--key", default=os.environ.get("SIMSERVER_HEALTH_KEY", DEFAULT_KEY))
    parser.add_argument("--timeout", type=float, default=3.0, metavar="S")
    args = parser.parse_args(argv)
    try:
        state = check(args.connect, args.key, args.timeout)
    except Exception as exc:  # any failure to connect is "unhealthy", with the reason
        print(f"unhealthy: {args.connect}: {exc}", file=sys.stderr)
        return 1
    if state is None:
        print(f"unhealthy: no state on {args.key} from {args.connect} within "
              f"{args.timeout:g} s", file=sys.stderr)
        return 1
    print(f"healthy: tick {state['tick']} ({state['sim_time_s']:.3f} s simulated)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
