"""Where the Rerun scene goes: a local viewer, a remote viewer, a served viewer, a file, or off.

``open_recording(mode, target)`` returns a ``rerun.RecordingStream`` (never the global
one) with Rerun's ``log_time`` timeline switched off, or None for ``off``. The modes:

``off``
    Nothing (the default of ``run-scenario``: a headless run never waits on a viewer).
``save``
    ``target`` is an ``.rrd`` file (overwritten); open it later with ``rerun FILE``.
``serve``
    A gRPC server in this process plus the web viewer; ``target`` is ``[HOST:]PORT`` of
    the gRPC server (default ``127.0.0.1:9876``). The URL to open is printed. The gRPC
    server binds to 127.0.0.1 unless another host is given (``0.0.0.0`` to let other
    machines connect). The web viewer (port ``web_port``, default 9090) is served
    offline on the gRPC server's host (``web_viewer_host``: no telemetry, no update
    check, no web fonts) in front of Rerun's own web server (``rr.serve_web_viewer``, on
    a free port: it always binds all interfaces in rerun-sdk 0.41 and serves only the
    viewer's HTML and wasm); both run until the process exits (there is no call to stop
    them); pass ``web_port=None`` to skip them. A stream that feeds the web viewer is
    flushed every ``WEB_FLUSH_TICK_S`` (fewer, larger chunks for a slow browser), and its
    gRPC server sends newest first (a late browser starts from live). From
    another machine, tunnel both ports (``ssh -L 9090:127.0.0.1:9090 -L
    9876:127.0.0.1:9876``). Returns at once; a late viewer gets what is buffered
    (``server_memory_limit``); ``rec.disconnect()`` stops the gRPC server.
``connect``
    Stream to a running viewer's gRPC URL (``target``, default
    ``rerun+http://127.0.0.1:9876/proxy``; start one with ``rerun``). Checked first with a
    short TCP connect: rerun-sdk 0.41's ``connect_grpc`` to an address where nothing
    listens blocks 5 s, then buffers in memory until logging blocks for good. A viewer
    that goes away later has the same effect on the logging process (so log from a
    process that the physics never waits on).
``spawn``
    Start a local viewer (``rerun`` on ``target`` port, default 9876) and stream to it.
    Refused without a display (``DISPLAY``/``WAYLAND_DISPLAY`` on Linux): rerun-sdk 0.41
    blocks about 11 s there before giving up. The spawned viewer's own gRPC server
    listens on all interfaces (rerun's default).

A live scene that a reset or a load splits into segments gets one recording per segment:
``segment_sink`` says where the later ones go (``save``: ``run.rrd``, then
``run.segment1.rrd``, ...; the other modes: the same viewer).

Errors are ``RerunSinkError`` with a message that names the mode and target.
"""

from __future__ import annotations

import errno
import os
import shutil
import socket
import sys
import uuid
from collections.abc import Callable
from pathlib import Path
from urllib.parse import quote, urlsplit

import rerun as rr
import rerun.blueprint as rrb

SINK_MODES = ("off", "save", "serve", "connect", "spawn")
"""Accepted modes, the headless-safe ones first."""

DEFAULT_GRPC_PORT = 9876
DEFAULT_WEB_PORT = 9090
DEFAULT_SERVE_HOST = "127.0.0.1"
DEFAULT_CONNECT_URL = f"rerun+http://127.0.0.1:{DEFAULT_GRPC_PORT}/proxy"
CONNECT_CHECK_TIMEOUT_S = 0.5
"""How long ``connect`` waits for the viewer's TCP port before refusing."""

DEFAULT_SERVER_MEMORY_LIMIT = "512MiB"
"""What ``serve`` buffers for late viewers (the oldest data is dropped beyond it)."""

WEB_FLUSH_TICK_S = 2.0
"""How often a stream that feeds the web viewer sends what it logged (``serve`` with a
``web_port``; Rerun's default is 0.2 s). Rerun sends a chunk per entity and flush (some 46
entities), and the web viewer takes them in on the page's thread, which on this GPU-less
2-core machine also draws every frame in software (SwiftShader): with Rerun's flush the
browser fell further behind live the longer it ran; with this one it catches up
(docs/clients.md section 5c). Live data reaches the browser up to this much later."""


