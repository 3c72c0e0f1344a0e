"""The live server under client load: many state subscribers while clients join and leave.

Run from the repository root::

    python -m benchmarks.bench_load [--seconds 30] [--subscribers 20] [--churn 10]

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
import os
import time

from simserver.testing import Client, RoleProcess, ServerProcess


def run(seconds: float, subscribers: int, churn: float, realtime: str = "auto") -> dict:
    """One loaded run of ``seconds``; the figures."""
    with ServerProcess(scene=None, log_level="WARNING",
                       extra_args=["--realtime", realtime]) as server, \
            Client(server, state_capacity=0) as probe:
        conn = server.client_args()
        driver = RoleProcess("driver", [*conn, "--rate", "1000"])
        subs = RoleProcess("multisub", [*conn, "--sessions", str(subscribers)])
        d0 = probe.diagnostics()
        churner = RoleProcess("churn", [*conn, "--rate", str(churn), "--life", "1.0",
                                        "--seconds", str(seconds)])
        churned = churner.wait(seconds + 60)
        d1 = probe.diagnostics()
        subs_result = subs.stop()
        driver.stop()
    final = server.final_stats()
    ticks = int(d1["tick"] - d0["tick"])

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
            "server_final": final, "loadavg_1min": os.getloadavg()[0],
            "finished": time.strftime("%Y-%m-%d %H:%M:%S")}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--subscribers", type=int, default=20)
    parser.add_argument("--churn", type=float, default=10.0, help="joins per second")
    parser.add_argument("--realtime", default="auto", choices=("auto", "off"))
    args = parser.parse_args(argv)
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
          f"{r['subscriber_states_min']}); commands dropped {r['cmd_dropped']}")
    return r


if __name__ == "__main__":
    main()
