"""Log files the server writes: opened safely, written off the tick, cut cleanly on failure.

An optional log must never take the server down nor be turned against the machine
(``docs/reliability.md``, "Logs that fail safe"; ``docs/security.md`` section 1):

- :func:`open_log_file` opens the path without following a symbolic link
  (``O_NOFOLLOW``: a link planted at the path would make the server, often root, truncate
  the link's target) and without blocking (``O_NONBLOCK``: a FIFO with no reader would hold
  the start-up for ever), then checks with ``fstat`` that it holds a regular file before
  it truncates anything;
- :class:`LogWriter` takes lines from the tick thread (an append to a deque, no I/O, no
  lock) and writes them from a thread of its own, so a slow or stalled disk never delays
  a tick. A write that fails (a full disk, an I/O error, the file size limit) closes the
  log with one warning: the lines written so far stay whole and an end line says where
  and why the log was cut. Space for that end line is reserved ahead of the data
  (``fallocate`` with ``FALLOC_FL_KEEP_SIZE``), so it can be written on a disk that is
  full.
"""

from __future__ import annotations

import collections
import ctypes
import ctypes.util
import errno
import logging
import logging.handlers
import math
import os
import queue
import resource
import stat
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

from simserver.adapters.validate import ConfigError

log = logging.getLogger("simserver")

LOG_RESERVE_BYTES = 16 * 1024
"""Space kept allocated past the written data for the end line of a cut log (an end line
with the full state is about 1 KiB)."""
LOG_PREALLOCATE_BYTES = 64 * 1024
"""Space allocated at a time ahead of the data (fewer ``fallocate`` calls)."""
MAX_PENDING_LINES = 200_000
"""Lines waiting for the writer thread at most (about 14 MB, 200 s of inputs changing at
every tick): past this the disk is not keeping up and the log is cut."""

_FALLOC_FL_KEEP_SIZE = 1
_KIND_NAMES = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO"),
               (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
               (stat.S_ISSOCK, "a socket"), (stat.S_ISLNK, "a symbolic link"))


def file_kind(mode: int) -> str:
    """What a file of this ``st_mode`` is, in words."""
    return next((name for test, name in _KIND_NAMES if test(mode)), "not a regular file")


def check_log_path(path: Path) -> str | None:
    """Why ``path`` cannot be a log (a link, not a regular file), or None; never opens it.

    For an early error at start-up; :func:`open_log_file` checks again on the open file.
    """
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return None
    except OSError as exc:
        return f"cannot examine it: {exc.strerror or exc}"
    if stat.S_ISLNK(mode):
        return "is a symbolic link: a log is never written through one"
    if not stat.S_ISREG(mode):
        return f"is {file_kind(mode)}, not a regular file"
    return None


