"""The long form (tests/long_form.py): the README's test command leaves its tests out,
``-m long`` selects them, and a stale name is an error."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from simserver.testing import REPO
from tests import long_form

A_LONG = next(iter(sorted(long_form.LONG_NODEIDS)))


class _Item:
    """What ``long_form.mark`` reads of a collected test: its nodeid and its marks."""

    def __init__(self, nodeid: str) -> None:
        self.nodeid = nodeid
        self.marks: list[str] = []

    def add_marker(self, marker: pytest.MarkDecorator) -> None:
        self.marks.append(marker.name)


def _config(args_source: pytest.Config.ArgsSource, markexpr: str = "") -> SimpleNamespace:
    deselected: list[_Item] = []
    return SimpleNamespace(
        args_source=args_source, option=SimpleNamespace(markexpr=markexpr),
        hook=SimpleNamespace(pytest_deselected=lambda items: deselected.extend(items)),
        deselected=deselected)


def _items(path: str) -> list[_Item]:
    """Every test ``LONG`` names in ``path``, and one it does not."""
    _, tests = long_form.LONG[path]
    return [_Item(f"{path}::{name}") for name in tests] + [_Item(f"{path}::test_not_long")]


def test_the_per_commit_run_leaves_the_long_tests_out_and_marks_them(monkeypatch):
    monkeypatch.delenv("SIMSERVER_SLOW", raising=False)
    path = A_LONG.split("::")[0]
    items = _items(path)
    config = _config(pytest.Config.ArgsSource.TESTPATHS)
    long_form.mark(config, items)
    assert [i.nodeid for i in items] == [f"{path}::test_not_long"]
    assert config.deselected and all(i.marks == ["long"] for i in config.deselected)
    assert {i.nodeid for i in config.deselected} == {
        f"{path}::{name}" for name in long_form.LONG[path][1]}


@pytest.mark.parametrize("source, markexpr, slow", [
    (pytest.Config.ArgsSource.TESTPATHS, "long", None),  # CI's second run
    (pytest.Config.ArgsSource.ARGS, "", None),  # a file named on the command line
    (pytest.Config.ArgsSource.TESTPATHS, "", "1"),  # SIMSERVER_SLOW=1: everything
])
def test_other_runs_keep_them_marked(monkeypatch, source, markexpr, slow):
    if slow:
        monkeypatch.setenv("SIMSERVER_SLOW", slow)
    else:
        monkeypatch.delenv("SIMSERVER_SLOW", raising=False)
    path = A_LONG.split("::")[0]
    items = _items(path)
    config = _config(source, markexpr)
    long_form.mark(config, items)
    assert len(items) == len(long_form.LONG[path][1]) + 1 and not config.deselected
    assert [i.marks for i in items].count(["long"]) == len(long_form.LONG[path][1])


def test_a_name_its_collected_file_lacks_is_an_error():
    path = A_LONG.split("::")[0]
    items = [i for i in _items(path) if i.nodeid != A_LONG]
    with pytest.raises(pytest.UsageError, match=A_LONG.replace("[", r"\[")):
        long_form.mark(_config(pytest.Config.ArgsSource.TESTPATHS), items)
    # a file not collected at all (another file named on the command line) is no error
    long_form.mark(_config(pytest.Config.ArgsSource.TESTPATHS), [_Item("tests/x.py::test_y")])
    # nor is one test of the file named on the command line (the others are not collected)
    long_form.mark(_config(pytest.Config.ArgsSource.ARGS), items[:1])


def test_this_session_follows_the_rule(request):
    """The running session itself: when it is the README's command, it holds no long test."""
    nodeids = {item.nodeid for item in request.session.items}
    if long_form.per_commit_run(request.config):
        assert not nodeids & long_form.LONG_NODEIDS


