"""The live server under client load: many state subscribers while clients join and leave;
and (``--hostile``) the loop while ``ctl/load`` and ``ctl/reset`` are prepared.

Run from the repository root::

    python -m benchmarks.bench_load [--seconds 30] [--subscribers 20] [--churn 10]
    python -m benchmarks.bench_load --hostile [--rounds 3]
    python -m benchmarks.bench_load --pieces [--rounds 5]
    python -m benchmarks.bench_load --latency [--seconds 8] [--rounds 2]

``--latency`` (issue 35 item 2): command-to-state latency p99 of the project's client
and of a client on zenoh's defaults, each without other clients (the baseline) and beside
the subscribers, one that never reads and the joins, with the ratio loaded / baseline
(``benchmarks.bench_cmd_latency``, which splits it by direction)::

    python -m benchmarks.bench_load --latency --seconds 8 --rounds 1 [--server-transport both]

``--hostile`` (issue 13: the loop never stalls more than 2 ms while a ``load`` is prepared;
issue 17: a ``reset`` with ``u_mps`` never makes a tick late): a driver at 1 kHz, a state
subscriber stamping every state's arrival, and per round, one after the other: a no-load
baseline window, then a ``load`` of a 10 MB scene, a YAML alias bomb, a deeply nested
file, a FIFO, two terrain scenes (OpenDRIVE, 6.6 and 18 MB of grids through shared memory)
and back, and ``reset`` at 1 and 20 m/s (2000 and 230 settling steps), each from its
request to its reply plus 0.1 s. Reports per action the largest gap between two states
received (the state stream, 1 kHz: 1 ms when nothing stalls) and the server's worst tick
lateness (its pacer) over the rounds, beside the baseline windows' (this VM stalls 1-6 ms
with nothing running: ``python -m benchmarks.bench_clock``), and whether every command
sent was received or counted.

Starts ``simserver serve`` (its default real-time scheduling) on a free loopback port, a
driver at 1 kHz, ``--subscribers`` state subscribers (each its own zenoh session, in one
process: ``simserver.testing.roles multisub``) that check every tick arrives, and
``--churn`` sessions a second joining (state subscription and a ``get_config``) and
leaving a second later (``roles churn``). Reports the server's late ticks (more than
1 ms after their deadline) and skipped deadlines over the loaded period (from its
diagnostics), the states each subscriber missed, and the joins answered.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from simserver.server.app import TICK_TRACE_ENV
from simserver.server.realtime import TickTrace
from simserver.testing import CONFIGS, Client, RoleProcess, ServerProcess, wait_until
from simserver.testing.hostile import hostile_files
from simserver.wire import protocol as proto


def run(seconds: float, subscribers: int, churn: float, realtime: str = "auto",
        trace: bool = True) -> dict:
    """One loaded run of ``seconds``; the figures (with ``trace``, also what made the late
    ticks late: :func:`late_tick_causes` of the server's :class:`TickTrace`)."""
    tmp = tempfile.TemporaryDirectory()
    trace_path = os.path.join(tmp.name, "ticks.npy")
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    if trace:
        env[TICK_TRACE_ENV] = trace_path
    with tmp, ServerProcess(scene=None, log_level="WARNING", env=env,
                            extra_args=["--realtime", realtime]) as server, \
            Client(server, state_capacity=0) as probe:
        conn = server.client_args()
        driver = RoleProcess("driver", [*conn, "--rate", "1000"])
        subs = RoleProcess("multisub", [*conn, "--sessions", str(subscribers)])
        d0 = probe.diagnostics()
        p0 = time.perf_counter_ns()  # CLOCK_MONOTONIC: the server's trace's clock too
        churner = RoleProcess("churn", [*conn, "--rate", str(churn), "--life", "1.0",
                                        "--seconds", str(seconds)])
        churned = churner.wait(seconds + 60)
        p1 = time.perf_counter_ns()
        d1 = probe.diagnostics(timeout_s=30.0)  # a loaded machine: 5 s was seen to pass
        subs_result = subs.stop()
        driver.stop()
        server.stop()
        causes = threads = None
        if trace and os.path.exists(trace_path + ".threads.json"):
            rows = np.load(trace_path)
            start = rows[:, TickTrace.COLUMNS.index("start")]
            inside = np.flatnonzero((start >= p0) & (start <= p1))
            causes = late_tick_causes(rows[inside], int(inside[0]) if inside.size else 0)
            with open(trace_path + ".threads.json", encoding="utf-8") as fh:
                threads = json.load(fh)
    final = server.final_stats()
    ticks = int(d1["tick"] - d0["tick"])
    sender_dropped = 0  # the server's state-tx queue (logged, also in publish_slow)
    for line in server.output:
        if "state-tx: " in line and "publications dropped" in line:
            sender_dropped = int(line.split("state-tx: ")[1].split()[0])

    def delta(name: str) -> int:
        return int(d1[name] - d0[name])

    return {"seconds": seconds, "subscribers": subscribers, "churn_per_s": churn,
            "realtime": realtime, "ticks": ticks, "late_ticks": delta("late_ticks"),
            "late_fraction": delta("late_ticks") / max(ticks, 1),
            "skipped_ticks": delta("skipped_ticks"), "lateness_max_us": float(
                d1["lateness_max_us"]), "publish_slow": delta("publish_slow"),
            "cmd_dropped": delta("cmd_dropped"), "ctl_busy": delta("ctl_busy"),
            "joined": churned["joined"] if churned else 0,
            "config_ok": churned["config_ok"] if churned else 0,
            "subscriber_missing_total": subs_result["missing_total"] if subs_result else None,
            "subscriber_states_min": subs_result["states_min"] if subs_result else None,
            "server_final": final, "sender_dropped": sender_dropped, "late_causes": causes,
            # over the whole server run: states the tick put itself, hand-offs to state-tx
            "publish_inline_puts": final.get("publish_inline_puts", 0),
            "publish_handoffs": final.get("publish_handoffs", 0),
            "threads": threads,
            "loadavg_1min": os.getloadavg()[0],
            "finished": time.strftime("%Y-%m-%d %H:%M:%S")}


LATE_NS = 1_000_000
CAUSES = ("work CPU", "work run-queue wait", "work blocked", "work in GC",
          "sleep overshoot run-queue wait", "sleep overshoot blocked", "spin preempted")


def late_tick_causes(rows: np.ndarray, first_index: int = 0) -> dict:
    """Where the time went in the episodes of late ticks of a :class:`TickTrace`.

    An episode is a run of ticks more than 1 ms late; it starts with the tick before it
    (whose work or whose wait made the first one late) and ends with its last late tick.
    Its time is split into the tick thread's own CPU time during the ticks' work, its
    run-queue wait (runnable, not running: other threads or processes on its core), the
    time it was blocked during work (the GIL, a lock; or not counted at all: a stall of
    the VM's vCPU, when it was never switched out), garbage collection, and in the
    pacer's wait the sleep's overshoot past its end (run-queue wait, or blocked: the GIL
    after the sleep, a late timer, the VM; ``extra_wakes`` counts the times the thread was
    scheduled in during the waits beyond once per sleep: 0 means no wait for the GIL or a
    lock, so a blocked overshoot was the timer or the VM). Returns the episodes, the
    totals per cause in ms and the count of episodes each cause dominated, and the ticks of
    most CPU (their loop count: ``first_index`` is the first row's).
    """
    c = {name: rows[:, i].astype(np.int64) for i, name in enumerate(TickTrace.COLUMNS)}
    late = (c["start"] - c["deadline"]) > LATE_NS
    totals = dict.fromkeys(CAUSES, 0.0)
    dominated = dict.fromkeys(CAUSES, 0)
    episodes = []
    i, n = 1, len(rows)
    while i < n:
        if not late[i] or late[i - 1]:
            i += 1
            continue
        j = i
        while j + 1 < n and late[j + 1]:
            j += 1
        part = dict.fromkeys(CAUSES, 0.0)
        switched_out = 0
        extra_wakes = 0  # in the waits, beyond the sleep's own: the GIL, a lock
        for k in range(i - 1, j + 1):  # the work of ticks i-1 .. j-1 and the waits before i..j
            if k < j:
                wall = c["end"][k] - c["start"][k]
                cpu = c["cpu_end"][k] - c["cpu_start"][k]
                delay = c["delay_end"][k] - c["delay_start"][k]
                gc_ns = c["gc"][k] - (c["gc"][k - 1] if k else 0)
                part["work CPU"] += cpu - gc_ns
                part["work in GC"] += gc_ns
                part["work run-queue wait"] += delay
                part["work blocked"] += max(wall - cpu - delay, 0)
                switched_out += int(c["runs_end"][k] - c["runs_start"][k])
            if k >= i and c["sleep_until"][k] and c["end"][k - 1] < c["deadline"][k]:
                over = max(c["woke"][k] - c["sleep_until"][k], 0)
                delay = c["delay_start"][k] - c["delay_end"][k - 1]
                part["sleep overshoot run-queue wait"] += min(delay, over)
                part["sleep overshoot blocked"] += max(over - delay, 0)
                extra_wakes += max(int(c["runs_start"][k] - c["runs_end"][k - 1]) - 1, 0)
            elif k >= i and c["end"][k - 1] < c["deadline"][k]:
                part["spin preempted"] += c["delay_start"][k] - c["delay_end"][k - 1]
        part = {k: v / 1e6 for k, v in part.items()}
        for k, v in part.items():
            totals[k] += v
        dominated[max(part, key=part.get)] += 1
        episodes.append({"first": i, "ticks": j - i + 1,
                         "lateness_ms": float(c["start"][i] - c["deadline"][i]) / 1e6,
                         "switched_out": switched_out, "extra_wakes": extra_wakes, **part})
        i = j + 1
    work_cpu = (c["cpu_end"] - c["cpu_start"]) / 1e3
    heaviest = np.argsort(work_cpu)[::-1][:8]
    return {"heaviest_ticks": [(int(k) + first_index, float(work_cpu[k])) for k in heaviest],
            "ticks": n, "late": int(late.sum()), "episodes": episodes,
            "totals_ms": totals, "dominated": dominated,
            "work_cpu_us_p50_p99_max": [float(np.percentile(work_cpu, 50)),
                                        float(np.percentile(work_cpu, 99)),
                                        float(work_cpu.max())] if n else [],
            "gc_ms_total": float(c["gc"][-1] - c["gc"][0]) / 1e6 if n else 0.0}


def print_causes(r: dict) -> None:
    """The late-tick causes and the server's busiest threads."""
    lc = r.get("late_causes")
    if lc:
        print(f"tick trace: {lc['late']} late ticks of {lc['ticks']} in "
              f"{len(lc['episodes'])} episodes; tick work CPU us p50/p99/max "
              + "/".join(f"{v:.0f}" for v in lc["work_cpu_us_p50_p99_max"])
              + f"; GC {lc['gc_ms_total']:.1f} ms in all")
        print("  time in the late episodes by cause, ms (episodes it dominated): " + "; ".join(
            f"{k} {v:.1f} ({lc['dominated'][k]})" for k, v in lc["totals_ms"].items() if v))
        print("  heaviest ticks (loop count: work CPU us): " + ", ".join(
            f"{k}: {v:.0f}" for k, v in lc["heaviest_ticks"]))
        worst = sorted(lc["episodes"], key=lambda e: -e["lateness_ms"])[:5]
        for e in worst:
            print(f"  episode at tick {e['first']}: {e['ticks']} late, first "
                  f"{e['lateness_ms']:.2f} ms, switched out in work {e['switched_out']}x, "
                  f"woken beyond the sleeps {e['extra_wakes']}x: " + ", ".join(
                      f"{k} {e[k]:.2f}" for k in CAUSES if e[k] >= 0.01))
    threads = r.get("threads")
    if threads:
        busiest = sorted(threads, key=lambda t: -t["cpu_s"])[:8]
        print("  server threads (CPU s / run-queue wait s, whole run): " + "; ".join(
            f"{t['name']} {t['policy'][6:]}{t['priority'] or ''} {t['cpu_s']:.1f}/"
            f"{t['run_delay_s']:.2f}" for t in busiest))


class ClockPeer:
    """The bare pacer (``benchmarks.bench_clock --realtime auto``, scheduled as the server's
    tick thread) in a process of its own beside a run: a stall of the whole VM delays it
    too, the server's own work does not (it costs it at most a share of the other core)."""

    def __init__(self, path: str) -> None:
        import subprocess
        import sys

        from simserver.testing import REPO

        self.path = path
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "benchmarks.bench_clock", "--seconds", "36000",
             "--realtime", "auto", "--save", path], cwd=REPO,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def stop(self) -> np.ndarray:
        """End it (SIGINT: it saves its ticks' start times); those start times."""
        import signal

        self.proc.send_signal(signal.SIGINT)
        self.proc.wait(timeout=60)
        return np.load(self.path)


