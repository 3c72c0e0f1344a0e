"""simserver sweep on real Dask clusters (issue 18).

Every run of a sweep is compared with a serial run of the same case in this process
(``load_scenario`` of the resolved, overridden configuration + ``run_scenario``): the
metrics are equal as numbers and the histories bit for bit; one history is compared with
``simserver run-scenario``'s own file. The clusters are real: an embedded ``LocalCluster``
with two worker processes, and a ``dask scheduler`` with ``dask worker`` processes on
loopback, one of which is killed in the middle of a sweep.
"""

from __future__ import annotations

import math
import os
import signal
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml

from simserver.adapters.history import read_history, result_columns
from simserver.adapters.validate import ConfigError
from simserver.sim.scenario import load_scenario, resolve_scenario, run_scenario
from simserver.sweep.engine import HISTORY_DIR, RESULTS_FILE, run_sweep
from simserver.sweep.metrics import evaluate
from simserver.sweep.resolved import run_id, with_overrides
from simserver.sweep.spec import load_sweep
from simserver.testing import CONFIGS, OutputProcess, free_port, wait_until

pytestmark = pytest.mark.timeout(240)

E2 = CONFIGS / "scenarios" / "e2_stop_downslope_paper_damping.yaml"
E3 = CONFIGS / "scenarios" / "e3_stop_from_turn.yaml"
B_LONG = "vehicle.tires.*.relaxation_length_long_m"
METRICS = [{"stopping_distance": {"from_s": 0.7}}, {"time_to_rest": {"from_s": 0.7}}, "yaw",
           "resting_forces", {"column": "u_mps", "stat": "min"}]
PY = sys.executable
# The tests that act on a running sweep (SIGINT, kill a worker) when its table's first
# checkpoint appears run each case for this long: 0.6 s of CPU a run here (the run and
# its history columns), so a 16-run sweep is still seconds from its end then. At the
# scenario's own 10 s a run takes 18 ms, and a 40-run sweep once ended before the test's
# SIGINT reached it (CI, stop 25).
LONG_RUN = {"duration_s": [200.0]}


def write_sweep(tmp_path: Path, name: str, **body) -> Path:
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump({"name": name, "metrics": METRICS, **body}))
    return path


def serial_rows(sweep_path: Path) -> dict[str, tuple[dict, dict]]:
    """run id -> (metrics, history columns) of each case run alone, here."""
    sweep = load_sweep(sweep_path)
    out = {}
    for case in sweep.cases:
        if case.resolved is None:
            continue
        resolved = with_overrides(resolve_scenario(case.base), case.params, "test")
        assert run_id(resolved) == case.run_id
        try:
            result = run_scenario(load_scenario(case.base, resolved))
        except ConfigError:
            continue
        cols = result_columns(result)
        out[case.run_id] = (evaluate(sweep.metrics, cols), cols)
    return out


def same(a: float, b: float) -> bool:
    return (isinstance(a, float) and isinstance(b, float) and math.isnan(a)
            and math.isnan(b)) or a == b


def assert_rows_match(rows: list[dict], serial: dict[str, tuple[dict, dict]]) -> None:
    ok = [r for r in rows if r["status"] == "ok"]
    assert {r["run_id"] for r in ok} == set(serial)
    for row in ok:
        metrics, _ = serial[row["run_id"]]
        for name, value in metrics.items():
            assert same(row[name], value), (row["case"], name, row[name], value)


