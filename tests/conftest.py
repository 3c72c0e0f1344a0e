"""Shared fixtures: repository paths, the reference tire of the paper, the long forms'
switch, and the README's server.

For tests of every module (use them rather than a copy of your own):

- ``slow_enabled(markexpr)`` / the ``only_when_slow`` fixture: a long form runs only with
  ``-m slow`` or ``SIMSERVER_SLOW=1``; the default suite (and CI) runs its short form, a
  test of its own beside it (the house rule for anything over ~10 s of waiting).
- ``paper_tire`` (session): the paper's packed tire.
- ``readme_server`` (module): the README's server on its fixed default port 7447. Only one
  may run at a time on the machine, so it holds ``readme_port_lock`` (a file lock shared by
  this run's xdist workers) while it runs.

The README's test command runs the suite in two xdist workers (``-n 2``), a file per worker
at a time (``--dist loadfile`` in ``pyproject.toml``), so a module's module-scoped server is
started once. Tests must therefore take free ports (``simserver.testing.free_port``) and
their own ``tmp_path``, never a fixed port or a fixed file of the checkout they write to.
Before the workers start, the controller compiles the numba kernels once
(``docker/warmup.py``, both tire models) so that the workers load them from the cache
instead of compiling the same kernels side by side; a run without ``-n`` compiles lazily
as before.
"""

from __future__ import annotations

import fcntl
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from simserver.testing import CONFIGS, REPO, ServerProcess

SAMPLE_TIR = CONFIGS / "tires" / "data" / "mf61_225_50R17_sample.tir"
"""The MF 6.1 sample property file, as shipped with the repository (the one the
``mf61_sample`` tire uses); ``tests/test_tir_file.py`` checks it is the third-party file
unchanged."""


def mf61_sample_coefficients(variant: bool = False) -> dict[str, float]:
    """The MF 6.1 coefficients of ``SAMPLE_TIR``, or with ``variant`` a set that takes the
    kernel's other branches: off-nominal pressure (dpi != 0, (p/p0)^QSY8), PKY5 != 0 (K_ya at
    gamma = 0 computed apart), LFZO != 1, a wider Fz range."""
    from simserver.adapters.tir_file import load_tir, mf61_coefficients

    c = mf61_coefficients(load_tir(SAMPLE_TIR))
    if not variant:
        return c
    return dict(c, INFLPRES=1.15 * c["NOMPRES"], PKY5=0.4, LFZO=1.1, FZMIN=0.0,
                FZMAX=3.0 * c["FNOMIN"])


def slow_enabled(markexpr: str | None) -> bool:
    """Whether the long (``slow``) tests should run.

    They run with ``SIMSERVER_SLOW=1`` in the environment or when pytest's ``-m``
    expression selects ``slow`` (``-m slow``); the default suite runs their short forms.
    """
    expr = markexpr or ""
    return os.environ.get("SIMSERVER_SLOW") == "1" or ("slow" in expr and "not slow" not in expr)


@pytest.fixture
def only_when_slow(request: pytest.FixtureRequest) -> None:
    """Skip the long form unless asked for (``-m slow`` or ``SIMSERVER_SLOW=1``)."""
    if not slow_enabled(request.config.getoption("markexpr")):
        pytest.skip("long form: run with -m slow or SIMSERVER_SLOW=1")


def _xdist_controller(config: pytest.Config) -> bool:
    """This process distributes the tests to xdist workers (``-n N``, N > 0)."""
    return not hasattr(config, "workerinput") and bool(
        getattr(config.option, "numprocesses", None)) and config.option.dist != "no"


