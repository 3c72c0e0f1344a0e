"""The live server's fixed-rate loop, apart from the vehicles it steps and from the transport.

One thread, one loop; every tick (:meth:`ServerLoop.tick`), for each vehicle slot in turn:

1. wait for the tick's absolute deadline (:class:`simserver.realtime.Pacer`: no drift;
   up to ``max_catchup_ticks`` late ticks run back to back, beyond that the passed
   deadlines are skipped and counted);
2. drain every command received since the last tick without blocking, and arbitrate
   (:class:`simserver.vehicle_slot.CommandArbiter`: the newest valid one wins);
3. the watchdog (:class:`simserver.vehicle_slot.Watchdog`);
4. step the simulation once, unless paused;
5. check the state is finite, else stop the car in a safe state
   (:meth:`simserver.vehicle_slot.VehicleSlot.check_finite`): before publishing;
6. publish the state (every ``state_every`` ticks) and, a few times a second, the
   diagnostics;
7. serve control requests through :data:`CONTROLS` (name -> handler), each validated
   first (:func:`simserver.protocol.validate_control`).

What the loop talks to is injected: the clock and sleep of its pacer, and per slot a
:class:`SlotPorts` (a command inbox, a control inbox, a publisher). The zenoh adapter is
one implementation (:mod:`simserver.adapters.zenoh_io`: ``Inbox``, ``ControlInbox`` with
``validate=False``, ``VehiclePublisher``; wired by ``simserver.server.SimServer``);
``tests/test_server_logic.py`` drives the same loop with a fake clock, list inboxes and a
recording publisher. The rules are those of ``docs/protocol.md``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from simserver import protocol as proto
from simserver.adapters.config import ConfigError
from simserver.realtime import DEFAULT_SPIN_NS, NS_PER_S, CpuMeter, Pacer, PacerStats
from simserver.vehicle_slot import VehicleSlot

if TYPE_CHECKING:
    from simserver.server import ServerConfig

log = logging.getLogger("simserver.server")


# ---------------------------------------------------------------------- the ports
class CommandInbox(Protocol):
    """Driver command payloads received since the last call, oldest first; never blocks."""

    def drain_newest(self) -> list[bytes]: ...


class ControlRequest(Protocol):
    """One control request: its name, its raw JSON payload, and one reply."""

    name: str
    payload: bytes

    def reply(self, body: bytes) -> None: ...


class ControlInbox(Protocol):
    """Control requests received since the last call; never blocks (usually empty)."""

    def poll(self) -> Iterable[ControlRequest]: ...


class Publisher(Protocol):
    """Where one vehicle's state and diagnostics go."""

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
        ``handler(slot, args) -> reply members``; ``args`` already validated.
    stalls_loop : bool
        The handler takes longer than a tick on purpose (``load`` compiles): after it
        succeeds, the pacer restarts its deadline sequence instead of catching up.
    """

    handler: Callable[[VehicleSlot, dict[str, Any]], dict[str, Any]]
    stalls_loop: bool = False


CONTROLS: Mapping[str, Control] = {
    "reset": Control(VehicleSlot.ctl_reset),
    "pause": Control(VehicleSlot.ctl_pause),
    "resume": Control(VehicleSlot.ctl_resume),
    "step": Control(VehicleSlot.ctl_step),
    "set_road": Control(VehicleSlot.ctl_set_road),
    "load": Control(VehicleSlot.ctl_load, stalls_loop=True),
    "get_config": Control(VehicleSlot.ctl_get_config),
}
"""Every control of ``docs/protocol.md`` section 3, by name."""
assert tuple(CONTROLS) == proto.CONTROL_NAMES, "one handler per control of the protocol"


def serve_control(slot: VehicleSlot, request: ControlRequest) -> Control | None:
    """Validate ``request``, run its handler on ``slot`` and answer it exactly once.

    Returns the control when it succeeded, None when it was answered with an error
    naming the field (``docs/protocol.md`` section 3; bad arguments change nothing).
    """
    name = request.name
    try:
        args = _validated(name, request.payload)
        control = CONTROLS[name]
        body = proto.reply_ok(**control.handler(slot, args))
    except proto.ProtocolError as exc:
        request.reply(proto.reply_error(exc))
        return None
    except ConfigError as exc:
        request.reply(proto.reply_error(f"{name}: {exc}", field=name))
        return None
    except Exception as exc:  # a bug must not stop the 1 kHz loop: answer, log, go on
        log.exception("control %s failed", name)
        request.reply(proto.reply_error(f"{name}: internal error ({type(exc).__name__})",
                                        field=name))
        return None
    request.reply(body)
    return control


def _validated(name: str, payload: bytes) -> dict[str, Any]:
    try:
        return proto.validate_control(name, payload)
    except proto.ProtocolError:
        raise
    except Exception as exc:  # a validator bug: answered like bad input, never escapes
        raise proto.ProtocolError(
            "request", f"could not be validated ({type(exc).__name__})") from exc


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

    Call :meth:`add` for each slot, then :meth:`run` (blocks until :meth:`stop`), or
    :meth:`start` and :meth:`tick` one at a time.
    """

    def __init__(self, cfg: ServerConfig, *, clock: Callable[[], int] = time.perf_counter_ns,
                 sleep: Callable[[float], object] = time.sleep,
                 spin_ns: int = DEFAULT_SPIN_NS, cpu: CpuMeter | None = None) -> None:
        self.clock = clock
        self.pacer = Pacer(period_ns=int(round(cfg.period_s * NS_PER_S)), spin_ns=spin_ns,
                           max_catchup_ticks=cfg.max_catchup_ticks, clock=clock, sleep=sleep)
        self.cpu = cpu if cpu is not None else CpuMeter(clock=clock)
        self.state_every = cfg.state_every
        self.diag_every = max(1, int(round(1.0 / (cfg.diag_hz * cfg.period_s))))
        self.slots: list[tuple[VehicleSlot, SlotPorts]] = []
        self.running = False
        self.loop_count = 0
        self.t0_ns = 0

    def add(self, slot: VehicleSlot, ports: SlotPorts) -> None:
        """Serve ``slot`` through ``ports`` from the next tick on."""
        self.slots.append((slot, ports))

    def start(self) -> None:
        """Start the clock: tick 0 is due now."""
        self.t0_ns = self.clock()
        self.cpu.percent()  # the first diagnostics' CPU reading starts here, not at compile
        self.pacer.start()
        self.loop_count = 0

    def stop(self, *_: Any) -> None:
        """Ask :meth:`run` to finish after the current tick (a signal handler)."""
        self.running = False

    def run(self) -> None:
        """Start the clock and tick until :meth:`stop`; ``running`` is set by the caller."""
        self.start()
        while self.running:
            self.tick()

    def tick(self) -> None:
        """Wait for the next deadline and run one tick of every slot."""
        self.pacer.wait()
        catching_up = self.pacer.catching_up
        now = self.clock()
        publish_state = self.loop_count % self.state_every == 0
        diag = self._diagnostics_source() if self.loop_count % self.diag_every == 0 else None
        for slot, ports in self.slots:
            slot.take_commands(ports.commands.drain_newest(), now)
            slot.apply_inputs(now)
            slot.advance()
            slot.check_finite()  # before publishing: no non-finite state leaves the server
            if publish_state:
                ports.publisher.publish_state(slot.state_payload(now, catching_up))
            if diag is not None:
                ports.publisher.publish_diagnostics(self._diagnostics(slot, *diag))
            for request in ports.controls.poll():
                control = serve_control(slot, request)
                if control is not None and control.stalls_loop:
                    self.pacer.rebase()
        self.loop_count += 1

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
        st = self.pacer.stats()
        timing = {"uptime_s": round(self.uptime_s(), 3),
                  "lateness_p50_us": st.lateness_p50_us,
                  "lateness_p99_us": st.lateness_p99_us,
                  "lateness_max_us": st.max_lateness_us, "overruns": st.overruns,
                  "skipped_ticks": st.skipped_ticks, "late_ticks": st.late_ticks}

        def of(slot: VehicleSlot) -> dict[str, Any]:
            return {"ticks": slot.tick, "steps_total": slot.steps_total}

        if len(self.slots) == 1:
            slot = self.slots[0][0]
            return {**of(slot), **timing, **slot.counters}
        return {**timing, "vehicles": {s.keys.vehicle: {**of(s), **s.counters}
                                       for s, _ in self.slots}}
