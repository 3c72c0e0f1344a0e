"""Shared fixtures: repository paths and the reference tire of the paper."""

from __future__ import annotations

import shlex
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import pytest

REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "configs"
SAMPLE_TIR = CONFIGS / "tires" / "data" / "mf61_225_50R17_sample.tir"
"""The MF 6.1 sample property file, as shipped with the repository (the one the
``mf61_sample`` tire uses): a byte-for-byte copy of the team's reference file
``SHARED_TIR`` (``tests/test_tir_file.py`` checks it where that exists), so that a clone
on any machine tests the same file."""
SHARED_TIR = REPO.parent / "shared" / "data" / "tires" / "mf61_225_50R17_sample.tir"


@pytest.fixture(scope="session")
def paper_tire():
    """Packed parameters of the paper's tire (configs/tires/paper_sti.yaml)."""
    from simserver.adapters.config import load_tire

    tp, _ = load_tire(CONFIGS / "tires" / "paper_sti.yaml")
    return tp


README_BIN = Path(sys.executable).parent
"""What the README's ``.venv/bin/`` means in tests: the environment running them."""


def as_written(command: str) -> list[str]:
    """argv of a README command, ``.venv/bin/X`` (or a bare ``simserver``) being this
    environment's ``X``."""
    argv = shlex.split(command)
    if argv[0].startswith(".venv/bin/"):
        argv[0] = str(README_BIN / argv[0].removeprefix(".venv/bin/"))
    elif argv[0] == "simserver":
        argv[0] = str(README_BIN / "simserver")
    return argv


def readme_main_job() -> str:
    """The job of the README's first command, after its install steps."""
    lines = (REPO / "README.md").read_text().splitlines()
    first = next(ln.strip() for ln in lines if ln.startswith("    python3 -m venv .venv"))
    return first.split("&&")[-1].strip()


@pytest.fixture(scope="module")
def readme_server() -> Iterator[SimpleNamespace]:
    """The README's main job as written, on its default endpoint (tcp/127.0.0.1:7447);
    at the end it must stop cleanly on SIGINT with its final statistics."""
    with socket.socket() as probe:
        if probe.connect_ex(("127.0.0.1", 7447)) == 0:
            pytest.skip("something already listens on 127.0.0.1:7447")
    proc = subprocess.Popen(as_written(readme_main_job()), cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        line = ""
        end = time.monotonic() + 120
        while "ready on" not in line and time.monotonic() < end and proc.poll() is None:
            line = proc.stdout.readline()
        assert "ready on simserver/car0" in line, line
        yield SimpleNamespace(endpoint="tcp/127.0.0.1:7447", vehicle_id="car0", proc=proc)
    finally:
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0 and "simserver: stopped" in out, out
