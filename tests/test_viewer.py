"""The live viewer's diagnostics land on the scene's time line at the server's period."""

from __future__ import annotations

import pytest

from simserver.adapters.rerun_scene import TICK_JITTER, TIMELINE
from simserver.adapters.viewer import log_diagnostics_payload
from simserver.wire import protocol as proto


def _diagnostics(tick: int, lateness_p99_us: float) -> bytes:
    values = {f.name: (0.0 if f.count == 1 else [0.0] * f.count)
              for f in proto.DIAGNOSTICS_FIELDS if f.name not in ("version", "reserved")}
    values.update(tick=tick, lateness_p99_us=lateness_p99_us)
    return proto.encode_diagnostics(**values)


def _jitter_rows(path):
    """(time in ns, value) of every tick-jitter sample in an .rrd file."""
    from rerun.chunk import RrdReader

    rows = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path != "/" + TICK_JITTER or chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        times = batch.column(TIMELINE).cast("int64").to_pylist()
        (scalars,) = [n for n in batch.schema.names if n.endswith("scalars")]
        rows += [(t, v[0]) for t, v in zip(times, batch.column(scalars).to_pylist(),
                                           strict=True)]
    return sorted(rows)


@pytest.mark.parametrize("period_s", [0.001, 0.002, 0.0005])
def test_diagnostics_time_is_tick_times_the_configured_period(tmp_path, period_s):
    import rerun as rr

    path = tmp_path / "diag.rrd"
    rec = rr.RecordingStream("simserver_viewer_test")
    rec.save(str(path))
    assert log_diagnostics_payload(rec, _diagnostics(4000, 12.5), period_s, 0)
    assert log_diagnostics_payload(rec, _diagnostics(8000, 25.0), period_s, 3)
    assert not log_diagnostics_payload(rec, b"not a diagnostics payload", period_s, 3)
    rec.flush()
    rec.disconnect()
    # the state's sim_time_s is tick x period; the diagnostics must sit on the same grid
    assert _jitter_rows(path) == [(round(4000 * period_s * 1e9), 12.5),
                                  (round(8000 * period_s * 1e9), 25.0)]
