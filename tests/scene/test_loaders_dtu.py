"""Loaders on the shared DTU scans, and Cameras.project against DTU's raw projection matrices."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from conftest import shared_path
from svolsdf.scene import load_scene


def _project_P(P: np.ndarray, pts: np.ndarray) -> np.ndarray:
    ph = P[:3, :4] @ np.c_[pts, np.ones(len(pts))].T
    return (ph[:2] / ph[2]).T


def _dtu_points(n=500, seed=0):
    # points in DTU's working volume (ObsMask9 bounding box, mm)
    rng = np.random.default_rng(seed)
    return rng.uniform([-73, -197, 472], [129, 183, 810], size=(n, 3))


@pytest.fixture(scope="module")
def scan65():
    return load_scene(shared_path("data", "dtu_scan65"), load_images=False)


@pytest.fixture(scope="module")
def raw9():
    return load_scene(shared_path("data", "dtu_raw"), load_images=False)


def test_idr_scan65_headers_only(scan65):
    root = shared_path("data", "dtu_scan65")
    s = scan65
    assert s.format == "idr" and len(s) == 49 and s.view_ids == list(range(49))
    assert (s.width, s.height) == (1600, 1200) and s.units == "mm" and s.images is None
    assert len(s.extras["mask_paths"]) == 49
    d = np.load(root / "cameras_sphere.npz")
    S = d["scale_mat_0"]
    assert s.normalization.scale == pytest.approx(S[0, 0])
    np.testing.assert_allclose(s.normalization.center.numpy(), S[:3, 3])
    # DTU's standard depth range (docs/method.md 1.1), and all cameras see the object at that range
    assert torch.allclose(s.depth_range, torch.tensor([425.0, 425 + 2.65 * 192],
                                                      dtype=torch.float64))
    zc = s.cameras.world_to_camera(s.normalization.center[None])[:, 0, 2]
    assert ((zc > 425) & (zc < 933.8)).all()
    # computed pairs agree with DTU's published pair.txt for view 0 on the set of neighbours
    assert set(s.pairs[0]) == {10, 1, 9, 12, 11, 13, 2, 8, 14, 27}


def test_idr_scan65_pixels_three_views():
    root = shared_path("data", "dtu_scan65")
    s = load_scene(root, views=[25, 22, 28], image_size=(160, 120))
    assert s.view_ids == [25, 22, 28] and s.images.shape == (3, 3, 120, 160)
    assert s.masks.shape == (3, 1, 120, 160) and 0.1 < float(s.masks.mean()) < 0.6
    assert 0 <= float(s.images.min()) and float(s.images.max()) <= 1


@pytest.mark.parametrize("size", [None, (768, 576)])
def test_project_matches_raw_P(raw9, size):
    """Pixels from Cameras.project match DTU's calibration P to << 0.01 px (native and 768x576)."""
    root = shared_path("data", "dtu_raw")
    s = raw9.select([0, 22, 25, 28, 48])
    if size is not None:
        s = s.resize(*size)  # images are None: cameras only
    assert s.format == "dtu_raw" and s.units == "mm"
    pts = _dtu_points()
    uv, z = s.cameras.project(torch.from_numpy(pts))
    for k, vid in enumerate(s.view_ids):
        P = np.loadtxt(root / "Calibration" / "cal18" / f"pos_{vid + 1:03d}.txt")
        if size is not None:
            sx, sy = size[0] / 1600, size[1] / 1200
            # pixel-centre convention: u' = sx (u + 0.5) - 0.5
            A = np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1]])
            P = A @ P
        ref = _project_P(P, pts)
        err = np.abs(uv[k].numpy() - ref).max()
        assert err < 1e-4, f"view {vid}: {err} px"
        assert (z[k] > 0).all()


def test_dtu_raw_extras_and_lighting(raw9):
    root = shared_path("data", "dtu_raw")
    s = raw9.select([3])
    assert s.extras["scan"] == 9 and s.extras["lighting"] == "3"
    assert s.extras["obs_mask"].endswith("ObsMask/ObsMask9_10.mat")
    assert s.image_paths[0].name == "rect_004_3_r5000.jpg"
    # the scan folder itself also works
    s2 = load_scene(root / "Rectified" / "scan9", views=[3], image_size=(768, 576))
    torch.testing.assert_close(s2.cameras.w2c, s.cameras.w2c)
    torch.testing.assert_close(s2.cameras.K, s.cameras.resize(768, 576).K)
    assert s2.images.shape == (1, 3, 576, 768)
    # normalization by VolSDF's rule: every camera within 3 / 1.1 of the unit frame
    full = raw9
    d = full.normalization.to_unit(full.cameras.centers).norm(dim=-1)
    assert float(d.max()) == pytest.approx(3 / 1.1, rel=1e-9)
    from svolsdf.scene.scene import SceneError
    with pytest.raises(SceneError, match="lighting 5"):
        load_scene(root, lighting=5, load_images=False)


def test_scan65_and_dtu_raw_share_the_rig(scan65, raw9):
    """Both shared scans use DTU's cal18 rig: the decomposed cameras agree."""
    a, b = scan65.select([0, 30]), raw9.select([0, 30])
    torch.testing.assert_close(a.cameras.K, b.cameras.K, atol=1e-3, rtol=1e-5)
    torch.testing.assert_close(a.cameras.w2c, b.cameras.w2c, atol=1e-3, rtol=1e-5)
