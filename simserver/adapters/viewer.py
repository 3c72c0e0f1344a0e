"""The live viewer: a separate process that turns the state topic into a Rerun scene.

Logging one frame costs about a millisecond of Python (measured for
``rerun_scene.SceneLogger``): in the 1 kHz process it would wreck the loop, even from a
thread. So the server never logs: ``simserver serve --viewer SINK`` starts this process,
which subscribes to the server's state and diagnostics like any client, through a bounded
ring buffer (the oldest messages are dropped if it falls behind, and counted from the gaps
in the tick numbers), and feeds ``SceneLogger``. A missing, slow or vanished viewer can
only slow this process, never the physics.

Two things keep this process out of the physics' way on a small machine (measured with
``benchmarks.bench_viewer``: on 2 cores a viewer at normal priority raised the server's
tick lateness p99 about tenfold):

- it decimates first: every state is decoded (a view of the bytes) to count gaps, but only
  the ``fps`` states per simulated second that become frames go through the Python-heavy
  path (road pose, rows, spin, batching). The wheels' spin angles are then integrated at
  the frame rate, which is what the picture shows;
- it lowers the CPU priority of all its threads before it opens its zenoh session and its
  recording, whose threads inherit it (``lower_priority``): ``simserver view`` runs at
  ``nice`` ``VIEW_NICE`` (a real-time server pre-empts it, a normal one meets it at a
  tenth of its weight, and it still gets CPU beside CPU-bound processes); the view that
  ``simserver serve --viewer`` starts on the server's own machine runs at idle priority
  (``SCHED_IDLE``: only CPU time nothing else wants, ``--idle-priority``).

The wire state carries the world pose; the scene is drawn in the road's frame, so the road
(from the ``get_config`` control, re-read once a second to follow ``set_road``) turns the
pose back into road-plane coordinates (``core.pose.road_pose``). On a terrain (a height
map or an OpenDRIVE road, read from the scene file ``get_config`` names, once per scene:
an OpenDRIVE road takes seconds) the plane is the one fitted under the car's wheels at
each frame (``rerun_scene.terrain_plane_under``), the terrain is drawn once and the
wheels stand on it. Quantities the wire does not carry (friction use, the damping share
of the forces) are drawn as missing.

Several cars in one world (issue 30): the viewer follows one car (``--car``, default
``car0``): it is drawn in full under ``world/car``, the blueprint's camera opens on it, and
its driver's-eye view is the 3D view's second tab (``rerun_scene.scene_blueprint``). Every
car the world message names (``{prefix}/world/state``) is drawn under
``world/cars/{id}`` with its id as a label (``rerun_fleet.FleetLogger``), at each frame of
the followed car, from the newest world message.

One recording per segment: a reset or a ``load`` restarts the server's tick and
``sim_time``, so when the tick goes back the viewer ends the current recording and starts
the next one (recording id ``{prefix}/{vehicle}``, then ``.../segment1``, ...), with the
vehicle and road ``get_config`` reports then. Each recording's ``sim_time`` timeline
runs forward only and holds its own static scene. ``save:run.rrd`` writes the segments
to ``run.rrd``, ``run.segment1.rrd``, ...; the other sinks stream them all to the same
viewer (``rerun_sink.segment_sink``).
"""

from __future__ import annotations

import json
import math
import os
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from simserver.adapters.config_paths import local_config_file
from simserver.core import layout as L
from simserver.core.params import VP_CG_HEIGHT_M
from simserver.core.road import road_axes
from simserver.wire import protocol as proto
from simserver.wire.state_schema import record_to_pose, record_to_rows

ROAD_POLL_S = 1.0

DEFAULT_FPS = 50.0
"""Frames the viewer draws per simulated second (``simserver view --fps``, the server's
``viewer_fps``): what a ``save:`` recording grows with (docs/clients.md section 5b)."""

WEB_FPS = 5.0
"""Frames per simulated second when the view serves Rerun's web viewer (``--web-port``)
and ``--fps`` is not given: a browser without a GPU draws a few frames a second, and every
frame sent costs its page's thread (docs/clients.md section 5c)."""