class RerunSinkError(ValueError):
    """A Rerun sink cannot be opened (bad mode or target, no viewer, port taken, ...)."""


def _stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def parse_sink(text: str) -> tuple[str, str | None]:
    """Split a ``MODE[:TARGET]`` option (``save:out/run.rrd``, ``serve:9876``, ``connect:URL``).

    Parameters
    ----------
    text : str
        The option's value.

    Returns
    -------
    tuple of (str, str or None)
        The mode (one of ``SINK_MODES``) and the target, if any.
    """
    mode, sep, target = text.partition(":")
    mode = mode.strip().lower()
    if mode not in SINK_MODES:
        raise RerunSinkError(f"rerun sink {text!r}: expected one of "
                             f"{', '.join(SINK_MODES)}, optionally followed by :TARGET")
    return mode, (target.strip() or None) if sep else None


def _split_host_port(mode: str, target: str | None, host: str, port: int) -> tuple[str, int]:
    if target:
        h, sep, p = target.rpartition(":")
        if not sep:
            h, p = host, target
        try:
            port = int(p)
        except ValueError:
            raise RerunSinkError(f"rerun {mode}: expected [HOST:]PORT, got {target!r}") from None
        host = h.strip("[]") or host
    if not 0 < port < 65536:
        raise RerunSinkError(f"rerun {mode}: port {port} is outside 1-65535")
    return host, port


def _check_port_free(mode: str, host: str, port: int) -> None:
    """Bind and release ``host:port`` so that a taken port fails here, clearly (rerun
    reports it only in its log, from a background thread)."""
    try:
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
            s.bind((host, port))
    except OSError as exc:
        why = "is in use" if exc.errno == errno.EADDRINUSE else f"cannot be bound: {exc}"
        raise RerunSinkError(f"rerun {mode}: {host}:{port} {why}") from exc


def _check_listening(url: str) -> None:
    parts = urlsplit(url)
    if parts.scheme not in ("rerun", "rerun+http", "rerun+https") or not parts.hostname:
        raise RerunSinkError(f"rerun connect: {url!r} is not a viewer URL "
                             f"(expected e.g. {DEFAULT_CONNECT_URL})")
    port = parts.port or (443 if parts.scheme == "rerun+https" else DEFAULT_GRPC_PORT)
    try:
        with socket.create_connection((parts.hostname, port), timeout=CONNECT_CHECK_TIMEOUT_S):
            pass
    except OSError as exc:
        raise RerunSinkError(
            f"rerun connect: no viewer listens at {url} ({exc.strerror or exc}); start one "
            f"with `rerun`, or use serve (the viewer connects to us) or save") from exc


def _viewer_executable() -> str | None:
    """The ``rerun`` viewer: on PATH, else beside this interpreter (a venv not activated)."""
    found = shutil.which("rerun")
    if found:
        return found
    beside = Path(sys.executable).parent / ("rerun.exe" if os.name == "nt" else "rerun")
    return str(beside) if beside.is_file() else None


def _has_display() -> bool:
    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def web_viewer_url(grpc_url: str, web_port: int, host: str = "127.0.0.1") -> str:
    """The address to open in a browser for the web viewer connected to ``grpc_url``."""
    return f"http://{host}:{web_port}/?url={quote(grpc_url, safe='')}"


def segment_path(path: str | os.PathLike[str], segment: int) -> Path:
    """The ``.rrd`` of segment ``segment`` of a live recording saved to ``path``.

    Segment 0 is ``path`` itself; segment ``k`` sits beside it as ``STEM.segment{k}.rrd``
    (``run.rrd``, ``run.segment1.rrd``, ...): a file of rerun-sdk 0.41's file sink holds
    the recording of one stream.
    """
    path = Path(path)
    return path if segment == 0 else path.with_name(f"{path.stem}.segment{segment}{path.suffix}")


