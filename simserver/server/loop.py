"""The live server's fixed-rate loop, apart from the vehicles it steps and from the transport.

One thread, one loop; every tick (:meth:`ServerLoop.tick`), for each vehicle slot in turn:

1. wait for the tick's absolute deadline (:class:`simserver.server.realtime.Pacer`: no drift;
   up to ``max_catchup_ticks`` late ticks run back to back, beyond that the passed
   deadlines are skipped and counted);
2. drain every command received since the last tick without blocking, and arbitrate
   (:class:`simserver.server.slot.CommandArbiter`: the newest valid one wins);
3. the watchdog (:class:`simserver.server.slot.Watchdog`);
4. step the simulation once, unless paused (with several cars, every car's inputs
   first, then one compiled step of their world for all: :meth:`ServerLoop._tick_world`);
5. check the state is finite, else stop the car in a safe state
   (:meth:`simserver.server.slot.VehicleSlot.check_finite`): before publishing;
6. publish the state (every ``state_every`` ticks) and, a few times a second, the
   diagnostics (the zenoh adapter's publisher puts a state in the tick while that is
   cheap, else queues it for its ``state-tx`` thread; the diagnostics always go there);
7. serve control requests through :data:`CONTROLS` (name -> handler), each validated
   first (:func:`simserver.wire.protocol.validate_control`). A ``load`` is read by a worker
   process; a ``load``'s result and a ``reset`` with ``u_mps`` are then applied one piece
   a tick after the tick's step (the result mapped, the model and start state built,
   ``SETTLE_STEPS_PER_TICK`` settling steps at a time, committed), each piece well under
   a millisecond (``python -m benchmarks.bench_load --pieces``), and answered when done.

What the loop talks to is injected: the clock and sleep of its pacer, and per slot a
:class:`SlotPorts` (a command inbox, a control inbox, a publisher). The zenoh adapter is
one implementation (:mod:`simserver.adapters.zenoh_io`: ``Inbox``, ``ControlInbox`` with
``validate=False``, ``VehiclePublisher``; wired by ``simserver.server.app.SimServer``);
``tests/test_server_logic.py`` drives the same loop with a fake clock, list inboxes and a
recording publisher. The rules are those of ``docs/protocol.md``.
"""

from __future__ import annotations

import functools
import gc
import logging
import math
import time
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import Future
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from simserver.adapters.config import ConfigError
from simserver.core.contact import K_EVENTS
from simserver.core.driver import drive
from simserver.server.load_worker import opened
from simserver.server.realtime import (
    DEFAULT_SPIN_NS,
    NS_PER_S,
    CpuMeter,
    Pacer,
    PacerStats,
    TickTrace,
)
from simserver.server.slot import StagedStart, VehicleSlot, unwrap_prepared
from simserver.server.state_frame import StateFrame
from simserver.server.state_frame import all_finite as all_finite_rows
from simserver.wire import protocol as proto

if TYPE_CHECKING:
    from simserver.server.config import ServerConfig

log = logging.getLogger("simserver.server")

JOB_TIMEOUT_S = 10.0
"""A control's off-tick job (``load``) that has shown no progress for this long is
abandoned (a FIFO; server config ``load_stall_s``). Progress: the worker's reports
(``simserver.server.load_worker.Progress``: a MiB of a large ``.xodr`` read, a piece of a road
rasterised) or CPU time it used (``ProcessPreparer.worker_cpu_s``: a worker at nice +5 on
a busy machine may take many seconds for one second of work; a blocked one uses none)."""
WORKING_CPU_S = 0.05
"""CPU seconds a worker must use between two looks (a second apart) to count as working."""
LOAD_TIMEOUT_S = 300.0
"""A job not done after this long is abandoned even while it progresses (server config
``load_timeout_s``): a road of a million geometries takes about 10 s of CPU."""
PROGRESS_LOG_S = 2.0
"""A job still going after this long logs its last progress message, at most this often."""
SETTLE_STEPS_PER_TICK = 50
"""Settling steps of a start at speed (``reset`` with ``u_mps``, a relaxed scene's
``load``) run after a tick's work, per tick: about 0.2 ms of the 1 ms period (4 us a
step); up to ``core.start.SETTLE_STEPS_MAX`` = 2000 steps are then ready in 40 ticks."""
CONTROLS_PER_TICK = 4
"""Control requests served per slot and tick at most; more wait in the inbox (bounded,
per client: ``simserver.adapters.zenoh_io.ControlInbox``)."""


# ---------------------------------------------------------------------- the ports
class CommandInbox(Protocol):
    """Driver command payloads received since the last call, oldest first; never blocks.

    At most ``capacity`` between two calls: beyond, the oldest are overwritten (a full
    drain is how the loop knows; the slot counts the loss from the ``seq`` gap).
    """

    capacity: int

    def drain_newest(self) -> list[bytes]: ...


class ControlRequest(Protocol):
    """One control request: its name, its raw JSON payload, and one reply."""

    name: str
    payload: bytes

    def reply(self, body: bytes) -> None: ...


class ControlInbox(Protocol):
    """Control requests received since the last call; never blocks (usually empty).

    ``poll(n)`` returns at most ``n`` (fairly taken from its clients); ``received``
    counts the requests, ``busy`` those it answered "busy" itself (a full queue).
    """

    received: int
    busy: int

    def poll(self, limit: int) -> Iterable[ControlRequest]: ...


