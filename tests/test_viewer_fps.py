"""The live view's frame rate, the rate a ``save:`` recording grows with (issue 32 item
5): the server's ``viewer_fps`` (``--viewer-fps``) reaches the viewer it starts, and the
recording keeps that many frames per simulated second, read back from the .rrd."""

from __future__ import annotations

import os
import signal
import sys

import numpy as np
import pytest

from simserver.adapters.rerun_scene import CAR, TIMELINE
from simserver.adapters.validate import ConfigError
from simserver.adapters.viewer import DEFAULT_FPS
from simserver.server.config import DEFAULT_SERVER_CONFIG, ServerConfig, load_server_config
from simserver.testing import Client, OutputProcess, ServerProcess, wait_until


def test_viewer_fps_default_is_the_viewers_and_bad_values_are_refused(tmp_path):
    assert load_server_config(DEFAULT_SERVER_CONFIG).viewer_fps == DEFAULT_FPS
    assert ServerConfig(path=tmp_path, scene=tmp_path).viewer_fps == DEFAULT_FPS
    assert load_server_config(DEFAULT_SERVER_CONFIG, viewer_fps=10.0).viewer_fps == 10.0
    for bad in (0.0, -5.0, 5000.0, "fast"):
        with pytest.raises(ConfigError, match="viewer_fps"):
            load_server_config(DEFAULT_SERVER_CONFIG, viewer_fps=bad)


def car_frame_times(path) -> list[int]:
    """sim_time (ns) of every frame of the car in a recording."""
    from rerun.chunk import RrdReader

    times: set[int] = set()
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == "/" + CAR and not chunk.is_static:
            times.update(chunk.to_record_batch().column(TIMELINE).cast("int64").to_pylist())
    return sorted(times)


def test_serve_passes_viewer_fps_to_its_viewer(tmp_path):
    """The server's viewer is started with the configured rate (its command is logged: the
    viewer itself runs at idle priority and may get no CPU on a busy machine)."""
    server = ServerProcess(viewer=f"save:{tmp_path / 'v.rrd'}",
                           extra_args=["--viewer-fps", "10"])
    try:
        wait_until(lambda: "live viewer: simserver view" in server.text(), bool,
                   timeout_s=30, what="the viewer's command line", interval_s=0.2)
    finally:
        server.stop(signal.SIGINT)
    (line,) = [ln for ln in server.text().splitlines() if "live viewer: simserver view" in ln]
    assert line.endswith("--fps 10"), line


def test_view_fps_decimates_the_saved_recording(tmp_path):
    """``simserver view --fps 10`` (what the server starts) keeps 10 car frames per
    simulated second in a ``save:`` recording."""
    rrd = tmp_path / "live.rrd"
    with ServerProcess() as server:
        view = OutputProcess([sys.executable, "-m", "simserver", "view", "--sink",
                              f"save:{rrd}", "--connect", server.endpoint, "--fps", "10",
                              "--normal-priority"])
        try:
            wait_until(lambda: rrd.exists() and os.path.getsize(rrd) > 100_000, bool,
                       timeout_s=240, what="the recording growing", interval_s=0.5)
            # then 4 s more of the server's simulated time in the recording
            with Client(server) as client:
                t0 = float(client.wait_state(timeout_s=20.0)["sim_time_s"])
                client.wait_state(lambda st: float(st["sim_time_s"]) > t0 + 4.0, 30.0,
                                  "4 s more of simulated time")
        finally:
            code = view.stop(signal.SIGINT, timeout_s=60)
    assert code == 0, view.text()
    times = car_frame_times(rrd)
    gaps_s = np.diff(times) / 1e9
    span_s = (times[-1] - times[0]) / 1e9
    print(f"\n{len(times)} car frames over {span_s:.1f} simulated s: "
          f"{(len(times) - 1) / span_s:.2f} per s; gaps {gaps_s.min():.3f} .. "
          f"{gaps_s.max():.3f} s, median {np.median(gaps_s):.3f} s")
    assert span_s > 2.0
    # RateGate lets through the first state at or after each 0.1 s grid point: no two
    # frames closer than 0.1 s (at the default 50 they are 0.02 s apart), and the regular
    # gap is 0.1 s; a viewer that fell behind (a busy machine) drops states, which only
    # makes some gaps longer
    assert gaps_s.min() >= 0.1 - 1.5e-3
    assert np.median(gaps_s) == pytest.approx(0.1, abs=1.5e-3)
