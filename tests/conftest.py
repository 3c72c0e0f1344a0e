"""Shared fixtures: repository paths and the reference tire of the paper."""

from __future__ import annotations

import os
import re
import shlex
import signal
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from simserver.testing import CONFIGS, REPO, OutputProcess, ServerProcess, free_port
from tests import long_form, suite_record

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
    return os.environ.get("SIMSERVER_SLOW") == "1" or _selects_slow(markexpr)


def _selects_slow(markexpr: str | None) -> bool:
    expr = markexpr or ""
    return "slow" in expr and "not slow" not in expr


def pytest_configure(config: pytest.Config) -> None:
    """``-m slow`` sets ``SIMSERVER_SLOW=1`` before the test modules are imported, so a size
    chosen at import (``slow_enabled(None)``: hypothesis' example counts, a module's soak
    length) is the long one under ``-m slow`` too, not only under ``SIMSERVER_SLOW=1``;
    in the beside half's pytest-xdist worker, its own kernel cache (``tests/long_form.py``)."""
    if _selects_slow(config.getoption("markexpr")):
        os.environ["SIMSERVER_SLOW"] = "1"
    long_form.configure_worker(config)  # under -n: the beside half's own kernel cache
    suite_record.pytest_configure(config)  # the suite's clocks (end of this file)


@pytest.hookimpl(tryfirst=True)  # before ``-m`` and ``-k`` select: they see the marks
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The long form (tests/long_form.py): its tests are marked ``long``, and the README's
    test command (the per-commit run) leaves them out; CI runs them with ``-m long``."""
    long_form.mark(config, items)


@pytest.hookimpl(optionalhook=True)  # pytest-xdist's hook: only with ``-n``
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """With ``-n`` (the README's test command: ``-n 2``), the two halves of
    ``tests/long_form.py`` (``BESIDE``), each whole on one worker."""
    return long_form.halves_scheduler(config, log)


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


README_ENDPOINT = "tcp/127.0.0.1:7447"
"""The README's zenoh endpoint: the server's default listen and the clients' default
connect. The README's commands run in tests with it moved to a free loopback port (and
the live view's gRPC port with it), so the README's test command passes while the
README's own server holds 7447 (as a newcomer leaves it running); the defaults themselves
are checked apart (``test_readme_commands.py::test_readme_defaults_are_one_endpoint``)."""


def readme_on(endpoint: str, text: str) -> str:
    """``text`` (a README command or its Python snippet) with the README's endpoint moved to
    ``endpoint``; a text that names none is returned as it is."""
    return text.replace(README_ENDPOINT, endpoint)


def readme_client(command: str, server: ServerProcess) -> list[str]:
    """argv of a README client command run against ``server`` (``readme_server``): as
    written, plus ``--connect`` to the server's endpoint in place of the default one."""
    return [*as_written(command), "--connect", server.endpoint]


@pytest.fixture(scope="module")
def readme_server() -> Iterator[ServerProcess]:
    """The README's main job as written, with the default config, except its two ports:
    zenoh listens on a free loopback port instead of 7447 and the live view serves on a
    free port instead of 9876 (``--listen``, ``--viewer serve:PORT``), so it runs beside a
    server the README started. At the end it must stop cleanly on SIGINT with its final
    statistics."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    argv = [*as_written(readme_main_job()), "--listen", endpoint,
            "--viewer", f"serve:{free_port()}"]
    server = ServerProcess(argv=argv, listen=[endpoint])
    try:
        assert "ready on simserver/car0" in server.ready_line, server.ready_line
        yield server
    finally:
        code = server.stop(signal.SIGINT)
    assert code == 0 and server.final_stats() is not None, server.text()


TWO_CARS = CONFIGS / "server" / "two_cars.yaml"
"""The shipped two-car server config: car0 at x = 0, car1 at x = 25 m on the flat, both
driven by clients."""


@pytest.fixture(scope="module")
def two_cars() -> Iterator[ServerProcess]:
    """A real server process on ``TWO_CARS`` (its own free loopback port), one per test
    module: a module that drives the cars does not move another module's parked ones."""
    with ServerProcess(config=TWO_CARS, scene=None) as server:
        yield server


def player(server: ServerProcess, car: str, scenario: Path) -> OutputProcess:
    """A ``clients.player`` process playing ``scenario`` (a keyframed inputs YAML) on
    ``car`` of ``server`` at 200 Hz, as a person's client would drive it."""
    return OutputProcess([sys.executable, "-m", "clients.player", str(scenario),
                          "--connect", server.endpoint, "--vehicle-id", car, "--rate", "200"])


# ----------------------------------------------- a module's fixture ends with its last user
# A server costs a quarter to 0.4 of a core while it runs, idle or not (its 1 kHz loop steps and
# publishes every tick): a module-scoped server kept until the end of its module runs beside
# every later test of the module and its servers, on a 2-core machine. So a module-scoped
# fixture is finished (its teardown run, with its checks) right after the teardown of the
# last test of its module that uses it, not at the end of the module (issue 33 item 3). A
# later test that asked for it only through ``request.getfixturevalue`` would get it anew.

_LAST_USE: dict[str, list[str]] = {}
"""nodeid of a test -> the module-scoped fixtures of its module that no later selected test
of the module uses (filled once the selection is known)."""


def pytest_collection_finish(session: pytest.Session) -> None:
    last: dict[tuple[str, str], str] = {}
    for item in session.items:
        module = item.getparent(pytest.Module)
        for name in item.fixturenames:  # the closure: fixtures of fixtures too
            last[(module.nodeid if module else "", name)] = item.nodeid
    _LAST_USE.clear()
    for (_, name), nodeid in last.items():
        _LAST_USE.setdefault(nodeid, []).append(name)


@pytest.hookimpl(trylast=True)  # after the test's own (function-scoped) fixtures are torn down
def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None) -> None:
    if nextitem is None or nextitem.getparent(pytest.Module) is not item.getparent(pytest.Module):
        return  # the module's end tears everything down anyway
    infos = getattr(item, "_fixtureinfo", None)
    request = getattr(item, "_request", None)
    if infos is None or request is None:
        return
    for name in reversed(_LAST_USE.get(item.nodeid, [])):  # dependents before dependencies
        defs = infos.name2fixturedefs.get(name)
        if defs and defs[-1].scope == "module":
            defs[-1].finish(request)


