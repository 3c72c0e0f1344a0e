"""The live ``.rrd``: one recording per segment (issue 13).

A reset or a ``load`` restarts the server's tick and ``sim_time``. The live viewer used
to go on logging into the same recording, so its ``sim_time`` timeline ran backwards and
the runs overlapped (and a load's new road replaced the old one's static scene). Now each
segment is a recording of its own: for ``save:FILE`` the first goes to FILE and segment
``k`` to ``FILE``'s stem + ``.segment{k}.rrd`` (``rerun_sink.segment_sink``). The test runs
``simserver view --sink save:...`` against a live server through a ``load`` and a
``reset`` and reads the files back with ``rerun.chunk.RrdReader``.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from simserver.adapters.rerun_scene import PLOT_SPEED, SCENE_INFO
from simserver.testing import (
    CONFIGS,
    Client,
    OutputProcess,
    ServerProcess,
    free_port,
    wait_until,
)

pytestmark = pytest.mark.timeout(300)

DRAWN_BYTES = 100_000
"""A segment's file past this size holds its static scene (about 140 kB with the first
frames; the header alone is about 1 kB)."""


def _recording(path: Path) -> dict:
    """The recording of one .rrd: its id, the speed plot's times in the order logged (s),
    and the scene note."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    (entry,) = reader.recordings()
    times: list[int] = []
    note = ""
    for chunk in reader.stream():
        batch = chunk.to_record_batch()
        if chunk.entity_path == "/" + PLOT_SPEED and not chunk.is_static:
            times += batch.column("sim_time").cast("int64").to_pylist()
        elif chunk.entity_path == "/" + SCENE_INFO:
            (text,) = [n for n in batch.schema.names if n.endswith(":text")]
            note = str(batch.column(text).to_pylist()[0])
    return {"id": entry.recording_id, "times_s": [t / 1e9 for t in times], "note": note}


def test_live_rrd_has_one_recording_per_segment(tmp_path):
    hill = CONFIGS / "scenes" / "hill_10pct_paper_sedan.yaml"
    rrd = tmp_path / "live.rrd"
    server = ServerProcess(vehicle_id="view", scene="flat_paper_sedan")
    watcher = Client(server, state_capacity=1 << 15, keep_history=True)
    env = dict(os.environ, XDG_CONFIG_HOME=str(tmp_path / "xdg_config"),
               XDG_DATA_HOME=str(tmp_path / "xdg_data"))
    viewer = OutputProcess(
        [sys.executable, "-m", "simserver", "view", "--sink", f"save:{rrd}", "--connect",
         server.endpoint, "--vehicle-id", "view", "--normal-priority"], env=env)
    try:
        def run_a_while(path: Path, what: str) -> None:
            """Until the viewer draws this segment into ``path`` (its static scene and
            first frames), then 0.5 s of simulated time more."""
            wait_until(lambda: path.exists() and path.stat().st_size > DRAWN_BYTES
                       or not viewer.alive(), timeout_s=60.0,
                       what=f"the viewer to draw {what}", interval_s=0.02)
            assert viewer.alive(), viewer.text()
            watcher.poll()  # the states queued so far are older than the drawing: drop them
            watcher.history.clear()

            def ran_500_ticks() -> bool:
                watcher.poll()
                h = watcher.history
                return len(h) > 1 and int(h[-1]["tick"]) - int(h[0]["tick"]) >= 500

            wait_until(ran_500_ticks, timeout_s=30.0, what=what, interval_s=0.02)

        run_a_while(rrd, "the flat segment")
        assert watcher.request("load", {"scene": str(hill)}, timeout_s=30.0)["ok"]
        run_a_while(tmp_path / "live.segment1.rrd", "the hill segment")
        assert watcher.request("reset", timeout_s=5.0)["ok"]
        run_a_while(tmp_path / "live.segment2.rrd", "the segment after the reset")
        assert viewer.stop(timeout_s=60.0) == 0, viewer.text()
    finally:
        viewer.kill()
        watcher.close()
        server.stop()
    files = sorted(tmp_path.glob("live*.rrd"))
    recordings = [_recording(f) for f in files]
    for f, r in zip(files, recordings, strict=True):
        t = r["times_s"]
        print(f"\n{f.name}: {r['id']}: {len(t)} frames, sim_time {t[0]:.3f} .. {t[-1]:.3f} s")
        assert t  # (the viewer may lag behind the server: the last may hold a few frames)
        assert all(b > a for a, b in zip(t, t[1:], strict=False)), \
            f"{f.name}: sim_time goes backwards"
    assert [f.name for f in files] == ["live.rrd", "live.segment1.rrd", "live.segment2.rrd"]
    assert all(len(r["times_s"]) > 10 for r in recordings[:2])  # 0.5 s at 50 fps: 25
    assert len({r["id"] for r in recordings}) == 3
    assert recordings[1]["times_s"][0] < 0.2 and recordings[2]["times_s"][0] < 0.2
    assert "grade +0 %" in recordings[0]["note"]
    assert "grade +10 %" in recordings[1]["note"] and "grade +10 %" in recordings[2]["note"]


