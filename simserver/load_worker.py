"""The server's off-tick worker: a separate process that reads and builds what a control
asks for (``load``), so the 1 kHz loop never parses a file.

A process, not a thread: YAML parsing holds Python's GIL for as long as it runs (a thread
would stop the tick just the same), an alias bomb's memory stays in the worker, and a
worker stuck on a file that never ends (a FIFO) is killed and replaced
(:meth:`ProcessPreparer.restart`). The loop submits a picklable ``(function, arguments)``
and polls the future between ticks (:class:`simserver.server_loop.ServerLoop`); the
worker runs at a lower priority than the server (nice +5, ``SCHED_OTHER``) and is
started and warmed (its imports, the configured scene read once) as the server starts.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any

log = logging.getLogger("simserver.server")

WORKER_NICE = 5
"""The worker yields the CPU to the server's threads when they are not real-time (under
SCHED_FIFO they always win); not more, or a busy machine starves a ``load``."""


def _worker_init() -> None:
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        os.nice(WORKER_NICE)
    except (OSError, AttributeError):
        pass


class ProcessPreparer:
    """One worker process running control jobs, replaced when it fails or hangs."""

    def __init__(self) -> None:
        self._pool: ProcessPoolExecutor | None = None
        self.restarts = 0
        self._promoted: set[int] = set()

    def _executor(self) -> ProcessPoolExecutor:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(
                max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                initializer=_worker_init)
        return self._pool

    def warm(self, fn: Callable[..., Any], *args: Any) -> Future:
        """Start the worker and give it a first job (its imports and one scene read) now,
        before the clock starts, so that a later job finds it ready; not waited for."""
        return self._executor().submit(fn, *args)

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        """Run ``fn(*args)`` in the worker; the future of its result."""
        pool = self._executor()
        future = pool.submit(fn, *args)
        self._promote_reader(pool)
        return future

    def _promote_reader(self, pool: ProcessPoolExecutor) -> None:
        """Give the pool's result-reading thread (it holds the GIL while it unpickles a
        result) the caller's real-time policy, one priority lower: at normal priority,
        preempted by CPU hogs while it held the GIL, it stalled the real-time tick 5 ms
        and more (issue 13). It sleeps on a pipe otherwise."""
        thread = getattr(pool, "_executor_manager_thread", None)
        tid = getattr(thread, "native_id", None)
        if tid is None or tid in self._promoted:
            return
        self._promoted.add(tid)
        try:
            if os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK != os.SCHED_FIFO:
                return
            priority = max(1, os.sched_getparam(0).sched_priority - 1)
            os.sched_setscheduler(tid, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK,
                                  os.sched_param(priority))
        except (OSError, AttributeError):
            pass  # not permitted, or the thread ended: it keeps its policy

    def restart(self) -> None:
        """Kill the worker (stuck or broken) and start a new one on the next submit."""
        pool, self._pool = self._pool, None
        if pool is None:
            return
        self.restarts += 1
        for proc in list(getattr(pool, "_processes", {}).values()):
            try:
                proc.kill()  # SIGKILL: a worker blocked in open() on a FIFO ignores nothing
            except OSError:
                pass
        pool.shutdown(wait=False, cancel_futures=True)

    def close(self) -> None:
        """Stop the worker."""
        pool, self._pool = self._pool, None
        if pool is not None:
            for proc in list(getattr(pool, "_processes", {}).values()):
                proc.kill()
            pool.shutdown(wait=True, cancel_futures=True)