# ------------------------------------------------------------------ CPU time per test
# On this shared 2-core machine a test's wall time says more about the other users than
# about the test (a server start took 15 s of wall for 1 s of CPU at load 15), so the
# suite's cost is compared in CPU seconds (issue 33 item 3): ``--cpu-report N`` prints the
# N tests that used the most CPU: the process's that ran the test (this one, or the
# pytest-xdist worker of its half under ``-n``) and its reaped children's (servers, clients
# and CLIs a test starts and stops; a module fixture's server is counted on the test whose
# setup or teardown started or stopped it). ``tests/suite_record.py`` measures it.

def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--cpu-report", type=int, default=0, metavar="N",
                     help="print the N tests that used the most CPU (the process that ran "
                          "each, this one or a worker, and the subprocesses it reaped), and "
                          "the total")


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter,
                            config: pytest.Config) -> None:
    n = config.getoption("cpu_report")
    cpu_by_test = suite_record.CPU  # every test's teardown report carries its CPU seconds
    if not n or not cpu_by_test:
        return
    tr = terminalreporter
    tr.write_sep("=", f"most CPU: {n} tests (the process that ran each, its reaped "
                      "subprocesses)")
    for nodeid, cpu in sorted(cpu_by_test.items(), key=lambda kv: -kv[1])[:n]:
        tr.write_line(f"{cpu:8.2f} s  {nodeid}")
    tr.write_line(f"{sum(cpu_by_test.values()):8.2f} s  CPU of all {len(cpu_by_test)} tests")


# ------------------------------------------------------- the record of the suite's time
# A run of the README's test command (the whole default suite) is recorded with its wall
# and CPU time: `python -m benchmarks --only suite` reports the recorded runs instead of
# running the suite again (issue 33 item 4). The hooks are tests/suite_record.py's
# (its pytest_configure is called from this file's).
from tests.suite_record import (  # noqa: E402,F401
    pytest_runtest_logreport,
    pytest_runtest_makereport,
    pytest_sessionfinish,
)
