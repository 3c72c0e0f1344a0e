"""The wall-clock pacer's logic, on a simulated clock (no wall-clock timing assertions)."""

from __future__ import annotations

import numpy as np
import pytest

from simserver.server.realtime import CpuMeter, Pacer, window_percentiles

P = 1_000_000  # 1 ms in ns
T0 = 5_000_000_000


class FakeClock:
    """A deterministic clock: every read costs ``read_ns``; ``sleep`` oversleeps by ``late_ns``.

    ``work(ns)`` stands for the loop's work between two ``wait()`` calls.
    """

    def __init__(self, t0: int = T0, read_ns: int = 1_000, late_ns: int = 50_000) -> None:
        self.t = t0
        self.read_ns = read_ns
        self.late_ns = late_ns
        self.reads = 0
        self.sleeps: list[float] = []

    def __call__(self) -> int:
        self.t += self.read_ns
        self.reads += 1
        return self.t

    def sleep(self, seconds: float) -> None:
        assert seconds > 0
        self.sleeps.append(seconds)
        self.t += round(seconds * 1e9) + self.late_ns

    def work(self, ns: int) -> None:
        self.t += ns


def make(clock: FakeClock, **kw) -> Pacer:
    pacer = Pacer(P, clock=clock, sleep=clock.sleep, **kw)
    pacer.start(T0)
    return pacer


def test_on_time_ticks_hit_their_absolute_deadlines():
    clock = FakeClock()
    pacer = make(clock, spin_ns=200_000)
    deadlines, lateness = [], []
    for _ in range(1000):
        lateness.append(pacer.wait())
        deadlines.append(pacer.deadline_ns)
        clock.work(300_000)
    assert deadlines == [T0 + n * P for n in range(1000)]
    # Only the first is "late" (start() set t0 in the past by one clock read).
    assert pacer.overruns == 1 and pacer.skipped_ticks == 0 and pacer.late_ticks == 0
    # Spinning ends within one clock read of the deadline.
    assert max(lateness[1:]) <= clock.read_ns
    assert pacer.next_deadline_ns == T0 + 1000 * P


def test_sleep_stops_spin_ns_before_the_deadline():
    clock = FakeClock(read_ns=1_000, late_ns=60_000)
    pacer = make(clock, spin_ns=200_000)
    pacer.wait()
    clock.sleeps.clear()
    clock.work(100_000)
    pacer.wait()
    # After 100 us of work (+ clock reads) it sleeps until 200 us before the deadline...
    # Tick 0 returned one clock read after T0, the work took 100 us, wait() read once.
    remaining = P - clock.read_ns - 100_000 - clock.read_ns
    assert clock.sleeps == [pytest.approx((remaining - 200_000) * 1e-9)]
    # ...and then spins to it: several clock reads, returning right after the deadline.
    assert 0 <= pacer.lateness_ns <= clock.read_ns


def test_sleep_only_mode():
    clock = FakeClock(late_ns=0)
    pacer = make(clock, spin_ns=0)
    pacer.wait()
    clock.work(400_000)
    pacer.wait()
    assert len(clock.sleeps) == 1
    assert pacer.lateness_ns <= clock.read_ns


def test_no_drift_over_a_long_run_with_jittery_work():
    rng = np.random.default_rng(0)
    clock = FakeClock(read_ns=3_000, late_ns=80_000)
    pacer = make(clock)
    n = 200_000
    work = rng.integers(0, 900_000, size=n)
    for k in range(n):
        pacer.wait()
        assert pacer.deadline_ns == T0 + k * P
        clock.work(int(work[k]))
    # After 200 s of simulated wall time the deadline is still exactly t0 + n * period.
    assert pacer.next_deadline_ns == T0 + n * P
    assert pacer.skipped_ticks == 0 and pacer.lag_ns == 0
    stats = pacer.stats()
    assert stats.period_mean_us == pytest.approx(1000.0, abs=0.01)