DEFAULT_WAIT_S = 60.0
"""How long ``simserver view`` waits for its server's first ``get_config`` reply
(``--wait``). On a busy machine the viewer runs at a lowered priority (``lower_priority``)
and may get no CPU for seconds while the server answers in milliseconds (issue 35): a single
short query made the viewer exit; it now retries for this long."""

RETRY_FIRST_S = 0.5
RETRY_MAX_S = 4.0
"""Backoff between ``get_config`` attempts: doubles from the first to the most."""
QUERY_TIMEOUT_MAX_S = 5.0
"""A single ``get_config`` attempt waits at most this long (the attempts' timeouts grow
with the backoff: a starved viewer gets a longer window each time)."""


_TERRAINS: dict[tuple[str, int], tuple[Any, Any]] = {}


def scene_terrain(scene_file: Path) -> tuple[Any, dict[str, Any] | None]:
    """The terrain of a scene file and its ``terrain_spec`` (``adapters.terrain_files``),
    kept per file and modification time: a reset starts a segment of the same scene, and
    an OpenDRIVE road takes seconds to rasterise."""
    from simserver.adapters.config import read_yaml
    from simserver.adapters.terrain_files import terrain_from_spec, terrain_spec

    key = (str(scene_file), scene_file.stat().st_mtime_ns)
    if key not in _TERRAINS:
        if scene_file.suffix == ".xosc":  # an OpenSCENARIO file: its road (its ego's scene)
            from simserver.sim.scene_files import load_scene

            spec = load_scene(scene_file).terrain_spec
        else:
            spec = terrain_spec(scene_file, read_yaml(scene_file).get("terrain"))
        _TERRAINS.clear()
        _TERRAINS[key] = (terrain_from_spec(spec), spec)
    return _TERRAINS[key]


class ServerWaitError(Exception):
    """No server answered ``get_config`` within the viewer's ``--wait``; the message
    says what was waited for, how long, and how to tell a busy server from a missing one."""


def endpoints_text(connect: list[str] | None, config_file: Path | None) -> str:
    """Where the viewer connects, for messages."""
    if connect:
        return ", ".join(connect)
    if config_file is not None:
        return f"the endpoints of {config_file}"
    return "(no endpoint)"


