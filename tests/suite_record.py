"""The record of the README's test command: how long each run of the whole default suite
took, kept so that ``python -m benchmarks`` can report the suite's time without running it.

``tests/conftest.py`` appends one entry when a session was the README's command
(``python -m pytest -q -n 2``: the ``testpaths`` default, no ``-k``, ``-m``, ``--deselect``,
``-x``, ``--lf`` or ``--sw``, ``SIMSERVER_SLOW`` unset; with or without ``-n``) and ran to
its end: the wall and CPU seconds from pytest's start to its end (this process and its
reaped subprocesses: under ``-n``, pytest-xdist's workers and everything they started), the
outcome counts, the exit status, whether the kernel cache held any compiled kernel at the
start (``cold``: a fresh clone's compile was paid in the run), the load average, the
commit, the date, and the ``SLOWEST`` slowest tests (``slowest``: ``[nodeid, seconds]``, a
test's setup + call + teardown, slowest first) and the ``SLOWEST`` that used the most CPU
(``most_cpu``, the same form: the process that ran the test, this one or a worker, and its
reaped subprocesses, from the end of one test's teardown there to the end of the next's; on
a shared machine the steadier figure).
``RECORD`` (below ``.pytest_cache/``,
ignored by git) keeps the last ``KEEP`` entries; ``python -m benchmarks --only suite`` reads
them (``--run-suite N`` runs the command N times instead) and prints the last run's slowest
tests; ``python -m tests.suite_record [FILE]`` prints every recorded run with its slowest
tests. The hooks below are ``tests/conftest.py``'s (imported there); ``-p tests.suite_record``
loads them into another pytest run (its test does).
"""

from __future__ import annotations

import json
import os
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
RECORD = Path(os.environ.get("SIMSERVER_SUITE_RECORD")
              or REPO / ".pytest_cache" / "simserver" / "suite_runs.json")
"""The recorded runs, oldest first (a JSON list of ``entry`` dicts); ``SIMSERVER_SUITE_RECORD``
moves it (the test of this module does)."""
KEEP = 10
SLOWEST = 30
"""How many of a run's slowest tests its entry keeps (issue 33: the slowest 30 before and
after)."""


def is_readme_command(config: Any) -> bool:
    """Whether the pytest session of ``config`` is the README's whole default suite: the
    per-commit run (``tests.long_form.per_commit_run``: the whole suite, no ``-m``,
    ``SIMSERVER_SLOW`` unset) with nothing left out or stopping it early."""
    from tests.long_form import per_commit_run

    opt = config.option
    return (per_commit_run(config) and not opt.keyword
            and not getattr(opt, "deselect", None) and not opt.maxfail
            and not getattr(opt, "lf", False) and not getattr(opt, "stepwise", False))


def kernel_cache_files() -> int:
    """How many compiled-kernel indexes (``*.nbi``) simserver's kernels have where this
    process would load them: ``SIMSERVER_CACHE_DIR`` if set, else the package's
    ``__pycache__`` directories (and ``NUMBA_CACHE_DIR`` if set); and where the beside
    half's worker of ``-n 2`` would (``tests.long_form.beside_kernel_cache``)."""
    from simserver.core import CACHE_DIR_ENV
    from tests.long_form import beside_kernel_cache

    roots = [os.environ.get(CACHE_DIR_ENV)] if os.environ.get(CACHE_DIR_ENV) else [
        REPO / "simserver", os.environ.get("NUMBA_CACHE_DIR")]
    roots.append(beside_kernel_cache())
    return sum(1 for root in roots if root for _ in Path(root).rglob("*.nbi"))


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, timeout=10,
                              capture_output=True, text=True).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def slowest(durations: dict[str, float], n: int = SLOWEST) -> list[list[Any]]:
    """The ``n`` longest of ``durations`` (nodeid -> seconds) as ``[nodeid, seconds]``,
    slowest first."""
    top = sorted(durations.items(), key=lambda kv: (-kv[1], kv[0]))[:n]
    return [[nodeid, round(seconds, 2)] for nodeid, seconds in top]


def entry(wall_s: float, cpu_s: float, exitstatus: int, counts: dict[str, int],
          cached_kernels_at_start: int, load_start: float,
          durations: dict[str, float] | None = None,
          cpu: dict[str, float] | None = None) -> dict[str, Any]:
    """One record: the run's figures and where they come from; ``durations`` (nodeid ->
    setup + call + teardown seconds) gives its ``slowest``, ``cpu`` (nodeid -> CPU seconds)
    its ``most_cpu``."""
    return {"wall_s": round(wall_s, 1), "cpu_s": round(cpu_s, 1), "exitstatus": exitstatus,
            "counts": counts, "cold": cached_kernels_at_start == 0,
            "loadavg_1min_start": round(load_start, 2),
            "loadavg_1min_end": round(os.getloadavg()[0], 2), "commit": _commit(),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "slowest": slowest(durations or {}), "most_cpu": slowest(cpu or {})}


def append(record: dict[str, Any], path: Path = RECORD) -> None:
    """Add ``record`` to the file at ``path``, keeping the last ``KEEP``."""
    runs = read(path)[-(KEEP - 1):] + [record]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(runs, indent=1) + "\n", encoding="utf-8")
    tmp.replace(path)


