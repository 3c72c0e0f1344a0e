"""The command ring's size in docs/protocol.md is the one the server uses (issue 13).

The doc said the server keeps at most 32 commands between two ticks while the server's
receive ring held 256. The size is now one constant of the contract,
``simserver.wire.protocol.COMMAND_RING_SLOTS``: the server declares its command subscriber
with it, the doc's generated constants list prints it, and the rule that mentions the
ring names the constant instead of a number of its own.
"""

from __future__ import annotations

import ast
import re

from simserver.testing import REPO
from simserver.wire import protocol as P

DOC = REPO / "docs" / "protocol.md"
SERVER_SOURCES = sorted((REPO / "simserver").rglob("*.py"))  # every room (the server/ one)


def _command_inbox_capacities() -> list[tuple[str, str | None]]:
    """``(file, capacity expression)`` of every ``declare_command_inbox`` call in the
    server package (None: no capacity given, the adapter's default)."""
    found = []
    for path in SERVER_SOURCES:
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                    and node.func.attr == "declare_command_inbox":
                cap = [k.value for k in node.keywords if k.arg == "capacity"] + node.args[:1]
                found.append((path.name, ast.unparse(cap[0]) if cap else None))
    return found


def test_the_server_declares_its_command_ring_with_the_protocol_constant():
    from simserver.adapters.zenoh_io import ZenohEndpoint

    calls = _command_inbox_capacities()
    assert calls, "no declare_command_inbox call found in simserver/"
    for name, capacity in calls:
        assert capacity in ("proto.COMMAND_RING_SLOTS", None), (name, capacity)
    default = ZenohEndpoint.declare_command_inbox.__defaults__
    assert default is not None and P.COMMAND_RING_SLOTS in default


def test_the_doc_states_the_ring_size_from_the_code():
    text = DOC.read_text(encoding="utf-8")
    constants = text.split("<!-- BEGIN GENERATED: constants -->")[1].split("<!-- END")[0]
    assert f"{P.COMMAND_RING_SLOTS} commands (`COMMAND_RING_SLOTS`)" in constants
    rule = re.search(r"2\. \*\*Newest wins\.\*\*(.*?)\n3\. ", text, re.DOTALL)
    assert rule is not None
    assert "`COMMAND_RING_SLOTS`" in rule.group(1)
    assert not re.search(r"at most \d+", rule.group(1)), rule.group(1)
