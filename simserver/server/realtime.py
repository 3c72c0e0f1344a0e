"""The fixed-rate wall-clock pacer of the 1 kHz loop, and its timing statistics.

Pure Python (``time.perf_counter_ns``); no allocation per tick beyond Python's own ints.

Deadlines
---------
Tick ``n`` is due at the absolute deadline ``t0 + n * period`` (integer nanoseconds),
never at "previous tick + period", so rounding and lateness never accumulate: over an
hour the deadline sequence is exactly ``3.6e6`` periods long. :meth:`Pacer.wait` sleeps
until ``spin_ns`` (default 200 us) before the deadline, then spins on the clock: a plain
sleep is about 100 us late on this VM, sleep-then-spin about 0.2 us
(``benchmarks/bench_clock.py`` measures it).

Overrun policy
--------------
When :meth:`Pacer.wait` is called after the deadline it is asked for (the previous tick's
work, or a stall of the VM, ran past it), the tick counts as an **overrun** and:

- if it is at most ``max_catchup_ticks`` whole periods behind, the tick is returned at
  once, and so are the following ones until the loop is back on schedule (**catch-up**,
  at most ``max_catchup_ticks + 1`` ticks back to back). Simulated time stays locked to
  wall time;
- if it is further behind, every whole period that has fully passed is dropped: the
  deadline index jumps to the latest deadline already due, and the dropped deadlines are
  counted in ``skipped_ticks``. From then on simulated time lags wall time by exactly
  ``skipped_ticks * period`` (:attr:`Pacer.lag_ns`).

The default ``max_catchup_ticks = 100`` (100 ms) covers the VM's own stalls (7-30 ms
measured), so skips happen only on real outages (a debugger, SIGSTOP, swapping). For an
intended pause of the loop (compiling a newly loaded vehicle) call :meth:`Pacer.rebase`
afterwards: the deadline sequence restarts from the present without counting skips.

Statistics
----------
Lateness (tick start minus its deadline) and period (start-to-start interval) of the last
``window`` ticks are kept in preallocated int64 ring buffers; :meth:`Pacer.stats` returns
their p50, p99 and max (and the period's min), plus cumulative counters.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

NS_PER_S = 1_000_000_000
DEFAULT_PERIOD_NS = 1_000_000  # 1 kHz
DEFAULT_SPIN_NS = 200_000
DEFAULT_MAX_CATCHUP_TICKS = 100
DEFAULT_LATE_THRESHOLD_NS = 1_000_000
DEFAULT_WINDOW = 4096


@dataclass(frozen=True, slots=True)
class PacerStats:
    """A snapshot of the pacer's counters and window statistics (times in microseconds).

    Attributes
    ----------
    ticks : int
        Ticks returned by :meth:`Pacer.wait` since :meth:`Pacer.start`.
    deadline_index : int
        Index of the next deadline (``ticks + skipped_ticks``).
    overruns : int
        Ticks whose deadline had already passed when :meth:`Pacer.wait` was called.
    skipped_ticks : int
        Deadlines dropped by the overrun policy.
    late_ticks : int
        Ticks started more than ``late_threshold_us`` after their deadline.
    late_threshold_us : float
        The threshold of ``late_ticks``.
    max_lateness_us : float
        Largest lateness since start.
    window_ticks : int
        Ticks in the window behind the percentile fields.
    lateness_p50_us, lateness_p99_us, lateness_max_us : float
        Tick start lateness over the window.
    period_p50_us, period_p99_us, period_max_us, period_min_us : float
        Start-to-start period over the window.
    period_mean_us : float
        Mean achieved period since start (excluding the gap over a :meth:`Pacer.rebase`).
    lag_s : float
        Simulated time behind wall time because of skipped ticks.
    """

    ticks: int
    deadline_index: int
    overruns: int
    skipped_ticks: int
    late_ticks: int
    late_threshold_us: float
    max_lateness_us: float
    window_ticks: int
    lateness_p50_us: float
    lateness_p99_us: float
    lateness_max_us: float
    period_p50_us: float
    period_p99_us: float
    period_max_us: float
    period_min_us: float
    period_mean_us: float
    lag_s: float


class Pacer:
    """Absolute-deadline pacer for a fixed-rate loop.

    Parameters
    ----------
    period_ns : int, optional
        Tick period in nanoseconds (default 1 ms).
    spin_ns : int, optional
        Sleep until this long before a deadline, then spin (default 200 us; 0 = sleep
        only).
    max_catchup_ticks : int, optional
        Overrun policy: catch up back to back when at most this many periods behind,
        otherwise skip (see the module docstring).
    late_threshold_ns : int, optional
        A tick later than this counts in ``late_ticks`` (default 1 ms).
    window : int, optional
        Ticks kept for the percentile statistics.
    clock : callable, optional
        Monotonic clock in integer nanoseconds (default ``time.perf_counter_ns``).
    sleep : callable, optional
        Sleep for a float number of seconds (default ``time.sleep``).

    Examples
    --------
    >>> pacer = Pacer()
    >>> pacer.start()
    >>> for _ in range(3):
    ...     lateness_ns = pacer.wait()  # returns at the tick's deadline
    ...     # step the physics, publish ...
    """

    def __init__(
        self,
        period_ns: int = DEFAULT_PERIOD_NS,
        *,
        spin_ns: int = DEFAULT_SPIN_NS,
        max_catchup_ticks: int = DEFAULT_MAX_CATCHUP_TICKS,
        late_threshold_ns: int = DEFAULT_LATE_THRESHOLD_NS,
        window: int = DEFAULT_WINDOW,
        clock: Callable[[], int] = time.perf_counter_ns,
        sleep: Callable[[float], object] = time.sleep,
    ) -> None:
        if int(period_ns) <= 0:
            raise ValueError(f"period_ns must be > 0, got {period_ns}")
        if int(spin_ns) < 0:
            raise ValueError(f"spin_ns must be >= 0, got {spin_ns}")
        if int(spin_ns) > int(period_ns) // 2:
            # under SCHED_FIFO the spin holds a core: at most half of each period
            raise ValueError(f"spin_ns must be at most half the period ({int(period_ns) // 2}"
                             f" ns), got {spin_ns}")
        if int(max_catchup_ticks) < 0:
            raise ValueError(f"max_catchup_ticks must be >= 0, got {max_catchup_ticks}")
        if int(window) < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        self.period_ns = int(period_ns)
        self.spin_ns = int(spin_ns)
        self.max_catchup_ticks = int(max_catchup_ticks)
        self.late_threshold_ns = int(late_threshold_ns)
        self.window = int(window)
        self.clock = clock
        self.sleep = sleep
        self._lateness = np.zeros(self.window, dtype=np.int64)
        self._period = np.zeros(self.window, dtype=np.int64)
        self._started = False
        self._reset_counters(0)

    def _reset_counters(self, t0_ns: int) -> None:
        self.t0_ns = t0_ns
        self.deadline_index = 0
        self.ticks = 0
        self.overruns = 0
        self.skipped_ticks = 0
        self.late_ticks = 0
        self.max_lateness_ns = 0
        self.deadline_ns = t0_ns
        self.lateness_ns = 0
        self.catching_up = False
        self.sleep_until_ns = 0  # the last wait's sleep: when it was to end (0: no sleep)
        self.woke_ns = 0  # ... and when it returned (TickTrace: a late wake-up)
        self._last_start_ns = -1
        self._lat_n = 0
        self._per_n = 0
        self._period_sum_ns = 0

    # ---------------------------------------------------------------- control

    def start(self, t0_ns: int | None = None) -> None:
        """Start (or restart) the deadline sequence; tick 0 is due at ``t0_ns`` (default now).

        Clears all counters and statistics.
        """
        self._reset_counters(self.clock() if t0_ns is None else int(t0_ns))
        self._started = True

    def rebase(self, t0_ns: int | None = None) -> None:
        """Restart the deadline sequence from ``t0_ns`` (default now), keeping counters.

        For intended stalls (loading a vehicle): the time in between is neither caught up
        nor counted as skipped. The next tick is due at ``t0_ns``.
        """
        if not self._started:
            raise RuntimeError("Pacer.rebase() before start()")
        now = self.clock() if t0_ns is None else int(t0_ns)
        # Deadlines stay t0 + index * period with a new origin.
        self.t0_ns = now - self.deadline_index * self.period_ns
        self._last_start_ns = -1  # the next period sample would span the stall

    @property
    def started(self) -> bool:
        """True once :meth:`start` was called."""
        return self._started

    @property
    def next_deadline_ns(self) -> int:
        """Absolute deadline of the next tick (clock nanoseconds)."""
        return self.t0_ns + self.deadline_index * self.period_ns

    @property
    def lag_ns(self) -> int:
        """Simulated time behind wall time because of skipped ticks."""
        return self.skipped_ticks * self.period_ns

    # ---------------------------------------------------------------- the tick

    def wait(self) -> int:
        """Block until the next tick's deadline and return its lateness in nanoseconds.

        Applies the overrun policy when called late (the tick is returned at once; see
        the module docstring). Updates :attr:`deadline_ns`, :attr:`lateness_ns`,
        :attr:`catching_up` (True when the tick was an overrun) and the counters.
        """
        if not self._started:
            raise RuntimeError("Pacer.wait() before start()")
        period = self.period_ns
        clock = self.clock
        deadline = self.t0_ns + self.deadline_index * period
        now = clock()
        if now <= deadline:
            self.catching_up = False
            remaining = deadline - now
            if remaining > self.spin_ns:
                self.sleep_until_ns = deadline - self.spin_ns
                self.sleep((remaining - self.spin_ns) * 1e-9)
                now = self.woke_ns = clock()
            else:
                self.sleep_until_ns = 0
            while now < deadline:
                now = clock()
        else:
            self.catching_up = True
            self.sleep_until_ns = 0
            self.overruns += 1
            behind = (now - deadline) // period
            if behind > self.max_catchup_ticks:
                self.deadline_index += behind
                self.skipped_ticks += behind
                deadline += behind * period
        lateness = now - deadline
        self.deadline_index += 1
        self.ticks += 1
        self.deadline_ns = deadline
        self.lateness_ns = lateness
        if lateness > self.late_threshold_ns:
            self.late_ticks += 1
        if lateness > self.max_lateness_ns:
            self.max_lateness_ns = lateness
        self._lateness[self._lat_n % self.window] = lateness
        self._lat_n += 1
        if self._last_start_ns >= 0:
            period_ns = now - self._last_start_ns
            self._period[self._per_n % self.window] = period_ns
            self._per_n += 1
            self._period_sum_ns += period_ns
        self._last_start_ns = now
        return lateness

    # ---------------------------------------------------------------- statistics

    def stats(self) -> PacerStats:
        """Counters and window statistics (allocates; call at diagnostics rate, not per tick)."""
        n_lat = min(self._lat_n, self.window)
        n_per = min(self._per_n, self.window)
        lat = self._lateness[:n_lat]
        per = self._period[:n_per]
        if n_lat:
            l50, l99, lmax = window_percentiles(lat)
        else:
            l50 = l99 = lmax = 0.0
        if n_per:
            p50, p99, pmax = window_percentiles(per)
            pmin = float(per.min())
        else:
            p50 = p99 = pmax = pmin = 0.0
        mean = self._period_sum_ns / self._per_n if self._per_n else 0.0
        us = 1e-3
        return PacerStats(
            ticks=self.ticks,
            deadline_index=self.deadline_index,
            overruns=self.overruns,
            skipped_ticks=self.skipped_ticks,
            late_ticks=self.late_ticks,
            late_threshold_us=self.late_threshold_ns * us,
            max_lateness_us=self.max_lateness_ns * us,
            window_ticks=n_lat,
            lateness_p50_us=float(l50) * us,
            lateness_p99_us=float(l99) * us,
            lateness_max_us=lmax * us,
            period_p50_us=float(p50) * us,
            period_p99_us=float(p99) * us,
            period_max_us=pmax * us,
            period_min_us=pmin * us,
            period_mean_us=mean * us,
            lag_s=self.lag_ns / NS_PER_S,
        )

    def lateness_window(self) -> np.ndarray:
        """Copy of the lateness samples in the window (ns, oldest first)."""
        return self._ring_copy(self._lateness, self._lat_n)

    def period_window(self) -> np.ndarray:
        """Copy of the period samples in the window (ns, oldest first)."""
        return self._ring_copy(self._period, self._per_n)

    def _ring_copy(self, buf: np.ndarray, n: int) -> np.ndarray:
        if n <= self.window:
            return buf[:n].copy()
        i = n % self.window
        return np.concatenate((buf[i:], buf[:i]))


def window_percentiles(samples: np.ndarray) -> tuple[float, float, float]:
    """p50, p99 (``np.percentile``'s linear interpolation) and maximum of ``samples``.

    One ``np.partition`` of a copy instead of ``np.percentile``: the diagnostics compute
    this in the tick a few times a second, and for 4096 samples it costs about a fifth
    (``np.percentile`` 43 us, a partition 9 us on this machine, fastest of 300).
    """
    n = samples.size
    ranks = [q * (n - 1) for q in (0.50, 0.99)]
    kth = sorted({int(r) for r in ranks} | {min(int(r) + 1, n - 1) for r in ranks} | {n - 1})
    part = np.partition(samples, kth)
    out = []
    for r in ranks:
        lo = int(r)
        hi = min(lo + 1, n - 1)
        a, b = float(part[lo]), float(part[hi])
        out.append(a + (b - a) * (r - lo))
    return out[0], out[1], float(part[n - 1])


class CpuMeter:
    """Process CPU use (all threads) as a percentage of one core since the last reading.

    Parameters
    ----------
    clock : callable, optional
        Wall clock in ns (default ``time.perf_counter_ns``).
    cpu_clock : callable, optional
        Process CPU time in ns (default ``time.process_time_ns``).
    """

    def __init__(
        self,
        clock: Callable[[], int] = time.perf_counter_ns,
        cpu_clock: Callable[[], int] = time.process_time_ns,
    ) -> None:
        self.clock = clock
        self.cpu_clock = cpu_clock
        self._wall0 = self._wall = clock()
        self._cpu0 = self._cpu = cpu_clock()

    def percent(self) -> float:
        """CPU percent since the previous call (or construction); 100 = one core busy."""
        wall, cpu = self.clock(), self.cpu_clock()
        dw, dc = wall - self._wall, cpu - self._cpu
        self._wall, self._cpu = wall, cpu
        return 100.0 * dc / dw if dw > 0 else 0.0

    def percent_total(self) -> float:
        """CPU percent since construction."""
        dw = self.clock() - self._wall0
        dc = self.cpu_clock() - self._cpu0
        return 100.0 * dc / dw if dw > 0 else 0.0


class TickTrace:
    """Per-tick timing of the loop for finding what makes a tick late (a diagnostic mode:
    ``SIMSERVER_TICK_TRACE=FILE`` in the server's environment; off by default).

    Per tick, one row of :data:`COLUMNS` (integer nanoseconds, raw cumulative counters; a
    ring of ``capacity`` rows): the deadline, the tick's start and end (wall clock), the
    pacer's sleep (when it was to end, when it returned), and at the start and end of the
    tick's work the tick thread's CPU time (``time.thread_time_ns``), its run-queue wait
    and its count of times scheduled in (``/proc/thread-self/schedstat``), and the time
    spent in garbage collection so far (``gc.callbacks``). Between two rows one can then
    tell the thread's own work (CPU time), waiting for a core while runnable (run-queue
    wait: other threads or processes at its priority or above) and being blocked (the rest:
    the sleep, the GIL, a lock) apart; a stall of the whole VM shows as none of these
    (and in a peer process: ``benchmarks.bench_clock``'s pacer). About 5 us a tick.
    :meth:`save` writes the rows (``numpy.save``) and a table of the process's threads
    (name, policy, CPU time, run-queue wait) beside them (``FILE.threads.json``).
    """

    COLUMNS = ("deadline", "start", "end", "sleep_until", "woke", "cpu_start", "cpu_end",
               "delay_start", "delay_end", "runs_start", "runs_end", "gc")

    def __init__(self, path: str, capacity: int = 1 << 17) -> None:
        import gc

        self.path = path
        self.capacity = capacity
        self.rows = np.zeros((capacity, len(self.COLUMNS)), dtype=np.int64)
        self.n = 0
        self.gc_ns = 0
        self._gc_t0 = 0
        self._fd = os.open(f"/proc/self/task/{threading_native_id()}/schedstat", os.O_RDONLY)
        gc.callbacks.append(self._on_gc)

    def _on_gc(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._gc_t0 = time.perf_counter_ns()
        elif self._gc_t0:
            self.gc_ns += time.perf_counter_ns() - self._gc_t0

    def _schedstat(self) -> tuple[int, int]:
        _, delay, runs = os.pread(self._fd, 128, 0).split()
        return int(delay), int(runs)

    def begin(self, pacer: Pacer, now: int) -> None:
        """At the start of a tick's work (after the pacer's wait), from the tick thread."""
        delay, runs = self._schedstat()
        row = self.rows[self.n % self.capacity]
        row[:9] = (pacer.deadline_ns, now, 0, pacer.sleep_until_ns,
                   pacer.woke_ns if pacer.sleep_until_ns else 0, time.thread_time_ns(), 0,
                   delay, 0)
        row[9] = runs

    def end(self) -> None:
        """At the end of the tick's work."""
        cpu = time.thread_time_ns()
        delay, runs = self._schedstat()
        row = self.rows[self.n % self.capacity]
        row[2] = time.perf_counter_ns()
        row[6] = cpu
        row[8] = delay
        row[10] = runs
        row[11] = self.gc_ns
        self.n += 1

    def save(self) -> None:
        """Write the rows (oldest first) and the thread table; close."""
        import gc
        import json

        if self._on_gc in gc.callbacks:
            gc.callbacks.remove(self._on_gc)
        n, cap = self.n, self.capacity
        rows = self.rows[:n] if n <= cap else np.concatenate(
            (self.rows[n % cap:], self.rows[:n % cap]))
        import io
        from pathlib import Path

        from simserver.adapters.config import ConfigError
        from simserver.server.logfile import write_log_bytes

        buf = io.BytesIO()
        np.save(buf, rows)
        try:  # a log the server writes: no symbolic link, regular files only, and a
            # failure (a full disk) is a warning, not a crash of the shutdown
            write_log_bytes(Path(self.path), buf.getvalue(), "tick trace")
            write_log_bytes(Path(self.path + ".threads.json"),
                            json.dumps(thread_table(), indent=1).encode(), "tick trace")
        except ConfigError as exc:
            logging.getLogger("simserver").warning("%s", exc)
        finally:
            os.close(self._fd)


def threading_native_id() -> int:
    """The calling thread's kernel thread id."""
    import threading

    return threading.get_native_id()


def thread_table(pid: int | str = "self") -> list[dict]:
    """Per thread of ``pid``: id, name, policy, priority, CPU time and run-queue wait (s)."""
    out = []
    for tid, name in sorted(process_threads(pid).items()):
        try:
            with open(f"/proc/{pid}/task/{tid}/schedstat", encoding="ascii") as fh:
                cpu, delay, runs = (int(v) for v in fh.read().split())
            policy, prio = thread_policy(tid)
        except (OSError, ValueError):
            continue
        out.append({"tid": tid, "name": name, "policy": policy, "priority": prio,
                    "cpu_s": cpu / NS_PER_S, "run_delay_s": delay / NS_PER_S,
                    "runs": runs})
    return out


# ============================================================================ scheduling
# The 1 kHz loop on a busy machine (issue 13): at normal priority two CPU-bound processes
# made 13 % of ticks more than 1 ms late on this 2-core machine; under SCHED_FIFO 0.17 %.
# The policy is asked per thread (Linux scheduling is per thread): the tick thread, and
# zenoh's own Rust threads that carry the commands in and the states out, found by name
# under /proc/self/task (zenoh names its runtimes' threads "rx-N", "tx-N", ...).

REALTIME_MODES = ("auto", "off")
"""``auto``: ask for SCHED_FIFO where the OS allows it, else a raised nice level or a
warning; ``off``: leave the scheduling alone."""
DEFAULT_RT_PRIORITY = 50
"""SCHED_FIFO priority of the tick thread (1-99); zenoh's threads get one less."""
DEFAULT_ZENOH_THREADS: tuple[str, ...] = ()
"""Name prefixes of the threads to promote besides the tick thread; empty: every thread
started after the scheduler was made (zenoh opens its session later): zenoh's Rust
threads, named ("rx-N", "tx-N", "app-N", "net-N", "acc-N") or not, and the load worker's
Python threads in this process (they take the GIL briefly to hand a result over: at
normal priority a CPU hog preempting one of them mid-way would hold the tick for
milliseconds). Beside two CPU hogs the command-to-state latency p99 was 8.5 ms promoting rx/tx
only, 2.9-3.7 ms promoting the named ones, 1.9 ms with every thread of both processes
at SCHED_FIFO (``chrt -f 50``; 20-60 s runs, load average 5-7)."""
FALLBACK_NICE = -10
"""Nice level asked for when no real-time policy is permitted."""
DEFAULT_CPU_LATENCY_US = 0
"""Wake-up latency held on ``/dev/cpu_dma_latency`` (PM QoS) while the server runs.

0 makes an idle CPU poll instead of halting (cpuidle's POLL state), so the tick's timer
and the threads its commands wake are not delayed by a halted CPU's (on a VM: the
hypervisor's) wake-up. The bare pacer as the tick thread on this VM, interleaved
(``python -m benchmarks.bench_clock --compare 4 --seconds 10``, quiet): 0.075 % of ticks
more than 1 ms late without, 0.010 % with, lateness p99 12 / 1 us, the same CPU. The
cost: idle CPUs spin (power, and a hypervisor's CPU) while the server runs."""

EXPECTED_LATENESS_WITHOUT_RT = (
    "expect late ticks when other processes want the CPU: measured on a 2-core machine "
    "as an ordinary user, beside two CPU-bound processes 1.9 % of ticks were more than "
    "1 ms late (lateness p99 1.94 ms; with SCHED_FIFO 4-5 ticks in 20 s), beside other "
    "real-time servers up to 46 % of the deadlines of a window skipped (lateness p99 "
    "18-93 ms, max 0.2 s)")
"""What the warning says to expect when no real-time policy was obtained (issue 35's
adversarial round, checkout 362909f; ``docs/realtime.md``)."""
RTKIT_SOFT_SHARE = 0.5
"""``RLIMIT_RTTIME``'s soft limit as a share of RealtimeKit's hard one: past the soft
limit the kernel sends SIGXCPU, on which the tick thread leaves SCHED_RR, long before the
hard limit's SIGKILL (a tick thread that never sleeps: ticks longer than the period)."""

try:  # children (the viewer, the load worker) must not inherit a real-time policy
    _RESET_ON_FORK = os.SCHED_RESET_ON_FORK
except AttributeError:  # pragma: no cover - not Linux
    _RESET_ON_FORK = 0


@dataclass(frozen=True)
class RealtimeSettings:
    """What real-time scheduling the server asks for (``simserver serve --realtime``).

    Attributes
    ----------
    mode : {"auto", "off"}
        See :data:`REALTIME_MODES`.
    priority : int
        SCHED_FIFO priority of the tick thread; zenoh's threads get ``priority - 1``.
    zenoh_threads : tuple of str
        Name prefixes of the process's other threads to promote too.
    cpus : tuple of int
        CPU affinity of the whole process (empty: leave it).
    lock_memory : bool
        ``mlockall(MCL_CURRENT | MCL_FUTURE)``: no page fault in the tick from swapped-out
        memory (needs CAP_IPC_LOCK or a large enough ``ulimit -l``).
    cpu_latency_us : int or None
        Held on ``/dev/cpu_dma_latency`` while the scheduler lives, where permitted (root);
        None: leave it (:data:`DEFAULT_CPU_LATENCY_US`).
    """

    mode: str = "auto"
    priority: int = DEFAULT_RT_PRIORITY
    zenoh_threads: tuple[str, ...] = DEFAULT_ZENOH_THREADS
    cpus: tuple[int, ...] = ()
    lock_memory: bool = False
    cpu_latency_us: int | None = DEFAULT_CPU_LATENCY_US

    def __post_init__(self) -> None:
        if self.mode not in REALTIME_MODES:
            raise ValueError(f"realtime: expected one of {', '.join(REALTIME_MODES)}, "
                             f"got {self.mode!r}")
        if not 2 <= int(self.priority) <= 99:
            raise ValueError(f"realtime priority: expected 2-99, got {self.priority}")


def parse_cpus(text: str) -> tuple[int, ...]:
    """``"1"``, ``"0,2"`` or ``"0-3"`` as a tuple of CPU numbers (ValueError if malformed)."""
    cpus: set[int] = set()
    for part in text.split(","):
        part = part.strip()
        lo, sep, hi = part.partition("-")
        if not lo.isdigit() or (sep and not hi.isdigit()):
            raise ValueError(f"cpus: {text!r} is not a CPU list like 1 or 0,2 or 0-3")
        cpus.update(range(int(lo), int(hi if sep else lo) + 1))
    return tuple(sorted(cpus))


def thread_policy(tid: int) -> tuple[str, int]:
    """``(policy name, priority)`` of thread ``tid`` of any process (from the kernel)."""
    policy = os.sched_getscheduler(tid) & ~_RESET_ON_FORK
    names = {os.SCHED_OTHER: "SCHED_OTHER", os.SCHED_FIFO: "SCHED_FIFO",
             os.SCHED_RR: "SCHED_RR", os.SCHED_BATCH: "SCHED_BATCH",
             os.SCHED_IDLE: "SCHED_IDLE"}
    return names.get(policy, str(policy)), os.sched_getparam(tid).sched_priority


def process_threads(pid: int | str = "self") -> dict[int, str]:
    """Thread id -> name (``comm``) of every thread of process ``pid``."""
    out = {}
    task = f"/proc/{pid}/task"
    for entry in os.listdir(task):
        try:
            with open(f"{task}/{entry}/comm", encoding="utf-8", errors="replace") as fh:
                out[int(entry)] = fh.read().strip()
        except OSError:
            continue  # the thread ended meanwhile
    return out


def open_files(pid: int | str = "self") -> dict[int, str]:
    """File descriptor -> what it points at (``/proc/PID/fd``: a path, ``socket:[inode]``,
    ``pipe:[inode]``...) for every descriptor of process ``pid``."""
    out = {}
    fd_dir = f"/proc/{pid}/fd"
    for entry in os.listdir(fd_dir):
        try:
            out[int(entry)] = os.readlink(f"{fd_dir}/{entry}")
        except OSError:
            continue  # closed meanwhile
    return out


class RealtimeScheduler:
    """Applies :class:`RealtimeSettings` to the calling (tick) thread and zenoh's threads.

    :meth:`apply` once, from the tick thread, before the clock starts (it logs one line
    saying what was applied, or a warning naming what to grant); :meth:`promote_new_threads`
    now and then (zenoh starts some threads only when the first peer connects).
    """

    def __init__(self, settings: RealtimeSettings,
                 log: Callable[[int, str], object] | None = None) -> None:
        self.settings = settings
        self.log = log
        self.policy = "unchanged"  # what the tick thread got: SCHED_FIFO, nice, unchanged
        self.applied: list[str] = []
        self.warnings: list[str] = []
        self.promoted: dict[int, str] = {}  # zenoh threads given the policy
        # threads that exist before zenoh starts (numpy's, say) are never promoted
        self._seen: set[int] = set(process_threads())
        self._rt_priority = settings.priority
        self._latency_fd: int | None = None
        self.rtkit_refusal = ""  # why RealtimeKit granted nothing, when asked
        self.rtkit_thread_refusals = 0  # threads RealtimeKit did not promote

    def apply(self) -> str:
        """Scheduling of the calling thread, affinity, locked memory; the summary line."""
        s = self.settings
        if s.mode == "off":
            self.policy = "off"
            return "real-time scheduling: off (--realtime off)"
        if s.cpus:
            try:
                os.sched_setaffinity(0, s.cpus)
                self.applied.append(f"CPUs {','.join(map(str, s.cpus))}")
            except (OSError, ValueError) as exc:
                self.warnings.append(f"CPU affinity {s.cpus} refused ({exc})")
        priority = self._permitted_priority()
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO | _RESET_ON_FORK, os.sched_param(priority))
            self._rt_priority = priority
            self.policy = "SCHED_FIFO"
            self.applied.insert(0, f"SCHED_FIFO priority {priority} for the tick thread")
        except (OSError, AttributeError) as exc:
            refused = getattr(exc, "strerror", None) or exc
            granted = self._ask_realtimekit(priority, refused)
            if not granted:
                self.warnings.append(
                    f"SCHED_FIFO refused ({refused}) and RealtimeKit granted nothing "
                    f"({self.rtkit_refusal}): {EXPECTED_LATENESS_WITHOUT_RT}; grant "
                    "CAP_SYS_NICE, an rtprio limit (ulimit -r 99; docker run --cap-add "
                    "SYS_NICE --ulimit rtprio=99) or RealtimeKit (docs/realtime.md), "
                    "or pass --realtime off to silence this")
                self._nice_fallback()
        if s.cpu_latency_us is not None:
            try:
                self._latency_fd = hold_cpu_latency(s.cpu_latency_us)
                self.applied.append(f"/dev/cpu_dma_latency held at {s.cpu_latency_us} us")
            except OSError as exc:  # not root: said, not warned (a tuning, not a need)
                self.applied.append(f"/dev/cpu_dma_latency not held ({exc.strerror})")
        if s.lock_memory:
            err = _mlockall()
            if err is None:
                self.applied.append("memory locked")
            else:
                self.warnings.append(f"mlockall refused ({err}): grant CAP_IPC_LOCK or "
                                     "ulimit -l unlimited")
        self.promote_new_threads()
        return self.summary()

    def _ask_realtimekit(self, priority: int, refused: object) -> bool:
        """SCHED_RR from RealtimeKit for the calling (tick) thread
        (:mod:`simserver.adapters.rtkit`); True if granted.

        RLIMIT_RTTIME is set as RealtimeKit requires, its soft limit at
        :data:`RTKIT_SOFT_SHARE` of the hard one with a SIGXCPU handler that takes every
        thread back to SCHED_OTHER before the kernel would kill the process. The other
        threads (zenoh's, the state and log writers, whose GIL the tick waits for) get
        ``priority - 1`` from RealtimeKit too, asked by a thread of their own as
        :meth:`promote_new_threads` finds them (a D-Bus call takes milliseconds: never
        in the tick)."""
        import queue
        import signal
        import threading

        from simserver.adapters import rtkit

        try:
            kit = rtkit.RealtimeKit()
        except rtkit.RtkitError as exc:
            self.rtkit_refusal = str(exc)
            return False
        try:
            soft, hard = kit.limit_rttime(RTKIT_SOFT_SHARE)
            granted = kit.make_thread_realtime(threading.get_native_id(), priority)
        except rtkit.RtkitError as exc:
            kit.close()
            self.rtkit_refusal = str(exc)
            return False
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGXCPU, self._leave_realtime)
        self._rt_priority = granted
        self.policy = "SCHED_RR"
        self.applied.insert(0, (
            f"SCHED_FIFO refused ({refused}); RealtimeKit granted SCHED_RR priority "
            f"{granted} for the tick thread (RLIMIT_RTTIME {soft / 1e3:g} ms, "
            f"{hard / 1e3:g} ms hard)"))
        self._rtkit_queue: queue.SimpleQueue = queue.SimpleQueue()
        started = threading.Event()

        def promote() -> None:
            self._seen.add(threading.get_native_id())  # not itself
            started.set()
            while True:
                item = self._rtkit_queue.get()
                if item is None:
                    break
                tid, name = item
                try:
                    kit.make_thread_realtime(tid, granted - 1)
                    self.promoted[tid] = name
                except rtkit.RtkitError as exc:  # ended meanwhile, or RealtimeKit's limits
                    self.rtkit_thread_refusals += 1
                    self.rtkit_refusal = str(exc)
            kit.close()

        threading.Thread(target=promote, name="rtkit-promote", daemon=True).start()
        started.wait(5.0)
        return True

    def _leave_realtime(self, signum: int, frame: object) -> None:
        """SIGXCPU: a real-time thread ran RLIMIT_RTTIME's soft limit without sleeping
        (which one the signal does not say); every thread back to SCHED_OTHER, before
        the kernel kills the process at the hard limit."""
        self.policy = "unchanged"  # no more promotions
        for tid in [0, *self.promoted]:
            try:
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
            except OSError:
                continue
        if self.log is not None:
            self.log(logging.WARNING, "real-time scheduling: a thread ran RealtimeKit's "
                     "RLIMIT_RTTIME without sleeping (ticks longer than the period?): "
                     "every thread back to normal priority")

    def release(self) -> None:
        """Stop holding ``/dev/cpu_dma_latency`` and asking RealtimeKit (idempotent; a
        process's end does it too)."""
        fd, self._latency_fd = self._latency_fd, None
        if fd is not None:
            os.close(fd)
        promoting = getattr(self, "_rtkit_queue", None)
        if promoting is not None:  # RealtimeKit's promoting thread ends
            promoting.put(None)

    def _permitted_priority(self) -> int:
        """The asked priority, capped by RLIMIT_RTPRIO unless we may exceed it."""
        want = self.settings.priority
        try:
            import resource

            soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
        except (ImportError, AttributeError, OSError):
            return want
        if soft == resource.RLIM_INFINITY or soft >= want or _has_cap_sys_nice():
            return want
        # below the limit an unprivileged process may ask; 0 or 1: try, fail, fall back
        return int(soft) if soft >= 2 else want

    def _nice_fallback(self) -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, FALLBACK_NICE)  # this thread (Linux)
            self.policy = f"nice {FALLBACK_NICE}"
            self.applied.insert(0, f"nice {FALLBACK_NICE} for the tick thread (fallback)")
        except OSError as exc:
            self.policy = "unchanged"
            self.warnings.append(f"nice {FALLBACK_NICE} refused too ({exc.strerror}): "
                                 "running at normal priority")

    def promote_new_threads(self) -> int:
        """Give zenoh's threads not seen before the tick thread's policy (priority - 1)."""
        if self.settings.mode == "off" or self.policy == "unchanged":
            return 0
        prefixes = self.settings.zenoh_threads
        try:  # once a second in the tick: list the ids, read only the new threads' names
            new = [int(t) for t in os.listdir("/proc/self/task") if int(t) not in self._seen]
        except OSError:
            return 0
        if not new:
            return 0
        n = 0
        for tid in new:
            self._seen.add(tid)
            try:
                with open(f"/proc/self/task/{tid}/comm", encoding="utf-8",
                          errors="replace") as fh:
                    name = fh.read().strip()
            except OSError:
                continue  # ended meanwhile
            if prefixes and not name.startswith(prefixes):
                continue
            if self.policy == "SCHED_RR":  # RealtimeKit's: its own thread asks for it
                self._rtkit_queue.put((tid, name))
                n += 1
                continue
            try:
                if self.policy == "SCHED_FIFO":
                    os.sched_setscheduler(tid, os.SCHED_FIFO | _RESET_ON_FORK,
                                          os.sched_param(self._rt_priority - 1))
                else:
                    os.setpriority(os.PRIO_PROCESS, tid, FALLBACK_NICE)
            except OSError:
                continue  # ended meanwhile, or refused: it keeps the default
            self.promoted[tid] = name
            n += 1
        if n and self.log is not None and self.applied:
            self.log(logging.DEBUG, f"real-time: {n} more zenoh thread(s) promoted")
        return n

    def summary(self) -> str:
        """One line: what was applied, and the warnings."""
        parts = list(self.applied)
        if self.policy not in ("off", "unchanged"):
            what = f"{self.policy} priority {self._rt_priority - 1}" \
                if self.policy in ("SCHED_FIFO", "SCHED_RR") else self.policy
            if self.policy == "SCHED_RR":
                what += " from RealtimeKit"
            names = ", ".join(p + "*" for p in self.settings.zenoh_threads) or \
                "(every thread started from now on)"
            parts.append(f"{what} for zenoh's threads {names} as they start "
                         f"({len(self.promoted)} so far)")
        line = "real-time scheduling: " + ("; ".join(parts) if parts else "none applied")
        if self.warnings:
            line += " (warning: " + "; ".join(self.warnings) + ")"
        return line


def hold_cpu_latency(us: int) -> int:
    """Ask the kernel (PM QoS) to keep every CPU's wake-up latency under ``us``; held while
    the returned descriptor stays open (OSError when not permitted)."""
    import struct

    fd = os.open("/dev/cpu_dma_latency", os.O_WRONLY)
    try:
        os.write(fd, struct.pack("i", int(us)))
    except OSError:
        os.close(fd)
        raise
    return fd


def _has_cap_sys_nice() -> bool:
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("CapEff:"):
                    return bool(int(line.split()[1], 16) & (1 << 23))  # CAP_SYS_NICE
    except OSError:
        pass
    return False


def _mlockall() -> str | None:
    """Lock current and future memory; None on success, else the error."""
    import ctypes
    import ctypes.util

    mcl_current, mcl_future = 1, 2
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        if libc.mlockall(mcl_current | mcl_future) != 0:
            return os.strerror(ctypes.get_errno())
    except OSError as exc:
        return str(exc)
    return None
