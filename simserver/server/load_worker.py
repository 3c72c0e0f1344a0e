"""The server's off-tick worker: a separate process that reads and builds what a control
asks for (``load``), so the 1 kHz loop never parses a file.

A process, not a thread: YAML parsing holds Python's GIL for as long as it runs (a thread
would stop the tick just the same), an alias bomb's memory stays in the worker, and a
worker stuck on a file that never ends (a FIFO) is killed and replaced
(:meth:`ProcessPreparer.restart`). The loop submits a picklable ``(function, arguments)``
and polls the future between ticks (:class:`simserver.server.loop.ServerLoop`); the
worker runs at a lower priority than the server (nice +5, ``SCHED_OTHER``) and is
started and warmed (its imports, the configured scene read once) as the server starts.

Big arrays do not cross the result pipe (issue 13). A terrain scene's result is megabytes
of height and friction grids (18 MB for ``velodrome.xodr``); pickled through the pipe,
the server's result thread unpickled them holding the GIL for 1.4-34 ms while the tick
waited. The worker writes every C-contiguous array of at least ``SHARE_MIN_BYTES`` of a
result into one file of ``SHARE_DIR`` (tmpfs: memory, no disk) and pickles only a
reference to it (:class:`SharedResult`, a few kilobytes). The server maps that file
(:func:`opened`, in the tick: tens of microseconds, no copy: the pages are the worker's),
unlinks its name at once, and the arrays are views on the mapping: the memory is freed
when the last of them goes, i.e. when the model holding them is swapped out.

Lifetime bound: a block's name exists only between the worker writing it and the server
mapping it (one result at a time: the loop prepares one load per vehicle; a block is the
size of one scene's big arrays, 18 MB for the largest shipped terrain). If the server
dies in between, or a late result is abandoned, the block is left in ``SHARE_DIR``; its
name carries the server's pid, and :func:`remove_stale_blocks` (run when a
:class:`ProcessPreparer` is made, restarted or closed) deletes the blocks of this server
and of servers no longer running. So at most one block per vehicle of a crashed server
outlives it, until the next server starts on the machine. A block that does not fit
(tmpfs full) is not made: the result then comes through the pipe as before. Mapped and
unlinked, a block still counts against the tmpfs until unmapped: the running model's and
the one being swapped in, at most twice a scene's arrays.
"""

from __future__ import annotations

import io
import itertools
import logging
import mmap
import multiprocessing
import os
import pickle
import queue
import select
import signal
import tempfile
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger("simserver.server")

WORKER_NICE = 5
"""The worker yields the CPU to the server's threads when they are not real-time (under
SCHED_FIFO they always win); not more, or a busy machine starves a ``load``."""


SHARE_DIR = Path("/dev/shm") if Path("/dev/shm").is_dir() else Path(tempfile.gettempdir())
"""Where result blocks are written: tmpfs where there is one (memory pages the server maps
as they are)."""
SHARE_PREFIX = "simserver-load-"
"""A block's file name: ``simserver-load-<server pid>-<worker pid>-<n>``."""
SHARE_MIN_BYTES = 64 * 1024
"""Arrays smaller than this are pickled as usual (copying them costs microseconds)."""
SHARE_ALIGN = 64
"""Each array starts at a multiple of this many bytes in its block (a cache line)."""


class _Block:
    """The shared file of one result, as pickled: unpickled by mapping it (:func:`_map`)."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.size = 0  # grows as arrays are pickled (pickled itself before the last one)

    def __reduce__(self) -> tuple[Any, ...]:
        return _map, (self.path,)


def _map(path: str) -> mmap.mmap:
    """Map a result block (shared, writable: the arrays keep numba's writable C-array type,
    so the compiled step is not specialised anew) and unlink its name: from now on its
    memory lives as long as the arrays viewing it."""
    fd = os.open(path, os.O_RDWR)
    try:
        mapping = mmap.mmap(fd, 0)  # the whole file
    finally:
        os.close(fd)
        os.unlink(path)
    return mapping


def _view(mapping: mmap.mmap, offset: int, dtype: str, shape: tuple[int, ...]) -> np.ndarray:
    """An array of a mapped block, without copying."""
    count = int(np.prod(shape, dtype=np.int64))
    return np.frombuffer(mapping, dtype=np.dtype(dtype), count=count,
                         offset=offset).reshape(shape)


class _SharingPickler(pickle.Pickler):
    """Pickles big C-contiguous arrays as views of ``block`` at increasing offsets (their
    bytes are written to it afterwards: :func:`share_result`)."""

    def __init__(self, file: io.BytesIO, block: _Block) -> None:
        super().__init__(file, protocol=pickle.HIGHEST_PROTOCOL)
        self.block = block
        self.arrays: list[tuple[int, np.ndarray]] = []

    def reducer_override(self, obj: Any) -> Any:
        if (type(obj) is np.ndarray and obj.nbytes >= SHARE_MIN_BYTES
                and obj.flags.c_contiguous and not obj.dtype.hasobject):
            offset = -(-self.block.size // SHARE_ALIGN) * SHARE_ALIGN
            self.block.size = offset + obj.nbytes
            self.arrays.append((offset, obj))
            return _view, (self.block, offset, obj.dtype.str, obj.shape)
        return NotImplemented


class SharedResult:
    """A job's result whose big arrays are in a shared block: :func:`opened` maps it."""

    def __init__(self, payload: bytes, path: str | None) -> None:
        self.payload = payload
        self.path = path  # None: nothing was big enough, the payload is self-contained

    def open(self) -> Any:
        """The result, its arrays viewing the block (which is unlinked)."""
        return pickle.loads(self.payload)


