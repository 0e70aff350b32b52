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
