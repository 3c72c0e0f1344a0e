"""The server's start and stop as a person reads them: a few labelled lines. At start what
is served, where, which car on which scene, at what rate, and how to drive and stop it;
at stop the statistics (the JSON line of the same figures is printed on request,
``simserver serve --stats-json``).

``ticks`` counts the ticks since the last reset or load (the tick restarts there, as the
state's ``tick`` does); ``steps_total`` the physics steps since the server started: both
are said in words.
"""

from __future__ import annotations

from typing import Any


def _n(value: Any) -> str:
    return f"{int(value):,}".replace(",", " ")


def _us(value: float) -> str:
    value = float(value)
    return f"{value / 1e3:.1f} ms" if value >= 1e3 else f"{value:.2f} us"


def start_text(ready: str, cars: list[tuple[str, str, str]], period_s: float,
               connect: str | None) -> str:
    """The start block: ``ready`` (the ``ready on ...`` line tools wait for) first, then
    each car (its key base, vehicle name and scene file), the rate, and how to drive it
    and how to stop.

    Parameters
    ----------
    ready : str
        The first line, as printed before this block existed.
    cars : list of (str, str, str)
        Each car's key base, vehicle name and scene file.
    period_s : float
        The tick period.
    connect : str or None
        An endpoint a client on this machine connects to (None: the server connects out).
    """
    lines = [ready]
    for base, vehicle, scene in cars:
        lines.append(f"  car       {base}: vehicle {vehicle}, scene {scene}")
    lines.append(f"  rate      {1.0 / period_s:g} Hz (a tick every {1e3 * period_s:g} ms)")
    if connect is not None:
        lines.append(f"  drive     simserver-driver --connect {connect}   (another terminal)")
    lines.append("  stop      Ctrl-C (prints the statistics)")
    return "\n".join(lines)


def stop_text(final: dict[str, Any]) -> str:
    """The stop block of ``final`` (``loop.final_stats``): timing once, then each
    vehicle's counters."""
    lines = [f"simserver: stopped after {float(final['uptime_s']):.1f} s",
             f"  timing    tick lateness p50 {_us(final['lateness_p50_us'])}, p99 "
             f"{_us(final['lateness_p99_us'])}, max {_us(final['lateness_max_us'])}; late "
             f"ticks {_n(final['late_ticks'])}, overruns {_n(final['overruns'])}, skipped "
             f"{_n(final['skipped_ticks'])}"]
    vehicles = final.get("vehicles") or {"": final}
    for name, v in vehicles.items():
        head = f"  {name}:" if name else ""
        if head:
            lines.append(head)
        lines += [
            f"  ticks     {_n(v.get('ticks', 0))} since the last reset or load, "
            f"{_n(v.get('steps_total', 0))} since start",
            f"  commands  {_n(v.get('cmd_received', 0))} received, {_n(v.get('cmd_rejected', 0))} "
            f"rejected, {_n(v.get('cmd_clamped', 0))} clamped, {_n(v.get('cmd_stale', 0))} stale, "
            f"{_n(v.get('cmd_dropped', 0))} dropped; controls {_n(v.get('ctl_received', 0))} "
            f"({_n(v.get('ctl_busy', 0))} refused as busy)",
            f"  states    {_n(v.get('state_published', 0))} published"
            + (f" ({_n(v.get('publish_inline_puts', 0))} put in the tick, "
               f"{_n(v.get('publish_slow', 0))} slow puts)"
               if "publish_inline_puts" in v else ""),
            f"  safety    watchdog trips {_n(v.get('watchdog_trips', 0))}, non-finite stops "
            f"{_n(v.get('nonfinite_stops', 0))}"]
    if "command_log_cut" in final:
        lines.append(f"  command log cut: {final['command_log_cut']}")
    return "\n".join(lines)
