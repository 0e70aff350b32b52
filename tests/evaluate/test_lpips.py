"""LPIPS v0.1 in plain torch against the published distances on the reference images."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from conftest import shared_path
from svolsdf.errors import InputError
from svolsdf.evaluate.lpips import LPIPS, lpips_distance


def _load(path) -> torch.Tensor:
    """(1, 3, H, W) in [-1, 1], as lpips.im2tensor."""
    a = np.array(Image.open(path).convert("RGB"), dtype=np.float32)
    return torch.from_numpy(a).permute(2, 0, 1)[None] / 127.5 - 1


def test_alexnet_matches_published_distances():
    ref_dir = shared_path("data", "lpips_ref")
    model = LPIPS("alex", shared_path("weights", "lpips"))
    ref, p0, p1 = (_load(ref_dir / f"ex_{n}.png") for n in ("ref", "p0", "p1"))
    assert round(float(model(ref, p0)[0]), 3) == 0.722
    assert round(float(model(ref, p1)[0]), 3) == 0.138
    assert float(model(ref, ref)[0]) == 0.0


def test_vgg_sanity_and_image_api():
    ref_dir = shared_path("data", "lpips_ref")
    model = LPIPS("vgg", shared_path("weights", "lpips") / "vgg16_lpips_v0.1.pth")
    ref, p0, p1 = (_load(ref_dir / f"ex_{n}.png")[..., :32, :32] for n in ("ref", "p0", "p1"))
    d = model(torch.cat([ref, p1]), torch.cat([p0, p1]))
    assert d.shape == (2,) and torch.isfinite(d).all()
    assert float(d[0]) > 0.05 and float(d[1]) == 0.0
    # [0, 1] image API: composites on white; a fully masked-out pair is white on both sides -> 0.
    x, y = (ref[0] + 1) / 2, (p0[0] + 1) / 2
    assert lpips_distance(x, y, model, mask=torch.zeros(32, 32)) == 0.0


def test_missing_weights_error(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        LPIPS("alex", tmp_path)
    with pytest.raises(InputError, match="'alex' or 'vgg'"):
        LPIPS("squeeze", tmp_path)
