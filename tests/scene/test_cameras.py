import math

import torch

from svolsdf.scene.cameras import Cameras, decompose_projection


def _random_cameras(V=3, W=160, H=120, dtype=torch.float64):
    g = torch.Generator().manual_seed(1)
    K = torch.zeros(V, 3, 3, dtype=dtype)
    K[:, 0, 0] = 150 + 10 * torch.rand(V, generator=g, dtype=dtype)
    K[:, 1, 1] = 148 + 10 * torch.rand(V, generator=g, dtype=dtype)
    K[:, 0, 1] = 0.3
    K[:, 0, 2] = W / 2 + torch.rand(V, generator=g, dtype=dtype)
    K[:, 1, 2] = H / 2 - torch.rand(V, generator=g, dtype=dtype)
    K[:, 2, 2] = 1
    w2c = torch.eye(4, dtype=dtype).repeat(V, 1, 1)
    for i in range(V):
        a = 0.3 * (i + 1)
        R = torch.tensor(
            [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]], dtype=dtype
        )
        w2c[i, :3, :3] = R
        w2c[i, :3, 3] = torch.tensor([0.1 * i, -0.2, 4.0], dtype=dtype)
    return Cameras(K, w2c, W, H)


def test_decompose_projection_recovers_k_and_pose():
    cams = _random_cameras()
    for i in range(len(cams)):
        P = cams.K[i] @ cams.w2c[i, :3] * -3.7  # arbitrary (negative) scale
        K, w2c = decompose_projection(P)
        torch.testing.assert_close(K, cams.K[i], atol=1e-9, rtol=1e-9)
        torch.testing.assert_close(w2c, cams.w2c[i], atol=1e-9, rtol=1e-9)


def test_project_unproject_round_trip():
    cams = _random_cameras()
    uv = torch.rand(3, 50, 2, dtype=torch.float64) * torch.tensor([160.0, 120.0],
                                                                 dtype=torch.float64)
    depth = 2 + 3 * torch.rand(3, 50, dtype=torch.float64)
    X = cams.unproject(uv, depth)
    uv2, d2 = cams.project(X)
    torch.testing.assert_close(uv2, uv, atol=1e-9, rtol=0)
    torch.testing.assert_close(d2, depth, atol=1e-9, rtol=0)


def test_rays_hit_unprojected_points():
    cams = _random_cameras()
    o, d, cos = cams.rays()
    depth = torch.full((3, cams.height * cams.width), 2.5, dtype=torch.float64)
    uv = cams.pixel_grid(dtype=torch.float64).reshape(1, -1, 2).expand(3, -1, -1)
    X = cams.unproject(uv, depth)
    torch.testing.assert_close(o + d * (depth / cos)[..., None], X, atol=1e-9, rtol=0)


def test_resize_keeps_image_borders():
    cams = _random_cameras()
    small = cams.resize(80, 60)
    corners = torch.tensor([[[-0.5, -0.5], [159.5, 119.5]]], dtype=torch.float64)
    X = cams.unproject(corners.expand(3, -1, -1), torch.full((3, 2), 3.0, dtype=torch.float64))
    uv, _ = small.project(X)
    expected = torch.tensor([[-0.5, -0.5], [79.5, 59.5]], dtype=torch.float64)
    torch.testing.assert_close(uv, expected.expand(3, -1, -1), atol=1e-9, rtol=0)


def test_transformed_frame_scales_depth():
    cams = _random_cameras()
    c = torch.tensor([0.3, -0.1, 0.2], dtype=torch.float64)
    s = 2.5
    X = torch.randn(20, 3, dtype=torch.float64)
    uv, d = cams.project(X)
    uv2, d2 = cams.transformed(c, s).project((X - c) / s)
    torch.testing.assert_close(uv2, uv, atol=1e-9, rtol=0)
    torch.testing.assert_close(d2, d / s, atol=1e-9, rtol=0)
