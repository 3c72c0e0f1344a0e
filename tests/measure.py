"""Run a command to its end and measure its peak resident memory (issue 34: a memory bound
is a property a test asserts, not a timing)."""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any


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


_LAUNCHER = """
import json, resource, subprocess, sys
argv, timeout_s, report, guard = json.loads(sys.argv[1])
def limit():
    resource.setrlimit(resource.RLIMIT_AS, (guard, guard))
try:
    code = subprocess.run(argv, preexec_fn=limit, timeout=timeout_s).returncode
except subprocess.TimeoutExpired:
    code = None
peak_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
with open(report, "w") as f:
    json.dump([code, peak_kb], f)
"""


def run_measured(argv: Sequence[str], timeout_s: float = 120.0, cwd: Path | None = None,
                 env: dict[str, str] | None = None, stdin: Any = subprocess.DEVNULL
                 ) -> Measured:
    """Run ``argv`` to its end (killed after ``timeout_s``) and measure its peak resident
    memory. Through a small launcher process: Linux counts the memory of the process a
    child was forked from into the child's ``ru_maxrss`` (a child of a 700 MB pytest read
    700 MB), so the command is forked from the launcher, which reports its children's
    peak (``RUSAGE_CHILDREN``: the command alone)."""
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err, \
            tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "report.json"
        job = json.dumps([list(argv), timeout_s, str(report), ADDRESS_SPACE_GUARD])
        launcher = subprocess.run([sys.executable, "-c", _LAUNCHER, job], cwd=cwd, env=env,
                                  stdin=stdin, stdout=out, stderr=err,
                                  timeout=timeout_s + 60.0, check=False)
        assert launcher.returncode == 0 and report.is_file(), "the launcher failed"
        code, peak_kb = json.loads(report.read_text())
        out.seek(0)
        err.seek(0)
        return Measured(code, out.read().decode(errors="replace"),
                        err.read().decode(errors="replace"), peak_kb / 1024.0)
