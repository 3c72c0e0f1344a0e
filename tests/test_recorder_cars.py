"""``simserver-recorder --cars``: every car of a multi-car server (or a chosen set) in one
long-form table with a ``car_id`` column, as the headless world history (issue 30 item 4).

A real two-car server (``configs/server/two_cars.yaml``: car0 at x = 0, car1 at x = 25 m),
the recorder a real subprocess; its files read back with pyarrow.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from clients import recorder
from clients.common import ClientError
from simserver.adapters.history import CAR_ID_COLUMN
from simserver.testing import OutputProcess, ServerProcess, client_command, client_env

pytestmark = pytest.mark.timeout(300)


def _record(server: ServerProcess, out: Path, cars: str) -> str:
    proc = OutputProcess(client_command("recorder", "--out", str(out), "--cars", cars,
                                        "--connect", server.endpoint, "--duration", "2",
                                        "--quiet"), env=client_env())
    with proc:
        assert proc.wait(120) == 0, proc.text()
    return proc.text()


def test_every_car_in_one_long_table(two_cars, tmp_path):
    _record(two_cars, tmp_path / "all", "all")
    table = pq.read_table(tmp_path / "all" / recorder.HISTORY_FILE)
    assert table.schema.names[0] == CAR_ID_COLUMN
    ids = table.column(CAR_ID_COLUMN).to_pylist()
    assert sorted(set(ids)) == ["car0", "car1"]
    # one car after the other (row-group statistics of car_id skip the other cars)
    assert ids == sorted(ids)
    x = table.column("world_x_m").to_numpy()
    t = table.column("time_s").to_numpy()
    for car, x0_m in (("car0", 0.0), ("car1", 25.0)):
        mine = np.array(ids) == car
        assert mine.sum() > 200  # 2 s of states
        assert np.allclose(x[mine], x0_m, atol=0.05)  # parked at its start pose
        assert np.all(np.diff(t[mine]) > 0)
    segments = json.loads(pq.ParquetFile(tmp_path / "all" / recorder.HISTORY_FILE)
                          .metadata.metadata[recorder.SEGMENTS_KEY.encode()])
    assert set(segments) == {"car0", "car1"}
    assert segments["car1"][0]["rows"] == int((np.array(ids) == "car1").sum())
    diag = pq.read_table(tmp_path / "all" / recorder.DIAGNOSTICS_FILE)
    assert diag.schema.names[0] == CAR_ID_COLUMN
    assert not (tmp_path / "all" / recorder.CARS_PARTS).exists()


def test_a_chosen_car(two_cars, tmp_path):
    _record(two_cars, tmp_path / "one", "car1")
    table = pq.read_table(tmp_path / "one" / recorder.HISTORY_FILE)
    assert set(table.column(CAR_ID_COLUMN).to_pylist()) == {"car1"}


@pytest.mark.parametrize("text", ["car0,car0", "car0,", "a/b"])
def test_bad_car_lists_are_refused(text):
    with pytest.raises(ClientError, match="--cars"):
        recorder.parse_cars(text)
    assert recorder.parse_cars("all") is None
    assert recorder.parse_cars("car0, car1") == ["car0", "car1"]