_START: dict[str, float] = {}
_DURATIONS: dict[str, float] = {}
"""Seconds per test of this session so far (kept in every session, recorded only for the
README's command): setup + call + teardown (a module or session fixture's set-up counts on
the test that started it, as in ``--durations``)."""
CPU: dict[str, float] = {}
"""CPU seconds per test of this session so far (every session: ``--cpu-report`` prints
them), from the ``CPU_PROPERTY`` of each test's teardown report."""
CPU_PROPERTY = "cpu_s"
"""The user property (``report.user_properties``) a test's teardown report carries its CPU
seconds in: those of the process that ran it (this one, or a pytest-xdist worker, whose
reports reach this process with their properties) and of the subprocesses it reaped, from
the end of the previous test's teardown there to the end of this one's."""
_CPU_MARK: dict[str, float] = {}


def _hookimpl(**options: bool) -> Any:
    """``pytest.hookimpl(**options)``; without pytest (``python -m benchmarks`` reads the
    record in an environment without the test extra) the hooks are plain functions."""
    try:
        import pytest
    except ImportError:
        return lambda hook: hook
    return pytest.hookimpl(**options)


def _cpu_s() -> float:
    """CPU seconds of this process and its reaped children."""
    import resource

    return sum(r.ru_utime + r.ru_stime for r in (resource.getrusage(resource.RUSAGE_SELF),
                                                 resource.getrusage(resource.RUSAGE_CHILDREN)))


def pytest_configure(config: Any) -> None:
    """Start the per-test CPU clock; start the run's clocks when the session is the
    README's command (in the process that reports it: not in a pytest-xdist worker)."""
    _CPU_MARK["cpu"] = _cpu_s()
    if is_readme_command(config) and not hasattr(config, "workerinput"):
        _START.update(wall=time.perf_counter(), cpu=_cpu_s(), load=os.getloadavg()[0],
                      kernels=kernel_cache_files())


@_hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: Any, call: Any) -> Iterator[None]:
    """Give each test's teardown report its CPU seconds (``CPU_PROPERTY``), measured in
    the process that ran it."""
    outcome = yield
    if call.when == "teardown":
        now = _cpu_s()
        outcome.get_result().user_properties.append((CPU_PROPERTY, now - _CPU_MARK["cpu"]))
        _CPU_MARK["cpu"] = now


def pytest_runtest_logreport(report: Any) -> None:
    """Add each phase (setup, call, teardown) of a test to its time, and its teardown's CPU
    seconds to ``CPU``."""
    _DURATIONS[report.nodeid] = _DURATIONS.get(report.nodeid, 0.0) + report.duration
    if report.when == "teardown":
        cpu = dict(report.user_properties).get(CPU_PROPERTY)
        if cpu is not None:
            CPU[report.nodeid] = cpu


@_hookimpl(trylast=True)  # after pytest-xdist's: its workers have exited, been reaped
def pytest_sessionfinish(session: Any, exitstatus: int) -> None:
    """Record the README's command's run unless it was interrupted."""
    import pytest

    if not _START or exitstatus == pytest.ExitCode.INTERRUPTED:
        return
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    counts = {k: len(v) for k, v in getattr(reporter, "stats", {}).items()
              if k in ("passed", "failed", "error", "skipped", "xfailed", "xpassed")}
    append(entry(time.perf_counter() - _START["wall"], _cpu_s() - _START["cpu"],
                 int(exitstatus), counts, int(_START["kernels"]), _START["load"], _DURATIONS,
                 CPU))


def read(path: Path = RECORD) -> list[dict[str, Any]]:
    """The recorded runs, oldest first ([] if none or unreadable)."""
    try:
        runs = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return []
    return [r for r in runs if isinstance(r, dict) and "wall_s" in r] if isinstance(
        runs, list) else []


def describe(run: dict[str, Any]) -> str:
    """One recorded run, its figures on one line then its slowest tests (one a line)."""
    head = (f"{run['date']} at {run.get('commit', '?')}: {run['wall_s']:.0f} s wall, "
            f"{run['cpu_s']:.0f} s CPU, exit {run['exitstatus']}, "
            + ("cold" if run.get("cold") else "warm") + " kernel cache, load "
            f"{run.get('loadavg_1min_start', 0):.1f}-{run.get('loadavg_1min_end', 0):.1f}; "
            + ", ".join(f"{v} {k}" for k, v in run.get("counts", {}).items()))
    top = run.get("slowest")
    if not top:
        return head + "\n  (no per-test durations in this entry: recorded before they were kept)"
    text = head + f"\n  slowest {len(top)} tests (setup + call + teardown), "  \
        f"{sum(s for _, s in top):.0f} s together:\n" + "\n".join(
            f"  {seconds:8.2f} s  {nodeid}" for nodeid, seconds in top)
    cpu = run.get("most_cpu")
    if cpu:
        text += f"\n  most CPU: {len(cpu)} tests (subprocesses included), "  \
            f"{sum(s for _, s in cpu):.0f} s together:\n" + "\n".join(
                f"  {seconds:8.2f} s  {nodeid}" for nodeid, seconds in cpu)
    return text


def main(argv: list[str] | None = None) -> None:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m tests.suite_record",
                                     description="print the recorded runs of the README's "
                                                 "test command with their slowest tests")
    parser.add_argument("record", nargs="?", type=Path, default=RECORD,
                        help=f"the record to read (default {RECORD})")
    parser.add_argument("--last", type=int, default=0, metavar="N",
                        help="only the last N runs")
    args = parser.parse_args(argv)
    runs = read(args.record)
    if not runs:
        raise SystemExit(f"{args.record}: no recorded run of the README's test command")
    for run in runs[-args.last:] if args.last else runs:
        print(describe(run))


if __name__ == "__main__":
    main()