def wait_for_config(ep: Any, where: str, wait_s: float, say: Any = None,
                    since: float | None = None) -> dict[str, Any]:
    """The server's ``get_config`` config, asked until it answers or ``wait_s`` passes.

    Each attempt first looks for the vehicle's liveliness token (``{prefix}/{vehicle}/
    alive``, declared by a running server), then asks ``get_config`` with a timeout that
    grows with the backoff (``RETRY_FIRST_S`` doubling to ``RETRY_MAX_S``, a query at most
    ``QUERY_TIMEOUT_MAX_S``), whatever the token said: on a starved machine the token's
    own query may time out too. Every failed attempt is reported through ``say`` (one
    line: what it waited for and when it retries).

    Parameters
    ----------
    ep : ZenohEndpoint
        The viewer's open endpoint.
    where : str
        ``"{prefix}/{vehicle} on {endpoints}"``, for the messages.
    wait_s : float
        Total time to wait (s); at least one attempt is made.
    say : callable, optional
        Takes each progress line (default: print to stderr).
    since : float, optional
        When the wait began (``time.monotonic()``; default now): the session's opening
        counts against ``wait_s`` too.

    Raises
    ------
    ServerWaitError
        Nothing answered within ``wait_s``; the message names the liveliness key and
        whether its token was seen (the server is up but busy) or not (not started, or
        not reachable at these endpoints).
    RuntimeError
        The server answered ``get_config`` with an error.
    """
    if say is None:
        def say(text: str) -> None:
            print(f"simserver view: {text}", file=sys.stderr, flush=True)
    alive_key = ep.keys.alive
    start = time.monotonic() if since is None else since
    deadline = start + max(0.0, wait_s)
    backoff_s = RETRY_FIRST_S
    attempts = 0
    token_seen = False
    diagnosis: str | None = None  # what the server wants that this client lacks
    while True:
        attempts += 1
        remaining = deadline - time.monotonic()
        query_s = max(0.5, min(QUERY_TIMEOUT_MAX_S, 2.0 * backoff_s, remaining))
        try:
            token = bool(ep.alive_tokens(timeout_s=min(1.0, query_s)))
        except Exception:  # noqa: BLE001 - a liveliness query that fails is no token
            token = False
        token_seen = token_seen or token
        try:
            reply = ep.request("get_config", timeout_s=query_s)
        except TimeoutError:
            reply = None
        except proto.ProtocolError as exc:
            raise RuntimeError(f"bad get_config reply from {where}: {exc}") from None
        if reply is not None:
            if not reply.get("ok"):
                raise RuntimeError(f"get_config failed on {where}: {reply}")
            return reply["config"]
        if not token_seen:
            # a plain-TCP peer pointed at a TLS server opens its session and then reaches
            # nobody: tell it what the server wants (issue 35); asked again each attempt
            # (a server started meanwhile changes the answer)
            diagnosis = _diagnose(ep)
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            break
        pause_s = min(backoff_s, remaining)
        token_text = (f"the liveliness token {alive_key} is there: the server is up, busy?"
                      if token else f"no liveliness token on {alive_key} yet")
        if diagnosis and not token:
            token_text += f"; {diagnosis}"
        say(f"waiting for {where}: no reply to get_config yet ({token_text}), "
            f"retrying in {pause_s:.2g} s")
        time.sleep(pause_s)
        backoff_s = min(RETRY_MAX_S, 2.0 * backoff_s)
    waited_s = time.monotonic() - start
    if token_seen:
        why = (f"its liveliness token {alive_key} was seen, so the server is up but too "
               "busy to answer (a loaded machine: give it a longer --wait, or start the "
               "viewer with --normal-priority)")
    elif diagnosis:
        why = f"its liveliness token {alive_key} was never seen: {diagnosis}"
    else:
        why = (f"its liveliness token {alive_key} was never seen, so no server for this "
               "vehicle is reachable there: it is not started, stopped, or --connect, "
               "--prefix or --vehicle-id do not match it (a server that is up but busy "
               "shows the token)")
    raise ServerWaitError(
        f"no reply to get_config from {where} after waiting {waited_s:.1f} s "
        f"({attempts} attempt(s), --wait {wait_s:g}): {why}")


def _diagnose(ep: Any) -> str:
    """What the server at the viewer's endpoints wants that its config lacks (TLS, the
    CA, a client certificate, credentials), or "" (``zenoh_diagnose.explain_unreached``)."""
    config = getattr(ep, "config", None)
    if config is None:
        return ""
    from simserver.adapters.zenoh_diagnose import explain_unreached

    return explain_unreached(config)


@dataclass
class ViewerStats:
    """What the viewer process did."""

    states_received: int = 0
    states_dropped: int = 0
    frames_logged: int = 0
    diagnostics: int = 0
    world_frames: int = 0
    storyboard_lines: int = 0  # a served scenario's state changes logged
    cpu_priority: str = "normal"