class Publisher(Protocol):
    """Where one vehicle's state and diagnostics go; never waits for a slow subscriber.

    ``slow_publishes`` counts the publishes that took longer than a tick's budget.
    """

    slow_publishes: int

    def publish_state(self, payload: bytes) -> None: ...
    def publish_diagnostics(self, payload: bytes) -> None: ...


@dataclass
class SlotPorts:
    """The transport side of one vehicle slot."""

    commands: CommandInbox
    controls: ControlInbox
    publisher: Publisher


# ---------------------------------------------------------------------- controls
@dataclass(frozen=True)
class Control:
    """A control of the table: its handler on a slot, and how it runs.

    Attributes
    ----------
    handler : callable
        ``handler(slot, args) -> reply members``; ``args`` already validated. Runs in the
        tick: it must be quick (microseconds).
    job : callable, optional
        For a control that reads files or builds a vehicle: ``job(slot, args) ->
        (function, arguments)``, picklable, run off the tick by the loop's
        :class:`Preparer`; then ``apply(slot, result)`` runs in the tick between two
        steps and returns the reply members. ``handler`` is then the in-one-go form
        (tools, tests).
    apply : callable, optional
        See ``job``; it returns a :class:`simserver.server.slot.StagedStart`, settled and
        committed like ``stage``'s.
    stage : callable, optional
        For a control that starts the car anew (``reset``): ``stage(slot, args) ->
        StagedStart``, quick; the loop runs its settling ``SETTLE_STEPS_PER_TICK`` steps
        per tick after the tick's work, then commits it between two ticks and answers.
    """

    handler: Callable[[VehicleSlot, dict[str, Any]], dict[str, Any]]
    job: Callable[[VehicleSlot, dict[str, Any]], tuple[Callable[..., Any], tuple]] | None = None
    apply: Callable[[VehicleSlot, Any], StagedStart] | None = None
    stage: Callable[[VehicleSlot, dict[str, Any]], StagedStart] | None = None


def _apply_load(slot: VehicleSlot, result: Any) -> StagedStart:
    return slot.apply_load(unwrap_prepared(result))


CONTROLS: Mapping[str, Control] = {
    "reset": Control(VehicleSlot.ctl_reset, stage=VehicleSlot.begin_reset),
    "pause": Control(VehicleSlot.ctl_pause),
    "resume": Control(VehicleSlot.ctl_resume),
    "step": Control(VehicleSlot.ctl_step),
    "set_road": Control(VehicleSlot.ctl_set_road),
    "load": Control(VehicleSlot.ctl_load, job=VehicleSlot.load_job, apply=_apply_load),
    "get_config": Control(VehicleSlot.ctl_get_config),
}
"""Every control of ``docs/protocol.md`` section 3, by name."""
assert tuple(CONTROLS) == proto.CONTROL_NAMES, "one handler per control of the protocol"


class Preparer(Protocol):
    """Runs a control's job off the tick (``concurrent.futures`` style)."""

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future: ...
    def restart(self) -> None: ...


class InlinePreparer:
    """Runs jobs at once, in the calling thread (tests; a loop with nothing slow to do)."""

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args))
        except Exception as exc:  # handed to the loop like a worker's failure
            future.set_exception(exc)
        return future

    def restart(self) -> None:
        """Nothing to restart."""


def _reply_error(request: ControlRequest, name: str, exc: Exception) -> None:
    """Answer ``request`` with the error ``exc`` (a bug is logged and answered too)."""
    if isinstance(exc, proto.ProtocolError):
        request.reply(proto.reply_error(exc))
    elif isinstance(exc, ConfigError):
        request.reply(proto.reply_error(f"{name}: {exc}", field=name))
    else:  # a bug must not stop the 1 kHz loop: answer, log, go on
        log.error("control %s failed", name, exc_info=exc)
        request.reply(proto.reply_error(f"{name}: internal error ({type(exc).__name__})",
                                        field=name))


def _attempt(request: ControlRequest, name: str, run: Callable[[], Any]) -> Any:
    """``run()``, or None when it raised (then ``request`` is answered with the error)."""
    try:
        return run()
    except Exception as exc:
        _reply_error(request, name, exc)
        return None


def _answer(request: ControlRequest, name: str, run: Callable[[], dict[str, Any]]) -> bool:
    """Run ``run`` and answer ``request`` with its members or the error; True if it succeeded."""
    members = _attempt(request, name, run)
    if members is None:
        return False
    request.reply(proto.reply_ok(**members))
    return True


def serve_control(slot: VehicleSlot, request: ControlRequest) -> Control | None:
    """Validate ``request``, run its handler on ``slot`` and answer it exactly once.

    Returns the control when it succeeded, None when it was answered with an error
    naming the field (``docs/protocol.md`` section 3; bad arguments change nothing).
    """
    name = request.name

    def run() -> dict[str, Any]:
        args = _validated(name, request.payload)  # an unknown name fails here
        return CONTROLS[name].handler(slot, args)

    return CONTROLS[name] if _answer(request, name, run) else None


WORLD_CONTROLS = ("pause", "resume", "step", "set_road")
"""The controls that act on the whole world when the loop serves several cars: one clock
steps every car (a car cannot pause alone), and the road is the world's. Asked on any car's
key; each car's handler runs (each car's log has the line) and the reply is the asking
car's."""


