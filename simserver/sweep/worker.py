"""What a Dask task does: run a batch of cases and return one result row per case.

Each case is loaded from its resolved configuration and run exactly as
``simserver run-scenario`` runs its file (``load_scenario`` + ``run_scenario``, a fresh
``Simulation`` each), so its numbers are the same bit for bit. A case that cannot load
(config error) or goes non-finite is a row with its status and error; nothing a case does
stops the batch.
"""

from __future__ import annotations

import asyncio
import functools
import os
import socket
import threading
import time
import traceback
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from distributed import WorkerPlugin

from simserver.adapters.validate import ConfigError
from simserver.sweep.metrics import Metric, evaluate
from simserver.sweep.spec import Case

OK, CONFIG_ERROR, NON_FINITE, FAILED = "ok", "config_error", "non_finite", "error"
VIOLATION = "violation"  # a soak broke an invariant
SOAK_METRICS = ("violations", "holds_checked", "holds_unjudged", "max_hold_creep_m",
                "max_speed_mps", "min_fz_n", "simulated_s")


@functools.cache
def history_column_places() -> dict[str, tuple[str, int]]:
    """Each history column's array (states, outputs, inputs, poses: the world pose of the
    states) and index in it, by name (the names of ``adapters.history.result_columns``)."""
    from simserver.adapters.history import INPUT_PREFIX, POSE_COLUMNS, STATE_COLUMNS
    from simserver.core import layout as L

    return {"time_s": ("states", L.TIME_S),
            **{name: ("states", idx) for name, idx in STATE_COLUMNS},
            **{name: ("outputs", idx) for idx, name in enumerate(L.OUTPUT_NAMES)},
            **{INPUT_PREFIX + name: ("inputs", idx) for idx, name in enumerate(L.INPUT_NAMES)},
            **{name: ("poses", slot) for name, slot in POSE_COLUMNS}}


class HistoryColumns(Mapping):
    """A run's history columns by name (``adapters.history.result_columns``), each a view
    of the result's arrays (float64, the same values; a metric reads a handful of columns,
    and copying them cost 0.4 ms of a 21 ms run)."""

    def __init__(self, result: Any) -> None:
        self._result = result
        self._where = history_column_places()
        self._made: dict[str, np.ndarray] = {}

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in self._made:
            array, idx = self._where[name]
            self._made[name] = getattr(self._result, array)[:, idx]  # poses: made once
        return self._made[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._where)

    def __len__(self) -> int:
        return len(self._where)


STREAM_ROWS = 512
"""Recorded rows a worker's run writes per compiled call (``run_for_metrics``): states and
outputs, 512 x 130 x 8 bytes = 532 KB, stay in a core's 2 MB L2 cache. Recording a whole
10 s run at 1 kHz instead wrote 10.6 MB of fresh arrays a run: 4 ms of page faults (system
CPU time) of a 24 ms run, and memory traffic that two workers on two cores share."""


KEEP_BYTES = 16 << 20  # kept-column arrays larger than this are not kept for the next run


class RowBuffers:
    """A worker thread's arrays, reused from run to run (a run's are valid until the next
    one in that thread): the compiled loop's state and output rows, and the kept columns
    of the run."""

    def __init__(self) -> None:
        from simserver.core import layout as L

        self.states = np.zeros((STREAM_ROWS, L.N_STATE))
        self.outputs = np.zeros((STREAM_ROWS, L.N_OUT))
        self._kept: dict[str, np.ndarray] = {}

    def kept(self, role: str, rows: int, columns: int) -> np.ndarray:
        """A ``(rows, columns)`` array for ``role``, grown when a run needs more."""
        have = self._kept.get(role)
        if have is None or have.size < rows * columns:
            have = np.empty(rows * columns)
            if have.nbytes <= KEEP_BYTES:
                self._kept[role] = have
        return have[:rows * columns].reshape(rows, columns)


_THREAD = threading.local()


def row_buffers() -> RowBuffers:
    """This thread's buffers: a ``dask worker`` may run several tasks at once, one a
    thread."""
    bufs = getattr(_THREAD, "row_buffers", None)
    if bufs is None:
        bufs = _THREAD.row_buffers = RowBuffers()
    return bufs


@dataclass
class MetricRun:
    """What ``run_for_metrics`` keeps of a run: some history columns, and whether it stayed
    finite."""

    columns: dict[str, np.ndarray]
    first_non_finite_s: float | None  # time of the first recorded row with a NaN or inf
    final_finite: bool
    wall_time_s: float  # of the compiled loop, as ``ScenarioResult.wall_time_s``