def rows_from_state(rec: np.ndarray, axes: np.ndarray, cg_height_m: float,
                    x: np.ndarray, out: np.ndarray, inputs: np.ndarray,
                    plane: tuple[float, float, float] | None = None) -> None:
    """Fill core-layout rows from one decoded VehicleState (missing quantities = NaN).

    The planar states are expressed on the road ``axes``, or on ``plane`` (grade %,
    cross-slope %, height at the world origin: a terrain's reference plane under the car,
    ``rerun_scene.terrain_plane_under``), whose slots ``REF_*`` are then set as the
    step's are. Either way the world pose is kept exactly.
    """
    from simserver.core.pose import road_pose

    pose = np.empty(L.N_POSE)
    record_to_pose(rec, pose)
    if plane is not None:
        grade, cross, height = plane
        axes = road_axes(grade, cross)
        pose[L.POSE_Z_M] -= height  # the plane passes through (0, 0, height)
        x[L.REF_GRADE_PCT], x[L.REF_CROSS_SLOPE_PCT], x[L.REF_HEIGHT_M] = grade, cross, height
    road_pose(pose, axes, cg_height_m, x)
    out[:] = np.nan
    record_to_rows(rec, x, out, inputs)  # every field the state table maps to a core slot
    # The slip fed to the tire model is not on the wire; the lagged slip states are what
    # the lagged-slip model feeds it (docs/model.md section 3), so they stand in for it.
    out[L.O_KAPPA] = rec["kappa_lag"]
    out[L.O_TAN_ALPHA] = rec["tan_alpha_lag"]


VIEW_NICE = 10
"""``simserver view``'s CPU priority by default: a ``nice`` level of the normal policy,
not ``SCHED_IDLE``. An idle thread runs only when a core has nothing else to do, and
beside two CPU-bound processes on 2 cores that is never: such a view used 1 s of CPU in
6 minutes and its web page stayed empty (``tests/test_web_view.py``, slow form), and a
view the user started by hand showed nothing. At nice 10 it gets about a tenth of a busy
core's share; a real-time server (``SCHED_FIFO``) still pre-empts it, and a normal one
meets it at a tenth of its weight."""

PRIORITIES = ("nice", "idle", "normal")
"""``run_viewer``'s CPU priorities: ``nice`` (``VIEW_NICE``, the default), ``idle``
(``SCHED_IDLE``: the view ``serve --viewer`` starts beside its physics), ``normal``
(unchanged)."""


def lower_priority(nice: int | None = None) -> str:
    """Put this process's threads, and every thread they start, at idle CPU priority
    (or, given ``nice``, at that ``nice`` level of the normal policy).

    Linux ``SCHED_IDLE``: the threads run only when a core has nothing else to do, so the
    1 kHz server never waits for the viewer to be descheduled. The policy is per thread
    (importing Rerun has already started its runtime's threads), so it is set on each
    thread of ``/proc/self/task``; threads started later inherit it. Elsewhere the lowest
    ``nice``. Returns what was applied (for the log), or why nothing was.
    """
    if nice is not None:  # per thread on Linux, inherited by the threads they start
        try:
            for tid in os.listdir("/proc/self/task"):
                try:
                    os.setpriority(os.PRIO_PROCESS, int(tid), nice)
                except ProcessLookupError:
                    pass
        except (AttributeError, OSError):
            try:
                os.nice(nice)
            except (AttributeError, OSError) as exc:
                return f"normal (could not lower: {exc})"
        return f"nice {nice}"
    try:
        for tid in os.listdir("/proc/self/task"):
            try:
                os.sched_setscheduler(int(tid), os.SCHED_IDLE, os.sched_param(0))
            except ProcessLookupError:  # the thread ended meanwhile
                pass
        return "SCHED_IDLE"
    except (AttributeError, OSError):
        pass
    try:
        os.nice(19)
        return "nice 19"
    except (AttributeError, OSError) as exc:
        return f"normal (could not lower: {exc})"


def segment_recording_id(base_id: str, segment: int) -> str:
    """Recording id of segment ``segment``: ``base_id``, then ``base_id/segment{k}``."""
    return base_id if segment == 0 else f"{base_id}/segment{segment}"