def test_catch_up_after_a_stall_keeps_the_deadline_sequence():
    clock = FakeClock()
    pacer = make(clock, max_catchup_ticks=10)
    for _ in range(5):
        pacer.wait()
    clock.work(int(5.5 * P))  # tick 4 started at its deadline, then a 5.5 ms stall
    results = []
    for _ in range(12):
        results.append((pacer.deadline_index, pacer.wait(), pacer.catching_up))
        clock.work(10_000)
    indices = [r[0] for r in results]
    assert indices == list(range(5, 17)), "no deadline may be skipped during catch-up"
    late = [r for r in results if r[2]]
    # Ticks 5..9 fell due during the stall: returned back to back, each an overrun.
    assert [r[0] for r in late] == [5, 6, 7, 8, 9]
    assert late[0][1] > 4 * P and all(a[1] > b[1] for a, b in zip(late, late[1:], strict=False))
    assert not any(r[2] for r in results[5:])
    assert pacer.skipped_ticks == 0 and pacer.overruns == 1 + 5
    assert pacer.late_ticks == sum(1 for r in results if r[1] > P)


@pytest.mark.parametrize(("behind", "skips"), [(10, 0), (11, 11), (250, 250)])
def test_overrun_policy_boundary(behind, skips):
    """Up to max_catchup_ticks whole periods behind: catch up; beyond: skip them all."""
    clock = FakeClock(read_ns=0)
    pacer = make(clock, max_catchup_ticks=10, spin_ns=0)
    pacer.wait()  # tick 0, due at T0
    # Tick 1 is due at T0 + P; arrive `behind` whole periods (plus half) after it.
    clock.t = T0 + P + behind * P + P // 2
    lateness = pacer.wait()
    assert pacer.overruns == 1
    assert pacer.skipped_ticks == skips
    assert pacer.lag_ns == skips * P
    assert pacer.deadline_ns == T0 + (1 + skips) * P
    assert lateness == (behind - skips) * P + P // 2
    assert pacer.next_deadline_ns == pacer.deadline_ns + P
    assert pacer.ticks == 2 and pacer.deadline_index == 2 + skips


