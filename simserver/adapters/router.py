"""``simserver router``: a zenoh router with the project's safe defaults (issue 35).

Several servers (one per car, on one or several machines) meet their clients through a
zenoh router (``docs/protocol.md`` section 5). zenoh's own router is the ``zenohd``
binary, which is not a Python package; a Python zenoh session opened with ``mode:
"router"`` routes the same way, so this is that session,
run until SIGINT/SIGTERM, with the defaults the server has:

- explicit listen endpoints only, loopback by default (``tcp/127.0.0.1:7447``); the
  routers and servers it joins are given with ``--connect``;
- multicast scouting and gossip off (nothing announced, nothing auto-connected), shared
  memory off, zenoh's BLOCK wait bounded (``zenoh_io.make_zenoh_config``);
- a zenoh file (``--zenoh-config``: TLS, user/password, access control, as
  ``configs/zenoh/router_auth_acl.json5``) is used as it is, its mode forced to router;
  ``--listen``/``--connect`` replace its endpoints when given. What
  ``zenoh_io.config_warnings`` finds risky in it is said at start;
- every ``tls/`` listen endpoint gets the accept-filtering TLS front of ``simserver
  serve`` (``tls_front.FrontSupervisor``, ``docs/security.md`` 5.1) unless ``--tls-front
  off``: zenoh's TLS listener pauses 100 ms after each failed handshake, so a burst of
  plain connects would lock new sessions out of the router as it did out of the server.
"""

from __future__ import annotations

import logging
import signal
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

log = logging.getLogger("simserver.router")

TLS_FRONT_MODES = ("auto", "off")


def router_config(listen: Sequence[str] | None = None, connect: Sequence[str] | None = None,
                  config_file: str | Path | None = None) -> Any:
    """The router's zenoh config (see the module docstring).

    Parameters
    ----------
    listen, connect : sequence of str, optional
        Endpoints; default: the file's, or without a file ``tcp/127.0.0.1:7447`` and none.
    config_file : str or Path, optional
        A zenoh JSON5/YAML file (TLS, credentials, access control), mode forced to router.

    Raises
    ------
    simserver.adapters.zenoh_io.ZenohConfigError
        Naming the file or the key.
    """
    from simserver.adapters.zenoh_io import _insert, make_zenoh_config

    cfg = make_zenoh_config(listen=listen, connect=connect, config_file=config_file,
                            mode="router")
    if config_file is None:
        # a router gossips the locators of the sessions it holds and connects to what it
        # hears of by default: here only the endpoints given are used
        _insert(cfg, "scouting/gossip/enabled", False, "router config")
    return cfg


def describe(cfg: Any) -> str:
    """One line: where the router listens, what it connects to, its scouting."""
    import json

    from simserver.adapters.zenoh_io import effective_endpoints

    listen = effective_endpoints(cfg) or ["(nothing)"]
    connect = effective_endpoints(cfg, "connect/endpoints") or ["(nothing)"]
    multicast = json.loads(cfg.get_json("scouting/multicast/enabled"))
    gossip = json.loads(cfg.get_json("scouting/gossip/enabled"))
    return (f"listening on {', '.join(listen)}; connecting to {', '.join(connect)}; "
            f"multicast scouting {'on' if multicast in (None, True) else 'off'}, gossip "
            f"{'off' if gossip is False else 'on'}")


def run_router(listen: Sequence[str] | None = None, connect: Sequence[str] | None = None,
               config_file: str | Path | None = None, tls_front: str = "auto",
               duration_s: float | None = None,
               say: Callable[[str], object] | None = None) -> int:
    """Run the router until SIGINT/SIGTERM (or ``duration_s``); returns 0.

    Prints ``simserver router: ready: <describe>`` once it listens (tests wait for it), each
    ``config_warnings`` of a user-given file first.

    Raises
    ------
    ZenohConfigError, ZenohOpenError, FrontError
        A bad config, a session that does not open (a port in use), a public TLS port
        that cannot be bound; each message names the endpoint or file.
    """
    import zenoh

    from simserver.adapters.zenoh_io import (
        ZenohOpenError,
        _clean,
        config_warnings,
        effective_endpoints,
    )

    if say is None:
        def say(text: str) -> None:
            print(f"simserver router: {text}", flush=True)
    if tls_front not in TLS_FRONT_MODES:
        raise ValueError(f"--tls-front: expected one of {', '.join(TLS_FRONT_MODES)}")
    cfg = router_config(listen, connect, config_file)
    public = effective_endpoints(cfg)
    fronts = None
    if tls_front == "auto" and any(ep.startswith("tls/") for ep in public):
        from simserver.adapters.tls_front import FrontSupervisor

        fronts = FrontSupervisor(public)
        cfg = router_config(fronts.zenoh_listen, connect, config_file)
    for warning in config_warnings(cfg):
        say(f"warning: {warning}")
    running = [True]

    def stop(*_: object) -> None:
        running[0] = False

    previous = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        try:
            session = zenoh.open(cfg)
        except zenoh.ZError as exc:
            raise ZenohOpenError(f"cannot open the router's zenoh session "
                                 f"({', '.join(public) or 'no listener'}): "
                                 f"{_clean(exc)}") from None
        with session:
            if fronts is not None:
                fronts.start()  # zenoh listens now: lock it to the fronts, start them
            text = describe(cfg)
            if fronts is not None:
                text += (f" (TLS front on {', '.join(fronts.public_listen)}; zenoh behind "
                         f"it on {', '.join(fronts.zenoh_listen)})")
            say(f"ready: {text}")
            end = None if duration_s is None else time.monotonic() + duration_s
            while running[0] and (end is None or time.monotonic() < end):
                time.sleep(0.1)
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        if fronts is not None:
            fronts.stop()
    say("stopped")
    return 0


def add_arguments(parser: Any) -> None:
    """The ``simserver router`` options."""
    parser.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                        help="endpoint to listen on, repeatable (default: the config "
                             "file's, else tcp/127.0.0.1:7447, loopback only)")
    parser.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                        help="a server or another router to join, repeatable (default: "
                             "the config file's, else none)")
    parser.add_argument("--zenoh-config", type=Path, default=None, metavar="FILE",
                        help="a zenoh JSON5 router config (TLS, credentials, access "
                             "control: configs/zenoh/router_auth_acl.json5); its mode is "
                             "forced to router")
    parser.add_argument("--tls-front", default="auto", choices=TLS_FRONT_MODES,
                        help="auto (default): the accept-filtering front of 'simserver "
                             "serve' before every tls/ listen endpoint (docs/security.md "
                             "5.1); off: zenoh listens there itself")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="stop after S seconds (default: until Ctrl-C)")


def main(args: Any) -> int:
    """``simserver router`` with parsed ``args``."""
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    return run_router(args.listen, args.connect, args.zenoh_config, args.tls_front,
                      args.duration)
