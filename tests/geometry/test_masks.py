"""Mask dilation and resizing to the depth size (svolsdf.geometry.masks)."""

from __future__ import annotations

import numpy as np
import torch
from scipy import ndimage
from skimage.morphology import disk

from svolsdf.geometry.masks import dilate_mask, mask_to_depth_resolution


def test_dilate_mask_equals_disk_dilation():
    g = np.random.default_rng(0)
    m = g.random((60, 70)) > 0.995
    for r in (0, 1, 3, 12):
        ours = dilate_mask(torch.from_numpy(m), r).numpy()
        ref = ndimage.binary_dilation(m, structure=disk(r)) if r > 0 else m
        np.testing.assert_array_equal(ours, ref)
    assert not dilate_mask(torch.zeros(5, 5), 3).any()


def test_mask_to_depth_resolution_keeps_any_coverage():
    m = torch.zeros(8, 8)
    m[3, 3] = 1
    r = mask_to_depth_resolution(m, 4, 4)
    assert r.dtype == torch.bool and r[1, 1] and r.sum() >= 1