def log_diagnostics_payload(rec_stream: Any, payload: bytes, period_s: float,
                            states_dropped: int, newest_tick: int | None = None,
                            ahead_ticks: int = 100) -> bool:
    """Log one Diagnostics payload on the ``sim_time`` timeline of the scene.

    Parameters
    ----------
    rec_stream : rerun.RecordingStream
        Where to log.
    payload : bytes
        A Diagnostics message of the wire protocol.
    period_s : float
        The server's tick period (its ``get_config`` reply, ``server.period_s``): the
        sample's simulated time is its tick times the period, as the state's
        ``sim_time_s`` is, so the diagnostics line up with the frames at any period.
    states_dropped : int
        States the viewer's ring buffer has dropped so far.
    newest_tick : int, optional
        Tick of the newest state of the current segment: a message more than
        ``ahead_ticks`` ahead of it was published before a reset or load that the states
        already show, and belongs to the previous segment's recording (not logged).
    ahead_ticks : int
        See ``newest_tick``.

    Returns
    -------
    bool
        False (nothing logged) when the payload does not decode or is of a past segment.
    """
    from simserver.adapters.rerun_scene import log_diagnostics

    try:
        d = proto.decode_diagnostics(payload)
    except proto.ProtocolError:
        return False
    if newest_tick is not None and int(d["tick"]) > newest_tick + ahead_ticks:
        return False
    log_diagnostics(rec_stream, float(d["tick"]) * period_s, float(d["lateness_p99_us"]),
                    states_dropped)
    return True


STORYBOARD_ENTITY = "storyboard"
"""Where a served scenario's storyboard state changes are logged (``TextLog`` entries on the
``sim_time`` timeline: docs/openscenario.md, "Served live")."""


def storyboard_text(entry: dict[str, Any]) -> str:
    """One storyboard state change as a line of the viewer's log."""
    if "note" in entry:
        return f"{entry.get('kind', '')} {entry.get('name', '')}: {entry['note']}"
    text = f"{entry['kind']} {entry['name']}: {entry['from']} -> {entry['to']}"
    if entry.get("cause"):
        text += " (" + json.dumps(entry["cause"], separators=(", ", ": ")) + ")"
    return text


def log_storyboard_payload(rec_stream: Any, payload: bytes) -> str | None:
    """Log one ``{prefix}/world/storyboard`` message (``protocol.ENCODING_STORYBOARD``) as
    a ``TextLog`` entry at its simulated time; its line (with the time), or None when it
    does not decode."""
    import rerun as rr

    from simserver.adapters.rerun_scene import TIMELINE, time_ns

    try:
        entry = json.loads(bytes(payload))
        text = storyboard_text(entry)
        t_s = entry.get("t_s")
    except (ValueError, KeyError, TypeError):
        return None
    timed = isinstance(t_s, (int, float)) and math.isfinite(t_s)
    if timed:
        rec_stream.set_time(TIMELINE, duration=time_ns(float(t_s))[()])
    level = rr.TextLogLevel.WARN if entry.get("note") else rr.TextLogLevel.INFO
    rec_stream.log(STORYBOARD_ENTITY, rr.TextLog(text, level=level))
    return f"t = {float(t_s):.3f} s: {text}" if timed else text


