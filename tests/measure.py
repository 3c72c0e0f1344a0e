"""Run a command to its end and measure its peak resident memory (issue 34: a memory bound
is a property a test asserts, not a timing)."""

from __future__ import annotations

import os
import resource
import subprocess
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from simserver.testing import wait_until


@dataclass
class Measured:
    """A finished subprocess: exit code, output, and its peak resident memory."""

    returncode: int | None  # None: still running at the timeout (then killed)
    stdout: str
    stderr: str
    peak_rss_mb: float


ADDRESS_SPACE_GUARD = 4 << 30
"""Address space a measured child may map (4 GiB): a regression that reads a 4 GiB file or
builds a huge grid then fails with a MemoryError instead of taking a shared machine's
memory. The tests assert the peak resident memory, far below it."""


def run_measured(argv: Sequence[str], timeout_s: float = 120.0, cwd: Path | None = None,
                 env: dict[str, str] | None = None, stdin: Any = subprocess.DEVNULL
                 ) -> Measured:
    """Run ``argv`` to its end (killed after ``timeout_s``) and measure its peak resident
    memory: the ``ru_maxrss`` of this child alone (``os.wait4``), not of every child the
    test process ever waited for (``RUSAGE_CHILDREN``)."""
    def guard() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE_GUARD, ADDRESS_SPACE_GUARD))

    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        proc = subprocess.Popen(list(argv), cwd=cwd, env=env, stdin=stdin, stdout=out,
                                stderr=err, preexec_fn=guard)
        try:
            _, status, usage = wait_until(lambda: os.wait4(proc.pid, os.WNOHANG),
                                          lambda r: r[0] == proc.pid, timeout_s=timeout_s,
                                          what=f"{list(argv)[:4]} to end", interval_s=0.02)
            code: int | None = os.waitstatus_to_exitcode(status)
        except TimeoutError:
            proc.kill()
            _, _, usage = os.wait4(proc.pid, 0)
            code = None
        proc.returncode = -9 if code is None else code  # reaped here, not by Popen
        out.seek(0)
        err.seek(0)
        return Measured(code, out.read().decode(errors="replace"),
                        err.read().decode(errors="replace"), usage.ru_maxrss / 1024.0)