def test_sustained_overload_skips_and_counts():
    """Work of 1.5 periods per tick: behind grows, then the skip rule bounds it."""
    clock = FakeClock(read_ns=0)
    pacer = make(clock, max_catchup_ticks=20, spin_ns=0)
    max_behind = 0
    for _ in range(500):
        pacer.wait()
        max_behind = max(max_behind, pacer.lateness_ns // P)
        clock.work(3 * P // 2)
    assert pacer.skipped_ticks > 0
    assert max_behind <= 20
    assert pacer.deadline_index == pacer.ticks + pacer.skipped_ticks


def test_rebase_after_an_intended_stall():
    clock = FakeClock()
    pacer = make(clock, max_catchup_ticks=5)
    for _ in range(3):
        pacer.wait()
    overruns = pacer.overruns
    clock.work(2 * 1_000_000_000)  # a 2 s compile while paused
    pacer.rebase()
    pacer.wait()
    assert pacer.skipped_ticks == 0 and pacer.overruns == overruns + 1
    assert pacer.lateness_ns <= 2 * clock.read_ns
    for _ in range(5):
        pacer.wait()
    assert pacer.stats().period_max_us < 1100  # the 2 s gap is not a period sample


def test_statistics_window_and_percentiles():
    clock = FakeClock(read_ns=0, late_ns=0)
    pacer = make(clock, window=100, spin_ns=0, late_threshold_ns=500_000)
    pacer.wait()
    # 150 more ticks; the work before every 10th runs 700 us past its deadline.
    for k in range(1, 151):
        clock.work(P + 700_000 if k % 10 == 0 else 100_000)
        pacer.wait()
    s = pacer.stats()
    assert s.ticks == 151 and s.window_ticks == 100
    lat = pacer.lateness_window()
    assert len(lat) == 100
    assert sorted(set(lat.tolist())) == [0, 700_000] and int(np.sum(lat > 0)) == 10
    assert s.lateness_max_us == 700.0 and s.lateness_p50_us == 0.0
    assert s.lateness_p99_us == pytest.approx(np.percentile(lat, 99) / 1000)
    assert s.late_ticks == pacer.late_ticks == 15 and s.overruns == 15
    per = pacer.period_window()
    assert len(per) == 100
    assert s.period_max_us == 1700.0 and s.period_min_us == 300.0
    assert s.max_lateness_us == 700.0


@pytest.mark.parametrize("n", [1, 2, 3, 99, 100, 101, 4095, 4096])
def test_window_percentiles_equal_numpys_linear_percentiles(n):
    """The partition-based p50/p99/max of the diagnostics give np.percentile's values
    (linear interpolation between ranks; the only difference is float rounding)."""
    rng = np.random.default_rng(n)
    for samples in (rng.integers(-5_000, 10_000_000, n), np.full(n, 7), np.arange(n)[::-1]):
        p50, p99, top = window_percentiles(samples)
        np.testing.assert_allclose([p50, p99], np.percentile(samples, (50.0, 99.0)),
                                   rtol=1e-12, atol=1e-9)
        assert top == samples.max()


def test_late_ticks_threshold_counts_exactly():
    clock = FakeClock(read_ns=0)
    pacer = make(clock, spin_ns=0, late_threshold_ns=P, max_catchup_ticks=100)
    pacer.wait()
    clock.t = T0 + P + 3 * P + 1  # tick 1 arrives 3 ms + 1 ns late
    for _ in range(6):
        pacer.wait()
    # Lateness: tick1 3P+1, tick2 2P+1, tick3 P+1 (all > P), tick4 1 ns, then on time.
    assert pacer.late_ticks == 3
    assert pacer.max_lateness_ns == 3 * P + 1


def test_misuse_is_an_error():
    with pytest.raises(RuntimeError, match="start"):
        Pacer().wait()
    with pytest.raises(RuntimeError, match="start"):
        Pacer().rebase()
    for kw in ({"period_ns": 0}, {"spin_ns": -1}, {"max_catchup_ticks": -1}, {"window": 0}):
        with pytest.raises(ValueError, match=next(iter(kw))):
            Pacer(**kw)
    # the spin phase is bounded: a SCHED_FIFO thread never holds a core a whole period
    with pytest.raises(ValueError, match="at most half the period"):
        Pacer(P, spin_ns=P // 2 + 1)


def test_start_resets_everything():
    clock = FakeClock()
    pacer = make(clock)
    clock.work(500 * P)
    pacer.wait()
    assert pacer.skipped_ticks > 0
    pacer.start()
    assert (pacer.ticks, pacer.overruns, pacer.skipped_ticks, pacer.deadline_index) == (0, 0, 0, 0)
    assert pacer.stats().window_ticks == 0


def test_cpu_meter():
    wall = [0]
    cpu = [0]
    meter = CpuMeter(clock=lambda: wall[0], cpu_clock=lambda: cpu[0])
    wall[0], cpu[0] = 1_000_000, 130_000
    assert meter.percent() == pytest.approx(13.0)
    wall[0], cpu[0] = 2_000_000, 1_130_000
    assert meter.percent() == pytest.approx(100.0)
    assert meter.percent_total() == pytest.approx(56.5)
    assert meter.percent() == 0.0  # no wall time elapsed


def test_tick_trace_tells_a_ticks_own_cpu_from_a_wait(tmp_path):
    """The tick trace (SIMSERVER_TICK_TRACE) behind bench_load's split of late ticks: a
    tick that computes for 3 ms shows 3 ms of its thread's CPU time; one that waits 3 ms
    (a sleep: as the GIL or a lock would) shows it as wall time without CPU or run-queue
    wait, and the thread scheduled in again. Rows and the thread table are saved."""
    import json
    import time

    from simserver.server.realtime import TickTrace

    path = str(tmp_path / "ticks.npy")
    trace = TickTrace(path, capacity=64)
    pacer = Pacer(period_ns=5_000_000)  # room for 3 ms of work a tick
    pacer.start()
    for i in range(12):
        pacer.wait()
        trace.begin(pacer, pacer.deadline_ns + pacer.lateness_ns)
        if i == 5:
            end = time.thread_time_ns() + 3_000_000
            while time.thread_time_ns() < end:
                pass
        elif i == 8:
            time.sleep(0.003)
        trace.end()
    trace.save()
    rows = np.load(path)
    col = {name: rows[:, k] for k, name in enumerate(TickTrace.COLUMNS)}
    cpu = col["cpu_end"] - col["cpu_start"]
    wall = col["end"] - col["start"]
    delay = col["delay_end"] - col["delay_start"]
    assert rows.shape == (12, len(TickTrace.COLUMNS))
    assert cpu[5] >= 3_000_000 and wall[5] >= cpu[5]
    # CPU time and run-queue wait are read at different instants: 0.5 ms of slack
    assert wall[8] - cpu[8] - delay[8] >= 2_500_000 and cpu[8] < 1_000_000
    assert col["runs_end"][8] > col["runs_start"][8]
    assert np.all(col["start"][1:] > col["start"][:-1])
    assert np.all(col["start"] - col["deadline"] >= 0)
    threads = json.loads(open(path + ".threads.json").read())
    assert any(t["cpu_s"] > 0.003 for t in threads)