def run_for_metrics(scenario: Any, names: Iterable[str]) -> MetricRun:
    """Run ``scenario`` as ``run_scenario`` does (``start_run``, the same compiled loop, so
    the same numbers bit for bit) but keep only the history columns ``names``: the states
    and outputs go through ``STREAM_ROWS`` reused rows, and each chunk's wanted columns are
    gathered into arrays reused from run to run (``scenario.step_chunks``, the stepper of
    ``run_scenario``). The columns are valid until the next run in this thread."""
    from simserver.core import layout as L
    from simserver.sim.scenario import start_run, step_chunks
    from simserver.sim.simulation import world_poses

    sim, inputs = start_run(scenario)
    n, every = scenario.n_steps, scenario.record_every
    n_rec = (n + every - 1) // every
    places = history_column_places()
    names = list(dict.fromkeys(names))
    by_array = {a: [name for name in names if places[name][0] == a]
                for a in ("states", "outputs", "inputs", "poses")}
    bufs = row_buffers()
    idx_s = [places[name][1] for name in by_array["states"]]
    idx_o = [places[name][1] for name in by_array["outputs"]]
    idx_p = [places[name][1] for name in by_array["poses"]]
    kept_s = bufs.kept("states", n_rec, len(idx_s))
    kept_o = bufs.kept("outputs", n_rec, len(idx_o))
    kept_p = bufs.kept("poses", n_rec, len(idx_p))
    first_bad: float | None = None
    t0 = time.perf_counter()
    for _, r0, states, outputs in step_chunks(sim, inputs, every, STREAM_ROWS * every,
                                              lambda _, rows: (bufs.states[:rows],
                                                               bufs.outputs[:rows])):
        rows = len(states)
        if idx_s:
            np.take(states, idx_s, axis=1, out=kept_s[r0:r0 + rows])
        if idx_o:
            np.take(outputs, idx_o, axis=1, out=kept_o[r0:r0 + rows])
        if idx_p:
            np.take(world_poses(scenario.scene, states), idx_p, axis=1,
                    out=kept_p[r0:r0 + rows])
        if first_bad is None and not (np.isfinite(states).all()
                                      and np.isfinite(outputs).all()):
            bad = ~(np.isfinite(states).all(axis=1) & np.isfinite(outputs).all(axis=1))
            first_bad = float(states[np.argmax(bad), L.TIME_S])
    wall = time.perf_counter() - t0
    columns = {name: kept_s[:, i] for i, name in enumerate(by_array["states"])}
    columns.update({name: kept_o[:, i] for i, name in enumerate(by_array["outputs"])})
    columns.update({name: kept_p[:, i] for i, name in enumerate(by_array["poses"])})
    columns.update({name: inputs[::every, places[name][1]] for name in by_array["inputs"]})
    return MetricRun(columns=columns, first_non_finite_s=first_bad,
                     final_finite=bool(np.isfinite(sim.x).all()), wall_time_s=wall)


def case_scene(base: str | Path, resolved: dict[str, Any]) -> Any:
    """A case's scene: its resolved YAML configuration's, or an ``.xosc`` base's (the ego's
    start with the case's parameters, ``xosc_run.xosc_scene``: sweep.spec)."""
    if "openscenario" in resolved:
        from simserver.sim.xosc_run import xosc_scene

        return xosc_scene(base, parameters=resolved["parameters"])
    from simserver.sim.scene import parse_scene

    return parse_scene(Path(base), resolved)


def warm_up(resolved: dict[str, Any], label: str) -> float:
    """Load (or compile) the compiled kernels on a case's scene (``Simulation.warm_up``).
    Returns the seconds; a scene that does not load warms nothing (its runs say why)."""
    from simserver.sim.simulation import Simulation

    t0 = time.perf_counter()
    try:
        scene = case_scene(label, resolved)
    except ConfigError:
        return 0.0
    Simulation(scene, float(resolved.get("dt_s", 0.001))).warm_up()
    return time.perf_counter() - t0


class WarmUp(WorkerPlugin):
    """A Dask worker plugin: every worker warms its kernels once, when it joins."""

    name = "simserver-warm-up"

    def __init__(self, resolved: dict[str, Any], label: str) -> None:
        self.resolved = resolved
        self.label = label

    async def setup(self, worker: Any) -> None:
        # in a thread: a first compile takes minutes on a loaded machine, and a worker
        # whose event loop is blocked sends no heartbeat (the scheduler removes it after
        # its worker-ttl, 5 minutes by default, and the plugin's registration fails)
        await asyncio.to_thread(warm_up, self.resolved, self.label)