def stall_split(rows: np.ndarray, peer: np.ndarray, t0: int, t1: int) -> dict:
    """The loop's stalls in ``[t0, t1]`` (CLOCK_MONOTONIC ns) split by whose they are.

    From the server's :class:`TickTrace` rows: ``tick_gap_ms``, the longest time between
    two tick starts (the state stream's gap without the transport and the subscriber);
    per tick ``own_ms``, the tick thread's CPU time in its work plus the time it waited
    for the GIL or a lock of the server's own threads (blocked after being switched out,
    in the work or beyond the pacer's sleep; each part's largest: ``own_cpu_ms``,
    ``own_wait_ms``); ``others_ms``, its run-queue wait (other
    processes at its priority or above: the server's own threads run below it); and
    ``vm_ms``, the rest of the stalls: blocked while never switched out (the vCPU not
    running) and sleeps that returned late with no other wake-up (a late timer or the VM).
    ``peer_ms``: the bare pacer's largest lateness in the same window (:class:`ClockPeer`):
    a stall there too is the VM's. The largest of each, in milliseconds."""
    c = {name: rows[:, i].astype(np.int64) for i, name in enumerate(TickTrace.COLUMNS)}
    inside = np.flatnonzero((c["start"] >= t0) & (c["start"] <= t1))
    out = {"tick_gap_ms": np.nan, "own_ms": np.nan, "own_cpu_ms": np.nan,
           "own_wait_ms": np.nan, "others_ms": np.nan, "vm_ms": np.nan, "peer_ms": np.nan}
    if inside.size > 1:
        k = inside[inside > 0]
        gap = c["start"][k] - c["start"][k - 1]
        wall = c["end"][k] - c["start"][k]
        cpu = c["cpu_end"][k] - c["cpu_start"][k]
        delay = c["delay_end"][k] - c["delay_start"][k]
        blocked = np.maximum(wall - cpu - delay, 0)
        switched = (c["runs_end"][k] - c["runs_start"][k]) > 0
        slept = c["sleep_until"][k] > 0
        over = np.where(slept, np.maximum(c["woke"][k] - c["sleep_until"][k], 0), 0)
        wait_delay = c["delay_start"][k] - c["delay_end"][k - 1]
        over_blocked = np.maximum(over - wait_delay, 0)
        extra = (c["runs_start"][k] - c["runs_end"][k - 1]) > 1
        own_wait = np.where(switched, blocked, 0) + np.where(extra, over_blocked, 0)
        own = cpu + own_wait
        vm = np.where(switched, 0, blocked) + np.where(extra, 0, over_blocked)
        out.update(tick_gap_ms=gap.max() / 1e6, own_ms=own.max() / 1e6,
                   own_cpu_ms=cpu.max() / 1e6, own_wait_ms=own_wait.max() / 1e6,
                   others_ms=(delay + wait_delay).max() / 1e6, vm_ms=vm.max() / 1e6)
    if peer.size > 1:
        p = peer[(peer >= t0) & (peer <= t1)]
        if p.size > 1:
            out["peer_ms"] = float(np.diff(p).max() - 1_000_000) / 1e6
    return {k: float(v) for k, v in out.items()}


