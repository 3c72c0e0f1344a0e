"""No import cycle among the modules of ``simserver`` (issue 29 item 4).

Every ``import`` and ``from ... import`` of a ``simserver`` module counts, wherever it
stands: at module level, inside a function (a lazy import), under ``if TYPE_CHECKING``.
A lazy import only defers a cycle to the first call; a type-only import still says the
lower module knows the higher one. So a cycle is broken by moving what both need into a
module below both (``simserver.sim.scene``, ``simserver.server.config``,
``simserver.errors``), never by moving the import into a function. Importing
``a.b.c`` also runs the packages ``a.b`` and ``a``, so those count as imported too.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

from simserver.testing import REPO


def module_files(root: Path, package: str = "simserver") -> dict[str, Path]:
    """Every module of ``package`` under ``root``, by dotted name (a package by its
    ``__init__.py``)."""
    mods = {}
    for path in sorted((root / package).rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        mods[".".join(parts)] = path
    return mods


def import_graph(root: Path, package: str = "simserver") -> dict[str, set[str]]:
    """Module -> the modules of ``package`` it imports anywhere in its file."""
    mods = module_files(root, package)

    def resolve(name: str) -> list[str]:
        """The module ``name`` names (or the module holding it) and its packages."""
        while name and name not in mods:
            name = name.rpartition(".")[0]
        parts = name.split(".") if name else []
        return [".".join(parts[:k]) for k in range(len(parts), 0, -1)]

    graph: dict[str, set[str]] = {}
    for mod, path in mods.items():
        package_of = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package_of.split(".")[:len(package_of.split(".")) - node.level + 1]
                    base = ".".join([*up, base] if base else up)
                # ``from a import b``: b may be a module of a, or a name in a
                names = [f"{base}.{alias.name}" for alias in node.names] + [base]
            else:
                continue
            for name in names:
                if name == package or name.startswith(package + "."):
                    targets.update(resolve(name))
        targets.discard(mod)
        # a module's own packages run before it: importing them is no edge back
        own = mod.split(".")
        graph[mod] = targets - {".".join(own[:k]) for k in range(1, len(own))}
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each as one
    cycle through it, sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(_cycle_through(graph, set(comp)))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def _cycle_through(graph: dict[str, set[str]], comp: set[str]) -> list[str]:
    """One closed path inside a strongly connected component, from its first module."""
    start = min(comp)
    path, seen = [start], {start}
    while True:  # walk inside the component until a module repeats
        nxt = min(w for w in graph[path[-1]] if w in comp)
        if nxt in seen:
            return [*path[path.index(nxt):], nxt]
        path.append(nxt)
        seen.add(nxt)


def test_no_import_cycle_among_simserver_modules():
    cycles = import_cycles(import_graph(REPO))
    assert not cycles, "import cycles (move what both need into a lower module):\n" + \
        "\n".join(" -> ".join(c) for c in cycles)


def _write(root: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def test_a_cycle_through_a_lazy_or_type_only_import_is_found(tmp_path):
    """The check sees the imports the rule counts: in a function, under TYPE_CHECKING,
    relative, and the package run by importing its module."""
    _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/low.py": "def f():\n    from pkg.high import g\n",
        "pkg/high.py": "from pkg import low\n",
        "pkg/typed.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                        "    from .other import T\n",
        "pkg/other.py": "import pkg.typed\n",
        "pkg/sub/__init__.py": "from pkg.sub.inner import x\n",
        "pkg/sub/inner.py": "x = 1\n",
        "pkg/user.py": "from pkg.sub.inner import x\n",
        "pkg/back.py": "import pkg.user\n",
        "pkg/fine.py": "from pkg import low\n",
    })
    graph = import_graph(tmp_path, "pkg")
    assert graph["pkg.user"] == {"pkg.sub.inner", "pkg.sub"}
    assert import_cycles(graph) == [["pkg.high", "pkg.low", "pkg.high"],
                                    ["pkg.other", "pkg.typed", "pkg.other"]]
    _write(tmp_path, {"pkg/sub/inner.py": "import pkg.back\n"})  # inner -> back -> user -> inner
    assert ["pkg.back", "pkg.user", "pkg.sub", "pkg.sub.inner", "pkg.back"] in \
        import_cycles(import_graph(tmp_path, "pkg"))


def test_the_readme_rooms_table_is_the_package():
    """README.md's rooms table is what docs/rooms.py makes of the package now (every room
    placed, its modules as on disk, its text from its docstring)."""
    proc = subprocess.run([sys.executable, str(REPO / "docs" / "rooms.py"), "--check",
                           str(REPO / "README.md")], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