def segment_sink(mode: str, target: str | None, segment: int) -> tuple[str, str | None]:
    """Where segment ``segment`` (0 = the first) of a live scene goes, as ``(mode, target)``.

    A reset or a load restarts the server's ``sim_time``; the live viewer starts a new
    recording for each such segment so that no recording's timeline runs backwards
    (``simserver.adapters.viewer``). Segment 0 goes to the sink as given; the later ones:

    - ``save``: a file of their own beside the first (``segment_path``);
    - ``serve``: streamed (``connect``) to the gRPC server the first segment's stream
      started, which stays up until the viewer ends, so a viewer attached there sees
      every segment;
    - ``connect``: the same viewer URL;
    - ``spawn``: the viewer spawned for the first segment (``connect`` to its port).
    """
    if segment == 0 or mode in ("off", "connect"):
        return mode, target
    if mode == "save":
        if not target:
            raise RerunSinkError("rerun save: a target .rrd file is required")
        return mode, str(segment_path(target, segment))
    if mode == "serve":
        host, port = _split_host_port(mode, target, DEFAULT_SERVE_HOST, DEFAULT_GRPC_PORT)
        if host in ("0.0.0.0", "::", ""):  # bound everywhere: reach it on loopback
            host = DEFAULT_SERVE_HOST
        host = f"[{host}]" if ":" in host else host
        return "connect", f"rerun+http://{host}:{port}/proxy"
    _, port = _split_host_port(mode, target, "127.0.0.1", DEFAULT_GRPC_PORT)  # spawn
    return "connect", f"rerun+http://127.0.0.1:{port}/proxy"


def _serve_web_viewer(host: str, web_port: int, grpc_url: str) -> None:
    """Rerun's web viewer for ``grpc_url`` at ``host:web_port``, offline
    (``web_viewer_host``: no telemetry, no update check, no web fonts): Rerun's own web
    server on a free port, the offline host in front of it."""
    from simserver.adapters.web_viewer_host import WebHostError, serve_offline

    with socket.socket() as s:  # a free port for Rerun's own web server
        s.bind(("127.0.0.1", 0))
        rerun_port = s.getsockname()[1]
    rr.serve_web_viewer(web_port=rerun_port, open_browser=False, connect_to=grpc_url)
    try:
        serve_offline(host, web_port, rerun_port, grpc_url)
    except (OSError, WebHostError) as exc:
        raise RerunSinkError(f"rerun serve: the web viewer on {host}:{web_port}: {exc}") from exc