def open_log_file(path: Path, what: str = "log") -> int:
    """Open ``path`` for writing a log from its start: a file descriptor.

    Raises ``ConfigError`` naming the file if it is a symbolic link, not a regular file
    (a FIFO, a device, a folder) or has other hard links; nothing is truncated then.
    Never blocks (a FIFO without a reader is refused at once).
    """
    flags = (os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        fd = os.open(path, flags, 0o644)
    except OSError as exc:
        refused = (errno.ELOOP, errno.ENXIO, errno.EISDIR)  # a link, a FIFO, a folder
        why = check_log_path(path) if exc.errno in refused else None
        raise ConfigError(f"{path}: cannot write the {what}: "
                          f"{why or exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise ConfigError(f"{path}: cannot write the {what}: it is "
                              f"{file_kind(st.st_mode)}, not a regular file")
        if st.st_nlink > 1:
            raise ConfigError(f"{path}: cannot write the {what}: the file has "
                              f"{st.st_nlink - 1} other hard link(s)")
        os.ftruncate(fd, 0)
        os.set_blocking(fd, True)
    except BaseException as exc:
        os.close(fd)
        if isinstance(exc, OSError):
            raise ConfigError(f"{path}: cannot write the {what}: "
                              f"{exc.strerror or exc}") from None
        raise
    return fd


def write_log_bytes(path: Path, data: bytes, what: str = "log") -> None:
    """Write a whole small file (at shutdown) through :func:`open_log_file`."""
    fd = open_log_file(path, what)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
    except OSError as exc:
        raise ConfigError(f"{path}: cannot write the {what}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)


_libc_fallocate: Callable[..., int] | None = None


def _fallocate_keep_size(fd: int, offset: int, length: int) -> None:
    """Allocate ``[offset, offset + length)`` without changing the file's size; raises
    ``OSError`` (``EOPNOTSUPP`` where the file system or libc cannot)."""
    global _libc_fallocate
    if _libc_fallocate is None:
        name = ctypes.util.find_library("c")
        fn = getattr(ctypes.CDLL(name, use_errno=True), "fallocate64", None) if name else None
        if fn is None:
            raise OSError(errno.EOPNOTSUPP, "fallocate is not available")
        fn.argtypes = (ctypes.c_int, ctypes.c_int, ctypes.c_int64, ctypes.c_int64)
        fn.restype = ctypes.c_int
        _libc_fallocate = fn
    if _libc_fallocate(fd, _FALLOC_FL_KEEP_SIZE, offset, length) != 0:
        err = ctypes.get_errno()
        raise OSError(err, os.strerror(err))


def _reason(exc: OSError) -> str:
    name = errno.errorcode.get(exc.errno or 0)
    return f"{exc.strerror or exc} ({name})" if name else str(exc.strerror or exc)


class LogWriter:
    """A log written line by line from a thread of its own (``docs/reliability.md``).

    Parameters
    ----------
    fd : int
        The open file (:func:`open_log_file`), written from offset 0; the writer owns it.
    path : Path
        Its path, for the warning.
    cut_line : callable
        ``cut_line(key, reason)``: the end line (text with its newline) of a log cut
        before the line of key ``key`` (the command log: its step), for ``reason``.
    period_s : float
        Longest time between two writes of the lines handed over.
    what : str
        What the log is, for the warning.

    The tick thread calls :meth:`put` (and, at shutdown, :meth:`close`); everything else
    runs on the writer thread. ``cut`` is the reason the log was cut, or None.
    """

    def __init__(self, fd: int, path: Path, cut_line: Callable[[int, str], str],
                 period_s: float, what: str = "log") -> None:
        self._fd = fd
        self.path = path
        self.what = what
        self._cut_line = cut_line
        self._period_s = period_s
        self._pending: collections.deque[tuple[int, str]] = collections.deque()
        self._wake = threading.Event()
        self._closing = False
        self._overrun_key: int | None = None
        self.cut: str | None = None
        self.stopped = False  # no more lines are taken (cut, or closed)
        self.bytes_written = 0
        self.lines_written = 0
        self._reserved_to = 0  # bytes allocated from the start of the file
        self._can_reserve = True
        soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
        self._size_limit = None if soft == resource.RLIM_INFINITY else int(soft)
        self._thread = threading.Thread(target=self._run, name=f"{what}-writer",
                                        daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ tick thread
    def put(self, key: int, line: str, urgent: bool = False) -> None:
        """Hand one line (with its newline) over; ``urgent``: written at once rather than
        within ``period_s``. Never blocks and never does I/O."""
        if self.stopped:
            return
        if len(self._pending) >= MAX_PENDING_LINES:
            self._overrun_key = key
            self.stopped = True
            self._wake.set()
            return
        self._pending.append((key, line))
        if urgent:
            self._wake.set()

    def close(self, last: tuple[int, str] | None = None, timeout_s: float = 10.0) -> None:
        """Hand over the last line, write everything, fsync and close (at shutdown)."""
        if last is not None:
            self.put(*last)
        self.stopped = True
        self._closing = True
        self._wake.set()
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            log.warning("%s: the %s could not be written within %.0f s of the shutdown "
                        "(a stalled disk?): left as it is", self.path, self.what, timeout_s)

    # ------------------------------------------------------------------ writer thread
    def _run(self) -> None:
        try:
            while True:
                self._wake.wait(self._period_s)
                self._wake.clear()
                closing = self._closing
                batch = []
                try:
                    while True:
                        batch.append(self._pending.popleft())
                except IndexError:
                    pass
                if batch and not self._write_batch(batch, final=closing):
                    return
                if self._overrun_key is not None:
                    self._fail(self._overrun_key, f"the disk did not keep up: "
                               f"{MAX_PENDING_LINES} lines were waiting to be written")
                    return
                if closing:
                    self._finish()
                    return
        except Exception as exc:  # a bug here must not reach the tick: close the log
            log.exception("%s: the %s writer failed", self.path, self.what)
            self._fail(None, f"the writer failed ({type(exc).__name__})")

    def _write_batch(self, batch: list[tuple[int, str]], final: bool) -> bool:
        data = "".join(line for _, line in batch).encode("utf-8")
        start = self.bytes_written
        try:
            # room for this data and, unless it is the last, for the end line of a cut
            self._allocate(start + len(data) + (0 if final else LOG_RESERVE_BYTES))
            self._pwrite_all(data, start)
        except OSError as exc:
            self._fail(batch[0][0], _reason(exc), truncate_to=start)
            return False
        self.bytes_written = start + len(data)
        self.lines_written += len(batch)
        return True

    def _allocate(self, end: int) -> None:
        if self._size_limit is not None and end > self._size_limit:
            raise OSError(errno.EFBIG, "the file size limit (RLIMIT_FSIZE) is reached")
        if not self._can_reserve or end <= self._reserved_to:
            return
        try:
            try:
                _fallocate_keep_size(self._fd, self._reserved_to,
                                     end + LOG_PREALLOCATE_BYTES - self._reserved_to)
                self._reserved_to = end + LOG_PREALLOCATE_BYTES
            except OSError as exc:
                if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
                    raise
                _fallocate_keep_size(self._fd, self._reserved_to, end - self._reserved_to)
                self._reserved_to = end
        except OSError as exc:
            if exc.errno in (errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
                self._can_reserve = False  # written without a reserve: a cut is best effort
                return
            raise

    def _pwrite_all(self, data: bytes, offset: int) -> None:
        view = memoryview(data)
        while view:
            n = os.pwrite(self._fd, view, offset)
            if n <= 0:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            view, offset = view[n:], offset + n

    def _fail(self, key: int | None, reason: str, truncate_to: int | None = None) -> None:
        """Cut the log: whole lines only, then the end line saying why; close it."""
        self.stopped = True
        self.cut = reason
        size = self.bytes_written if truncate_to is None else truncate_to
        marked = False
        try:
            os.ftruncate(self._fd, size)  # drop a line written in part
            if key is not None and size > 0:  # a log with no header holds nothing to mark
                end = self._cut_line(key, reason).encode("utf-8")
                try:
                    self._pwrite_all(end, size)  # into the reserved space
                    marked = True
                except OSError:
                    os.ftruncate(self._fd, size)
        except OSError:
            pass
        log.warning("%s: the %s cannot be written (%s): closed%s; the live loop goes on",
                    self.path, self.what, reason,
                    " with its end marked" if marked else "")
        self._close_fd()

    def _finish(self) -> None:
        try:
            os.ftruncate(self._fd, self.bytes_written)  # release the space reserved past it
            os.fsync(self._fd)
        except OSError:  # a file system without fsync: the data was written
            pass
        self._close_fd()

    def _close_fd(self) -> None:
        if self._fd >= 0:
            try:
                os.close(self._fd)
            except OSError:
                pass
            self._fd = -1


# ---------------------------------------------------------------- the process's own log
LOG_QUEUE_LINES = 10_000
"""Log records waiting for the output thread at most; past this they are dropped and
counted (a stalled terminal or pipe must not grow the server's memory)."""


class _DroppingQueueHandler(logging.handlers.QueueHandler):
    """A ``QueueHandler`` that never blocks: a full queue drops the record and counts it."""

    def __init__(self, q: queue.Queue) -> None:
        super().__init__(q)
        self.dropped = 0

    def enqueue(self, record: logging.LogRecord) -> None:
        try:
            self.queue.put_nowait(record)
        except queue.Full:
            self.dropped += 1


class ProcessLog:
    """The process's log lines written by a thread of their own (``configure_logging``).

    ``logging.basicConfig`` writes each record in the thread that logs it. The tick thread
    logs (a watchdog trip, a refused control), and a write to a terminal or a pipe that
    nobody reads fast enough blocks once its buffer is full (64 KiB for a pipe): the tick
    would wait on it. Here a log call only formats the record and puts it on a bounded
    queue (``LOG_QUEUE_LINES``); the ``simserver-log`` thread writes it out.
    """

    def __init__(self, level: str | int, stream, fmt: str) -> None:
        self._queue: queue.Queue = queue.Queue(LOG_QUEUE_LINES)
        self.handler = _DroppingQueueHandler(self._queue)
        self._out = logging.StreamHandler(stream)
        self._out.setFormatter(logging.Formatter(fmt))
        root = logging.getLogger()
        for old in list(root.handlers):
            root.removeHandler(old)
        root.addHandler(self.handler)
        root.setLevel(level.upper() if isinstance(level, str) else level)
        self._thread: threading.Thread | None = threading.Thread(
            target=self._write_loop, name="simserver-log", daemon=True)
        self._thread.start()

    def renew_thread(self, timeout_s: float = 1.0) -> None:
        """Replace the writer thread by one started from the calling thread, so that it
        gets that thread's scheduling: the server calls it from the tick thread once the
        real-time policy is applied (``RealtimeScheduler.promote_new_threads`` then gives
        it the priority below the tick's, as zenoh's threads). A writer at normal
        priority, preempted by CPU hogs while it holds the GIL, would stall the tick."""
        old = self._thread
        if old is None:
            return
        try:
            self._queue.put(None, timeout=timeout_s)  # the old writer ends after the queue
            old.join(timeout_s)
        except queue.Full:
            pass  # the output is stuck: the new writer takes over what comes next
        self._thread = threading.Thread(target=self._write_loop, name="simserver-log",
                                        daemon=True)
        self._thread.start()

    def _write_loop(self) -> None:
        while (record := self._queue.get()) is not None:
            self._out.handle(record)

    @property
    def dropped(self) -> int:
        """Records dropped because the output did not keep up."""
        return self.handler.dropped

    def close(self, timeout_s: float = 5.0) -> None:
        """Write what is queued and stop the thread (idempotent); a stream still blocked
        after ``timeout_s`` is left to its daemon thread."""
        thread, self._thread = self._thread, None
        if thread is None:
            return
        logging.getLogger().removeHandler(self.handler)
        try:
            self._queue.put(None, timeout=timeout_s)
        except queue.Full:
            return
        thread.join(timeout_s)
        if self.dropped:
            print(f"simserver: {self.dropped} log lines dropped (the output did not keep up)",
                  file=sys.stderr)


_process_log: ProcessLog | None = None


def configure_logging(level: str | int = "INFO", stream=None,
                      fmt: str = "%(asctime)s %(levelname)s %(name)s: %(message)s"
                      ) -> ProcessLog:
    """Send every log record of this process through ``ProcessLog`` to ``stream``
    (default ``sys.stderr``): a log call never waits on the output."""
    global _process_log
    if _process_log is not None:
        _process_log.close()
    _process_log = ProcessLog(level, sys.stderr if stream is None else stream, fmt)
    return _process_log


def renew_log_thread() -> None:
    """``ProcessLog.renew_thread`` of the process's log, if ``configure_logging`` made one
    (a server run in-process by tests keeps the caller's logging)."""
    if _process_log is not None:
        _process_log.renew_thread()


class RateLimitedLog:
    """Log a recurring warning at most once per ``interval_s``, with the count in between
    (to ``logger``, default the ``simserver`` logger)."""

    def __init__(self, interval_s: float = 1.0, logger: logging.Logger | None = None) -> None:
        self.interval_s = interval_s
        self.log = logger or log
        self._last = -math.inf
        self._suppressed = 0

    def warn(self, message: str, now_s: float | None = None) -> None:
        """Log ``message`` unless one was logged less than ``interval_s`` before ``now_s``."""
        now = time.monotonic() if now_s is None else now_s
        if now - self._last >= self.interval_s:
            extra = f" ({self._suppressed} more since the last report)" if self._suppressed else ""
            self.log.warning("%s%s", message, extra)
            self._last = now
            self._suppressed = 0
        else:
            self._suppressed += 1