class StampedStates:
    """A state subscriber that stamps each arrival (``perf_counter_ns``) with its tick."""

    def __init__(self, client: Client) -> None:
        self.lock = threading.Lock()
        self.stamps: list[tuple[int, int]] = []
        self.sub = client.ep.session.declare_subscriber(client.ep.keys.state, self._on)

    def _on(self, sample) -> None:
        now = time.perf_counter_ns()
        tick = int(proto.decode_state(bytes(sample.payload))["tick"])
        with self.lock:
            self.stamps.append((now, tick))

    def largest_gap_ms(self, t0_ns: int, t1_ns: int) -> float:
        """The longest time between two states received in ``[t0_ns, t1_ns]``."""
        with self.lock:
            times = np.array([t for t, _ in self.stamps if t0_ns <= t <= t1_ns], dtype=np.int64)
        return float(np.diff(times).max()) / 1e6 if len(times) > 1 else float("nan")


HOSTILE_ACTIONS: tuple[tuple[str, str, dict], ...] = (
    ("load 10 MB scene", "load", {"scene": "big"}),
    ("load alias bomb", "load", {"scene": "bomb"}),
    ("load deep nesting", "load", {"scene": "deep"}),
    ("load FIFO", "load", {"scene": "fifo"}),
    ("load OpenDRIVE crest (6.6 MB grids)", "load",
     {"scene": "scenes/crest_curve_paper_sedan.yaml"}),
    ("load OpenDRIVE velodrome (18 MB grids)", "load",
     {"scene": "scenes/velodrome_paper_sedan.yaml"}),
    ("load flat", "load", {"scene": "scenes/flat_paper_sedan.yaml"}),
    ("reset u_mps 1 (2000 settling steps)", "reset", {"u_mps": 1.0}),
    ("reset u_mps 20 (230 settling steps)", "reset", {"u_mps": 20.0}),
)


