"""Running a sweep on Dask distributed: the client, the batches, the results table, resume.

The engine is Dask's: an embedded ``LocalCluster`` (one single-threaded worker process
per core, forked from this process, see ``FORK_WORKERS``) by default, or an existing
scheduler (``tcp://HOST:8786``). Every worker warms
its compiled kernels once when it joins (``worker.WarmUp``, a worker plugin); workers
that share a cache load what one of them compiled: ``SIMSERVER_CACHE_DIR`` (``core``'s
shared cache, keyed by the sources and not by their path: the LocalCluster's workers
inherit it from this process, remote workers take it from their own environment, and
checkouts at other paths share it) or ``NUMBA_CACHE_DIR`` (``--numba-cache``; the default
is numba's own cache next to the sources). Cases go out in batches, several runs per
task, so a task lasts well over Dask's 100 ms guidance. A task whose worker dies is run
again elsewhere by the scheduler (and ``retries`` covers a task that raised), so no run
is lost. The results table (``results.parquet``, one row per run) is rewritten atomically
as batches finish, so an interrupted sweep keeps what it ran and ``--resume`` runs only
the cases whose run id (the hash of the resolved configuration) is not in it.
"""

from __future__ import annotations

import logging
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from simserver.sweep.spec import Case, Sweep
from simserver.sweep.worker import FAILED, OK, WarmUp, run_batch

RESULTS_FILE = "results.parquet"
HISTORY_DIR = "histories"
CHECKPOINT_EVERY_S = 0.5  # the first checkpoint of the table; then see CHECKPOINT_COST
# the table is rewritten whole: a later checkpoint waits this many times the last write's
# duration (and 2 s or more), so the writes take at most 2 % of this process's core, which
# on a machine with one core per worker is taken from a worker
CHECKPOINT_COST = 50.0
CHECKPOINT_LATER_S = 2.0
# The embedded LocalCluster's Dask settings: its default housekeeping runs in this
# process (scheduler, nannies) and in the workers, on the cores that do the runs. Every
# 20 ms an event-loop health tick, every 100 ms a memory check, every 10 ms a statistical
# profile of the task's thread: 56 ms of CPU per second in this process and 40 per
# worker, measured with two idle workers (10 and 29 with these settings). Slower
# housekeeping does the same checks: a worker over its memory limit is still stopped,
# within a second.
LOCAL_CLUSTER_CONFIG = {
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "2s",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.worker.profile.enabled": False,
}
# The LocalCluster's worker processes are forked from this process, which has imported
# distributed, numba and simserver (and loaded the tire kernels) already; spawned, each
# worker imported them again, 1.5 s of CPU before its first run. With ``--numba-cache``
# they are spawned: NUMBA_CACHE_DIR takes effect only in a process that has not imported
# numba yet. A worker its nanny restarts later is spawned either way.
FORK_WORKERS = True
GUIDED_ROUNDS = 4  # a batch is the remaining runs / (GUIDED_ROUNDS x workers), see batches
MAX_BATCH = 64  # runs: a lost worker costs little
MIN_TASK_S = 0.1  # Dask's guidance: a task lasts 100 ms or more
STEP_COST_S = 2.5e-6  # s per simulated step (benchmarks/bench_step.py: 1.5-4 us), task sizes only
TASK_RETRIES = 2
FIRST_COLUMNS = ("run_id", "case", "base", "scenario")
LAST_COLUMNS = ("status", "error", "wall_time_s", "sim_wall_time_s", "worker")


@dataclass
class SweepOutcome:
    rows: list[dict[str, Any]]  # the whole table, by case
    ran: int  # runs done by this invocation
    skipped: int  # runs already in the table (--resume)
    failed: int  # of those run now, not ok
    wall_time_s: float
    workers: int
    ready_s: float = 0.0  # of wall_time_s, until the workers were up and warm
    close_s: float = 0.0  # of wall_time_s, closing the client and the LocalCluster
    metric_columns: list[str] = field(default_factory=list)
    # process CPU seconds from the first task submitted to the last row in: this process
    # (client, and for a LocalCluster its scheduler and nannies) and the workers, summed
    client_cpu_s: float = math.nan
    worker_cpu_s: float = math.nan


def flat_row(row: dict[str, Any], parameters: tuple[str, ...]) -> dict[str, Any]:
    """A worker's row as a table row: parameters and metrics as columns of their own."""
    out = {k: row[k] for k in FIRST_COLUMNS}
    out.update({p: row["params"].get(p) for p in parameters})
    out.update(row["metrics"])
    out.update({k: row[k] for k in LAST_COLUMNS})
    return out


