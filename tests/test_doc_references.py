"""References stay inside the repository: docs/model.md citations name sections that exist,
Markdown links resolve, and nothing points at documents a clone does not have."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
MODEL_DOC = REPO / "docs" / "model.md"
SELF_CHECKS = {"tests/test_doc_references.py", "tests/test_param_tables.py"}
"""Tests that name the forbidden references in order to look for them."""
CHECKED = sorted(
    p for p in (REPO / name for name in subprocess.run(
        ["git", "ls-files", "*.py", "*.md", "*.yaml", "*.json5", "*.toml", "Dockerfile",
         ".ci/run"], cwd=REPO, capture_output=True, text=True, check=True).stdout.split())
    if p.exists() and str(p.relative_to(REPO)) not in SELF_CHECKS
)
"""The files these rules are enforced on: every file git tracks (code, docs, configs), but
the two tests that spell out what they look for."""
OUTSIDE = re.compile(
    r"\.\./shared|shared/docs|shared/data|platform[- ]notes|\.\./seed/|REPO\.parent"
)


def _text(path: Path) -> str:
    return path.read_text(encoding="utf-8")


def model_sections() -> set[str]:
    """Section numbers of docs/model.md: '1', '4b', '8.2', ..."""
    return set(re.findall(r"^#{2,3} (\d+[a-z]?(?:\.\d+)?)\.? ", _text(MODEL_DOC), re.M))


def test_model_doc_keeps_the_cited_numbering():
    assert {"1", "2", "3", "4", "4b", "5", "6", "7", "8", "8.1", "8.2", "9"} <= model_sections()
    items_4b = _text(MODEL_DOC).split("## 4b.", 1)[1].split("\n## ", 1)[0]
    assert re.findall(r"^(\d)\. ", items_4b, re.M) == ["1", "2", "3", "4", "5"]


@pytest.mark.parametrize("path", [p for p in CHECKED if p.is_file()],
                         ids=lambda p: str(p.relative_to(REPO)))
def test_references_point_inside_the_repository(path):
    text = _text(path)
    assert not OUTSIDE.search(text), f"{path.name} refers to a document outside the repository"
    # every model.md citation names the file by its path in the repository
    for match in re.finditer(r"(\S*)model\.md", text):
        assert match.group(1).endswith(("docs/", "(")), match.group(0)
    sections = model_sections()
    for cited in re.findall(r"model\.md\)?,? sections? (\d+[a-z]?(?:\.\d+)?)", text):
        assert cited in sections, f"{path.name} cites docs/model.md section {cited}"
    for cited in re.findall(r"model\.md\)? (\d+[a-z]) item", text):
        assert cited in sections, f"{path.name} cites docs/model.md {cited}"
    if path.suffix == ".md":
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
            if not re.match(r"[a-z]+:", target):
                assert (path.parent / target).exists(), f"{path.name}: broken link {target}"
