"""Honest dependencies: every package the code imports is declared in pyproject.toml, and
CI lints the tree with the pinned ruff."""

from __future__ import annotations

import ast
import functools
import re
import sys
import tomllib
from collections.abc import Iterator
from importlib.metadata import packages_distributions
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FIRST_PARTY = {"simserver", "clients", "benchmarks", "tests"}


def _name(requirement: str) -> str:
    """The normalised distribution name of a requirement string (PEP 503)."""
    name = re.match(r"[A-Za-z0-9._-]+", requirement).group(0)
    return re.sub(r"[-_.]+", "-", name).lower()


def _statements(tree: ast.Module) -> Iterator[ast.AST]:
    """Every statement of ``tree``, nested ones too: an import is a statement, so this
    finds the imports ``ast.walk`` finds without visiting every expression (5x faster)."""
    stack: list[ast.AST] = list(tree.body)
    while stack:
        node = stack.pop()
        yield node
        for field in ("body", "orelse", "finalbody", "handlers", "cases"):
            stack.extend(getattr(node, field, ()))


def _imported_top_levels(folder: str) -> dict[str, set[str]]:
    """Top-level third-party modules imported anywhere under ``folder`` -> files."""
    local = {p.stem for p in (REPO / folder).glob("*.py")}
    found: dict[str, set[str]] = {}
    for path in sorted((REPO / folder).rglob("*.py")):
        if (path.parent / "requirements.txt").exists():
            continue  # run in an environment of its own, made from that file (a benchmark's)
        for node in _statements(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top in sys.stdlib_module_names or top in FIRST_PARTY or top in local:
                    continue
                found.setdefault(top, set()).add(str(path.relative_to(REPO)))
    return found


def _declared() -> tuple[set[str], dict[str, set[str]]]:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    extras = {extra: {_name(r) for r in reqs}
              for extra, reqs in project["optional-dependencies"].items()}
    return {_name(r) for r in project["dependencies"]}, extras


@functools.cache
def _top_level_distributions() -> dict[str, list[str]]:
    """``packages_distributions()``, read once: it walks every installed distribution's
    file list (0.1-0.3 s a call, and the test asks about every imported module)."""
    return packages_distributions()


def _distributions(module: str) -> set[str]:
    return {_name(d) for d in _top_level_distributions().get(module, [])}


def test_every_imported_package_is_declared():
    runtime, extras = _declared()
    optional = set().union(*extras.values())
    missing = []
    for folder in ("simserver", "clients", "benchmarks", "docker"):
        for module, files in _imported_top_levels(folder).items():
            dists = _distributions(module)
            # the runtime needs its own dependencies; an optional extra (pygame for the
            # joystick input) is allowed where the code imports it only when asked for
            if not dists & (runtime | optional):
                missing.append(f"{module} ({', '.join(sorted(files))}): {sorted(dists)}")
    for module, files in _imported_top_levels("tests").items():
        if not _distributions(module) & (runtime | extras["test"]):
            missing.append(f"{module} ({', '.join(sorted(files))})")
    assert not missing, "imported but not declared in pyproject.toml: " + "; ".join(missing)


def test_dependencies_are_pinned_and_ci_runs_ruff():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    for req in project["dependencies"] + project["optional-dependencies"]["test"]:
        assert re.search(r"==|>=.*<", req), f"{req}: pin it (== or a bounded range)"
    assert "ruff" in {_name(r) for r in project["optional-dependencies"]["test"]}
    assert ".venv/bin/ruff check ." in (REPO / ".ci" / "run").read_text().splitlines()
