"""The live loop with several cars in one world: late ticks and command-to-state latency.

Run from the repository root::

    python -m benchmarks.bench_multicar [--cars 1,8,32] [--seconds 20] [--hogs 2]

For each car count ``n`` it writes a server config of ``n`` cars on the flat
(``configs/server/two_cars.yaml``'s form, ``simserver.server.fleet``): ``car0`` and ``car1``
driven over zenoh by this process, the others driven by keyframes (traffic creeping in D
at a light throttle, each in its own lane), and starts ``simserver serve`` on it (its own
process, the default real-time scheduling; the world message at its default 100 Hz). This
process drives both cars at ``--cmd-hz`` each, every command sent at a random instant of
its slot (as ``benchmarks.bench_server``), and times, per driven car, the first state of
that car that reflects each command (arrivals stamped in zenoh's receiving thread). The
tick figures are the server's: its ticks more than 1 ms late over the whole run (its
``stopped`` line) and the median over its 4096-tick diagnostics windows of their p99
lateness. ``--hogs N`` runs N CPU-bound processes beside it.

The runs of the car counts alternate in ``--rounds`` rounds (1, 8, 32, 1, 8, 32, ...) so
that the VM's own stalls spread over all counts; each figure is quoted per round. The
figures of a shared machine are noisy: compare the counts within one run.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections import deque
from pathlib import Path

import numpy as np
import zenoh

from benchmarks.bench_server import TICK_S, cpu_hogs
from simserver.testing import REPO, Client, ServerProcess
from simserver.wire import protocol as proto

FLAT = REPO / "configs" / "scenes" / "flat_paper_sedan.yaml"
DRIVEN = ("car0", "car1")
LANE_M = 4.0  # lateral spacing of the cars' lanes
GAP_M = 12.0  # spacing along a lane


def write_config(folder: Path, n_cars: int) -> Path:
    """A server config of ``n_cars`` on the flat: ``car0``, ``car1`` driven by clients, the
    rest by a creeping keyframe track; four lanes, the cars ``GAP_M`` apart in each."""
    creep = folder / "creep.yaml"
    creep.write_text("name: creep\nduration_s: 600\ninputs:\n"
                     "  - {t: 0.0, gear: D, throttle: 0.08, brake: 0.0}\n")
    cars = []
    for k in range(n_cars):
        car_id = DRIVEN[k] if k < len(DRIVEN) else f"traffic{k}"
        entry = {"id": car_id, "pose": {"x_m": GAP_M * (k // 4), "y_m": LANE_M * (k % 4),
                                        "yaw_rad": 0.0}}
        if k >= len(DRIVEN):
            entry |= {"driven_by": "keyframes", "keyframes": str(creep)}
        cars.append(entry)
    path = folder / f"cars{n_cars}.yaml"
    path.write_text(json.dumps({"scene": str(FLAT), "max_cars": max(32, n_cars),
                                "cars": cars}))
    return path


def run_once(n_cars: int, seconds: float, cmd_hz: float, folder: Path) -> dict:
    """One server of ``n_cars`` for ``seconds``: the tick figures and, per driven car, the
    command-to-state latency."""
    config = write_config(folder, n_cars)
    server = ServerProcess(scene=None, config=config, ready_timeout_s=300.0)
    try:
        return _measure(server, n_cars, seconds, cmd_hz)
    finally:
        server.stop()


def _measure(server: ServerProcess, n_cars: int, seconds: float, cmd_hz: float) -> dict:
    from simserver.server.realtime import RealtimeScheduler, RealtimeSettings

    client_rt = RealtimeScheduler(RealtimeSettings(mode="auto", priority=40,
                                                   cpu_latency_us=None))
    driven = DRIVEN[:min(n_cars, len(DRIVEN))]
    clients = {c: Client(server, vehicle_id=c, state_capacity=0) for c in driven}
    arrivals: dict[str, deque] = {c: deque() for c in driven}
    subs = []
    latencies: dict[str, list[float]] = {c: [] for c in driven}
    sent: dict[str, dict[int, int]] = {c: {} for c in driven}
    seqs = dict.fromkeys(driven, 0)
    diags: list[np.void] = []
    try:
        for car, client in clients.items():
            queue = arrivals[car]

            def on_state(sample, queue=queue) -> None:  # zenoh's thread: stamp first
                queue.append((time.monotonic_ns(), sample.payload.to_bytes()))

            subs.append(client.ep.session.declare_subscriber(
                client.ep.keys.state, zenoh.handlers.Callback(on_state, indirect=False)))
        client_rt.apply()
        rng = np.random.default_rng(11)
        period = 1.0 / cmd_hz
        t0 = time.monotonic()
        next_at = {c: t0 + rng.uniform(0.0, TICK_S) for c in driven}
        slot = dict.fromkeys(driven, t0)
        t_end = t0 + seconds
        promote_at = t0 + 1.0
        while time.monotonic() < t_end:
            now = time.monotonic()
            for car, client in clients.items():
                if now >= next_at[car]:
                    seqs[car] += 1
                    t_ns = time.monotonic_ns()
                    sent[car][seqs[car]] = t_ns
                    phase = now % 20.0
                    client.pub.put(proto.encode_command(
                        steer=0.05 * np.sin(phase / 3.0), throttle=0.15, gear=proto.Gear.D,
                        seq=seqs[car], sender_time_ns=t_ns))
                    slot[car] += period
                    next_at[car] = slot[car] + rng.uniform(0.0, TICK_S)
                queue = arrivals[car]
                while queue:
                    t_rx, payload = queue.popleft()
                    s = int(proto.decode_state(payload)["last_cmd_seq"])
                    if s in sent[car]:
                        latencies[car].append((t_rx - sent[car].pop(s)) / 1e3)
            for payload in clients[driven[0]].diag.drain_newest():
                diags.append(proto.decode_diagnostics(payload))
            time.sleep(0.0005)
            if now >= promote_at:
                promote_at = now + 1.0
                client_rt.promote_new_threads()
    finally:
        for sub in subs:
            sub.undeclare()
        for client in clients.values():
            client.close()
        client_rt.release()
    server.stop()
    final = server.final_stats()
    timing = final if "ticks" in final else {**final, **next(iter(final["vehicles"].values()))}
    windows = [d for d in diags if int(d["window_ticks"]) >= 4096] or diags[-1:]
    out = {"cars": n_cars, "seconds": seconds, "ticks": timing["ticks"],
           "late_ticks": final["late_ticks"],
           "late_fraction": final["late_ticks"] / max(timing["ticks"], 1),
           "skipped_ticks": final["skipped_ticks"],
           "lateness_p99_us": float(np.median([w["lateness_p99_us"] for w in windows]))
           if windows else float("nan"),
           "cpu_percent": float(np.median([d["cpu_percent"] for d in diags]))
           if diags else float("nan"),
           "loadavg_1min": os.getloadavg()[0]}
    for car in driven:
        lat = np.array(latencies[car])
        out[f"{car}_latency_p50_us"] = float(np.percentile(lat, 50)) if lat.size else None
        out[f"{car}_latency_p99_us"] = float(np.percentile(lat, 99)) if lat.size else None
        out[f"{car}_commands_acknowledged"] = int(lat.size)
    return out


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cars", default="1,8,32",
                        help="car counts, comma-separated (default 1,8,32)")
    parser.add_argument("--seconds", type=float, default=20.0, help="per run (default 20)")
    parser.add_argument("--rounds", type=int, default=1, help="rounds over the counts")
    parser.add_argument("--cmd-hz", type=float, default=200.0, help="per driven car")
    parser.add_argument("--hogs", type=int, default=0,
                        help="CPU-bound processes at normal priority during the runs")
    parser.add_argument("--json", action="store_true", help="one JSON line per run")
    args = parser.parse_args(argv)
    counts = [int(c) for c in args.cars.split(",")]
    results = []
    with tempfile.TemporaryDirectory() as tmp, cpu_hogs(args.hogs):
        for r in range(args.rounds):
            for n in counts:
                res = run_once(n, args.seconds, args.cmd_hz, Path(tmp)) | {
                    "round": r, "hogs": args.hogs}
                results.append(res)
                if args.json:
                    print(json.dumps(res), flush=True)
                    continue
                lat = "; ".join(
                    f"{c} command-to-state p50 {res[f'{c}_latency_p50_us']:.0f} us, p99 "
                    f"{res[f'{c}_latency_p99_us']:.0f} us ({res[f'{c}_commands_acknowledged']}"
                    " commands)" for c in DRIVEN[:min(n, 2)])
                print(f"round {r}: {n:2d} cars, {args.hogs} hogs, {res['ticks']} ticks: "
                      f"{100 * res['late_fraction']:.2f} % > 1 ms late, lateness p99 "
                      f"{res['lateness_p99_us']:.0f} us, skipped {res['skipped_ticks']}, "
                      f"server CPU {res['cpu_percent']:.0f} %, load {res['loadavg_1min']:.1f}"
                      f" | {lat}", flush=True)
    return results


if __name__ == "__main__":
    main(sys.argv[1:])