def hostile(rounds: int = 3, baseline_s: float = 1.0, realtime: str = "auto") -> dict:
    """The loop during hostile loads and resets at speed against no-load baselines."""
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        files = hostile_files(tmp)
        cfg = tmp / "server.yaml"
        cfg.write_text(f"scene: {CONFIGS / 'scenes' / 'flat_paper_sedan.yaml'}\n"
                       f"config_dirs: [{tmp}, {CONFIGS}]\nviewer: off\n", encoding="utf-8")
        per: dict[str, dict[str, list]] = {}
        windows_ns: list[tuple[str, int, int, int]] = []  # label, baseline from, to, end
        trace_path = str(tmp / "ticks.npy")
        env = dict(os.environ, PYTHONUNBUFFERED="1", **{TICK_TRACE_ENV: trace_path})
        with ServerProcess(config=cfg, scene=None, log_level="WARNING", env=env,
                           extra_args=["--realtime", realtime]) as server, \
                Client(server, state_capacity=0) as client:
            stamps = StampedStates(client)
            peer = ClockPeer(str(tmp / "peer.npy"))
            driver = None
            try:
                driver = RoleProcess("driver", [*server.client_args(), "--rate", "1000",
                                                "--profile", "throttle:0.2"])
                wait_until(lambda: len(stamps.stamps) > 100, what="the state stream")
                for _ in range(rounds):
                    for label, name, args in HOSTILE_ACTIONS:
                        args = {k: str(files.get(v, v)) if k == "scene" else v
                                for k, v in args.items()}
                        d0 = client.diagnostics()
                        b0 = time.perf_counter_ns()
                        time.sleep(baseline_s)  # the no-load baseline just before
                        b1 = time.perf_counter_ns()
                        client.diag.drain_newest()
                        reply = client.request(name, args, timeout_s=30.0)
                        time.sleep(0.1)
                        t1 = time.perf_counter_ns()
                        windows = [proto.decode_diagnostics(p)
                                   for p in client.diag.drain_newest()]
                        d1 = client.diagnostics()
                        windows.append(d1)
                        entry = per.setdefault(label, {"gap_ms": [], "base_gap_ms": [],
                                                       "lateness_ms": [], "ok": [],
                                                       "took_s": [], "error": []})
                        entry["gap_ms"].append(stamps.largest_gap_ms(b1, t1))
                        entry["base_gap_ms"].append(stamps.largest_gap_ms(b0, b1))
                        entry["lateness_ms"].append(
                            max(float(w["lateness_max_us"]) for w in windows) / 1e3)
                        entry["ok"].append(bool(reply["ok"]))
                        entry["took_s"].append((t1 - b1) / 1e9 - 0.1)
                        entry["error"].append(reply.get("error", ""))
                        entry.setdefault("skipped", []).append(
                            int(d1["skipped_ticks"] - d0["skipped_ticks"]))
                        windows_ns.append((label, b0, b1, t1))
                sent = driver.stop()
            finally:
                if driver is not None:
                    driver.kill()
                server.stop()
                peer_starts = peer.stop()
        final = server.final_stats()
        rows = np.load(trace_path)
        for label, b0, b1, t1 in windows_ns:
            entry = per[label]
            for key, value in stall_split(rows, peer_starts, b1, t1).items():
                entry.setdefault(key, []).append(value)
            for key, value in stall_split(rows, peer_starts, b0, b1).items():
                entry.setdefault("base_" + key, []).append(value)
    all_base = [g for e in per.values() for g in e["base_gap_ms"]]
    base_split = {k: [v for e in per.values() for v in e["base_" + k]]
                  for k in ("tick_gap_ms", "own_ms", "own_cpu_ms", "own_wait_ms",
                            "others_ms", "vm_ms", "peer_ms")}
    return {"rounds": rounds, "actions": per, "baseline_gap_ms": all_base,
            "baseline_split": base_split,
            "cmd_sent": sent["sent"] if sent else None,
            "cmd_received": final["cmd_received"], "cmd_dropped": final["cmd_dropped"],
            "loadavg_1min": os.getloadavg()[0], "finished": time.strftime("%Y-%m-%d %H:%M:%S")}


