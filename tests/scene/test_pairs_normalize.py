"""View selection (MVSNet) and normalization (VolSDF) on known geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scene_testkit import random_cameras

from svolsdf.scene.cameras import Cameras
from svolsdf.scene.normalize import (
    axes_center,
    normalize_cameras,
    points_depth_range,
    sphere_depth_range,
)
from svolsdf.scene.pairs import (
    compute_pairs,
    read_pair_file,
    view_selection_scores,
    write_pair_file,
)
from svolsdf.scene.scene import Normalization, SceneError


def _cams(n=6, seed=0):
    K, w2c = random_cameras(n, seed=seed)
    return Cameras(torch.from_numpy(K), torch.from_numpy(w2c), 40, 30)


def test_score_of_one_point_matches_the_piecewise_gaussian():
    p = torch.zeros(1, 3, dtype=torch.float64)
    for theta in (2.0, 5.0, 15.0):
        t = math.radians(theta)
        centers = torch.tensor([[0, 0, 10.0], [10 * math.sin(t), 0, 10 * math.cos(t)]],
                               dtype=torch.float64)
        s = view_selection_scores(centers, p, torch.ones(1, 2, dtype=torch.bool))
        sigma = 1.0 if theta <= 5 else 10.0
        expect = math.exp(-((theta - 5) ** 2) / (2 * sigma**2))
        assert float(s[0, 1]) == pytest.approx(expect, rel=1e-3)  # float32 angles
        assert float(s[1, 0]) == float(s[0, 1]) and float(s[0, 0]) == 0


def test_pairs_prefer_the_nearest_moderate_baseline():
    # cameras on a circle around the origin, 4 degrees apart: nearest neighbours rank first
    cams = []
    for i in range(8):
        a = math.radians(4 * i)
        c = np.array([10 * math.sin(a), 0, -10 * math.cos(a)])
        z = -c / np.linalg.norm(c)
        x = np.cross([0, -1, 0], z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        w = np.eye(4)
        w[:3, :3], w[:3, 3] = R, -R @ c
        cams.append(w)
    K = torch.tensor([[50.0, 0, 20], [0, 50, 15], [0, 0, 1]], dtype=torch.float64)
    c = Cameras(K.expand(8, 3, 3).clone(), torch.from_numpy(np.stack(cams)), 40, 30)
    norm = Normalization(torch.zeros(3, dtype=torch.float64), 1.0, 1.0)
    pairs, scores = compute_pairs(c, list(range(100, 108)), normalization=norm, num=3)
    # baselines 4, 8, 12 deg: G(8) = 0.96 > G(12) = 0.78 > G(4) = 0.61 (sigma2 = 10 is wide,
    # sigma1 = 1 narrow), so MVSNet's rule prefers 8 degrees
    assert pairs[100] == [102, 103, 101]
    assert pairs[104][:2] in ([102, 106], [106, 102])
    assert all(a >= b for a, b in zip(scores[104], scores[104][1:], strict=False))


def test_pair_file_roundtrip(tmp_path):
    pairs = {0: [2, 1], 1: [0], 2: [1, 0]}
    scores = {0: [3.0, 1.5], 1: [2.0], 2: [1.0, 0.5]}
    p = write_pair_file(tmp_path / "pair.txt", pairs, scores)
    assert read_pair_file(p) == (pairs, scores)
    p.write_text("3\n0\n2 1\n")
    with pytest.raises(SceneError, match="pair.txt: malformed"):
        read_pair_file(p)


def test_axes_center_finds_the_common_point():
    c = _cams(6)
    x = axes_center(c.centers, c.view_dirs)
    # random_cameras look at (0.3, -0.2, 0.1) up to 0.05 noise
    assert float((x - torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)).norm()) < 0.1


def test_normalize_cameras_volsdf_rule():
    c = _cams(7, seed=2)
    n = normalize_cameras(c)
    d = n.to_unit(c.centers).norm(dim=-1)
    assert float(d.max()) == pytest.approx(3 / 1.1) and n.radius == 3.0  # ~2.73
    # unit-frame cameras: same pixels for mapped points
    cu = c.transformed(n.center, n.scale)
    pts = torch.randn(20, 3, dtype=torch.float64)
    uv_w, z_w = c.project(n.to_world(pts))
    uv_u, z_u = cu.project(pts)
    torch.testing.assert_close(uv_w, uv_u)
    torch.testing.assert_close(z_w / n.scale, z_u)


def test_sphere_and_points_depth_ranges():
    c = _cams(4)
    n = Normalization(torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64), 0.5, 1.0)
    dr = sphere_depth_range(c, n)
    # every point of the sphere lies inside [near, far] of every view
    g = torch.Generator().manual_seed(0)
    u = torch.randn(500, 3, generator=g, dtype=torch.float64)
    pts = n.to_world(u / u.norm(dim=-1, keepdim=True))
    z = c.world_to_camera(pts)[..., 2]
    assert (z >= dr[:, :1] - 1e-9).all() and (z <= dr[:, 1:] + 1e-9).all()
    assert torch.allclose(dr[:, 1] - dr[:, 0], torch.full((4,), 1.0, dtype=torch.float64))
    pr, counts = points_depth_range(c, pts)
    assert (counts > 10).all() and (pr[:, 0] <= z.min(1).values).all()
    inside = torch.zeros(500, 4, dtype=torch.bool)
    pr2, counts2 = points_depth_range(c, pts, visibility=inside)
    assert torch.isnan(pr2).all() and (counts2 == 0).all()