def test_the_listing_names_every_long_test_and_the_kept_ones():
    text = long_form.describe()
    assert all(f"`{nodeid.split('::', 1)[1]}`" in text for nodeid in long_form.LONG_NODEIDS)
    assert all(nodeid in text for nodeid in long_form.PER_COMMIT)
    assert not set(long_form.PER_COMMIT) & long_form.LONG_NODEIDS


# ------------------------------------------------------------------ the per-commit run's halves
# what a test file uses to start a simserver server or open a zenoh session (the fixtures and
# helpers of tests/conftest.py and simserver.testing, zenoh itself); other processes (Dask's
# scheduler and workers, command lines) are fine
_LIVE = re.compile(r"\b(ServerProcess|readme_server|two_cars|import zenoh|zenoh\.open)\b")


def test_the_beside_half_starts_no_server_and_opens_no_zenoh_session():
    """``BESIDE``'s files run beside the main half's live servers: none of them may start a
    simserver server or open a zenoh session of its own (the main half's live tests count
    the sessions, states and late ticks of their own servers)."""
    assert len(long_form.BESIDE_FILES) == sum(len(f) for f in long_form.BESIDE.values())
    for path in sorted(long_form.BESIDE_FILES):
        source = (REPO / path).read_text(encoding="utf-8")  # a missing file fails here
        assert not _LIVE.findall(source), (path, sorted(set(_LIVE.findall(source))))
    assert long_form.half_of("tests/test_slip.py::test_zero_speed_is_regular") == "beside"
    assert long_form.half_of("tests/test_server.py::test_x") == "main"


def test_two_workers_run_each_half_whole_on_its_worker_with_its_own_kernel_cache(tmp_path):
    """A real ``pytest -n 2`` of a scratch suite with this conftest's hooks: the tests of the
    beside half's files all run on ``BESIDE_WORKER`` with its own kernel cache (from which
    it drops another source state's kernels), the others on the other worker with the cache
    of the environment (here none)."""
    (tmp_path / "t").mkdir()
    for name in ("a", "b", "c", "d"):
        cache = long_form.beside_kernel_cache() if name in "bd" else None
        (tmp_path / "t" / f"test_{name}.py").write_text(
            "import os\n\n\n" + "".join(
                f"def test_{i}():\n"
                f"    assert os.environ.get('SIMSERVER_CACHE_DIR') == {cache!r}\n\n\n"
                for i in range(3)))
    (tmp_path / "pytest.ini").write_text("[pytest]\ntestpaths = t\n")
    (tmp_path / "t" / "conftest.py").write_text(
        "import pytest\nfrom tests import long_form\n"
        "long_form.BESIDE_FILES = frozenset({'t/test_b.py', 't/test_d.py'})\n\n\n"
        "def pytest_configure(config):\n"
        "    long_form.configure_worker(config)\n\n\n"
        "@pytest.hookimpl(optionalhook=True)\n"
        "def pytest_xdist_make_scheduler(config, log):\n"
        "    return long_form.halves_scheduler(config, log)\n")
    stale = Path(long_form.beside_kernel_cache()) / "simserver-0000another0state00"
    (stale / "simserver" / "core").mkdir(parents=True, exist_ok=True)  # another commit's
    env = {k: v for k, v in os.environ.items() if k != "SIMSERVER_CACHE_DIR"}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])
    proc = subprocess.run([sys.executable, "-m", "pytest", "-n", "2", "-v", "-p",
                           "no:cacheprovider"], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert not stale.exists()  # the beside worker dropped the other source state's kernels
    worker = {}  # file -> the workers its tests ran on
    for line in proc.stdout.splitlines():
        found = re.match(r"\[(gw\d)\] .*PASSED (t/test_\w\.py)::", line)
        if found:
            worker.setdefault(found.group(2), set()).add(found.group(1))
    assert worker == {"t/test_a.py": {"gw0"}, "t/test_b.py": {long_form.BESIDE_WORKER},
                      "t/test_c.py": {"gw0"}, "t/test_d.py": {long_form.BESIDE_WORKER}}, \
        proc.stdout
