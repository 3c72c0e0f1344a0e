"""The CommonRoad comparison says why when it cannot run, and never gives a figure then."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks import bench_commonroad


def test_an_environment_that_cannot_be_made_is_a_skip_with_its_reason(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder\n", encoding="utf-8")
    monkeypatch.setattr(bench_commonroad, "ENV_DIR", blocker / "commonroad")
    result = bench_commonroad.main(["--rounds", "1"])
    assert set(result) == {"skipped"}
    assert "cannot create a virtual environment" in result["skipped"]
    assert str(blocker) in result["skipped"]
    assert "CommonRoad comparison skipped" in capsys.readouterr().out


def test_the_environment_is_reused_only_when_made_from_the_same_requirements(
    tmp_path: Path,
) -> None:
    env = tmp_path / "env"
    python = env / "bin" / "python"
    python.parent.mkdir(parents=True)
    python.write_text("", encoding="utf-8")
    (env / bench_commonroad.STAMP).write_text(
        bench_commonroad.REQUIREMENTS.read_text(encoding="utf-8"), encoding="utf-8")
    assert bench_commonroad.ensure_environment(env) == python  # nothing made, nothing run
