"""The long form (tests/long_form.py): the README's test command leaves its tests out,
``-m long`` selects them, and a stale name is an error."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

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