def serve_world_control(slot: VehicleSlot, slots: list[VehicleSlot],
                        request: ControlRequest) -> None:
    """A :data:`WORLD_CONTROLS` control asked on ``slot``'s key, run on every car of the
    world: the asking car's first (an error there is the answer, nothing changed), then
    the others'; answered once, with the asking car's members."""
    name = request.name

    def run() -> dict[str, Any]:
        args = _validated(name, request.payload)
        handler = CONTROLS[name].handler
        members = handler(slot, args)
        for other in slots:
            if other is not slot:
                try:
                    handler(other, args)
                except proto.ProtocolError:
                    pass  # ``step`` on a car not paused (the asking one was, by a fault stop)
        return members

    _answer(request, name, run)


def _validated(name: str, payload: bytes) -> dict[str, Any]:
    try:
        return proto.validate_control(name, payload)
    except proto.ProtocolError:
        raise
    except Exception as exc:  # a validator bug: answered like bad input, never escapes
        raise proto.ProtocolError(
            "request", f"could not be validated ({type(exc).__name__})") from exc


@dataclass
class PendingJob:
    """A control whose job runs off the tick, or whose start settles in pieces (``staged``):
    answered when it is applied."""

    request: ControlRequest
    control: Control
    future: Future | None
    submitted_ns: int
    staged: StagedStart | None = None
    make: Callable[[], StagedStart] | None = None  # a job's result, mapped: staged next tick
    progress_seen: int = -1  # the worker's progress counter when last looked at
    progress_ns: int = 0  # when it last moved (the stall timeout counts from here)
    logged_ns: int = 0  # when its progress was last logged
    cpu_checked_ns: int = 0  # when the worker's CPU time was last read
    cpu_s: float | None = None  # the worker's CPU time then


