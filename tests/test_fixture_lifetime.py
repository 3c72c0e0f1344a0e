"""A module-scoped fixture ends right after the last test of its module that uses it
(tests/conftest.py: a server kept to the end of its module costs a share of a core beside
every later test), with its teardown run then; the tests after it see it finished."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

EVENTS: list[str] = []


@pytest.fixture(scope="module")
def resource() -> Iterator[str]:
    EVENTS.append("set up")
    yield "resource"
    EVENTS.append("torn down")


@pytest.fixture(scope="module")
def depends_on_resource(resource: str) -> Iterator[str]:
    EVENTS.append("dependent set up")
    yield resource + "+"
    EVENTS.append("dependent torn down")


def test_first_user(resource: str) -> None:
    assert resource == "resource" and EVENTS[-1] == "set up"


def test_last_user_through_a_dependent_fixture(depends_on_resource: str) -> None:
    assert depends_on_resource == "resource+"
    assert "torn down" not in EVENTS  # still there for its last user


def test_after_the_last_user() -> None:
    if "set up" in EVENTS:  # (not when this test is selected alone)
        assert EVENTS[-2:] == ["dependent torn down", "torn down"], EVENTS
