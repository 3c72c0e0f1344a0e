"""docs/results.md: every Python block runs as written against a real run (the CLI's
history, summary and Rerun recording of E5, and ``compare`` of it with itself), so the
way it shows to read results stays true for the installed pyarrow and rerun-sdk."""

from __future__ import annotations

import contextlib
import io
import os
import re
import subprocess
import sys

import pytest

from simserver.testing import CONFIGS, REPO

pytestmark = pytest.mark.timeout(300)

DOC = REPO / "docs" / "results.md"


def test_every_python_block_of_the_results_doc_runs(tmp_path):
    out = tmp_path / "e5"
    env = dict(os.environ, XDG_CONFIG_HOME=str(tmp_path / "xdg_config"),
               XDG_DATA_HOME=str(tmp_path / "xdg_data"))
    subprocess.run([sys.executable, "-m", "simserver", "run-scenario",
                    str(CONFIGS / "scenarios" / "e5_hold_restart_uphill.yaml"), "--out",
                    str(out), "--no-plots", "--quiet", "--rrd", str(out / "scene.rrd")],
                   cwd=REPO, env=env, check=True, capture_output=True, timeout=240)
    subprocess.run([sys.executable, "-m", "simserver", "compare", str(out), str(out),
                    "--out", str(out / "compare"), "--no-plot"],
                   cwd=REPO, env=env, check=True, capture_output=True, timeout=240)
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(encoding="utf-8"), re.S)
    assert len(blocks) == 4
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        for block in blocks:
            exec(compile(block, str(DOC), "exec"), {"OUT": out, "CMP": out / "compare"})  # noqa: S102
    text = printed.getvalue()
    assert "14400 rows, 72.0 s" in text
    assert re.search(r"held 2\.\d+-66\.00 s: creep 0\.00\d\d mm", text)
    assert "B shifted by +0 s (first input change)" in text
    assert "u_mps: max |A-B| 0 at" in text and "hold 0: creep A-B 0.0 m" in text
    assert "/world/car" in text or "car rows" in text