PIECE_SCENES = ("scenes/velodrome_paper_sedan.yaml", "scenes/flat_paper_sedan.yaml",
                "scenes/crest_curve_paper_sedan.yaml", "scenes/hills_paper_sedan.yaml")


def pieces(rounds: int = 5) -> dict:
    """Per-tick work of a load (each scene of ``PIECE_SCENES``) and of a reset at 1 and
    20 m/s, in microseconds: ``{label: {piece: [per round]}}``."""
    from simserver.server.app import new_simulation
    from simserver.server.config import load_server_config
    from simserver.server.load_worker import ProcessPreparer, opened
    from simserver.server.loop import SETTLE_STEPS_PER_TICK
    from simserver.server.slot import VehicleSlot, unwrap_prepared
    from simserver.sim.scene import load_scene

    cfg = load_server_config(CONFIGS / "server" / "default.yaml", viewer="off")
    slot = VehicleSlot(cfg, new_simulation(load_scene(cfg.scene), cfg.period_s))
    slot.warm_up()
    gc.collect()  # as the server's loop does before its clock starts (ServerLoop.start)
    gc.freeze()
    clock = time.thread_time_ns  # the work itself: CPU time, not the VM's stalls
    out: dict[str, dict[str, list[float]]] = {}

    def settle(staged, row: dict[str, list[float]]) -> None:
        longest = 0
        while True:
            t = clock()
            done = staged.advance(SETTLE_STEPS_PER_TICK)
            longest = max(longest, clock() - t)
            if done:
                break
        row.setdefault("settle piece (max)", []).append(longest / 1e3)
        t = clock()
        staged.commit()
        row.setdefault("commit", []).append((clock() - t) / 1e3)

    preparer = ProcessPreparer()
    try:
        for _ in range(rounds):
            for scene in PIECE_SCENES:
                fn, args = slot.load_job({"scene": scene})
                result = preparer.submit(fn, *args).result(timeout=120)
                row = out.setdefault(f"load {scene}", {})
                t0 = clock()
                value = opened(result)
                t1 = clock()
                staged = slot.apply_load(unwrap_prepared(value))
                t2 = clock()
                del value
                row.setdefault("map result", []).append((t1 - t0) / 1e3)
                row.setdefault("build", []).append((t2 - t1) / 1e3)
                settle(staged, row)
                for _ in range(100):
                    slot.sim.step()
            for u_mps in (1.0, 20.0):
                row = out.setdefault(f"reset u_mps {u_mps:g}", {})
                t0 = clock()
                staged = slot.begin_reset({"u_mps": u_mps})
                row.setdefault("build", []).append((clock() - t0) / 1e3)
                settle(staged, row)
    finally:
        preparer.close()
    return out