def test_local_cluster_two_workers_identical_to_serial_and_run_scenario(tmp_path):
    path = write_sweep(tmp_path, "local", scenarios=[str(E2), str(E3)], histories=True,
                       cases=[{}, {B_LONG: 0.03}, {B_LONG: 0.25, "road.grade_pct": -8.0},
                              {"vehicle.chassis.mass_kg": -5.0},
                              {"vehicle.chasis.mass_kg": 1500.0}])
    sweep = load_sweep(path)
    outcome = run_sweep(sweep, tmp_path / "out", workers=2, quiet=True)
    assert outcome.workers == 2
    rows = outcome.rows
    assert len(rows) == 10 and len({r["run_id"] for r in rows}) == 10
    # two dask worker processes did the runs, none of them this process
    pids = {r["worker"].rsplit(":", 1)[1] for r in rows if r["status"] == "ok"}
    assert str(os.getpid()) not in pids
    # the broken cases end with their errors, naming the file and the dotted path
    broken = {r["case"]: r for r in rows if r["status"] != "ok"}
    assert sorted(broken) == [3, 4, 8, 9]
    assert all(r["status"] == "config_error" for r in broken.values())
    assert "#vehicle.chassis: key 'mass_kg': -5 is outside" in broken[3]["error"]
    assert "parameter 'vehicle.chasis.mass_kg': no key 'chasis'" in broken[4]["error"]
    # the table on disk is the outcome's
    table = pq.read_table(tmp_path / "out" / RESULTS_FILE).to_pylist()
    assert [r["run_id"] for r in table] == [r["run_id"] for r in rows]
    serial = serial_rows(path)
    assert_rows_match(table, serial)
    for rid, (_, cols) in serial.items():
        hist = read_history(tmp_path / "out" / HISTORY_DIR / f"{rid}.parquet")
        assert hist.keys() == cols.keys()
        for name, values in cols.items():
            assert np.array_equal(hist[name], values, equal_nan=True), (rid, name)
    # an overridden case against `simserver run-scenario` of it written out resolved
    case = next(r for r in rows if r["case"] == 2)
    case_file = tmp_path / "case2.yaml"
    case_file.write_text(yaml.safe_dump(next(c.resolved for c in sweep.cases if c.index == 2)))
    proc = OutputProcess([PY, "-m", "simserver", "run-scenario", str(case_file), "--out",
                          str(tmp_path / "cli"), "--no-plots", "--quiet"], ready="wrote")
    assert proc.wait(120) == 0, proc.text()
    cli = read_history(tmp_path / "cli")
    mine = read_history(tmp_path / "out" / HISTORY_DIR / f"{case['run_id']}.parquet")
    assert cli.keys() == mine.keys()
    for name in cli:
        assert np.array_equal(cli[name], mine[name], equal_nan=True), name


def table_rows(path: Path) -> int:
    try:
        return pq.read_metadata(path).num_rows
    except (OSError, ValueError):
        return 0


def test_scheduler_and_workers_on_loopback_a_killed_worker_loses_no_run(tmp_path):
    n = 16
    path = write_sweep(tmp_path, "cluster", scenarios=[str(E2)],
                       grid={B_LONG: {"from": 0.02, "to": 0.3, "num": n}, **LONG_RUN})
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    scheduler = OutputProcess([PY, "-m", "distributed.cli.dask_scheduler", "--host",
                               "127.0.0.1", "--port", str(port), "--no-dashboard"],
                              ready="Scheduler at")
    workers = []
    try:
        assert scheduler.wait_ready(60), scheduler.text()
        workers = [OutputProcess([PY, "-m", "distributed.cli.dask_worker", address,
                                  "--nthreads", "1", "--no-nanny", "--no-dashboard"],
                                 ready="Registered to") for _ in range(2)]
        for w in workers:
            assert w.wait_ready(60), w.text()
        out = tmp_path / "out"
        sweep = OutputProcess([PY, "-m", "simserver", "sweep", str(path), "--out", str(out),
                               "--scheduler", address, "--batch", "1", "--quiet",
                               "--no-plots"], ready="runs/min")
        # mid-sweep: some runs are in the table, not all; kill a worker that did some
        done = wait_until(lambda: table_rows(out / RESULTS_FILE), lambda k: k > 0,
                          timeout_s=120, what="the first checkpoint of the table")
        rows_now = pq.read_table(out / RESULTS_FILE).to_pylist()
        victim = next(w for w in workers
                      if any(r["worker"].endswith(f":{w.pid}") for r in rows_now))
        victim.kill()
        assert done < n, "the sweep ended before a worker could be killed"
        assert sweep.wait(180) == 0, sweep.text()
        assert f"{n} runs (0 failed" in sweep.text()
    finally:
        for proc in (*workers, scheduler):
            proc.stop(timeout_s=20)
    table = pq.read_table(out / RESULTS_FILE).to_pylist()
    assert len(table) == n and len({r["run_id"] for r in table}) == n
    assert all(r["status"] == "ok" for r in table)
    survivor = next(w for w in workers if w is not victim)
    assert any(r["worker"].endswith(f":{survivor.pid}") for r in table)
    assert_rows_match(table, serial_rows(path))


def test_resume_after_ctrl_c_runs_only_the_rest(tmp_path):
    n = 16
    path = write_sweep(tmp_path, "resume", scenarios=[str(E2)],
                       grid={B_LONG: {"from": 0.02, "to": 0.3, "num": n}, **LONG_RUN})
    out = tmp_path / "out"
    args = [PY, "-m", "simserver", "sweep", str(path), "--out", str(out), "--workers", "1",
            "--batch", "1", "--quiet", "--no-plots"]
    first = OutputProcess(args, ready="runs/min")
    done = wait_until(lambda: table_rows(out / RESULTS_FILE), lambda k: k > 0,
                      timeout_s=120, what="the first checkpoint of the table")
    first.stop(signal.SIGINT, timeout_s=60)
    assert first.returncode == 130, first.text()
    kept = pq.read_table(out / RESULTS_FILE).to_pylist()
    assert done <= len(kept) < n
    second = OutputProcess([*args, "--resume"], ready="runs/min")
    assert second.wait(120) == 0, second.text()
    assert f"{n - len(kept)} runs (0 failed, {len(kept)} already done)" in second.text()
    table = pq.read_table(out / RESULTS_FILE).to_pylist()
    assert len(table) == n and len({r["run_id"] for r in table}) == n
    assert [r["case"] for r in table] == list(range(n))
    kept_by_id = {r["run_id"]: r for r in kept}
    for row in table:  # the runs of the first invocation are kept as they were
        if row["run_id"] in kept_by_id:
            assert row == kept_by_id[row["run_id"]]


