"""The ROS 2 adapter as a child of ``serve``: started when the server is ready, restarted
with backoff when it dies, stopped with the server.

An adapter that crashes (or is killed) would otherwise leave ROS users without the car and
without a word on the ROS side (issue 34: after a ``kill -9`` it stayed gone). The
supervisor's thread waits for the child (``waitpid``, holding no lock the loop needs),
logs each end with its exit code and starts it again after a delay: :data:`FIRST_DELAY_S`,
doubled after each run shorter than :data:`HEALTHY_RUN_S` up to :data:`MAX_DELAY_S` (a
child that cannot start does not spin), back to the first delay after a healthy run.
:meth:`status` (the ``ros2`` member of ``get_config``'s reply) says what it is doing.
"""

from __future__ import annotations

import contextlib
import logging
import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

log = logging.getLogger("simserver.server")

FIRST_DELAY_S = 0.5
"""Wait before the first restart after a crash (a ``kill -9``: back within 2 s, issue 34)."""

MAX_DELAY_S = 30.0
"""The longest wait between restarts of a child that keeps dying at once."""

HEALTHY_RUN_S = 30.0
"""A run at least this long resets the delay to :data:`FIRST_DELAY_S`."""


class AdapterSupervisor:
    """One child process (the ROS 2 adapter), kept running until :meth:`stop`.

    Parameters
    ----------
    args : sequence of str
        Its command line.
    name : str
        What to call it in the log ("the ROS 2 adapter").
    """

    def __init__(self, args: Sequence[str], name: str = "the ROS 2 adapter") -> None:
        self.args = list(args)
        self.name = name
        self.proc: subprocess.Popen | None = None
        self.state = "stopped"  # starting/running, restarting (waiting its delay), stopped
        self.restarts = 0
        self.last_exit_code: int | None = None
        self.restart_at: float | None = None  # monotonic time of the next start
        self.started_at = 0.0
        self._delay_s = FIRST_DELAY_S
        self._stopping = threading.Event()
        self._lock = threading.Lock()  # start/stop against the watcher's restart
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Start the child and the thread that watches it."""
        with self._lock:
            self._spawn()
        self._thread = threading.Thread(target=self._watch, name="ros2-watch", daemon=True)
        self._thread.start()

    def _spawn(self) -> None:
        self.proc = subprocess.Popen(self.args)
        self.started_at = time.monotonic()
        self.state, self.restart_at = "running", None

    def _watch(self) -> None:
        while not self._stopping.is_set():
            proc = self.proc
            assert proc is not None
            code = proc.wait()
            if self._stopping.is_set():
                return
            ran_s = time.monotonic() - self.started_at
            self._delay_s = FIRST_DELAY_S if ran_s >= HEALTHY_RUN_S else self._delay_s
            self.last_exit_code = code
            self.state = "restarting"
            self.restart_at = time.monotonic() + self._delay_s
            log.error("%s (pid %d) ended with exit code %d after %.1f s; restarting it in "
                      "%.1f s", self.name, proc.pid, code, ran_s, self._delay_s)
            if self._stopping.wait(self._delay_s):
                return
            self._delay_s = min(2.0 * self._delay_s, MAX_DELAY_S)
            with self._lock:
                if self._stopping.is_set():
                    return
                try:
                    self._spawn()
                except OSError as exc:  # cannot even start: try again after the delay
                    log.error("%s could not be restarted: %s", self.name, exc)
                    self.restart_at = time.monotonic() + self._delay_s
                    if self._stopping.wait(self._delay_s):
                        return
                    continue
                self.restarts += 1
            log.warning("%s restarted (pid %d, restart %d)", self.name, self.proc.pid,
                        self.restarts)

    def status(self) -> dict[str, Any]:
        """What the supervisor is doing, for ``get_config``'s reply."""
        proc = self.proc
        out: dict[str, Any] = {"state": self.state, "restarts": self.restarts,
                               "last_exit_code": self.last_exit_code,
                               "pid": proc.pid if proc is not None and self.state == "running"
                               else None}
        restart_at = self.restart_at
        if self.state == "restarting" and restart_at is not None:
            out["restart_in_s"] = round(max(0.0, restart_at - time.monotonic()), 3)
        return out

    def stop(self, stop_child: Callable[[subprocess.Popen], None]) -> None:
        """No more restarts; the child is stopped with ``stop_child``."""
        self._stopping.set()
        with self._lock:
            self.state = "stopped"
            proc = self.proc
        if proc is not None:
            with contextlib.suppress(OSError):
                stop_child(proc)
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5)