def test_where_the_later_segments_go():
    from simserver.adapters.rerun_sink import segment_path, segment_sink

    assert segment_path("out/run.rrd", 0) == Path("out/run.rrd")
    assert segment_path("out/run.rrd", 2) == Path("out/run.segment2.rrd")
    assert segment_sink("save", "out/run.rrd", 0) == ("save", "out/run.rrd")
    assert segment_sink("save", "out/run.rrd", 1) == ("save", "out/run.segment1.rrd")
    # serve: the first segment's gRPC server (on loopback when bound everywhere) takes all
    assert segment_sink("serve", None, 1) == ("connect", "rerun+http://127.0.0.1:9876/proxy")
    assert segment_sink("serve", "0.0.0.0:9000", 3) == \
        ("connect", "rerun+http://127.0.0.1:9000/proxy")
    assert segment_sink("connect", "rerun+http://h:1/proxy", 2) == \
        ("connect", "rerun+http://h:1/proxy")
    assert segment_sink("spawn", "9877", 1) == ("connect", "rerun+http://127.0.0.1:9877/proxy")


def test_the_serve_sink_carries_every_segment(tmp_path):
    """Segment 1 streams into segment 0's own gRPC server (no second server, no error)."""
    from simserver.adapters.rerun_sink import open_recording, segment_sink

    port = free_port()
    first = open_recording("serve", f"127.0.0.1:{port}", recording_id="seg0", web_port=None,
                           announce=None)
    try:
        mode, target = segment_sink("serve", f"127.0.0.1:{port}", 1)
        second = open_recording(mode, target, recording_id="seg1", announce=None)
        second.flush()
        second.disconnect()
    finally:
        first.disconnect()


def test_diagnostics_of_a_past_segment_are_not_logged_into_the_new_one(tmp_path):
    """A Diagnostics message published just before a reset, read after the states that
    show it, is ahead of the new segment's newest tick: it stays out of its recording."""
    import rerun as rr

    from simserver.adapters.viewer import log_diagnostics_payload
    from simserver.wire import protocol as proto

    values = {f.name: (0.0 if f.count == 1 else [0.0] * f.count)
              for f in proto.DIAGNOSTICS_FIELDS if f.name not in ("version", "reserved")}
    rec = rr.RecordingStream("simserver_viewer_test")
    rec.save(str(tmp_path / "d.rrd"))
    old = proto.encode_diagnostics(**dict(values, tick=4000))
    new = proto.encode_diagnostics(**dict(values, tick=40))
    assert not log_diagnostics_payload(rec, old, 0.001, 0, newest_tick=35)
    assert log_diagnostics_payload(rec, new, 0.001, 0, newest_tick=35)
    assert log_diagnostics_payload(rec, old, 0.001, 0)  # no segment information: logged
    rec.disconnect()