def run_viewer(sink: str, connect: list[str] | None, prefix: str = "simserver",
               vehicle_id: str = "car0", fps: float = DEFAULT_FPS, queue: int = 2048,
               duration_s: float | None = None, config_file: Path | None = None,
               web_port: int | None = None, check_listener: bool = True,
               priority: str = "nice", wait_s: float = DEFAULT_WAIT_S) -> ViewerStats:
    """Subscribe to a server and log its scene to ``sink`` until SIGINT/SIGTERM.

    Parameters
    ----------
    sink : str
        ``MODE[:TARGET]`` as ``rerun_sink.parse_sink`` takes it (``serve``, ``save:F.rrd``,
        ``connect:URL``, ``spawn``).
    connect : list of str or None
        Zenoh endpoints of the server; None keeps those of ``config_file``.
    prefix, vehicle_id : str
        Which vehicle.
    fps : float
        Frames per simulated second drawn.
    queue : int
        Ring-buffer capacity for states (older ones are dropped when full).
    duration_s : float, optional
        Stop after this many wall seconds (tests, benchmarks).
    config_file : Path, optional
        A zenoh JSON5 config instead of the defaults.
    web_port : int, optional
        ``serve``: also host Rerun's web viewer on this port. Off by default: rerun-sdk
        0.41 binds it to all interfaces, and the server's defaults stay on loopback.
    check_listener : bool
        ``connect``: refuse at once when nothing listens at the URL.
    priority : str
        One of ``PRIORITIES``: ``nice`` (``VIEW_NICE``, the default: the view keeps
        drawing beside CPU-bound processes, a real-time server pre-empts it), ``idle``
        (``SCHED_IDLE``: only CPU time nothing else wants; ``serve --viewer``'s view),
        ``normal``.
    wait_s : float
        How long to wait for the server's first ``get_config`` reply, and for a client-mode
        session to open (``wait_for_config``), before ``ServerWaitError``.
    """
    stats = ViewerStats()
    if priority not in PRIORITIES:
        raise ValueError(f"priority {priority!r}: expected one of {', '.join(PRIORITIES)}")
    if priority != "normal":  # before the sessions: the threads they start inherit it
        stats.cpu_priority = lower_priority(VIEW_NICE if priority == "nice" else None)
    from simserver.adapters.rerun_fleet import FleetLogger
    from simserver.adapters.rerun_scene import RateGate
    from simserver.adapters.zenoh_io import ZenohEndpoint, make_zenoh_config

    recordings = _Recordings(sink, f"{prefix}/{vehicle_id}", web_port, check_listener)
    if recordings.current is None:
        return stats
    running = [True]

    def stop(*_: Any) -> None:
        running[0] = False

    previous = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
    x = np.zeros(L.N_STATE)
    out = np.zeros(L.N_OUT)
    inputs = np.zeros(L.N_INPUT)
    where = f"{prefix}/{vehicle_id} on {endpoints_text(connect, config_file)}"
    wait_start = time.monotonic()
    wait_deadline = wait_start + max(0.0, wait_s)
    try:
        # a config file's own listen and connect endpoints are kept unless --connect
        # is given (its client-mode TLS or credentials settings need its endpoints)
        ep = _open_endpoint(
            lambda: ZenohEndpoint(make_zenoh_config(
                listen=[] if config_file is None else None, connect=connect,
                config_file=config_file), prefix=prefix, vehicle=vehicle_id),
            where, wait_deadline)
        with ep:
            states = ep.declare_state_inbox(capacity=queue)
            diags = ep.declare_diag_inbox()
            worlds = ep.declare_inbox(proto.world_keys(prefix).state, 16)
            storyboard = ep.declare_inbox(proto.world_keys(prefix).storyboard, 1024)
            world: proto.WorldState | None = None
            config = wait_for_config(ep, where, wait_s, since=wait_start)
            scene = _SegmentScene(recordings.current, config, 0, vehicle_id)
            fleet = FleetLogger(recordings.current, vehicle_id)
            state_every = int(config["server"]["state_every"])
            period_s = float(config["server"]["period_s"])
            last_tick: int | None = None
            frame_gate = RateGate(fps)  # decimate before the Python-heavy path
            t_start = last_poll = time.monotonic()
            while running[0]:
                now = time.monotonic()
                if duration_s is not None and now - t_start > duration_s:
                    break
                if now - last_poll > ROAD_POLL_S:  # follow set_road
                    last_poll = now
                    try:
                        reply = ep.request("get_config", timeout_s=1.0)
                    except TimeoutError:  # busy: follow the road at the next poll
                        reply = {}
                    if reply.get("ok"):
                        scene.follow_road(reply["config"])
                for world_payload in reversed(worlds.drain_newest()):
                    try:  # the newest that decodes; a bad one is skipped
                        world = proto.decode_world(world_payload)
                        break
                    except proto.ProtocolError:
                        continue
                payloads = states.drain_newest()
                for payload in payloads:
                    try:
                        rec = proto.decode_state(payload)
                    except proto.ProtocolError:
                        continue
                    stats.states_received += 1
                    tick = int(rec["tick"])
                    if last_tick is not None and tick < last_tick:
                        # a reset or a load: the next segment, in a recording of its own
                        scene.logger.flush()
                        seg_config = wait_for_config(ep, where, wait_s)
                        scene = _SegmentScene(recordings.next(), seg_config,
                                              recordings.segment, vehicle_id)
                        fleet = FleetLogger(recordings.current, vehicle_id)
                        frame_gate.reset()
                    elif last_tick is not None and tick > last_tick + state_every:
                        # the ring dropped the oldest: count what never arrived
                        stats.states_dropped += (tick - last_tick) // state_every - 1
                    last_tick = tick
                    time_s = float(rec["sim_time_s"])
                    if not frame_gate.due(time_s):
                        continue
                    rows_from_state(rec, scene.axes, scene.h_cg, x, out, inputs,
                                    scene.plane_under(rec))
                    if scene.logger.log_frame(time_s, x, out, inputs):
                        stats.frames_logged += 1
                        if world is not None:  # every car, at the followed car's frame
                            fleet.log(time_s, world)
                            stats.world_frames += 1
                for payload in storyboard.drain_newest():  # a served scenario's
                    line = log_storyboard_payload(recordings.current, payload)
                    if line is not None:  # in the terminal too: a handful a scenario
                        stats.storyboard_lines += 1
                        print(f"simserver view: storyboard {line}", file=sys.stderr,
                              flush=True)
                for payload in diags.drain_newest():
                    if log_diagnostics_payload(recordings.current, payload, period_s,
                                               stats.states_dropped, last_tick,
                                               100 * state_every):
                        stats.diagnostics += 1
                if not payloads:
                    time.sleep(0.005)
            scene.logger.flush()
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        recordings.close()
    return stats


