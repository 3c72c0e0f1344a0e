"""The README's two commands stay true: CI runs the test command verbatim, and the main
command's job runs; generated docs are current."""

from __future__ import annotations

import shlex
import subprocess
import sys

from tests.conftest import REPO, readme_main_job, readme_without_performance_block


def readme_commands() -> list[str]:
    lines = (REPO / "README.md").read_text().splitlines()
    return [ln.strip() for ln in lines if ln.startswith("    python3 -m venv .venv")]


def test_exactly_two_commands_and_ci_runs_the_test_one():
    cmds = readme_commands()
    assert len(cmds) == 2
    ci = (REPO / ".ci" / "run").read_text()
    assert cmds[1] in ci.splitlines()
    assert "pytest" in cmds[1] and "pytest" not in cmds[0]
    # and, after it, the long form the test command leaves out (tests/long_form.py)
    lines = ci.splitlines()
    assert lines[lines.index(cmds[1]) + 1:].count(".venv/bin/python -m pytest -q -m long") == 1


def test_main_command_job_runs(readme_server):
    """The job after the install step, as written, with this environment: the server comes
    up on the default loopback endpoint (the fixture checks its clean stop on SIGINT)."""
    assert shlex.split(readme_main_job())[:2] == [".venv/bin/simserver", "serve"]
    assert readme_server.proc.poll() is None


def test_scenario_command_runs(tmp_path):
    """The README's headless example, as written."""
    text = (REPO / "README.md").read_text()
    line = next(ln.strip() for ln in text.splitlines()
                if ln.strip().startswith(".venv/bin/simserver run-scenario"))
    args = [a if not a.startswith("out/") else str(tmp_path / a) for a in shlex.split(line)[1:]]
    proc = subprocess.run([sys.executable, "-m", "simserver", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "out" / "e2" / "history.parquet").exists()


def test_history_column_doc_is_current():
    from simserver.adapters.history import column_doc_markdown

    assert column_doc_markdown() in (REPO / "docs" / "history_columns.md").read_text()


def test_performance_table_is_the_benchmark_report():
    """The README's performance block is the one ``python -m benchmarks`` wrote into
    docs/performance.md (the same rows, the same run), not figures typed by hand."""
    _, block = readme_without_performance_block((REPO / "README.md").read_text())
    report = (REPO / "docs" / "performance.md").read_text()
    assert "Quick run" not in report, "docs/performance.md must come from a full run"

    def table(text: str) -> list[str]:
        lines = text.splitlines()
        start = next(i for i, line in enumerate(lines) if line.startswith("| figure |"))
        rows = []
        for line in lines[start:]:
            if not line.startswith("|"):
                break
            rows.append(line)
        return rows

    rows = table(block)
    assert len(rows) > 10 and rows == table(report)
    commit = next(ln for ln in report.splitlines() if ln.startswith("- **commit**"))
    assert commit.split(": ", 1)[1].split()[0] in block