def _column(values: list[Any]) -> pa.Array:
    present = [v for v in values if v is not None]
    if present and all(isinstance(v, bool) for v in present):
        return pa.array(values, type=pa.bool_())
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in present):
        if all(isinstance(v, int) for v in present) and present:
            return pa.array(values, type=pa.int64())
        return pa.array([math.nan if v is None else float(v) for v in values],
                        type=pa.float64())
    return pa.array([None if v is None else str(v) for v in values], type=pa.string())


def write_table(rows: list[dict[str, Any]], path: Path) -> None:
    """The rows as one Parquet table, written to a temporary file then renamed."""
    names: list[str] = list(FIRST_COLUMNS)
    for row in rows:
        names += [k for k in row if k not in names and k not in LAST_COLUMNS]
    names += list(LAST_COLUMNS)
    rows = sorted(rows, key=lambda r: r["case"])
    table = pa.table({n: _column([r.get(n) for r in rows]) for n in names})
    tmp = path.with_suffix(".parquet.tmp")
    pq.write_table(table, tmp)
    os.replace(tmp, path)


def read_table(path: Path) -> list[dict[str, Any]]:
    return pq.read_table(path).to_pylist() if path.is_file() else []


def estimated_run_s(case: Case) -> float:
    """A rough wall time of one case: its simulated steps x ``STEP_COST_S``."""
    if case.resolved is None:
        return 0.0
    soak = case.resolved.get("soak")
    duration = float(soak["duration_s"] if isinstance(soak, dict)
                     else case.resolved.get("duration_s", 0.0))
    return duration / float(case.resolved.get("dt_s", 0.001)) * STEP_COST_S


