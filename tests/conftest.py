"""Shared fixtures: repository paths and the reference tire of the paper."""

from __future__ import annotations

from pathlib import Path

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
