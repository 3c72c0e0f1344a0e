"""How far Rerun's web viewer in a browser lags behind live (issue 35 item 3).

Run from the repository root (needs Debian's ``chromium``)::

    python -m benchmarks.bench_web_view [--seconds 80] [--hogs 0] [--before]

Starts a server (viewer off), ``simserver view --sink serve:PORT --web-port PORT`` beside
it, and headless Chromium with software GL (SwiftShader, ``simserver.testing.browser``)
on the printed URL. Every ``--every`` seconds after the page is opened it saves what the
page's viewer holds (its own ``save_recording``) and compares the newest ``sim_time`` the
car has there with the server's newest state: the lag behind live. ``--before`` runs the
view as it was before the web decimation (50 frames per simulated second, Rerun's 0.2 s
flush). ``--hogs N`` runs N CPU-bound processes beside it. Prints one line per sample
and a summary line.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

from simserver.testing import Client, OutputProcess, ServerProcess, free_port
from simserver.testing.browser import (
    Browser,
    BrowserError,
    recording_extent,
    web_viewer_recording,
)

HOG = "while True: pass"

WINDOW = (640, 400)
"""The browser window (CSS pixels): software GL's cost grows with the pixels drawn."""


def view_argv(endpoint: str, grpc_port: int, web_port: int, *extra: str) -> list[str]:
    return [sys.executable, "-m", "simserver", "view", "--sink", f"serve:{grpc_port}",
            "--web-port", str(web_port), "--connect", endpoint, "--wait", "240", *extra]


def web_url(viewer: OutputProcess, timeout_s: float = 240.0) -> str:
    """The web viewer's address that ``simserver view`` prints."""
    line = viewer.wait_for_line("rerun: serving; open http", timeout_s=timeout_s)
    return line.split("open ", 1)[1].split(" ", 1)[0]


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=80.0)
    parser.add_argument("--every", type=float, default=20.0)
    parser.add_argument("--hogs", type=int, default=0)
    parser.add_argument("--before", action="store_true")
    parser.add_argument("--normal-priority", action="store_true",
                        help="run the view at normal CPU priority (default: the view's "
                             "own, nice 10)")
    args = parser.parse_args(argv)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    extra: list[str] = []
    if args.normal_priority:
        extra.append("--normal-priority")
    if args.before:
        extra = ["--fps", "50"]
        env["RERUN_FLUSH_TICK_SECS"] = "0.2"
    tmp = Path(tempfile.mkdtemp(prefix="simserver_web_view_"))
    hogs = [OutputProcess([sys.executable, "-c", HOG]) for _ in range(args.hogs)]
    lags: list[float | None] = []
    try:
        with ServerProcess() as server, Client(server) as client:
            viewer = OutputProcess(view_argv(server.endpoint, free_port(), free_port(),
                                             *extra), env=env)
            try:
                url = web_url(viewer)
                with Browser(*WINDOW) as browser:
                    t0 = time.monotonic()
                    browser.goto(url)
                    k = 0
                    while time.monotonic() - t0 < args.seconds:
                        time.sleep(max(0.0, t0 + (k + 1) * args.every - time.monotonic()))
                        k += 1
                        live_s = float(client.newest()["sim_time_s"])
                        rrd = tmp / f"web{k}.rrd"
                        newest = None
                        if web_viewer_recording(browser, rrd):
                            _, newest = recording_extent(rrd, "/world/car")
                        lag = None if newest is None else live_s - newest
                        lags.append(lag)
                        print(f"{time.monotonic() - t0:6.1f} s after opening: live "
                              f"{live_s:.1f} s, the browser's car at "
                              f"{'-' if newest is None else f'{newest:.1f} s'}, behind by "
                              f"{'-' if lag is None else f'{lag:.1f} s'}", flush=True)
                    shot: Path | None = tmp / "web.png"
                    try:  # a page that is far behind may not answer in time
                        shot.write_bytes(browser.screenshot_png())
                    except BrowserError:
                        shot = None
            finally:
                viewer.stop()
                stats = [ln for ln in viewer.text().splitlines() if ln.startswith("viewer:")]
                print(stats[-1] if stats else viewer.text()[-400:], flush=True)
    finally:
        for hog in hogs:
            hog.kill()
    mode = "before (50 fps, 0.2 s flush)" if args.before else "now"
    last = lags[-1] if lags else None
    print(f"web view {mode}, {args.hogs} hog(s): behind live by "
          f"{'-' if last is None else f'{last:.1f} s'} after {args.seconds:g} s "
          f"(samples: {', '.join('-' if x is None else f'{x:.1f}' for x in lags)}); "
          f"load average {os.getloadavg()[0]:.1f}; screenshot {shot}", flush=True)
    return {"lags_s": lags, "screenshot": str(shot)}


if __name__ == "__main__":
    main()