def test_soak_case_is_run_soak_of_its_scene_and_seed(tmp_path):
    from simserver.sim.scene import load_scene
    from simserver.sim.soak import run_soak
    from simserver.sweep.worker import run_case

    scene_file = CONFIGS / "scenes" / "flat_mf_hatchback.yaml"
    path = tmp_path / "soak.yaml"
    path.write_text(yaml.safe_dump({"name": "soak", "kind": "soak",
                                    "scenarios": [str(scene_file)],
                                    "soak": {"duration_s": 20.0, "seeds": 2}}))
    sweep = load_sweep(path)
    assert [c.params for c in sweep.cases] == [{"soak.seed": 0}, {"soak.seed": 1}]
    assert sweep.cases[0].run_id != sweep.cases[1].run_id
    for case in sweep.cases:
        row = run_case(case, sweep.metrics, None)
        report = run_soak(load_scene(scene_file), 20.0, seed=case.params["soak.seed"])
        assert row["status"] == ("ok" if report.ok else "violation"), row["error"]
        assert row["metrics"]["violations"] == len(report.violations)
        assert row["metrics"]["max_speed_mps"] == report.max_speed_mps
        assert row["metrics"]["min_fz_n"] == report.min_fz_n
        assert row["metrics"]["max_hold_creep_m"] == report.max_hold_creep_m


def _workers_numba_cache_dirs(client) -> set[str]:
    return set(client.run(lambda: __import__("numba").core.config.CACHE_DIR).values())


def test_numba_cache_is_the_workers_cache_and_only_theirs(tmp_path):
    """``--numba-cache DIR``: every LocalCluster worker has numba's cache in DIR (so a
    machine compiles once); this process keeps its own."""
    from simserver.sweep.engine import open_client

    cache = tmp_path / "numba-cache"
    before = os.environ.get("NUMBA_CACHE_DIR")
    client = open_client(None, 2, cache)
    try:
        assert os.environ.get("NUMBA_CACHE_DIR") == before  # this process: unchanged
        assert cache.is_dir()
        assert _workers_numba_cache_dirs(client) == {str(cache.resolve())}
    finally:
        cluster = client.cluster
        client.close()
        cluster.close()
    plain = open_client(None, 1, None)  # without the option: numba's own default
    try:
        assert _workers_numba_cache_dirs(plain) == {os.environ.get("NUMBA_CACHE_DIR", "")}
    finally:
        cluster = plain.cluster
        plain.close()
        cluster.close()


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_numba_cache_a_sweep_compiles_into_it_once(tmp_path, request):
    """The long form (run with ``-m slow`` or ``SIMSERVER_SLOW=1``): ``simserver sweep
    --numba-cache DIR`` on an empty DIR compiles the kernels into it (index files
    appear), and a second sweep on it adds none: loaded, not compiled again. The rows
    equal a serial run (as every sweep's)."""
    from tests.conftest import slow_enabled

    if not slow_enabled(request.config.getoption("markexpr")):
        pytest.skip("long form: run with -m slow or SIMSERVER_SLOW=1")
    cache = tmp_path / "cache"
    path = write_sweep(tmp_path, "cached", scenarios=[str(E2)], cases=[{}, {B_LONG: 0.2}])
    args = [PY, "-m", "simserver", "sweep", str(path), "--workers", "2", "--numba-cache",
            str(cache), "--quiet", "--no-plots"]
    first = OutputProcess([*args, "--out", str(tmp_path / "one")], ready="runs/min")
    assert first.wait(1500) == 0, first.text()
    index = sorted(p.relative_to(cache) for p in cache.rglob("*.nbi"))
    assert any("integrator" in str(p) for p in index), index
    stamps = {p: (cache / p).stat().st_mtime_ns for p in index}
    second = OutputProcess([*args, "--out", str(tmp_path / "two")], ready="runs/min")
    assert second.wait(600) == 0, second.text()
    assert sorted(p.relative_to(cache) for p in cache.rglob("*.nbi")) == index
    assert {p: (cache / p).stat().st_mtime_ns for p in index} == stamps
    assert_rows_match(pq.read_table(tmp_path / "two" / RESULTS_FILE).to_pylist(),
                      serial_rows(path))
