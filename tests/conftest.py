"""Shared fixtures: paths to ../shared (tests skip with a reason when it is absent)."""

from __future__ import annotations

from pathlib import Path

import svolsdf  # noqa: F401  (sets OMP_WAIT_POLICY before torch loads)
import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def shared_path(*parts: str) -> Path:
    """Path under ../shared, or skip the test naming what is missing."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"{p} is absent (the team's shared data lives in ../shared)")
    return p


@pytest.fixture(autouse=True)
def _seed_and_threads():
    torch.manual_seed(0)
    yield