_counter = itertools.count()


def share_result(value: Any, server_pid: int) -> SharedResult:
    """``value`` pickled with its big arrays written to a new block (in the worker)."""
    path = SHARE_DIR / f"{SHARE_PREFIX}{server_pid}-{os.getpid()}-{next(_counter)}"
    block = _Block(str(path))
    buffer = io.BytesIO()
    pickler = _SharingPickler(buffer, block)
    pickler.dump(value)
    if not pickler.arrays:
        return SharedResult(buffer.getvalue(), None)
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError:  # no room or no tmpfs: through the pipe, as before
        return SharedResult(pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL), None)
    try:
        # the pages reserved first: a full tmpfs (a container's 64 MB /dev/shm) is then an
        # ENOSPC here, not a SIGBUS while writing through the mapping
        os.posix_fallocate(fd, 0, block.size)
        with mmap.mmap(fd, block.size) as out:
            for offset, array in pickler.arrays:
                out[offset:offset + array.nbytes] = memoryview(array).cast("B")
    except OSError:
        os.close(fd)
        os.unlink(path)
        return SharedResult(pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL), None)
    os.close(fd)
    return SharedResult(buffer.getvalue(), str(path))


def run_shared(server_pid: int, fn: Callable[..., Any], *args: Any) -> SharedResult:
    """Run ``fn(*args)`` in the worker and share its result's big arrays."""
    from simserver.adapters.validate import report_progress

    report_progress(f"{getattr(fn, '__name__', 'a job')} started")  # queued no longer
    return share_result(fn(*args), server_pid)


def _warm(fn: Callable[..., Any], *args: Any) -> Any:
    """The warm-up job, its start and end reported: a job queued behind it is seen to wait
    on a worker that progresses, not on a stuck one."""
    from simserver.adapters.validate import report_progress

    report_progress("warming up")
    try:
        return fn(*args)
    finally:
        report_progress("warmed up")


def opened(result: Any) -> Any:
    """A job's result as the loop uses it: a :class:`SharedResult` mapped, else as it is."""
    return result.open() if isinstance(result, SharedResult) else result


class Releaser:
    """Drops what a swap replaced (the old model and scene) in a thread of its own.

    Freeing a terrain's grids is a ``munmap`` that returns their pages: 20-40 ms for 18 MB on
    this VM, far more than a tick. Dropped in the tick thread, it would stall it (a numpy
    array's own memory is even freed holding the GIL); here the last reference goes in this
    thread, and a mapped block is unmapped with the GIL released (CPython's ``mmap``)."""

    def __init__(self) -> None:
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="simserver-release",
                                        daemon=True)
        self._thread.start()

    def release(self, item: Any) -> None:
        """Take ``item`` (the caller must hold no other reference to it)."""
        self._queue.put(item)

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            del item

    def idle(self) -> bool:
        """True when nothing waits to be dropped (tests)."""
        return self._queue.empty()


_releaser: Releaser | None = None


def release_later(item: Any) -> None:
    """Drop ``item`` in the :class:`Releaser` thread (started on first use)."""
    global _releaser
    if _releaser is None:
        _releaser = Releaser()
    _releaser.release(item)


def remove_stale_blocks(server_pid: int | None = None, directory: Path | None = None) -> int:
    """Delete the result blocks left in ``SHARE_DIR`` by this server (``server_pid``: a
    result abandoned when its worker was killed) and by servers no longer running (a
    crash); the number deleted."""
    removed = 0
    for path in (directory or SHARE_DIR).glob(f"{SHARE_PREFIX}*"):
        try:
            owner = int(path.name[len(SHARE_PREFIX):].split("-")[0])
        except ValueError:
            continue
        if owner != server_pid:
            try:
                os.kill(owner, 0)
                continue  # another running server's
            except ProcessLookupError:
                pass
            except PermissionError:
                continue  # another user's running process
        try:
            path.unlink()
            removed += 1
        except OSError:
            pass
    return removed


