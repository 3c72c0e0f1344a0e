"""The live view in Rerun's web viewer, in a real browser (issue 35 item 3).

``simserver view --sink serve:PORT --web-port PORT`` beside a real server, opened in
headless Chromium with software GL (SwiftShader: this machine has no GPU), driven over
the DevTools protocol (``simserver.testing.browser``). The car counts as drawn when the
page's own viewer holds the car's entities and frames of it on the ``sim_time`` timeline
(its ``save_recording``, read back with ``rerun.chunk.RrdReader``): before the web
decimation the page showed the blueprint but "The recording has no timeline sim_time"
and every panel empty, falling further behind live. The page must not reach beyond this
machine: Rerun's update check is off and everything else off-machine (telemetry, web
fonts) is refused by the page's policy (``adapters.web_viewer_host``).

The default run starts the view once; ``-m slow`` (or ``SIMSERVER_SLOW=1``) starts it 10
times beside two CPU-bound processes on this 2-core machine, at the view's default idle
priority, and needs every start to draw the car. Skipped where Debian's ``chromium`` is
not installed.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path
from urllib.parse import urlsplit

import pytest

from simserver.adapters.rerun_scene import BODY_SHELL, WHEEL_TIRES
from simserver.adapters.viewer import WEB_NICE
from simserver.testing import OutputProcess, ServerProcess, free_port, wait_until
from simserver.testing.browser import (
    Browser,
    chromium_path,
    recording_extent,
    web_viewer_recording,
)
from tests.conftest import slow_enabled

pytestmark = [pytest.mark.timeout(3600),
              pytest.mark.skipif(chromium_path() is None,
                                 reason="needs Debian's chromium (apt-get install chromium)")]

CAR_ENTITY = "/world/car"
CAR_PARTS = {"/" + BODY_SHELL, *("/" + t for t in WHEEL_TIRES)}
"""The car's body and tires (``rerun_scene``): what is drawn of it."""
DRAW_TIMEOUT_S = 240.0
"""How long one start may take to draw the car in the page (server up; a starved 2-core
machine: the page's wasm alone takes 10-35 s to compile there)."""

HOG = "while True: pass"

WINDOW = (640, 400)
"""The browser window (CSS pixels): software GL's cost grows with the pixels drawn."""
LOOPBACK = ("127.0.0.1", "localhost", "[::1]", "::1")


def off_machine(url: str) -> bool:
    """Whether ``url`` names a host other than this machine (data: and blob: are local)."""
    parts = urlsplit(url)
    return parts.scheme in ("http", "https", "ws", "wss") and parts.hostname not in LOOPBACK


def start_view(server: ServerProcess, tmp: Path) -> tuple[OutputProcess, str]:
    """``simserver view`` serving the web viewer for ``server``; returns it and the
    page's address it printed."""
    argv = [sys.executable, "-m", "simserver", "view", "--sink", f"serve:{free_port()}",
            "--web-port", str(free_port()), "--connect", server.endpoint, "--wait", "240"]
    env = dict(os.environ, PYTHONUNBUFFERED="1", XDG_CONFIG_HOME=str(tmp / "xdg_config"),
               XDG_DATA_HOME=str(tmp / "xdg_data"))
    viewer = OutputProcess(argv, env=env)
    line = viewer.wait_for_line("rerun: serving; open http", timeout_s=DRAW_TIMEOUT_S)
    return viewer, line.split("open ", 1)[1].split(" ", 1)[0]


def draws_the_car(server: ServerProcess, tmp: Path) -> tuple[bool, str]:
    """One start: the view, a fresh browser on its page, and whether the page's viewer
    came to hold frames of the car on ``sim_time`` within ``DRAW_TIMEOUT_S``; with what
    happened, for the failure message. Also checks that the page reached nothing off
    this machine."""
    viewer, url = start_view(server, tmp)
    t0 = time.monotonic()
    rrd = tmp / "page.rrd"
    seen: dict[str, object] = {}
    try:
        with Browser(*WINDOW) as browser:
            browser.goto(url)

            def car_frames() -> bool:
                if not viewer.alive() or not web_viewer_recording(browser, rrd):
                    return False
                paths, newest = recording_extent(rrd, CAR_ENTITY)
                seen.update(entities=len(paths), newest_sim_time_s=newest)
                # the car's frames and its drawn parts: with newest first the static
                # body and wheels may come after the first frames
                return newest is not None and CAR_PARTS <= paths

            try:
                wait_until(car_frames, timeout_s=DRAW_TIMEOUT_S, interval_s=2.0,
                           what="the web viewer to hold frames of the car")
                drawn = True
            except TimeoutError:
                drawn = False
            reached = [u for u in browser.requests if off_machine(u)
                       and browser.blocked.get(u) != "csp"]
            assert not reached, f"the page reached beyond this machine: {reached}"
            assert not any("fonts.g" in u for u in browser.requests), browser.requests
    finally:
        code = viewer.stop(timeout_s=60.0)
    assert "Traceback" not in viewer.text(), viewer.text()
    assert code == 0, viewer.text()
    # not SCHED_IDLE: an idle view beside two CPU hogs got no CPU (viewer.WEB_NICE)
    assert f"CPU priority nice {WEB_NICE}" in viewer.text(), viewer.text()[-300:]
    return drawn, (f"{time.monotonic() - t0:.0f} s, page holds {seen}; viewer: "
                   f"{viewer.text()[-600:]}")


@pytest.mark.parametrize("starts, hogs", [
    pytest.param(1, 0, id="once"),
    pytest.param(10, 2, id="10-starts-2-hogs", marks=pytest.mark.slow),
])
def test_the_web_viewer_draws_the_car_every_start(request, starts, hogs):
    if starts > 1 and not slow_enabled(request.config.getoption("markexpr")):
        pytest.skip("slow: run with -m slow or SIMSERVER_SLOW=1")
    hog_procs = [OutputProcess([sys.executable, "-c", HOG]) for _ in range(hogs)]
    results: list[tuple[bool, str]] = []
    try:
        with ServerProcess() as server, tempfile.TemporaryDirectory() as tmp:
            for k in range(starts):
                results.append(draws_the_car(server, Path(tmp)))
                print(f"start {k + 1}: {'drew the car' if results[-1][0] else 'NOT drawn'}"
                      f" ({results[-1][1][:120]})", flush=True)
    finally:
        for hog in hog_procs:
            hog.kill()
    drawn = sum(ok for ok, _ in results)
    print(f"\nweb view: {drawn} of {starts} starts drew the car, {hogs} CPU hog(s) beside; "
          f"load average {os.getloadavg()[0]:.1f}")
    assert drawn == starts, [why for ok, why in results if not ok]
