"""The stage-key formula of run folders made before the keys came from the stages' declarations
(`svolsdf.pipeline.legacy_keys`), frozen: the runner recognises such a folder's finished stages
by it once. Its values must not move (test_keys_before_sections.py and test_old_run_folder.py
check it against real old run folders)."""

from __future__ import annotations

import pytest

import svolsdf
import svolsdf.pipeline.legacy_keys as legacy
from svolsdf.config import Config, preset
from svolsdf.pipeline.keys import STAGES

VIEWS = [0, 1, 2]

#: the earlier formula's stage keys (in `STAGES` order) of the defaults and the presets, with the
#: version "pinned", as that formula's tests pinned them
PINNED = {
    "defaults": "d260427d8ce9 16dbf7e854f9 d9476149c525 e566642d357a 4176f0fee367 570ed9a7dc69 "
                "5fa6188dcc53",
    "fast": "d260427d8ce9 11eef0e27282 1c56f9684c56 ddd6930391aa db6ed3132a8b def80ccacd2a "
            "c045e97438aa",
    "paper": "d260427d8ce9 407d7e6ab236 70cdfa8b5213 ca48d7438d86 4176f0fee367 39f7eb1fcecf "
             "595955346277",
}


@pytest.mark.parametrize("name", sorted(PINNED))
def test_the_frozen_keys_keep_their_values(name, monkeypatch):
    monkeypatch.setattr(svolsdf, "__version__", "pinned")
    cfg = Config() if name == "defaults" else preset(name)
    cfg.scene.path = "/nonexistent/tiny-scene"
    keys = legacy.legacy_stage_keys(cfg, VIEWS)
    assert " ".join(keys[s] for s in STAGES) == PINNED[name]


def test_width_half_default_keeps_the_keys_paper_had(monkeypatch):
    """``mvs.width = half-default`` is the ratios ``paper`` meant before it became the paper's
    explicit numbers: under the frozen formula its keys are those the old ``paper`` had (run
    folders of that reading are recognised), and today's ``paper`` has others (its finer stages
    rerun)."""
    def keyed(width: str) -> dict:
        c = preset("fast")
        c.scene.path = "scene"
        c.mvs.width = width
        return legacy.legacy_stage_keys(c, VIEWS)

    new_paper, half = keyed("paper"), keyed("half-default")
    monkeypatch.setattr(legacy, "_WIDTH_KEYS", {})  # the keys before the rename
    monkeypatch.setattr(legacy, "_WIDTH_MARKED", ())
    old_paper = keyed("paper")
    assert half == old_paper
    # stage 1 and the field do not depend on the finer stages' width: kept; the rest reruns
    assert [s for s in STAGES if new_paper[s] != old_paper[s]] == [
        "mvs23", "unguided", "fusion", "mesh"]
