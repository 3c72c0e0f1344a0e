"""The README's two commands stay true: CI runs the test command verbatim, and the main
command's job runs; generated docs are current."""

from __future__ import annotations

import shlex
import subprocess
import sys

from tests.conftest import REPO


def readme_commands() -> list[str]:
    lines = (REPO / "README.md").read_text().splitlines()
    return [ln.strip() for ln in lines if ln.startswith("    python3 -m venv .venv")]


def test_exactly_two_commands_and_ci_runs_the_test_one():
    cmds = readme_commands()
    assert len(cmds) == 2
    ci = (REPO / ".ci" / "run").read_text()
    assert cmds[1] in ci.splitlines()
    assert "pytest" in cmds[1] and "pytest" not in cmds[0]


def test_main_command_job_runs(tmp_path):
    """The job after the install step, as written, with this interpreter."""
    job = readme_commands()[0].split("&&")[-1].strip()
    args = shlex.split(job)
    assert args[0] == ".venv/bin/simserver"
    args = [a if not a.startswith("out/") else str(tmp_path / a) for a in args[1:]]
    proc = subprocess.run([sys.executable, "-m", "simserver", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "out" / "e2"
    assert (out / "history.parquet").exists() and (out / "summary.json").exists()


def test_history_column_doc_is_current():
    from simserver.adapters.history import column_doc_markdown

    assert column_doc_markdown() in (REPO / "docs" / "history_columns.md").read_text()