# ---------------------------------------------------------------------- the loop
class ServerLoop:
    """The fixed-rate loop over one or more vehicle slots.

    Parameters
    ----------
    cfg : ServerConfig
        Timing: ``period_s``, ``state_every``, ``diag_hz``, ``max_catchup_ticks``.
    clock : callable, optional
        Monotonic clock in integer nanoseconds, for the pacer and the slots' watchdogs
        (default ``time.perf_counter_ns``).
    sleep : callable, optional
        The pacer's sleep in seconds (default ``time.sleep``).
    spin_ns : int, optional
        The pacer's spin phase before each deadline.
    cpu : CpuMeter, optional
        CPU use reported in the diagnostics (default: the process's, on ``clock``).
    preparer : Preparer, optional
        Runs the jobs of controls that read files (``load``) off the tick (default
        :class:`InlinePreparer`; the server passes a worker process).
    job_timeout_s : float
        A job not done after this long is answered with an error and its worker
        restarted (a file that never ends, a parser that does not return).
    controls_per_tick : int
        Control requests served per slot and tick at most (the rest wait in the inbox).
    trace : TickTrace, optional
        Per-tick timing rows (a diagnostic mode), saved when :meth:`run` ends.

    Call :meth:`add` for each slot, then :meth:`run` (blocks until :meth:`stop`), or
    :meth:`start` and :meth:`tick` one at a time. ``every_second`` holds callables run
    once a second between two ticks (the server's housekeeping).
    """

    def __init__(self, cfg: ServerConfig, *, clock: Callable[[], int] = time.perf_counter_ns,
                 sleep: Callable[[float], object] = time.sleep,
                 spin_ns: int = DEFAULT_SPIN_NS, cpu: CpuMeter | None = None,
                 preparer: Preparer | None = None, job_timeout_s: float | None = None,
                 load_timeout_s: float | None = None,
                 controls_per_tick: int = CONTROLS_PER_TICK,
                 trace: TickTrace | None = None) -> None:
        self.clock = clock
        self.trace = trace
        period_ns = int(round(cfg.period_s * NS_PER_S))
        self.pacer = Pacer(period_ns=period_ns, spin_ns=min(spin_ns, period_ns // 2),
                           max_catchup_ticks=cfg.max_catchup_ticks, clock=clock, sleep=sleep)
        self.cpu = cpu if cpu is not None else CpuMeter(clock=clock)
        self.state_every = cfg.state_every
        self.diag_every = max(1, int(round(1.0 / (cfg.diag_hz * cfg.period_s))))
        self.second_every = max(1, int(round(1.0 / cfg.period_s)))
        self.preparer: Preparer = preparer if preparer is not None else InlinePreparer()
        if job_timeout_s is None:
            job_timeout_s = getattr(cfg, "load_stall_s", JOB_TIMEOUT_S)
        if load_timeout_s is None:
            load_timeout_s = getattr(cfg, "load_timeout_s", LOAD_TIMEOUT_S)
        self.job_timeout_ns = int(job_timeout_s * NS_PER_S)
        self.load_timeout_ns = int(max(load_timeout_s, job_timeout_s) * NS_PER_S)
        self._progress = getattr(self.preparer, "progress", None)
        self._worker_cpu = getattr(self.preparer, "worker_cpu_s", None)
        self.controls_per_tick = controls_per_tick
        self.slots: list[tuple[VehicleSlot, SlotPorts]] = []
        self.pending: dict[int, PendingJob] = {}  # by slot index
        self.every_second: list[Callable[[], None]] = []
        # run once a tick after the step, between two ticks; each must cost microseconds
        # (simserver.server.scenario_live applies its worker's driver targets here)
        self.tick_hooks: list[Callable[[], None]] = []
        self.running = False
        # several cars: the world they share, stepped once a tick for all (add()), and the
        # world message (simserver.server.fleet.WorldMessage) with where it goes
        self.world: Any = None
        self.world_message: Any = None
        self.traffic_every = max(1, int(round(1.0 / (proto.TRAFFIC_STATE_HZ * cfg.period_s))))
        self.publish_world: Callable[[bytes], None] | None = None
        self.world_desk: Any = None  # the world's controls (simserver.server.world_desk)
        # every car's state record, its copies of the world's rows filled in one go a tick
        self.state_frame: StateFrame | None = None
        self._message_noted: Any = None  # the world message the published states are noted in
        self._plan: list = [()]  # what each car does at each tick of the cycle (_make_plan)
        self._plan_rows: list[np.ndarray] = [np.zeros(0, dtype=np.int64)]
        self._input_slots: list[VehicleSlot] = []
        # the built-in driver's cars (simserver.server.live_drivers): prepared off the
        # tick, their arrays assembled when the world's cars change, driven each tick
        self.live_drivers: Any = None
        self.drivers: Any = None  # core.driver.Drivers of the world's cars, or None
        self._held: set[VehicleSlot] = set()  # cars held through the last world step
        self._driver_ids: list[str] = []
        # contact events (docs/model.md section 16): read from the world's ring after the
        # step that wrote them, counted per car, published once each (docs/protocol.md 5.1)
        self.publish_collision: Callable[[bytes], None] | None = None
        self.contact_events_seen = 0  # the ring's count up to which events were read
        self.contact_events_lost = 0  # overwritten in the ring before they were read
        self.collisions_dropped = 0  # not publishable (a non-finite value, an id too long)
        self.loop_count = 0
        self.t0_ns = 0
        self._skipped_seen = 0
        self._jobs_busy: dict[int, int] = {}

    def add(self, slot: VehicleSlot, ports: SlotPorts) -> None:
        """Serve ``slot`` through ``ports`` from the next tick on.

        Slots whose simulations share one ``world`` (``simserver.server.fleet.build_world``) are
        the cars of that world: the tick steps it once for all (:meth:`_tick_world`), and
        the controls that act on the world (``pause``,
        ``resume``, ``step``, ``set_road``: :data:`WORLD_CONTROLS`) act on every car."""
        self.slots.append((slot, ports))
        worlds = {id(getattr(s.sim, "world", s.sim)) for s, _ in self.slots}
        shared = len(self.slots) > 1 and len(worlds) == 1  # else each slot its own world
        for s, _ in self.slots:
            s.shared_world = shared
        self.world = slot.sim.world if shared or self._driven_alone() else None
        self._cars_changed()
        self.assemble_drivers()

    def remove(self, slot: VehicleSlot) -> SlotPorts:
        """Stop serving ``slot`` (between ticks) and take its car out of the world
        (``World.remove_car``: the other cars keep their rows' bits); its ports are
        returned for the caller to close. A job of its still pending is answered with an
        error."""
        index = next(i for i, (s, _) in enumerate(self.slots) if s is slot)
        _, ports = self.slots.pop(index)
        job = self.pending.pop(index, None)
        if job is not None:
            name = job.request.name
            job.request.reply(proto.reply_error(f"{name}: the car was removed; nothing "
                                                "changed", field=name))
        self.pending = {i - (i > index): j for i, j in self.pending.items()}
        self._jobs_busy = {i - (i > index): n for i, n in self._jobs_busy.items()
                           if i != index}
        world = getattr(slot.sim, "world", None)
        if world is not None and slot.keys.vehicle in getattr(world, "ids", ()):
            if len(world) > 1:
                world.remove_car(slot.keys.vehicle)
        shared = len(self.slots) > 1 and self.world is not None
        for s, _ in self.slots:
            s.shared_world = shared
        if not shared and not self._driven_alone():
            self.world = None
        if self.live_drivers is not None:
            self.live_drivers.forget(slot.keys.vehicle)
        self._cars_changed()
        self.assemble_drivers()
        return ports

    def _driven_alone(self) -> bool:
        """One car, driven by the built-in driver (a ``cars:`` list of one): the tick
        steps its world as the world's (``drive`` writes its inputs first)."""
        return len(self.slots) == 1 and self.slots[0][0].driven_by == "driver"

    def assemble_drivers(self, fresh: bool = False) -> None:
        """The driver arrays of the world's cars now (between ticks: after a car is added
        or removed, each driven car's driver state carried over by id; ``fresh``: after a
        reset, every driver starts anew). Nothing to drive: None."""
        world, live = self.world, self.live_drivers
        if world is None or not live:
            self.drivers, self._driver_ids = None, []
            return
        self.drivers = live.assemble(world, None if fresh else self.drivers,
                                     self._driver_ids)
        self._driver_ids = list(world.ids)

    def _cars_changed(self) -> None:
        """The state frame's and the world message's cars after a car was added or
        removed."""
        self._bind_frame()
        self._make_plan()
        self._message_noted = None  # its rows are the cars' of now: filled anew when due
        message = self.world_message
        if message is not None:
            message.set_cars([s.keys.vehicle for s, _ in self.slots],
                             [s.driven_by for s, _ in self.slots])
            if self.state_frame is not None:  # filled from the world by _bind_frame
                message.seed(self.state_frame.records)

    def _bind_frame(self) -> None:
        """The state records of the world's cars filled in one go a tick
        (``simserver.server.state_frame``), when the loop's cars are the world's in its
        order (they are: a car joins and leaves both together); else each car fills its
        own, as a single car does."""
        world = self.world
        slots = [s for s, _ in self.slots]
        if world is not None:  # the tick's finite check compiled or loaded here, not in it
            all_finite_rows(world.data.x, world.data.out)
        if world is None or [s.keys.vehicle for s in slots] != list(world.ids):
            if self.state_frame is not None:  # each record its own again (a copy)
                for slot in slots:
                    slot.record = slot.record.copy()
            self.state_frame = None
            return
        if self.state_frame is None:
            self.state_frame = StateFrame()
        self.state_frame.bind(slots)
        # its kernel compiled or loaded from the cache here, between ticks, not in the
        # first tick that publishes (the copied fields are written again before use)
        self.state_frame.fill(world, np.arange(len(slots), dtype=np.int64))

    def start(self) -> None:
        """Start the clock: tick 0 is due now.

        Before it, the heap built so far (compiled kernels, configs, the transport) is
        collected once and frozen: a garbage collection that falls in a tick then walks
        only what was allocated since, not the whole heap.
        """
        gc.collect()
        gc.freeze()
        self.t0_ns = self.clock()
        self.cpu.percent()  # the first diagnostics' CPU reading starts here, not at compile
        self.pacer.start()
        self.loop_count = 0
        self._skipped_seen = 0

    def stop(self, *_: Any) -> None:
        """Ask :meth:`run` to finish after the current tick (a signal handler)."""
        self.running = False

    def run(self) -> None:
        """Start the clock and tick until :meth:`stop`; ``running`` is set by the caller."""
        self.start()
        try:
            while self.running:
                self.tick()
        finally:
            if self.trace is not None:
                self.trace.save()

    def tick(self) -> None:
        """Wait for the next deadline and run one tick of every slot."""
        pacer = self.pacer
        pacer.wait()
        catching_up = pacer.catching_up
        skipped = pacer.skipped_ticks != self._skipped_seen
        self._skipped_seen = pacer.skipped_ticks
        now = self.clock()
        trace = self.trace
        if trace is not None:
            trace.begin(pacer, now)
        count = self.loop_count
        publish_state = count % self.state_every == 0
        diag_tick = count % self.diag_every == 0
        if self.world is not None:
            self._tick_world(now, skipped, catching_up, publish_state, diag_tick)
        else:
            self._tick_slots(now, skipped, catching_up, publish_state, diag_tick)
        if self.world_desk is not None:  # cars added and removed between two ticks
            self.world_desk.tick(now)
        for hook in self.tick_hooks:  # e.g. a served scenario's posted driver targets
            hook()
        message = self.world_message
        if message is not None and message.due(count):
            uptime_s = (now - self.t0_ns) / NS_PER_S
            if self._message_noted is message:  # every car's newest state noted as published
                self.publish_world(message.payload_noted(count, uptime_s))
            else:  # a new message, or the cars changed: every car's newest state once
                self.publish_world(message.payload(
                    [s.last_published for s, _ in self.slots], count, uptime_s))
                self._message_noted = message
        if count % self.second_every == self.second_every // 2:  # between diagnostics
            for job in self.every_second:
                job()
        self.loop_count += 1
        if trace is not None:
            trace.end()

    def _tick_slots(self, now: int, skipped: bool, catching_up: bool, publish_state: bool,
                    diag_tick: bool) -> None:
        """One tick of a single car (each slot steps its own simulation)."""
        diag = None
        for index, (slot, ports) in enumerate(self.slots):
            if skipped:
                slot.skipped_before = True
            payloads = ports.commands.drain_newest()
            slot.take_commands(payloads, now, len(payloads) >= ports.commands.capacity)
            slot.apply_inputs(now)
            slot.advance()
            slot.check_finite()  # before publishing: no non-finite state leaves the server
            if publish_state:
                payload = slot.state_payload(now, catching_up)
                if payload is not None:  # None: no finite state to publish yet
                    ports.publisher.publish_state(payload)
                    noted = self._message_noted
                    if noted is not None and slot.last_published is payload:
                        noted.note(index, payload)
            if diag_tick:  # after the state: the window's percentiles never delay it
                diag = diag or self._diagnostics_source()
                self._port_counters(index, slot, ports)
                ports.publisher.publish_diagnostics(self._diagnostics(slot, *diag))
            self._serve_controls(index, slot, ports, now, catching_up)

    def _tick_world(self, now: int, skipped: bool, catching_up: bool, publish_state: bool,
                    diag_tick: bool) -> None:
        """One tick of the cars of a world: every car's commands and inputs, then one
        compiled step of the world for all of them (docs/model.md section 14), then each
        car's checks, state, diagnostics and controls. A car paused alone (a fault stop)
        keeps its state through the world's step (its rows are put back after it).

        What costs per car is spread so that no tick carries it for every car at once,
        and what can be done for every car at once is (issue 30: 32 cars in the 1 ms
        budget): the states are checked for finite values once for the whole world (a car
        is looked at alone only when something is not finite); the copied fields of the state
        records of the cars that publish this tick, and their server fields that follow
        from the physics, are filled together by a fixed number of compiled calls
        (:class:`simserver.server.state_frame.StateFrame`), then each of those cars writes
        its own fields; a car not driven by a client (keyframes,
        the built-in driver) publishes its state at :attr:`traffic_every` ticks, car ``k``
        at its own phase (its clients want the traffic, not its every tick: the world
        message carries every car), and its command inbox and control requests are looked
        at then too (a control to it is answered within 10 ms); car ``k``'s diagnostics go
        out at its own phase of the diagnostics period. Which cars have something to do at
        which tick is planned when the cars change (:meth:`_make_plan`), so the tick's
        Python passes over those cars only, apart from each car's ``advance`` (its tick
        count, its command log)."""
        slots = self.slots
        count = self.loop_count
        plan = self._plan[count % len(self._plan)]
        if skipped:
            for slot, _ in slots:
                slot.skipped_before = True
        for _, slot, ports, _, commands, _ in plan:
            if commands:  # a client's car every tick, another at its own phase only
                payloads = ports.commands.drain_newest()
                slot.take_commands(payloads, now, len(payloads) >= ports.commands.capacity)
        for slot in self._input_slots:  # clients (watchdog) and keyframes: not the driver's
            slot.apply_inputs(now)
        drivers = self.drivers
        if drivers is not None:  # the driven cars' inputs from the states now (model.md 15)
            drive(self.world.model, self.world.data, drivers)
        stepped = False
        for slot, _ in slots:  # each car's inputs logged (the driver's too), ticks counted
            slot.stepping = slot.advance(step=False)
            stepped = stepped or slot.stepping
        if stepped:
            held = [(s, s.sim.x.copy(), s.sim.out.copy()) for s, _ in slots
                    if not s.stepping]
            self.world.step()
            for s, x, out in held:
                s.sim.x[:] = x
                s.sim.out[:] = out
            if held or self._held:  # rare: a car paused alone (a fault stop)
                self._note_held([s for s, _, _ in held])
        data = self.world.data
        if data.contacts.count[K_EVENTS] != self.contact_events_seen:  # rare: a contact
            self._contact_events(count)
        all_finite = all_finite_rows(data.x, data.out)
        if not all_finite:  # each car looked at alone (a non-finite one is stopped: reset)
            for slot, _ in slots:
                slot.check_finite()  # before publishing: nothing non-finite leaves
        diag = None
        pending = self.pending
        if pending:  # a job's car is served every tick until it is answered
            plan = self._with_pending(plan, pending)
        frame = self.state_frame
        noted = self._message_noted  # the world message, noting each new state
        if publish_state and frame is not None:  # the publishing cars' fields in one go
            frame.fill(self.world, self._plan_rows[count % len(self._plan_rows)])
        for index, slot, ports, diag_due, commands, serve in plan:
            if all_finite:
                slot.state_finite = True  # check_finite's verdict, without its own look
            if publish_state and commands:  # a client's car, or another at its phase
                payload = slot.state_payload(now, catching_up, frame, index)
                if payload is not None:
                    ports.publisher.publish_state(payload)
                    if noted is not None and slot.last_published is payload:
                        noted.note(index, payload)
            if diag_due:
                diag = diag or self._diagnostics_source()
                self._port_counters(index, slot, ports)
                ports.publisher.publish_diagnostics(self._diagnostics(slot, *diag))
            if serve:  # traffic: at its phase (10 ms)
                self._serve_controls(index, slot, ports, now, catching_up)

    def _note_held(self, held: list[VehicleSlot]) -> None:
        """Cars held through a world step (their rows put back) and cars stepping again
        after a hold: a car's steps then lag the world's, so its command log says at
        which world step its steps go on (a ``world`` line, event ``resume``:
        ``simserver.server.world_replay``). Off the common path: only while a car is held."""
        world_step = self.world.steps - 1  # the step just taken
        serving = {id(s) for s, _ in self.slots}
        for slot in self._held.difference(held):
            if slot.stepping and id(slot) in serving and slot.command_log is not None:
                slot.command_log.write({"step": slot.steps_total - 1, "world": {
                    "event": "resume", "step": world_step}})
        self._held = set(held)

    def _make_plan(self) -> None:
        """What each car does at each tick of the world's cycle (when the cars change):
        ``_plan[tick % cycle]`` lists, in the cars' order, the cars with something to do
        at that tick: ``(index, slot, ports, diagnostics due, commands and state due,
        controls served)``. A client's car has its commands, state and controls every
        tick; another (keyframes, the built-in driver) at its phase of
        :attr:`traffic_every`; car ``k``'s diagnostics at its phase of the diagnostics
        period. So a tick's Python passes over the cars that publish, not over every car
        of the world (``benchmarks.bench_multicar``: 32 cars)."""
        every, diag_every = self.traffic_every, self.diag_every
        cycle = every * diag_every // math.gcd(every, diag_every)
        cars = [(index, slot, ports, slot.driven_by == "client")
                for index, (slot, ports) in enumerate(self.slots)]
        plan = []
        for tick in range(cycle):
            entries = []
            for index, slot, ports, client in cars:
                phase = (tick + index) % every == 0
                diag_due = (tick + index) % diag_every == 0
                if client or phase or diag_due:
                    entries.append((index, slot, ports, diag_due, client or phase,
                                    client or phase))
            plan.append(tuple(entries))
        self._plan = plan
        self._plan_rows = [np.array([e[0] for e in entries if e[4]], dtype=np.int64)
                           for entries in plan]  # the cars that publish: the frame's rows
        self._input_slots = [slot for slot, _ in self.slots if slot.driven_by != "driver"]

    def _with_pending(self, plan: tuple, pending: dict[int, PendingJob]) -> list:
        """``plan`` with the cars of pending jobs served too (their controls only)."""
        have = {entry[0] for entry in plan}
        extra = [(index, self.slots[index][0], self.slots[index][1], False, False, True)
                 for index in pending if index not in have]
        out = list(plan)
        for entry in extra:
            out.append(entry)
        for k, entry in enumerate(out):
            if entry[0] in pending and not entry[5]:
                out[k] = entry[:5] + (True,)
        out.sort(key=lambda entry: entry[0])
        return out

    def _contact_events(self, tick: int) -> None:
        """The world's new contact events (``World.contact_events``, after the step that
        wrote them, so the rows are the cars' of now): each counted in both cars'
        diagnostics and published once on ``{prefix}/world/collision``; the events the
        ring lost (more than ``core.contact.EVENT_RING`` in one step) counted. Runs only
        in a tick whose step wrote an event; the put goes through a sender thread."""
        events, total, lost = self.world.contact_events(self.contact_events_seen)
        self.contact_events_seen = total
        self.contact_events_lost += lost
        by_id = {s.keys.vehicle: s for s, _ in self.slots}
        for s, _ in self.slots:
            s.counters["contact_events_lost"] = self.contact_events_lost
        for e in events:
            for car in (e["car_a"], e["car_b"]):
                slot = by_id.get(car)
                if slot is not None:
                    slot.counters["contact_events"] += 1
            if self.publish_collision is None:
                continue
            try:
                payload = proto.encode_collision(
                    seq=e["seq"], tick=tick, sim_time_s=e["time_s"], car_a=e["car_a"],
                    car_b=e["car_b"], closing_speed_mps=e["closing_speed_mps"],
                    x_m=e["x_m"], y_m=e["y_m"], lost=self.contact_events_lost)
            except proto.ProtocolError:  # nothing non-finite leaves the server
                self.collisions_dropped += 1
                continue
            self.publish_collision(payload)

    def _serve_controls(self, index: int, slot: VehicleSlot, ports: SlotPorts,
                        now: int, catching_up: bool = False) -> None:
        """Apply a finished job; settle a staged start a little further (not while catching
        up: late ticks come first) and commit it when ready; serve the quick controls; hand
        slow ones to the preparer."""
        pending = self.pending.get(index)
        if pending is not None:  # one piece of its work per tick (each well under 1 ms)
            if pending.make is not None:
                self._begin_stage(index, pending.request, pending.control, pending.make, now,
                                  settle_now=False)
            elif pending.staged is not None:
                if not catching_up:
                    self._settle(index, pending)
            else:
                self._finish_job(index, slot, pending, now)
        for request in ports.controls.poll(self.controls_per_tick):
            name = request.name
            control = CONTROLS.get(name)
            if self.world is not None and name in WORLD_CONTROLS:
                serve_world_control(slot, [s for s, _ in self.slots], request)
                continue
            if control is None or (control.job is None and control.stage is None):
                serve_control(slot, request)
                continue
            try:  # bad arguments are named first, busy or not
                args = _validated(name, request.payload)
            except proto.ProtocolError as exc:
                request.reply(proto.reply_error(exc))
                continue
            if index in self.pending:
                self._jobs_busy[index] = self._jobs_busy.get(index, 0) + 1
                request.reply(proto.reply_error(
                    f"{name}: busy: a {self.pending[index].request.name} is still being "
                    "prepared; ask again when it has been answered", field=name))
                continue
            if control.stage is not None:
                self._begin_stage(index, request, control,
                                  functools.partial(control.stage, slot, args), now)
                continue
            try:
                fn, job_args = control.job(slot, args)
            except proto.ProtocolError as exc:
                request.reply(proto.reply_error(exc))
                continue
            job = self.pending[index] = PendingJob(request, control,
                                                   self.preparer.submit(fn, *job_args), now)
            if job.future.done():  # an inline preparer: all of it, answered in this tick
                self._finish_job(index, slot, job, now)
                while (job := self.pending.get(index)) is not None and job.make is not None:
                    self._begin_stage(index, job.request, job.control, job.make, now)
                    if (job := self.pending.get(index)) is not None:
                        job.staged.prepared.finish()
                        self._settle(index, job)

    def _begin_stage(self, index: int, request: ControlRequest, control: Control,
                     make: Callable[[], StagedStart], now: int, settle_now: bool = True) -> None:
        """Make a staged start (errors answered, nothing changed) and, with ``settle_now``,
        take its first piece of settling now: committed and answered at once when that was
        all (a reset at rest is answered in its tick); else from the next tick on."""
        self.pending.pop(index, None)
        staged = _attempt(request, request.name, make)
        if staged is not None:
            pending = self.pending[index] = PendingJob(request, control, None, now, staged)
            if settle_now:
                self._settle(index, pending)

    def _settle(self, index: int, pending: PendingJob) -> None:
        """Advance a staged start by ``SETTLE_STEPS_PER_TICK`` steps; commit and answer it
        when it is settled (between this tick's step and the next)."""
        staged = pending.staged
        assert staged is not None
        done = _attempt(pending.request, pending.request.name,
                        lambda: staged.advance(SETTLE_STEPS_PER_TICK))
        if done is None:  # answered with the error; the running car is untouched
            del self.pending[index]
        elif done:
            del self.pending[index]
            _answer(pending.request, pending.request.name, staged.commit)

    def _port_counters(self, index: int, slot: VehicleSlot, ports: SlotPorts) -> None:
        """The transport's counters into the slot's (diagnostics, the stopped line)."""
        c = slot.counters
        c["ctl_received"] = ports.controls.received
        c["ctl_busy"] = ports.controls.busy + self._jobs_busy.get(index, 0)
        c["publish_slow"] = ports.publisher.slow_publishes

    def _finish_job(self, index: int, slot: VehicleSlot, pending: PendingJob,
                    now: int) -> None:
        name = pending.request.name
        future = pending.future
        if future.done():
            del self.pending[index]
            exc = future.exception()
            if exc is not None:
                log.error("control %s: its worker failed: %r", name, exc)
                pending.request.reply(proto.reply_error(
                    f"{name}: the worker preparing it failed ({type(exc).__name__}); "
                    "nothing changed", field=name))
                self.preparer.restart()
                return
            # a worker's result maps its big arrays (shared memory: no copy, no unpickling
            # of megabytes in the tick; simserver.server.load_worker) in this tick; the next one
            # builds its model and start state, the ones after settle (a relaxed start) and
            # commit it: a few hundred microseconds of work per tick at most
            value = _attempt(pending.request, name, lambda: opened(future.result()))
            if value is not None:
                self.pending[index] = PendingJob(
                    pending.request, pending.control, None, now,
                    make=lambda: pending.control.apply(slot, value))
        else:
            self._watch_job(index, pending, now)

    def _watch_job(self, index: int, pending: PendingJob, now: int) -> None:
        """A job still running: note its progress (logged every ``PROGRESS_LOG_S``);
        abandon it when it has shown none for ``job_timeout_ns`` or has run for
        ``load_timeout_ns``."""
        name = pending.request.name
        progress = self._progress
        if progress is not None:
            seen = progress.seen()
            if seen != pending.progress_seen:
                if pending.progress_seen >= 0:  # the first look only takes the count
                    pending.progress_ns = now
                pending.progress_seen = seen
                if now - max(pending.submitted_ns, pending.logged_ns) >= PROGRESS_LOG_S * NS_PER_S:
                    pending.logged_ns = now
                    log.info("control %s: preparing for %.0f s: %s", name,
                             (now - pending.submitted_ns) / NS_PER_S, progress.message())
        cpu = self._worker_cpu
        if cpu is not None and now - pending.cpu_checked_ns >= NS_PER_S:
            pending.cpu_checked_ns = now
            used = cpu()
            if used is not None and pending.cpu_s is not None \
                    and used - pending.cpu_s >= WORKING_CPU_S:
                pending.progress_ns = now  # slow, but working
            pending.cpu_s = used
        quiet_ns = now - max(pending.submitted_ns, pending.progress_ns)
        took_ns = now - pending.submitted_ns
        if quiet_ns <= self.job_timeout_ns and took_ns <= self.load_timeout_ns:
            return
        del self.pending[index]
        if quiet_ns > self.job_timeout_ns:
            why = (f"not prepared within {self.job_timeout_ns / NS_PER_S:.0f} s of its last "
                   "progress (a file that never ends, a FIFO?; server config load_stall_s)")
        else:
            why = (f"not prepared within {self.load_timeout_ns / NS_PER_S:.0f} s (server "
                   "config load_timeout_s)")
        log.error("control %s: %s: worker restarted", name, why)
        pending.request.reply(proto.reply_error(f"{name}: {why}; nothing changed", field=name))
        self.preparer.restart()

    def uptime_s(self) -> float:
        """Wall time since :meth:`start`."""
        return (self.clock() - self.t0_ns) / NS_PER_S

    def _diagnostics_source(self) -> tuple[PacerStats, float, float]:
        return self.pacer.stats(), self.cpu.percent(), self.uptime_s()

    @staticmethod
    def _diagnostics(slot: VehicleSlot, st: PacerStats, cpu_percent: float,
                     uptime_s: float) -> bytes:
        return proto.encode_diagnostics(
            window_ticks=st.window_ticks, tick=slot.tick, uptime_s=uptime_s,
            lateness_p50_us=st.lateness_p50_us, lateness_p99_us=st.lateness_p99_us,
            lateness_max_us=st.lateness_max_us, period_p50_us=st.period_p50_us,
            period_p99_us=st.period_p99_us, period_max_us=st.period_max_us,
            period_min_us=st.period_min_us, cpu_percent=cpu_percent,
            overruns=st.overruns, skipped_ticks=st.skipped_ticks, late_ticks=st.late_ticks,
            **slot.counters,
        )

    def final_stats(self) -> dict[str, Any]:
        """The ``simserver: stopped`` summary: timing, and per slot its ticks and counters.

        With one slot its fields are at the top level (the documented line); with several
        they are under ``"vehicles"``, by vehicle id.
        """
        for index, (slot, ports) in enumerate(self.slots):
            self._port_counters(index, slot, ports)
        st = self.pacer.stats()
        timing = {"uptime_s": round(self.uptime_s(), 3),
                  "lateness_p50_us": st.lateness_p50_us,
                  "lateness_p99_us": st.lateness_p99_us,
                  "lateness_max_us": st.max_lateness_us, "overruns": st.overruns,
                  "skipped_ticks": st.skipped_ticks, "late_ticks": st.late_ticks}

        def of(slot: VehicleSlot, ports: SlotPorts) -> dict[str, Any]:
            out = {"ticks": slot.tick, "steps_total": slot.steps_total}
            # a publisher that puts in the tick while that is cheap (the zenoh adapter's):
            # how many states it put there, and how often it handed them to its thread
            for name in ("inline_puts", "handoffs"):
                value = getattr(ports.publisher, name, None)
                if value is not None:
                    out["publish_" + name] = value
            return out

        if len(self.slots) == 1:
            slot, ports = self.slots[0]
            return {**of(slot, ports), **timing, **slot.counters}
        return {**timing, "vehicles": {s.keys.vehicle: {**of(s, p), **s.counters}
                                       for s, p in self.slots}}
