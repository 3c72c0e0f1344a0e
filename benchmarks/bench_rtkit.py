"""Real time without root (issue 35 item 1): the tick's lateness beside CPU hogs for a
server run as root, as an ordinary user with RealtimeKit, with CAP_SYS_NICE, and with
nothing.

Run from the repository root, as root (it starts a system bus, polkitd and
rtkit-daemon of its own, ``simserver.testing.rtkit_bus``, and an unprivileged user)::

    python -m benchmarks.bench_rtkit [--seconds 20] [--rounds 2] [--hogs 2]

``--hogs N`` CPU-bound processes run at normal priority for the whole benchmark (a busy
machine). Each round starts ``simserver serve`` (no client: the tick's own timing) once
in each set-up, interleaved, for ``--seconds`` wall seconds after it is ready:

- ``root``: as root, as shipped (SCHED_FIFO 50 for the tick thread and 49 for zenoh's
  threads, ``/dev/cpu_dma_latency`` held at 0);
- ``rtkit``: an unprivileged user (rtprio limit 0, no capability) with RealtimeKit on
  the system bus: SCHED_RR 20 for the tick thread, zenoh's threads at normal priority;
- ``cap_sys_nice``: the same user with CAP_SYS_NICE alone (what ``docker run --cap-add
  SYS_NICE`` or ``setcap cap_sys_nice+ep`` gives; an rtprio limit, ``limits.conf``'s
  ``rtprio 99`` or ``docker run --ulimit rtprio=99``, permits the same SCHED_FIFO):
  SCHED_FIFO 50/49, no ``/dev/cpu_dma_latency``;
- ``user``: the same user without RealtimeKit (no bus): normal priority.

Figures per set-up (from each server's ``simserver: stopped`` line): ticks more than 1
ms late as a share of all ticks, deadlines skipped, the worst lateness, and the lateness
p99 of the last 4096 ticks; the median over the rounds and each round's.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.bench_server import cpu_hogs
from simserver.testing import ServerProcess, free_port, rtkit_bus, serve_args

SETUPS = ("root", "rtkit", "cap_sys_nice", "user")


def one_run(setup: str, seconds: float, user: Any, env: dict[str, str],
            bus: rtkit_bus.RtkitBus) -> dict[str, Any]:
    """One server in ``setup`` for ``seconds`` after ready; its final statistics."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    argv = serve_args(listen=[endpoint])
    run_env = dict(env)
    if setup == "root":
        run_env.pop("NUMBA_CACHE_DIR", None)
        run_env["HOME"] = os.environ.get("HOME", "/root")
    elif setup == "rtkit":
        argv = rtkit_bus.as_user(user, argv)
        run_env.update(bus.env())
    elif setup == "cap_sys_nice":
        argv = rtkit_bus.as_user(user, argv, cap="sys_nice")
    else:
        argv = rtkit_bus.as_user(user, argv)
    with ServerProcess(argv=argv, listen=[endpoint], env=run_env) as server:
        line = server.wait_for_line("real-time scheduling:")
        time.sleep(seconds)  # a benchmark's measuring window, not a wait for a condition
        server.stop()
    final = server.final_stats()
    if final is None:
        raise RuntimeError(f"{setup}: no final statistics:\n{server.text()[-2000:]}")
    return {"scheduling": line.split("real-time scheduling: ", 1)[1].strip(),
            "ticks": final["ticks"], "late_ticks": final["late_ticks"],
            "late_share": final["late_ticks"] / max(1, final["ticks"]),
            "skipped_ticks": final["skipped_ticks"],
            "lateness_max_ms": final["lateness_max_us"] / 1e3,
            "lateness_p99_last_window_us": final["lateness_p99_us"]}


def run(seconds: float, rounds: int, hogs: int) -> dict[str, Any]:
    why = rtkit_bus.missing()
    if why is not None:
        raise SystemExit(f"bench_rtkit: {why}")
    user = rtkit_bus.unprivileged_user()
    home = Path(tempfile.mkdtemp(prefix="simserver-rt-home-", dir="/tmp"))
    os.chown(home, user.pw_uid, user.pw_gid)
    try:
        cache = rtkit_bus.user_kernel_cache(home / "numba", user)
        env = dict(os.environ, PYTHONUNBUFFERED="1", HOME=str(home),
                   NUMBA_CACHE_DIR=str(cache))
        env.pop("DBUS_SYSTEM_BUS_ADDRESS", None)
        out: dict[str, list[dict[str, Any]]] = {s: [] for s in SETUPS}
        load = []
        with rtkit_bus.RtkitBus() as bus, cpu_hogs(hogs):
            for r in range(rounds):
                for setup in SETUPS:
                    out[setup].append(one_run(setup, seconds, user, env, bus))
                    load.append(os.getloadavg()[0])
                    print(f"round {r + 1} {setup}: {out[setup][-1]}", flush=True)
    finally:
        shutil.rmtree(home, ignore_errors=True)
    summary = {s: {"late_share_median": float(np.median([x["late_share"] for x in v])),
                   "late_shares": [x["late_share"] for x in v],
                   "skipped_ticks": [x["skipped_ticks"] for x in v],
                   "lateness_max_ms": [round(x["lateness_max_ms"], 2) for x in v],
                   "lateness_p99_last_window_us": [round(x["lateness_p99_last_window_us"])
                                                   for x in v],
                   "scheduling": v[0]["scheduling"]} for s, v in out.items()}
    return {"seconds": seconds, "rounds": rounds, "hogs": hogs,
            "load_average": [min(load), max(load)], "setups": summary}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--hogs", type=int, default=2)
    parser.add_argument("--json", type=Path, default=None, help="write the figures here")
    args = parser.parse_args(argv)
    r = run(args.seconds, args.rounds, args.hogs)
    root = r["setups"]["root"]["late_share_median"]
    for setup, s in r["setups"].items():
        ratio = s["late_share_median"] / root if root > 0 else float("inf")
        print(f"{setup:>12}: ticks > 1 ms late {100 * s['late_share_median']:.3f} % "
              f"(median of {r['rounds']}; rounds {[f'{100 * x:.3f}' for x in s['late_shares']]}"
              f" %; {ratio:.2f} x root's), skipped {s['skipped_ticks']}, max "
              f"{s['lateness_max_ms']} ms, p99 of the last 4096 ticks "
              f"{s['lateness_p99_last_window_us']} us")
    print(f"{r['hogs']} CPU hogs, {r['seconds']:g} s per run, load average "
          f"{r['load_average'][0]:.1f}-{r['load_average'][1]:.1f}")
    if args.json is not None:
        args.json.write_text(json.dumps(r, indent=1) + "\n", encoding="utf-8")
    return r


if __name__ == "__main__":
    main()
