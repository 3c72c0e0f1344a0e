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
                self.sleep((remaining - self.spin_ns) * 1e-9)
                now = clock()
            while now < deadline:
                now = clock()
        else:
            self.catching_up = True
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
            l50, l99 = np.percentile(lat, (50.0, 99.0))
            lmax = float(lat.max())
        else:
            l50 = l99 = lmax = 0.0
        if n_per:
            p50, p99 = np.percentile(per, (50.0, 99.0))
            pmax, pmin = float(per.max()), float(per.min())
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