def run_case(case: Case, metrics: tuple[Metric, ...], history_dir: str | None) -> dict[str, Any]:
    """One case -> its row: run id, case, parameters, metrics, status, error, wall time."""
    from simserver.adapters.history import write_history
    from simserver.sim.scenario import load_scenario, run_scenario

    t0 = time.perf_counter()
    row: dict[str, Any] = {"run_id": case.run_id, "case": case.index,
                           "base": Path(case.base).name, "scenario": "",
                           "params": dict(case.params), "metrics": {}, "status": OK,
                           "error": "", "sim_wall_time_s": np.nan,
                           "worker": f"{socket.gethostname()}:{os.getpid()}"}
    if case.resolved is None:
        row.update(status=CONFIG_ERROR, error=case.error)
    else:
        try:
            if "soak" in case.resolved:
                run_soak_case(case, row)
                row["wall_time_s"] = time.perf_counter() - t0
                return row
            if "openscenario" in case.resolved:
                run_xosc_case(case, metrics, history_dir, row)
                row["wall_time_s"] = time.perf_counter() - t0
                return row
            scenario = load_scenario(case.base, case.resolved)
            row["scenario"] = scenario.name
            if scenario.n_steps < 1:
                raise ConfigError(f"{case.base}: key 'duration_s': shorter than one step")
            if history_dir is None and scenario.speed_hold is None:  # only the columns
                # the metrics read (a speed hold steps in its control periods: run_scenario)
                run = run_for_metrics(scenario, (c for m in metrics for c in m.columns))
                row["sim_wall_time_s"] = run.wall_time_s
                row["metrics"] = evaluate(metrics, run.columns)
                t_bad = run.first_non_finite_s
                finite = t_bad is None and run.final_finite
            else:
                result = run_scenario(scenario)
                row["sim_wall_time_s"] = result.wall_time_s
                row["metrics"] = evaluate(metrics, HistoryColumns(result))
                t_bad, finite = non_finite(result)
                write_history(result, Path(history_dir) / f"{case.run_id}.parquet")
            if not finite:
                t_bad = scenario.duration_s if t_bad is None else t_bad
                row.update(status=NON_FINITE,
                           error=f"the run went non-finite (NaN or inf) at t = {t_bad:g} s")
        except ConfigError as exc:
            row.update(status=CONFIG_ERROR, error=str(exc))
        except Exception as exc:  # noqa: BLE001 - recorded in the table; the sweep goes on
            last = traceback.extract_tb(exc.__traceback__)[-1]
            row.update(status=FAILED, error=f"{type(exc).__name__}: {exc} "
                                            f"({Path(last.filename).name}:{last.lineno})")
    row["wall_time_s"] = time.perf_counter() - t0
    return row


def non_finite(result: Any) -> tuple[float | None, bool]:
    """A ``ScenarioResult``'s first recorded time with a NaN or inf (None: none) and
    whether it stayed finite to its final state."""
    bad = ~(np.isfinite(result.states).all(axis=1) & np.isfinite(result.outputs).all(axis=1))
    t_bad = float(result.time_s[np.argmax(bad)]) if bad.any() else None
    return t_bad, t_bad is None and bool(np.isfinite(result.final_state).all())


def run_xosc_case(case: Case, metrics: tuple[Metric, ...], history_dir: str | None,
                  row: dict[str, Any]) -> None:
    """An ``.xosc`` case: played headless as ``simserver run-scenario FILE.xosc`` plays it
    (``xosc_run.play``) with the case's parameters; the metrics are the ego's
    (``xosc_run.ego_name``), the run is non-finite if any car is; its history is the
    world's (a ``car_id`` column, ``write_world_history``)."""
    from simserver.adapters.history import write_world_history
    from simserver.sim.xosc_run import ego_name, play

    r = case.resolved
    run = play(case.base, duration_s=float(r["duration_s"]), dt_s=float(r["dt_s"]),
               parameters=r["parameters"])
    ego = ego_name(run.scenario)
    row["scenario"] = f"{Path(case.base).stem} (ego {ego})"
    row["sim_wall_time_s"] = run.wall_time_s
    row["metrics"] = evaluate(metrics, HistoryColumns(run.result.cars[ego]))
    if history_dir is not None:
        write_world_history(run.result.cars, Path(history_dir) / f"{case.run_id}.parquet")
    for cid, result in run.result.cars.items():
        t_bad, finite = non_finite(result)
        if not finite:
            t_bad = run.end_time_s if t_bad is None else t_bad
            row.update(status=NON_FINITE, error=f"car {cid!r} went non-finite (NaN or inf) "
                                                f"at t = {t_bad:g} s")
            return


def run_soak_case(case: Case, row: dict[str, Any]) -> None:
    """A soak case: ``run_soak`` on the case's scene, as ``simserver soak`` runs it."""
    from simserver.sim.soak import run_soak

    soak = case.resolved["soak"]
    scene = case_scene(case.base, case.resolved)
    row["scenario"] = str(case.resolved.get("name", ""))
    report = run_soak(scene, float(soak["duration_s"]), seed=int(soak["seed"]),
                      dt_s=float(case.resolved.get("dt_s", 0.001)))
    summary = report.as_dict()
    row["sim_wall_time_s"] = report.wall_s
    row["metrics"] = {"violations": len(report.violations),
                      **{k: float(summary[k]) for k in SOAK_METRICS[1:]}}
    if not report.ok:
        row.update(status=VIOLATION, error="; ".join(
            f"{v.invariant} at t = {v.time_s:g} s: {v.detail}" for v in report.violations))


def run_batch(cases: list[Case], metrics: tuple[Metric, ...],
              history_dir: str | None) -> list[dict[str, Any]]:
    """A Dask task: several cases, so the per-task overhead stays small against the work."""
    return [run_case(case, metrics, history_dir) for case in cases]
