"""The record of the README's test command (tests/suite_record.py): a real pytest run of a
small suite in a scratch directory, with the record's hooks loaded (``-p``), is recorded
when it is the whole default suite and not when it is a selection."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from simserver.testing import REPO


def _pytest(cwd: Path, record: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "SIMSERVER_SLOW"}
    env["SIMSERVER_SUITE_RECORD"] = str(record)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "tests.suite_record",
                           "-p", "no:cacheprovider", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=120)


def test_whole_default_suite_is_recorded_and_a_selection_is_not(tmp_path: Path) -> None:
    (tmp_path / "pytest.ini").write_text("[pytest]\ntestpaths = t\n")
    (tmp_path / "t").mkdir()
    (tmp_path / "t" / "test_a.py").write_text(
        "def test_one():\n    assert True\n\n\ndef test_two():\n    assert True\n")
    record = tmp_path / "record.json"

    proc = _pytest(tmp_path, record)  # the README's command: the testpaths default
    assert proc.returncode == 0, proc.stdout + proc.stderr
    runs = json.loads(record.read_text())
    assert len(runs) == 1, runs
    run = runs[0]
    assert run["counts"] == {"passed": 2} and run["exitstatus"] == 0
    assert 0 < run["wall_s"] < 120 and run["cpu_s"] >= 0 and isinstance(run["cold"], bool)
    # its slowest tests, slowest first, each with its setup + call + teardown seconds
    assert sorted(nodeid for nodeid, _ in run["slowest"]) == ["t/test_a.py::test_one",
                                                              "t/test_a.py::test_two"]
    seconds = [s for _, s in run["slowest"]]
    assert seconds == sorted(seconds, reverse=True) and all(s >= 0 for s in seconds)
    assert sorted(nodeid for nodeid, _ in run["most_cpu"]) == ["t/test_a.py::test_one",
                                                               "t/test_a.py::test_two"]
    assert all(s >= 0 for _, s in run["most_cpu"])

    for selection in (["-k", "one"], ["t/test_a.py"], ["-x"], ["-m", "not slow"]):
        proc = _pytest(tmp_path, record, *selection)
        assert proc.returncode == 0, proc.stdout + proc.stderr
        assert len(json.loads(record.read_text())) == 1, selection

    # a failing run of the whole suite is recorded too, with its status
    (tmp_path / "t" / "test_b.py").write_text("def test_fails():\n    assert False\n")
    proc = _pytest(tmp_path, record)
    assert proc.returncode == 1
    runs = json.loads(record.read_text())
    assert [r["exitstatus"] for r in runs] == [0, 1]
    assert runs[-1]["counts"] == {"passed": 2, "failed": 1}


def test_slowest_keeps_the_longest_tests_and_the_printout_lists_them(tmp_path: Path) -> None:
    from tests import suite_record

    durations = {f"t/test_x.py::test_{i}": float(i) for i in range(40)}
    top = suite_record.slowest(durations)
    assert len(top) == suite_record.SLOWEST == 30
    assert top[0] == ["t/test_x.py::test_39", 39.0] and top[-1] == ["t/test_x.py::test_10", 10.0]

    record = tmp_path / "record.json"
    cpu = {f"t/test_x.py::test_{i}": 0.5 * i for i in range(40)}
    suite_record.append(suite_record.entry(12.0, 10.0, 0, {"passed": 40}, 5, 1.0, durations,
                                           cpu), record)
    proc = subprocess.run([sys.executable, "-m", "tests.suite_record", str(record)], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert "12 s wall" in lines[0] and "slowest 30 tests" in lines[1], proc.stdout
    assert lines[2].split() == ["39.00", "s", "t/test_x.py::test_39"], lines[2]
    assert "test_10" in lines[31], proc.stdout
    assert "most CPU: 30 tests" in lines[32] and lines[33].split() == [
        "19.50", "s", "t/test_x.py::test_39"], proc.stdout
    assert len(lines) == 63 and "test_10" in lines[-1], proc.stdout
