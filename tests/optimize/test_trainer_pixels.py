"""optimize/trainer.py: a step's pixels are distinct and uniform over the image, as randperm's."""

from __future__ import annotations

import torch

from svolsdf.optimize.trainer import distinct_pixels


def test_distinct_pixels_are_distinct_in_range_and_uniform():
    g = torch.Generator().manual_seed(0)
    # 60 of 200: repeats are common (about 9 per draw), so the redraw runs
    counts = torch.zeros(200)
    for _ in range(2000):
        p = distinct_pixels(200, 40, g)
        assert p.shape == (40,) and len(torch.unique(p)) == 40
        assert int(p.min()) >= 0 and int(p.max()) < 200
        counts += torch.bincount(p, minlength=200)
    # each pixel is drawn with probability 40/200: 400 of 2000 draws, sd 18
    assert (counts - 400).abs().max() < 5 * 18, counts
    # a share above a quarter of the pixels takes the permutation; n > count is capped
    assert len(torch.unique(distinct_pixels(10, 8, g))) == 8
    assert len(distinct_pixels(5, 9, g)) == 5