def _exit_with(server_pid: int) -> None:
    """End this worker when the server ``server_pid`` is gone, however it ended.

    A ``ProcessPoolExecutor`` worker waits on its call queue, whose pipe it also holds
    open for writing (the queue is pickled to it whole), so a server killed with SIGKILL
    never gives it an end of file: it would wait for ever, an orphan. A pidfd of the server
    becomes readable when the server exits (Linux 5.3+); elsewhere the worker looks at its
    parent once a second."""
    try:
        fd = os.pidfd_open(server_pid)
    except (AttributeError, OSError):
        fd = None
    if fd is not None:
        select.select([fd], [], [])
    else:
        while os.getppid() == server_pid:
            time.sleep(1.0)
    os._exit(0)


_CLOCK_TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
PROGRESS_TEXT_BYTES = 200
"""The last progress message a worker reports is kept to this many bytes."""


class Progress:
    """A job's signs of life, shared between the server and its worker: a counter the
    worker bumps at each :func:`simserver.adapters.validate.report_progress` (a MiB of an
    ``.xodr`` read, a road rasterised) and the last message. The loop abandons a job whose
    counter has not moved for its stall time (a FIFO, a parser that does not return), not
    one that is slow but going on (``simserver.server.loop``); reading it is two memory
    loads, fit for the tick."""

    def __init__(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        self.count = ctx.RawValue("q", 0)
        self.text = ctx.RawArray("c", PROGRESS_TEXT_BYTES)

    def report(self, message: str) -> None:
        """In the worker: the message stored, then the counter bumped."""
        self.text.value = message.encode("utf-8", "replace")[:PROGRESS_TEXT_BYTES - 1]
        self.count.value += 1

    def seen(self) -> int:
        return self.count.value

    def message(self) -> str:
        return self.text.value.decode("utf-8", "replace")


def _worker_init(server_pid: int, progress: Progress | None = None) -> None:
    # Ctrl-C in a terminal signals the whole process group, the worker too: the server
    # ends it when it stops, so it ignores SIGINT (it was spawned with SIGINT blocked,
    # ``ProcessPreparer._spawn_without_sigint``, so none arrived during its imports; one
    # pending now is discarded by the ignore before the unblock)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    threading.Thread(target=_exit_with, args=(server_pid,), name="simserver-exit-with-server",
                     daemon=True).start()
    if progress is not None:
        from simserver.adapters.validate import set_progress_sink

        set_progress_sink(progress.report)
        progress.report("worker started")
        import simserver.sim.scenario  # noqa: F401 - the heavy imports, then said done
        from simserver.adapters.opendrive import compile_kernels

        progress.report("worker imports done")
        compile_kernels()  # from numba's cache; compiled once after an install
        progress.report("worker ready")
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
        self.server_pid = os.getpid()
        self.progress = Progress()
        remove_stale_blocks(self.server_pid)

    def _executor(self) -> ProcessPoolExecutor:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(
                max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                initializer=_worker_init, initargs=(self.server_pid, self.progress))
        return self._pool

    def warm(self, fn: Callable[..., Any], *args: Any) -> Future:
        """Start the worker and give it a first job (its imports and one scene read) now,
        before the clock starts, so that a later job finds it ready; not waited for."""
        return self._spawn_without_sigint(self._executor().submit, _warm, fn, *args)

    @staticmethod
    def _spawn_without_sigint(submit: Callable[..., Future], *args: Any) -> Future:
        """``submit(*args)`` with SIGINT blocked in this thread, so that a worker it
        spawns starts with SIGINT blocked (a signal mask survives fork and exec) until
        ``_worker_init`` ignores it: a Ctrl-C to the process group during the worker's
        seconds of imports otherwise printed a ``KeyboardInterrupt`` traceback from them
        (issue 32). A SIGINT meanwhile goes to another thread of the server, which does
        not block it, so the server's own Ctrl-C is not lost."""
        old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            return submit(*args)
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        """Run ``fn(*args)`` in the worker; the future of its result (a
        :class:`SharedResult`: :func:`opened` gives the value)."""
        pool = self._executor()
        future = self._spawn_without_sigint(pool.submit, run_shared, self.server_pid, fn, *args)
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

    def worker_cpu_s(self) -> float | None:
        """CPU seconds the worker process has used (``/proc``), None where unknown: a worker
        that uses CPU is working (slowly, on a busy machine, at nice +5), one blocked on a
        FIFO uses none. Read at most once a second by the loop (tens of microseconds)."""
        pool = self._pool
        procs = list(getattr(pool, "_processes", {}) or {}) if pool is not None else []
        total = 0.0
        for pid in procs:
            try:
                with open(f"/proc/{pid}/stat", "rb") as f:
                    fields = f.read().rsplit(b")", 1)[1].split()
            except (OSError, IndexError):
                return None
            total += (int(fields[11]) + int(fields[12])) / _CLOCK_TICKS  # utime, stime
        return total if procs else None

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
        remove_stale_blocks(self.server_pid)  # a result the killed worker left behind

    def close(self) -> None:
        """Stop the worker."""
        pool, self._pool = self._pool, None
        if pool is not None:
            for proc in list(getattr(pool, "_processes", {}).values()):
                proc.kill()
            pool.shutdown(wait=True, cancel_futures=True)
        remove_stale_blocks(self.server_pid)
