"""Fixtures of the command-line tests."""

import pytest


@pytest.fixture
def seen(monkeypatch):
    """The config `reconstruct` builds: the pipeline is replaced by a recorder (no run)."""
    import svolsdf.pipeline as pl

    got = {}

    class Recorder:
        def __init__(self, cfg, out, progress=True):
            got["cfg"] = cfg

        def run(self):
            return {"points": "p", "mesh": None, "timing": {}}

    monkeypatch.setattr(pl, "Pipeline", Recorder)
    return got
