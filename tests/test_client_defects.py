"""Client-side defects a new user met (issue 13), each pinned by a test that failed before.

- The usage line of every client names the command users run (``simserver-driver``,
  ``simserver-player``, ``simserver-recorder``: the ``project.scripts`` of
  ``pyproject.toml``), not ``python -m clients.X``.
"""

from __future__ import annotations

import importlib
import tomllib

import pytest

from tests.serverproc import REPO

CLIENT_MODULES = ("driver", "player", "recorder")


def _scripts() -> dict[str, str]:
    """``project.scripts`` of pyproject.toml: command -> ``module:function``."""
    with open(REPO / "pyproject.toml", "rb") as fh:
        return tomllib.load(fh)["project"]["scripts"]


@pytest.mark.parametrize("name", CLIENT_MODULES)
def test_usage_line_names_the_installed_command(name):
    module = importlib.import_module(f"clients.{name}")
    command = {target: cmd for cmd, target in _scripts().items()}[f"clients.{name}:main"]
    assert module.PROG == command  # the name in the clients' messages
    parser = module.build_parser()
    assert parser.prog == command
    assert parser.format_usage().startswith(f"usage: {command} ")
    assert "python -m" not in parser.format_usage()