def print_pieces(out: dict) -> None:
    """The figures of :func:`pieces`."""
    print("per-tick work of a load / reset in the server (thread CPU time, us, median [max] "
          "over the rounds)")
    for label, row in out.items():
        print(f"{label:42s} " + "; ".join(
            f"{name} {np.median(v):.0f} [{max(v):.0f}]" for name, v in row.items()))


def print_hostile(r: dict) -> None:
    """The figures of :func:`hostile`."""
    base = np.array(r["baseline_gap_ms"])
    print(f"hostile loads and resets at speed, {r['rounds']} rounds, driver at 1 kHz, load "
          f"average {r['loadavg_1min']:.2f}; largest gap between two states received, ms")
    print(f"no-load baseline windows (1 s each, {len(base)}): p50 "
          f"{np.nanpercentile(base, 50):.2f}, p90 {np.nanpercentile(base, 90):.2f}, max "
          f"{np.nanmax(base):.2f}")
    bs = r.get("baseline_split")
    if bs:
        print("  baseline windows, max: " + ", ".join(
            f"{k[:-3]} {np.nanmax(v):.2f}" for k, v in bs.items()))
    for label, e in r["actions"].items():
        gaps = np.array(e["gap_ms"])
        print(f"{label:42s} gap max {np.nanmax(gaps):6.2f} (median of rounds "
              f"{np.nanmedian(gaps):5.2f}); baseline before it {np.nanmax(e['base_gap_ms']):5.2f}; "
              f"tick lateness max {max(e['lateness_ms']):5.2f}; skipped {sum(e['skipped'])}; "
              f"answered in {max(e['took_s']):.3f} s; "
              + ("ok" if all(e["ok"]) else f"error: {e['error'][0]}"))
        if "own_ms" in e:
            print(f"{'':42s} split (max over rounds, ms): tick-start gap "
                  f"{np.nanmax(e['tick_gap_ms']):5.2f}, the server's own "
                  f"{np.nanmax(e['own_ms']):5.2f} (CPU {np.nanmax(e['own_cpu_ms']):5.2f}, "
                  f"waits {np.nanmax(e['own_wait_ms']):5.2f}), run-queue wait "
                  f"{np.nanmax(e['others_ms']):5.2f}, VM {np.nanmax(e['vm_ms']):5.2f}; "
                  f"clock-floor peer {np.nanmax(e['peer_ms']):5.2f}")
    print(f"commands: {r['cmd_sent']} sent, {r['cmd_received']} received + "
          f"{r['cmd_dropped']} counted as dropped")


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--subscribers", type=int, default=20)
    parser.add_argument("--churn", type=float, default=10.0, help="joins per second")
    parser.add_argument("--realtime", default="auto", choices=("auto", "off"))
    parser.add_argument("--hostile", action="store_true",
                        help="the loop during hostile loads and resets at speed instead")
    parser.add_argument("--pieces", action="store_true",
                        help="the per-tick work of loads and resets, in-process, instead")
    parser.add_argument("--rounds", type=int, default=None,
                        help="with --hostile (default 3), --pieces (default 5) or "
                        "--latency (default 2)")
    parser.add_argument("--latency", action="store_true",
                        help="command-to-state latency of the project's client and of one "
                        "on zenoh's defaults, without other clients and beside the "
                        "subscribers, a slow one and the joins, instead "
                        "(benchmarks.bench_cmd_latency; --seconds per window)")
    parser.add_argument("--server-transport", default="default",
                        choices=("default", "lowlatency", "normal", "both"),
                        help="with --latency: the server's zenoh transport "
                        "(benchmarks.bench_cmd_latency --server-transport)")
    args = parser.parse_args(argv)
    if args.latency:
        from benchmarks import bench_cmd_latency

        transports = (("lowlatency", "normal") if args.server_transport == "both"
                      else (args.server_transport,))
        r = bench_cmd_latency.run(args.seconds, args.rounds or 2, args.subscribers,
                                  args.churn, 200.0, True, transports)
        bench_cmd_latency.print_summary(r)  # its last line: the rounds and load average
        return r
    if args.pieces:
        r = pieces(args.rounds or 5)
        print_pieces(r)
        return r
    if args.hostile:
        r = hostile(args.rounds or 3, realtime=args.realtime)
        print_hostile(r)
        return r
    r = run(args.seconds, args.subscribers, args.churn, args.realtime)
    print(f"load run {r['seconds']:.0f} s: {r['subscribers']} state subscribers, "
          f"{r['churn_per_s']:g} clients joining and leaving per second ({r['joined']} "
          f"joined, {r['config_ok']} get_config answered), driver at 1 kHz, server "
          f"realtime {r['realtime']}, load average {r['loadavg_1min']:.2f}")
    print(f"ticks > 1 ms late: {r['late_ticks']} of {r['ticks']} "
          f"({100 * r['late_fraction']:.2f} %), skipped {r['skipped_ticks']}, max lateness "
          f"(last window) {r['lateness_max_us'] / 1e3:.2f} ms; slow publications "
          f"{r['publish_slow']}")
    print(f"states missed by the {r['subscribers']} subscribers: "
          f"{r['subscriber_missing_total']} (fewest received by one: "
          f"{r['subscriber_states_min']}); commands dropped {r['cmd_dropped']}; dropped "
          f"by the server's sender queue (at least) {r['sender_dropped']}")
    print(f"states put in the tick (the rest by its state-tx thread), whole server run: "
          f"{r['publish_inline_puts']}; hand-offs to the thread {r['publish_handoffs']}")
    print_causes(r)
    return r


if __name__ == "__main__":
    main()
