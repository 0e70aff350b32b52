"""Shared fixtures: paths to ../shared (tests skip with a reason when it is absent)."""

from __future__ import annotations

import os

# before torch loads its OpenMP runtime (see svolsdf/__init__.py): spinning threads make the
# tests several times slower on a shared machine
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
import torch  # noqa: E402

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


@pytest.fixture
def seen(monkeypatch):
    """CLI tests: the config `reconstruct` builds; the pipeline is replaced by a recorder."""
    import svolsdf.pipeline as pl

    got = {}

    class Recorder:
        def __init__(self, cfg, out, progress=True):
            got["cfg"] = cfg

        def run(self):
            return {"points": "p", "mesh": None, "timing": {}}

    monkeypatch.setattr(pl, "Pipeline", Recorder)
    return got