def batches(cases: list[Case], n_workers: int, batch_runs: int | None) -> list[list[Case]]:
    """The cases in tasks of several runs each.

    ``batch_runs``: that many runs per task. Otherwise guided self-scheduling: each batch
    takes the remaining runs / (``GUIDED_ROUNDS`` x workers), so the batches shrink toward
    the end and the workers finish within one small batch of each other (equal batches of
    n / (8 workers) left one worker idle for up to a whole batch at the tail: 0.3 s of
    the relaxation study's 2.4 s on two workers). A batch holds at most ``MAX_BATCH`` runs
    and enough runs to last ``MIN_TASK_S`` (estimated from the runs' step counts), the
    task size Dask's per-task overhead asks for.
    """
    if batch_runs:
        return [cases[i:i + batch_runs] for i in range(0, len(cases), batch_runs)]
    typical_s = sorted(estimated_run_s(c) for c in cases)[len(cases) // 2] if cases else 0.0
    min_runs = max(1, min(MAX_BATCH, math.ceil(MIN_TASK_S / typical_s)
                          if typical_s > 0.0 else MAX_BATCH))
    out, start = [], 0
    while start < len(cases):
        remaining = len(cases) - start
        size = min(MAX_BATCH, max(min_runs,
                                  math.ceil(remaining / (GUIDED_ROUNDS * max(1, n_workers)))))
        out.append(cases[start:start + size])
        start += size
    return out


def workers_cpu_s(client: Any) -> float:
    """The process CPU seconds of every worker, summed (``time.process_time`` there)."""
    return float(sum(client.run(time.process_time).values()))


def open_client(scheduler: str | None, workers: int | None, numba_cache: Path | None) -> Any:
    """A Dask client: to ``scheduler``, or to a new ``LocalCluster`` of worker processes."""
    import dask
    from dask.distributed import Client, LocalCluster

    if scheduler is not None:
        return Client(scheduler, timeout="30s")
    env: dict[str, str] = {}
    if numba_cache is not None:
        numba_cache.mkdir(parents=True, exist_ok=True)
        env["NUMBA_CACHE_DIR"] = str(numba_cache.resolve())
    # The worker processes are spawned with this process's environment: NUMBA_CACHE_DIR
    # must be there before they import numba. It is set only while the cluster starts, so
    # this process (a test, a library user) keeps its own. A worker the nanny restarts
    # later is given it as ``env`` (Dask sets it in the new process before the worker
    # starts).
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    config = dict(LOCAL_CLUSTER_CONFIG)
    if numba_cache is None and FORK_WORKERS:
        config["distributed.worker.multiprocessing-method"] = "fork"
    try:
        with dask.config.set(config):
            cluster = LocalCluster(n_workers=workers or os.cpu_count() or 1,
                                   threads_per_worker=1, processes=True,
                                   dashboard_address=None, silence_logs=logging.ERROR,
                                   env=env)
            return Client(cluster)
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def run_sweep(sweep: Sweep, out: Path, *, scheduler: str | None = None,
              workers: int | None = None, resume: bool = False,
              batch_runs: int | None = None, numba_cache: Path | None = None,
              quiet: bool = False) -> SweepOutcome:
    """Run every case of ``sweep`` not already in ``out/results.parquet`` (with ``resume``)
    and write the table. Ctrl-C keeps the finished runs in the table and re-raises."""
    from dask.distributed import as_completed
    from tqdm import tqdm

    out.mkdir(parents=True, exist_ok=True)
    table_path = out / RESULTS_FILE
    # a run that raised (``error``) may go through another time; the other statuses are
    # what the configuration gives
    rows = [r for r in read_table(table_path) if r["status"] != FAILED] if resume else []
    done_ids = {r["run_id"] for r in rows}
    todo = [c for c in sweep.cases if c.run_id not in done_ids]
    skipped = len(sweep.cases) - len(todo)
    history_dir = None
    if sweep.histories:
        history_dir = str((out / HISTORY_DIR).resolve())
        Path(history_dir).mkdir(exist_ok=True)
    t0 = time.perf_counter()
    failed = 0
    n_workers = 0
    ready_s = close_s = 0.0
    client_cpu_s = worker_cpu_s = math.nan
    client = open_client(scheduler, workers, numba_cache) if todo else None
    try:
        if client is not None:
            warm = next((c for c in sweep.cases if c.resolved is not None), None)
            if warm is not None:
                client.register_plugin(WarmUp(warm.resolved, warm.base))
            client.wait_for_workers(1, timeout=120)
            # asked of the scheduler now: ``scheduler_info()`` returns the client's cached
            # identity, which its periodic refresh (that lists no workers) can overwrite
            n_workers = len(client.nthreads())
            ready_s = time.perf_counter() - t0
            client_cpu0, worker_cpu0 = time.process_time(), workers_cpu_s(client)
            futures = {}
            for i, chunk in enumerate(batches(todo, max(1, n_workers), batch_runs)):
                future = client.submit(run_batch, chunk, sweep.metrics, history_dir,
                                       retries=TASK_RETRIES, pure=False,
                                       key=f"sweep-{sweep.name}-{i}-{chunk[0].run_id}")
                futures[future] = chunk
            show = not quiet and sys.stderr.isatty()
            next_write = time.perf_counter() + CHECKPOINT_EVERY_S
            with tqdm(total=len(todo), desc=sweep.name, unit="run", file=sys.stderr,
                      disable=not show) as bar:
                for future in as_completed(futures):
                    try:
                        new = future.result()
                    except Exception as exc:  # noqa: BLE001 - the batch's runs are recorded
                        new = [lost_row(c, exc) for c in futures[future]]
                    for row in new:
                        rows.append(flat_row(row, sweep.parameters))
                        failed += row["status"] != OK
                    bar.update(len(new))
                    bar.set_postfix(failed=failed)
                    if time.perf_counter() >= next_write:
                        t_write = time.perf_counter()
                        write_table(rows, table_path)
                        now = time.perf_counter()
                        next_write = now + max(CHECKPOINT_LATER_S,
                                               CHECKPOINT_COST * (now - t_write))
            client_cpu_s = time.process_time() - client_cpu0
            worker_cpu_s = workers_cpu_s(client) - worker_cpu0
    finally:
        if rows:
            write_table(rows, table_path)
        if client is not None:
            t_close = time.perf_counter()
            cluster = client.cluster
            client.close()
            if cluster is not None:
                cluster.close()
            close_s = time.perf_counter() - t_close
    metric_columns = [k for r in rows for k in r
                      if k not in (*FIRST_COLUMNS, *LAST_COLUMNS, *sweep.parameters)]
    return SweepOutcome(rows=sorted(rows, key=lambda r: r["case"]), ran=len(todo),
                        skipped=skipped, failed=failed,
                        wall_time_s=time.perf_counter() - t0, workers=n_workers,
                        ready_s=ready_s, close_s=close_s,
                        metric_columns=list(dict.fromkeys(metric_columns)),
                        client_cpu_s=client_cpu_s, worker_cpu_s=worker_cpu_s)


def lost_row(case: Case, exc: BaseException) -> dict[str, Any]:
    """The row of a case whose task failed as a whole (its worker kept dying)."""
    return {"run_id": case.run_id, "case": case.index, "base": Path(case.base).name,
            "scenario": "", "params": dict(case.params), "metrics": {}, "status": FAILED,
            "error": f"{type(exc).__name__}: {exc}", "wall_time_s": math.nan,
            "sim_wall_time_s": math.nan, "worker": ""}
