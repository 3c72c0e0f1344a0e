"""Shared fixtures: repository paths and the reference tire of the paper."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "configs"
SHARED_TIR = REPO.parent / "shared" / "data" / "tires" / "mf61_225_50R17_sample.tir"


@pytest.fixture(scope="session")
def paper_tire():
    """Packed parameters of the paper's tire (configs/tires/paper_sti.yaml)."""
    from simserver.adapters.config import load_tire

    tp, _ = load_tire(CONFIGS / "tires" / "paper_sti.yaml")
    return tp