def open_recording(
    mode: str,
    target: str | os.PathLike[str] | None = None,
    application_id: str = "simserver",
    recording_id: str | None = None,
    *,
    default_blueprint: rrb.BlueprintLike | None = None,
    web_port: int | None = DEFAULT_WEB_PORT,
    server_memory_limit: str = DEFAULT_SERVER_MEMORY_LIMIT,
    check_listener: bool = True,
    announce: Callable[[str], None] | None = _stderr,
    flush_tick_s: float | None = None,
) -> rr.RecordingStream | None:
    """Open a recording stream on the sink ``mode``.

    Parameters
    ----------
    mode : str
        One of ``SINK_MODES`` (see the module docstring).
    target : str or path, optional
        ``save``: the file (required). ``serve``: ``[HOST:]PORT`` of the gRPC server.
        ``connect``: the viewer's URL. ``spawn``: the viewer's port.
    application_id : str
        Rerun application id (blueprints are stored per application).
    recording_id : str, optional
        Default a fresh UUID. Streams with the same id merge in the viewer.
    default_blueprint : rerun.blueprint.BlueprintLike, optional
        Sent with the sink as the application's default layout.
    web_port : int, optional
        ``serve``: also host the web viewer on this port; None skips it.
    server_memory_limit : str
        ``serve``: what the gRPC server buffers for late viewers.
    check_listener : bool
        ``connect``: refuse at once if nothing accepts a TCP connection at the URL.
    announce : callable, optional
        Called with one line saying where the data goes (default: print to stderr).
    flush_tick_s : float, optional
        How often the stream sends what was logged (Rerun's default 0.2 s); None: Rerun's
        default, or ``WEB_FLUSH_TICK_S`` for ``serve`` with a ``web_port``; Rerun's
        ``RERUN_FLUSH_TICK_SECS`` in the environment wins over both.

    Returns
    -------
    rerun.RecordingStream or None
        None for ``off``.

    Raises
    ------
    RerunSinkError
        Unknown mode, missing or bad target, no display (``spawn``), nothing listening
        (``connect``), port in use (``serve``), unwritable file (``save``).
    """
    mode = mode.strip().lower()
    if mode not in SINK_MODES:
        raise RerunSinkError(f"rerun sink {mode!r}: expected one of {', '.join(SINK_MODES)}")
    if mode == "off":
        return None
    say = announce or (lambda _msg: None)
    target_text = None if target is None else os.fspath(target)

    # Validate before creating the stream, so that a refused sink leaves nothing running.
    if mode == "save":
        if not target_text:
            raise RerunSinkError("rerun save: a target .rrd file is required")
        path = Path(target_text)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RerunSinkError(f"rerun save: {path}: cannot write: "
                                 f"{exc.strerror or exc}") from exc
        from simserver.adapters.config import ConfigError
        from simserver.server.logfile import open_log_file

        try:  # like every file the server writes: no link followed, regular files only,
            # never blocking on a FIFO (docs/security.md section 1)
            os.close(open_log_file(path, "recording"))
        except ConfigError as exc:
            raise RerunSinkError(f"rerun save: {exc}") from None
    elif mode == "serve":
        host, port = _split_host_port(mode, target_text, DEFAULT_SERVE_HOST, DEFAULT_GRPC_PORT)
        _check_port_free(mode, host, port)
        if web_port is not None:
            _check_port_free(mode, host, web_port)
    elif mode == "connect":
        url = target_text or DEFAULT_CONNECT_URL
        if check_listener:
            _check_listening(url)
    else:  # spawn
        _, port = _split_host_port(mode, target_text, "127.0.0.1", DEFAULT_GRPC_PORT)
        if not _has_display():
            raise RerunSinkError("rerun spawn: no display (DISPLAY/WAYLAND_DISPLAY unset); "
                                 "use serve and open the printed URL, or save to a file")
        viewer_exe = _viewer_executable()
        if viewer_exe is None:
            raise RerunSinkError("rerun spawn: no `rerun` viewer executable on PATH or beside "
                                 f"{sys.executable}")

    if flush_tick_s is None and mode == "serve" and web_port is not None:
        flush_tick_s = WEB_FLUSH_TICK_S
    if os.environ.get("RERUN_FLUSH_TICK_SECS"):  # Rerun's own setting, when given, wins
        flush_tick_s = None
    batcher = None if flush_tick_s is None else rr.ChunkBatcherConfig(flush_tick=flush_tick_s)
    rec = rr.RecordingStream(application_id, recording_id=recording_id or str(uuid.uuid4()),
                             batcher_config=batcher)
    rec.set_log_time_enabled(False)
    if mode == "save":
        rec.save(path, default_blueprint=default_blueprint)
        say(f"rerun: recording to {path}")
    elif mode == "serve":
        # a browser opened late starts from the present, not from a replay of every
        # chunk since the start (it takes them in slowly: WEB_FLUSH_TICK_S)
        sink = rr.GrpcServerSink(bind_ip=host, port=port,
                                 server_memory_limit=server_memory_limit,
                                 newest_first=web_port is not None)
        rec.set_sinks(sink, default_blueprint=default_blueprint)
        grpc_url = sink.uri
        if web_port is not None:
            web_host = host if host not in ("0.0.0.0", "::", "") else DEFAULT_SERVE_HOST
            _serve_web_viewer(host, web_port, grpc_url)
            say(f"rerun: serving; open {web_viewer_url(grpc_url, web_port, web_host)} "
                f"(or `rerun {grpc_url}`)")
        else:
            say(f"rerun: serving; open with `rerun {grpc_url}`")
    elif mode == "connect":
        rec.connect_grpc(url, default_blueprint=default_blueprint)
        say(f"rerun: streaming to {url}")
    else:
        rr.spawn(port=port, connect=True, default_blueprint=default_blueprint, recording=rec,
                 executable_path=viewer_exe)
        say(f"rerun: spawned a viewer on port {port} (it listens on all interfaces)")
    return rec