def _open_endpoint(open_once: Any, where: str, deadline: float) -> Any:
    """``open_once()`` retried until ``deadline`` (monotonic s) while it fails to open.

    A zenoh peer opens at once and connects in the background; a client-mode session
    (``mode: "client"`` in a ``--zenoh-config``, the TLS examples) fails to open while
    its server is not there yet, so it is retried with the same backoff as
    ``get_config``. A bad config (``ZenohConfigError``) is not retried.
    """
    from simserver.adapters.zenoh_io import ZenohOpenError

    start = time.monotonic()
    backoff_s = RETRY_FIRST_S
    while True:
        try:
            return open_once()
        except ZenohOpenError as exc:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise ServerWaitError(
                    f"no zenoh session to {where} after waiting "
                    f"{time.monotonic() - start:.1f} s: {exc} (the server is not started, "
                    "not reachable at these endpoints, or refuses this client's TLS or "
                    "credentials settings)") from None
            pause_s = min(backoff_s, remaining)
            print(f"simserver view: waiting for {where}: the session does not open yet "
                  f"({exc}), retrying in {pause_s:.2g} s", file=sys.stderr, flush=True)
            time.sleep(pause_s)
            backoff_s = min(RETRY_MAX_S, 2.0 * backoff_s)


class _Recordings:
    """The viewer's recordings, one per segment (see the module docstring).

    Parameters
    ----------
    sink : str
        ``MODE[:TARGET]`` of the first segment (``rerun_sink.segment_sink`` derives the
        others).
    base_id : str
        Recording id of the first segment (``segment_recording_id``).
    web_port : int or None
        ``serve``: the web viewer's port (first segment only).
    check_listener : bool
        ``connect``: refuse at once when nothing listens.
    """

    def __init__(self, sink: str, base_id: str, web_port: int | None,
                 check_listener: bool) -> None:
        from simserver.adapters.rerun_sink import parse_sink

        self.mode, self.target = parse_sink(sink)
        self.base_id = base_id
        self.web_port = web_port
        self.check_listener = check_listener
        self.segment = 0
        self.current = self._open(0)
        self.first = self.current
        """serve: the first stream owns the gRPC server every segment goes to."""

    def _open(self, segment: int) -> Any:
        from simserver.adapters.rerun_sink import WEB_FLUSH_TICK_S, open_recording, segment_sink

        mode, target = segment_sink(self.mode, self.target, segment)
        # every segment that reaches the web viewer is flushed at its pace
        web = self.mode == "serve" and self.web_port is not None
        return open_recording(mode, target, application_id="simserver",
                              recording_id=segment_recording_id(self.base_id, segment),
                              web_port=self.web_port if segment == 0 else None,
                              check_listener=self.check_listener,
                              flush_tick_s=WEB_FLUSH_TICK_S if web else None)

    @staticmethod
    def _end(rec_stream: Any) -> None:
        rec_stream.flush()
        rec_stream.disconnect()

    def next(self) -> Any:
        """End the current segment's recording (but not the gRPC server of ``serve``)
        and open the next one; returns it."""
        if self.current is not self.first or self.mode != "serve":
            self._end(self.current)
            if self.current is self.first:
                self.first = None
        self.segment += 1
        self.current = self._open(self.segment)
        return self.current

    def close(self) -> None:
        """End every open recording (the last one, and the one serving, if apart)."""
        self._end(self.current)
        if self.first is not None and self.first is not self.current:
            self._end(self.first)