def pytest_sessionstart(session: pytest.Session) -> None:
    """Under xdist, compile the numba kernels once, before the workers start (this hook runs
    before xdist's own, which is ``trylast``): the workers then load them from the cache.
    Without it both workers' first servers compile the same kernels side by side (about a
    minute of CPU each on this 2-core machine). With a warm cache this costs a few seconds
    (the kernels loaded, a one-second soak per tire model)."""
    if not _xdist_controller(session.config) or session.config.option.collectonly:
        return
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, str(REPO / "docker" / "warmup.py"), "--configs",
                           str(CONFIGS)], cwd=REPO, capture_output=True, text=True,
                          timeout=900)
    if proc.returncode != 0:  # the tests that need the kernels will say why, one by one
        print(f"numba warm-up failed (exit {proc.returncode}):\n{proc.stdout}{proc.stderr}",
              file=sys.stderr)
    else:
        summary = proc.stdout.strip().splitlines()[-1:] or [""]
        print(f"\nnumba warm-up before the workers: {time.monotonic() - t0:.0f} s "
              f"({summary[0]})", file=sys.stderr)


@pytest.fixture(scope="session")
def paper_tire():
    """Packed parameters of the paper's tire (configs/tires/paper_sti.yaml)."""
    from simserver.adapters.config import load_tire

    tp, _ = load_tire(CONFIGS / "tires" / "paper_sti.yaml")
    return tp


README_BIN = Path(sys.executable).parent
"""What the README's ``.venv/bin/`` means in tests: the environment running them."""


def as_written(command: str) -> list[str]:
    """argv of a README command, ``.venv/bin/X`` (or a bare ``simserver``) being this
    environment's ``X``."""
    argv = shlex.split(command)
    if argv[0].startswith(".venv/bin/"):
        argv[0] = str(README_BIN / argv[0].removeprefix(".venv/bin/"))
    elif argv[0] == "simserver":
        argv[0] = str(README_BIN / "simserver")
    return argv


PERFORMANCE_BLOCK = re.compile(
    r"(<!-- BEGIN GENERATED: performance\b[^>]*-->)(.*?)(<!-- END GENERATED: performance -->)",
    re.S)
"""The README's generated performance block (``python -m benchmarks`` writes it between
these markers): groups ``begin, block, end``."""


def readme_without_performance_block(readme: str) -> tuple[str, str]:
    """``(the README without its generated performance block, that block)``."""
    m = PERFORMANCE_BLOCK.search(readme)
    assert m, "the README has no generated performance block"
    return readme[:m.start()] + readme[m.end():], m.group(2)


def readme_main_job() -> str:
    """The job of the README's first command, after its install steps."""
    lines = (REPO / "README.md").read_text().splitlines()
    first = next(ln.strip() for ln in lines if ln.startswith("    python3 -m venv .venv"))
    return first.split("&&")[-1].strip()


@pytest.fixture(scope="session")
def readme_port_lock(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A lock file shared by this run's xdist workers (in their common temporary root) for
    the README's fixed port: hold it (``fcntl.flock``) while a server listens there."""
    base = tmp_path_factory.getbasetemp()  # .../pytest-N/popen-gwK under xdist
    return (base.parent if base.name.startswith("popen-gw") else base) / "readme_port.lock"


@pytest.fixture(scope="module")
def readme_server(readme_port_lock: Path) -> Iterator[ServerProcess]:
    """The README's main job as written, on its default endpoint (tcp/127.0.0.1:7447);
    at the end it must stop cleanly on SIGINT with its final statistics.

    The README's commands use the default port: if something else holds it, the tests of
    those commands cannot run, and that is a failure to fix (stop the other server), not
    a reason to skip them. Another module of this run that holds it (an xdist worker) is
    waited for, through ``readme_port_lock``."""
    with open(readme_port_lock, "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released once the module's server has stopped
        yield from _readme_server()


def _readme_server() -> Iterator[ServerProcess]:
    with socket.socket() as probe:
        if probe.connect_ex(("127.0.0.1", 7447)) == 0:
            pytest.fail("something already listens on 127.0.0.1:7447, the README's default "
                        "endpoint: stop it (another simserver?) to run the README's commands",
                        pytrace=False)
    server = ServerProcess(argv=as_written(readme_main_job()), listen=["tcp/127.0.0.1:7447"])
    try:
        assert "ready on simserver/car0" in server.ready_line, server.ready_line
        yield server
    finally:
        code = server.stop(signal.SIGINT)
    assert code == 0 and server.final_stats() is not None, server.text()
