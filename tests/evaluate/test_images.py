"""Masked PSNR / SSIM against scikit-image (docs/method.md 8.3)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from svolsdf.errors import InputError
from svolsdf.evaluate.images import composite_white, masked_psnr, ssim


def _pair(h=33, w=41):
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(3, h, w, generator=g)
    pred = (gt + 0.1 * torch.randn(3, h, w, generator=g)).clamp(0, 1)
    mask = torch.rand(1, h, w, generator=g) > 0.4
    return pred, gt, mask


def test_psnr_matches_skimage_on_masked_pixels():
    pred, gt, mask = _pair()
    m = mask[0].numpy()
    want = peak_signal_noise_ratio(gt.numpy()[:, m].astype(np.float64),
                                   pred.numpy()[:, m].astype(np.float64), data_range=1.0)
    assert masked_psnr(pred, gt, mask) == pytest.approx(want, abs=1e-5)
    assert masked_psnr(pred, gt, mask[0].float()) == pytest.approx(want, abs=1e-5)  # (H, W)
    want_all = peak_signal_noise_ratio(gt.numpy().astype(np.float64),
                                       pred.numpy().astype(np.float64), data_range=1.0)
    assert masked_psnr(pred, gt) == pytest.approx(want_all, abs=1e-5)


def test_psnr_known_value_and_edge_cases():
    gt = torch.zeros(3, 8, 8)
    pred = gt + 0.1
    assert masked_psnr(pred, gt) == pytest.approx(20.0)  # MSE 0.01
    mask = torch.zeros(1, 8, 8)
    mask[:, :4] = 1
    pred[:, 4:] = 1.0  # errors only in the background
    assert masked_psnr(pred, gt, mask) == pytest.approx(20.0)
    assert masked_psnr(gt, gt) == math.inf
    assert math.isnan(masked_psnr(pred, gt, torch.zeros(8, 8)))
    with pytest.raises(InputError, match="mask is"):
        masked_psnr(pred, gt, torch.ones(1, 7, 8))


@pytest.mark.parametrize("data_range", [1.0, 2.0])
def test_ssim_matches_skimage_with_white_compositing(data_range):
    pred, gt, mask = _pair()
    x = composite_white(pred, mask).numpy().astype(np.float64)
    y = composite_white(gt, mask).numpy().astype(np.float64)
    want = structural_similarity(x, y, channel_axis=0, data_range=data_range, win_size=7,
                                 gaussian_weights=False)
    assert ssim(pred, gt, mask, data_range=data_range) == pytest.approx(want, abs=1e-5)


def test_ssim_without_mask_and_identity():
    pred, gt, _ = _pair(20, 24)
    want = structural_similarity(pred.numpy().astype(np.float64), gt.numpy().astype(np.float64),
                                 channel_axis=0, data_range=1.0)
    assert ssim(pred, gt) == pytest.approx(want, abs=1e-5)
    assert ssim(gt, gt) == pytest.approx(1.0)


def test_composite_white():
    img = torch.full((3, 2, 2), 0.25)
    m = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    out = composite_white(img, m)
    assert torch.equal(out[:, 0, 0], torch.full((3,), 0.25))
    assert torch.equal(out[:, 0, 1], torch.ones(3))