class _SegmentScene:
    """The scene of one segment: its recording, vehicle, road and ``SceneLogger``.

    Parameters
    ----------
    rec_stream : rerun.RecordingStream
        The segment's recording (named after the vehicle id, segment and scene).
    config : dict
        The ``config`` of a ``get_config`` reply at the segment's start.
    segment : int
        0, then +1 at each reset or load.
    vehicle_id : str
        For the recording's name.
    """

    def __init__(self, rec_stream: Any, config: dict[str, Any], segment: int,
                 vehicle_id: str) -> None:
        from simserver.adapters.config import load_vehicle

        self.rec_stream = rec_stream
        self.segment = segment
        self.vehicle = load_vehicle(local_config_file(config["vehicle"]["path"]))
        self.scene_path = str(config["scene"]["path"])
        self.vehicle_path = str(config["vehicle"]["path"])
        try:
            self.terrain, self.terrain_spec = scene_terrain(local_config_file(self.scene_path))
        except (OSError, ValueError) as exc:  # ConfigError is a ValueError
            from simserver.core.terrain import plane_terrain

            print(f"simserver view: the scene's terrain cannot be read here ({exc}); "
                  "drawing the road plane", file=sys.stderr, flush=True)
            self.terrain, self.terrain_spec = plane_terrain(), None
        rec_stream.send_recording_name(
            f"{vehicle_id} segment {segment}: {Path(self.scene_path).stem}")
        self._set_road(config["road"], send_blueprint=True)

    def _set_road(self, road: dict[str, Any], send_blueprint: bool) -> None:
        from simserver.adapters.rerun_scene import SceneLogger

        self.road = road
        self.logger = SceneLogger(self.rec_stream, self.vehicle.vp, self.vehicle.tp,
                                  road["grade_pct"], road["cross_slope_pct"], self.terrain,
                                  self.terrain_spec, fps=None,
                                  send_blueprint=send_blueprint)  # decimated by the caller
        self.axes = road_axes(road["grade_pct"], road["cross_slope_pct"])
        self.h_cg = float(self.vehicle.vp[VP_CG_HEIGHT_M])

    def plane_under(self, rec: np.ndarray) -> tuple[float, float, float] | None:
        """On a terrain, the reference plane under the car of state ``rec``; else None."""
        if not self.logger.ground.on_terrain:
            return None
        from simserver.adapters.rerun_scene import terrain_plane_under

        return terrain_plane_under(self.terrain, self.logger.geometry, float(rec["x_m"]),
                                   float(rec["y_m"]), float(rec["yaw_rad"]))

    def follow_road(self, config: dict[str, Any]) -> None:
        """A ``set_road`` within the segment: draw on the new road from now on.

        A changed vehicle or scene is a ``load``, whose reset starts the next segment
        (with its own recording) once the states show the tick going back.
        """
        if str(config["scene"]["path"]) != self.scene_path \
                or str(config["vehicle"]["path"]) != self.vehicle_path:
            return
        if config["road"] != self.road:
            self.logger.flush()
            self._set_road(config["road"], send_blueprint=False)
