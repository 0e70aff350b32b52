"""The mode and ablation rules of `svolsdf.pipeline.options`, over every choice the schema
declares: which stages run and what the final depth is."""

from __future__ import annotations

import itertools

import pytest

from svolsdf.config import Config, choices
from svolsdf.pipeline import options

CASES = list(itertools.product(choices("train.mode"), (None, *choices("train.ablation"))))


def _cfg(mode, ablation) -> Config:
    cfg = Config()
    cfg.train.mode, cfg.train.ablation = mode, ablation
    return cfg


@pytest.mark.parametrize("mode, ablation", CASES)
def test_the_rules_by_mode_and_ablation(mode, ablation):
    cfg = _cfg(mode, ablation)
    assert options.is_baseline(cfg) == (mode == "volsdf")
    assert options.guided_mvs(cfg) == options.uses_prior(cfg) == (mode == "svolsdf")
    assert options.has_guide(cfg) == (mode != "mvs-only")
    assert options.guide_from_consistency(cfg) == (ablation == "soft-consistency-only")
    assert options.fits_to_mvs_depth(cfg) == (ablation in ("mse", "no-prob-volume"))
    assert options.runs_mvs1(cfg) == (mode in ("svolsdf", "mvs-only") or ablation is not None)
    assert options.has_field(cfg) == (mode in ("svolsdf", "volsdf")
                                      and ablation != "soft-consistency-only")


@pytest.mark.parametrize("mode", choices("train.mode"))
def test_every_mode_fuses_its_depth_within_the_same_masks(mode):
    """Issue 50: the fast preset's 4 px mask dilation holds for every mode's final depth, a
    field's (guided stages 2-3, VolSDF's rendering) by fusion.guided_dilation, the MVS cascade's
    alone (mvs-only) by fusion.unguided_dilation; and a changed dilation remakes the points of
    the modes that took the released 12 px before (their fusion key changes, nothing else)."""
    from dataclasses import replace

    from svolsdf.config import preset
    from svolsdf.pipeline.keys import stage_keys

    cfg = preset("fast")
    cfg.train.mode = mode
    assert options.mask_dilation(cfg) == 4
    acting = "unguided_dilation" if mode == "mvs-only" else "guided_dilation"
    keys = {}
    for d in (None, 4, 12):
        c = replace(cfg, fusion=replace(cfg.fusion, **{acting: d}))
        assert options.mask_dilation(c) == d
        keys[d] = stage_keys(c, [0, 1, 2])
    for a, b in ((None, 4), (4, 12)):
        assert {s for s in keys[a] if keys[a][s] != keys[b][s]} <= {"fusion", "mesh"}
        assert keys[a]["fusion"] != keys[b]["fusion"]
