"""The report's CPU rasterizer against its per-pixel loop twin and known depths."""

from __future__ import annotations

import numpy as np
import pytest

from svolsdf.evaluate.raster import (
    rasterize_mesh,
    rasterize_mesh_reference,
    shade,
    vertex_normals,
)

W, H = 20, 16
K = np.array([[18.0, 0, 9.5], [0, 18.0, 7.5], [0, 0, 1]])


def _random_mesh(seed=0, n=12):
    rng = np.random.default_rng(seed)
    v = rng.uniform([-1, -1, 3], [1, 1, 6], size=(3 * n, 3))
    return v, np.arange(3 * n).reshape(n, 3)


@pytest.mark.parametrize("seed", [0, 1])
def test_rasterize_matches_reference(seed):
    v, f = _random_mesh(seed)
    w2c = np.eye(4)
    w2c[:3, 3] = [0.1, -0.2, 0.3]
    fast = rasterize_mesh(v, f, K, w2c, W, H)
    ref = rasterize_mesh_reference(v, f, K, w2c, W, H)
    assert (fast.face >= 0).sum() > 20
    np.testing.assert_array_equal(fast.face, ref.face)
    np.testing.assert_allclose(fast.depth, ref.depth, rtol=1e-12)
    np.testing.assert_allclose(fast.bary, ref.bary, atol=1e-12)


def test_plane_depth_is_exact_and_bary_sum_to_one():
    # a slanted plane z = 4 + 0.5 x, two triangles covering the view
    x = np.array([-3.0, 3.0, -3.0, 3.0])
    y = np.array([-3.0, -3.0, 3.0, 3.0])
    v = np.c_[x, y, 4 + 0.5 * x]
    f = np.array([[0, 1, 3], [0, 3, 2]])
    r = rasterize_mesh(v, f, K, np.eye(4), W, H)
    assert (r.face >= 0).all()
    u, w = np.meshgrid(np.arange(W), np.arange(H))
    xn = (u - K[0, 2]) / K[0, 0]  # ray x / z
    want = 4 / (1 - 0.5 * xn)
    np.testing.assert_allclose(r.depth, want, rtol=1e-9)
    np.testing.assert_allclose(r.bary.sum(-1), 1.0, atol=1e-12)


def test_large_triangles_are_split_into_chunks(monkeypatch):
    import svolsdf.evaluate.raster as raster

    v, f = _random_mesh(2)
    whole = rasterize_mesh(v, f, K, np.eye(4), W, H)
    monkeypatch.setattr(raster, "_CHUNK", 7)
    chunked = rasterize_mesh(v, f, K, np.eye(4), W, H)
    np.testing.assert_array_equal(whole.face, chunked.face)


def test_shade_faces_the_camera():
    v = np.array([[-3.0, -3, 4], [3, -3, 4], [-3, 3, 4], [3, 3, 4]])
    f = np.array([[0, 1, 3], [0, 3, 2]])
    r = rasterize_mesh(v, f, K, np.eye(4), W, H)
    pic, nmap = shade(r, f, vertex_normals(v, f), np.eye(4),
                      colors=np.full((4, 3), 255, np.uint8))
    assert pic.shape == (H, W, 3) and pic.dtype == np.uint8
    # camera-frame normal (0, 0, -1) -> (0.5, 0.5, 0) * 255
    np.testing.assert_array_equal(nmap[5, 5], [128, 128, 0])
    assert 150 < pic[5, 5, 0] < 255
