"""The ground truth as the official evaluation prepares it (svolsdf.evaluate.protocol)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from svolsdf.evaluate.protocol import official_resize, official_resize_mask, official_test_images


def test_official_resize_is_cubic_without_antialiasing():
    # a 1-pixel checkerboard shrunk 2x: an antialiased resize averages it to grey, OpenCV's
    # INTER_CUBIC (no antialiasing) samples between pixels and keeps a strong pattern
    y, x = np.mgrid[0:64, 0:96]
    board = torch.from_numpy(((x // 3 + y // 3) % 2).astype(np.float32))[None].expand(3, -1, -1)
    ours = official_resize(board, 32, 21)
    aa = F.interpolate(board[None], size=(21, 32), mode="bicubic", align_corners=False,
                       antialias=True)[0]
    assert ours.shape == (3, 21, 32)
    assert float(ours.std()) > float(aa.std()) * 1.2
    flat = torch.full((3, 40, 50), 0.4)
    assert torch.allclose(official_resize(flat, 20, 15), torch.full((3, 15, 20), 0.4), atol=1e-6)
    assert official_resize(flat, 50, 40) is flat
    with pytest.raises(ValueError):
        official_resize(flat[0], 20, 15)


def test_official_mask_is_bilinear_then_half():
    m = torch.zeros(1, 40, 40)
    m[:, 10:30, 10:30] = 1
    r = official_resize_mask(m, 20, 20)
    assert r.dtype == torch.bool and r.shape == (20, 20)
    assert bool(r[5:15, 5:15].all()) and not bool(r[:4].any())
    assert int(r.sum()) == 100


def test_official_test_images_of_a_synthetic_scene(tmp_path):
    from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

    make_synthetic_scene(tmp_path / "scene", SynthConfig(views=3, width=64, height=48, seed=2,
                                                         supersample=1))
    images, masks = official_test_images(tmp_path / "scene", [0, 1], (32, 24))
    assert images.shape == (2, 3, 24, 32)
    assert float(images.min()) >= 0 and float(images.max()) <= 1
    assert masks is None or masks.shape == (2, 24, 32)
