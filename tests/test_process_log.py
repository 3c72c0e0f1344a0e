"""The server's own log lines (``simserver.server.logfile.ProcessLog``): a log call never waits
on the output. A terminal or pipe that nobody reads blocks its writer once full (64 KiB
for a pipe); the tick thread logs (watchdog trips, refused controls), so with
``logging.basicConfig`` it would have waited there (issue 34, the ROS 2 flood finding)."""

from __future__ import annotations

import logging
import threading

import pytest

from simserver.server.logfile import LOG_QUEUE_LINES, ProcessLog
from simserver.testing import wait_until

pytestmark = pytest.mark.timeout(60)


class BlockedStream:
    """A stream whose ``write`` blocks until released, as a full pipe does."""

    def __init__(self) -> None:
        self.released = threading.Event()
        self.entered = threading.Event()
        self.text: list[str] = []

    def write(self, text: str) -> None:
        self.entered.set()
        self.released.wait()
        self.text.append(text)

    def flush(self) -> None:
        pass


def test_log_calls_return_while_the_output_is_blocked_then_every_line_is_written():
    root = logging.getLogger()
    saved = (list(root.handlers), root.level)
    stream = BlockedStream()
    plog = ProcessLog("INFO", stream, "%(levelname)s %(message)s")
    try:
        log = logging.getLogger("simserver.server")
        done = threading.Event()

        def tick_thread_logs() -> None:  # as the tick would: many lines, output blocked
            for k in range(1000):
                log.warning("watchdog %d", k)
            done.set()

        threading.Thread(target=tick_thread_logs, daemon=True).start()
        assert stream.entered.wait(10)  # the writer is stuck in write()
        # with a handler writing in the caller's thread, this never came: the test would
        # hang on the first call until its timeout
        assert done.wait(10), "a log call waited on the blocked output"
        stream.released.set()
        wait_until(lambda: len(stream.text) >= 1000, timeout_s=10,
                   what="every line written once the output moves")
        assert stream.text[0].startswith("WARNING watchdog 0")
        assert stream.text[999].startswith("WARNING watchdog 999")
        assert plog.dropped == 0
    finally:
        stream.released.set()
        plog.close()
        root.handlers[:] = saved[0]
        root.setLevel(saved[1])


def test_a_stuck_output_drops_and_counts_lines_past_the_queue():
    root = logging.getLogger()
    saved = (list(root.handlers), root.level)
    stream = BlockedStream()
    plog = ProcessLog("INFO", stream, "%(message)s")
    try:
        log = logging.getLogger("simserver.server")
        for k in range(LOG_QUEUE_LINES + 500):
            log.warning("line %d", k)
        # one record is in the writer's hand, LOG_QUEUE_LINES wait: the rest dropped
        assert LOG_QUEUE_LINES + 500 - plog.dropped in (LOG_QUEUE_LINES, LOG_QUEUE_LINES + 1)
    finally:
        stream.released.set()
        plog.close()
        root.handlers[:] = saved[0]
        root.setLevel(saved[1])


def test_the_writer_renewed_from_another_thread_keeps_the_order():
    root = logging.getLogger()
    saved = (list(root.handlers), root.level)
    stream = BlockedStream()
    stream.released.set()
    plog = ProcessLog("INFO", stream, "%(message)s")
    try:
        log = logging.getLogger("simserver.server")
        for k in range(50):
            log.warning("a%d", k)
        renewer = threading.Thread(target=plog.renew_thread)
        renewer.start()
        renewer.join()
        for k in range(50):
            log.warning("b%d", k)
        wait_until(lambda: len(stream.text) >= 100, timeout_s=10, what="100 lines")
        assert [t.strip() for t in stream.text] == [f"a{k}" for k in range(50)] + \
            [f"b{k}" for k in range(50)]
    finally:
        plog.close()
        root.handlers[:] = saved[0]
        root.setLevel(saved[1])
