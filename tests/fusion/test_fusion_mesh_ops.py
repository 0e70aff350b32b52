"""Tests for svolsdf.fusion.mesh_ops on analytic SDFs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from fusion_synth import look_at_camera, sphere_depth

from svolsdf.fusion.cull import cull_by_frusta, cull_by_masks, cull_unseen
from svolsdf.fusion.mesh_ops import (
    colors_from_fn,
    colors_from_images,
    extract_mesh,
    largest_component,
    model_colour_fn,
    save_mesh,
    submesh,
    to_world,
    vertex_normals,
)
from svolsdf.io.ply import read_ply
from svolsdf.scene.cameras import Cameras
from svolsdf.scene.scene import Normalization


def sphere_sdf(center=(0.0, 0.0, 0.0), r=0.6):
    c = torch.tensor(center)

    def fn(x):
        return (x - c.to(x)).norm(dim=-1) - r

    return fn


class Counting:
    def __init__(self, fn):
        self.fn, self.n = fn, 0

    def __call__(self, x):
        self.n += x.shape[0]
        return self.fn(x)


def test_sphere_vertices_at_radius_and_outward_faces():
    res = 40
    v, f = extract_mesh(sphere_sdf(r=0.6), bounds=1.0, resolution=res, chunk=5000)
    assert v.dtype == torch.float32 and f.dtype == torch.int64 and f.shape[1] == 3
    cell = 2.0 / (res - 1)
    r = v.norm(dim=-1)
    assert (r - 0.6).abs().max() < cell * math.sqrt(3) / 2
    assert (r - 0.6).abs().mean() < 0.1 * cell
    # Outward orientation: face normals agree with the radial direction; enclosed volume > 0.
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    n = torch.linalg.cross(b - a, c - a)
    assert ((n * (a + b + c)).sum(-1) > 0).float().mean() > 0.99
    vol = (a * torch.linalg.cross(b, c)).sum() / 6
    assert abs(float(vol) - 4 / 3 * math.pi * 0.6**3) < 0.02
    vn = vertex_normals(v, f)
    assert ((vn * v / r[:, None]).sum(-1) > 0.95).all()


def test_box_bounds_and_level():
    box = torch.tensor([[-0.2, -0.7, -0.7], [0.7, 0.7, 0.7]])
    v, f = extract_mesh(sphere_sdf(r=0.3), bounds=box, resolution=30, level=0.1)
    assert (v.norm(dim=-1) - 0.4).abs().max() < 0.05
    assert v[:, 0].min() >= -0.2 - 1e-6  # clipped by the box: an open mesh
    with pytest.raises(ValueError, match="does not cross"):
        extract_mesh(sphere_sdf(r=3.0), bounds=1.0, resolution=8)
    with pytest.raises(ValueError, match="bounds"):
        extract_mesh(sphere_sdf(), bounds=[[0, 0, 0], [0, 1, 1]], resolution=8)


def test_coarse_to_fine_equals_dense():
    fn = sphere_sdf(center=(0.1, -0.05, 0.02), r=0.55)
    dense_fn, c2f_fn = Counting(fn), Counting(fn)
    vd, fd = extract_mesh(dense_fn, bounds=1.0, resolution=73)
    vc, fc = extract_mesh(c2f_fn, bounds=1.0, resolution=73, coarse_to_fine=True,
                          coarse_step=4)
    assert c2f_fn.n < 0.5 * dense_fn.n
    torch.testing.assert_close(vc, vd)
    torch.testing.assert_close(fc, fd)
    # Resolution not a multiple of the step, and a non-Lipschitz (scaled) SDF.
    fn3 = lambda x: 3.0 * fn(x)  # noqa: E731
    vd, fd = extract_mesh(fn3, bounds=1.0, resolution=38)
    vc, fc = extract_mesh(fn3, bounds=1.0, resolution=38, coarse_to_fine=True, coarse_step=5)
    torch.testing.assert_close(vc, vd)
    torch.testing.assert_close(fc, fd)


def test_to_world():
    norm = Normalization(center=torch.tensor([10.0, -5.0, 300.0], dtype=torch.float64),
                         scale=200.0)
    v = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.5, -0.25]])
    w = to_world(v, norm)
    torch.testing.assert_close(w, torch.tensor([[10.0, -5.0, 300.0], [210.0, 95.0, 250.0]]))


def test_largest_component_removes_floater():
    big = sphere_sdf(center=(-0.3, 0.0, 0.0), r=0.45)
    small = sphere_sdf(center=(0.6, 0.3, 0.0), r=0.15)
    v, f = extract_mesh(lambda x: torch.minimum(big(x), small(x)), 1.0, resolution=40)
    v2, f2 = largest_component(v, f)
    assert 0 < len(f2) < len(f)
    d_big = (v2 - torch.tensor([-0.3, 0.0, 0.0])).norm(dim=-1)
    assert (d_big - 0.45).abs().max() < 0.05
    assert f2.max() == len(v2) - 1 and f2.min() == 0
    # Only the floater's faces were removed.
    d_all = (v - torch.tensor([-0.3, 0.0, 0.0])).norm(dim=-1)
    assert len(v2) == int(((d_all - 0.45).abs() < 0.05).sum())


def test_submesh_reindexes():
    v = torch.arange(15, dtype=torch.float32).reshape(5, 3)
    f = torch.tensor([[0, 1, 2], [2, 3, 4]])
    v2, f2, idx = submesh(v, f, torch.tensor([False, True]))
    assert idx.tolist() == [2, 3, 4] and f2.tolist() == [[0, 1, 2]]
    torch.testing.assert_close(v2, v[2:])


def _two_cams():
    c0 = look_at_camera((0.0, 0.0, -4.0))
    c1 = look_at_camera((0.0, 0.0, 4.0))  # opposite side
    return Cameras(torch.cat([c0.K, c1.K]), torch.cat([c0.w2c, c1.w2c]), 48, 40)


def test_colors_from_images_by_normals_and_depth():
    cams = _two_cams()
    v, f = extract_mesh(sphere_sdf(r=1.0), bounds=1.2, resolution=24)
    n = vertex_normals(v, f)
    images = torch.zeros(2, 3, 40, 48)
    images[0, 0] = 1.0  # view 0 red
    images[1, 2] = 1.0  # view 1 blue
    col = colors_from_images(v, n, images, cams)
    z = v[:, 2]
    front, back = z < -0.3, z > 0.3  # camera 0 sits at z = -4
    assert (col[front] == torch.tensor([255, 0, 0], dtype=torch.uint8)).all()
    assert (col[back] == torch.tensor([0, 0, 255], dtype=torch.uint8)).all()
    # Depth-tested visibility with exact depth maps (at half resolution) gives the same split.
    depths = torch.stack([sphere_depth(cams[i].resize(24, 20), torch.zeros(3, dtype=torch.float64),
                                       1.0).float() for i in range(2)])
    col_d = colors_from_images(v, n, images, cams, depths=depths, depth_rel_tol=0.03)
    inner = z.abs() > 0.8  # away from the silhouettes of the 7 px disk
    assert (col_d[inner] == col[inner]).all()
    # A vertex hidden from both (depth maps far away) gets the default grey.
    col_g = colors_from_images(v, n, images, cams, depths=depths * 3)
    assert (col_g == 128).all()


def test_colors_from_fn():
    v = torch.randn(10, 3)
    n = torch.nn.functional.normalize(torch.randn(10, 3), dim=-1)
    col = colors_from_fn(v, n, lambda p, nn: (nn + 1) / 2, chunk=3)
    torch.testing.assert_close(col, ((n + 1) / 2 * 255).round().to(torch.uint8))


class ToyModel:
    """A sphere field whose gradient needs autograd; colour = view direction mapped to [0, 1]."""

    def sdf_and_grad(self, x, create_graph=True):
        x = x.detach().requires_grad_(True)
        sdf = x.norm(dim=-1) - 0.5
        (grad,) = torch.autograd.grad(sdf.sum(), x, create_graph=create_graph)
        return sdf, grad, x * 2

    def colour(self, x, view_dir, normal, feature):
        assert torch.allclose(normal, torch.nn.functional.normalize(x, dim=-1), atol=1e-5)
        return (view_dir + 1) / 2


def test_model_colour_fn_under_no_grad():
    v, f = extract_mesh(sphere_sdf(r=0.5), bounds=1.0, resolution=16)
    n = vertex_normals(v, f)
    with torch.no_grad():
        col = colors_from_fn(v, n, model_colour_fn(ToyModel()), chunk=100)
    torch.testing.assert_close(col, ((-n + 1) / 2 * 255).round().to(torch.uint8))


def test_cull_by_frusta_and_masks():
    cam = look_at_camera((0.0, 0.0, -4.0), W=48, H=40, f=55.0)
    v, f = extract_mesh(sphere_sdf(r=1.0), bounds=1.2, resolution=20)
    # Shift the sphere so that part of it leaves the image on the right (+x).
    v = v + torch.tensor([1.9, 0.0, 0.0])
    v2, f2, idx = cull_by_frusta(v, f, cam)
    assert 0 < len(f2) < len(f)
    uv, z = cam.project(v2[f2].double().mean(1))
    assert (uv[0, :, 0] <= 47.5).all() and (z > 0).all()
    torch.testing.assert_close(v2, v[idx])
    # Masks: only the left half of the image is object; centroids on the right are removed.
    v = v - torch.tensor([1.9, 0.0, 0.0])
    mask = torch.zeros(1, 1, 80, 96)  # twice the camera resolution
    mask[..., :48] = 1
    v3, f3, _ = cull_by_masks(v, f, Cameras(cam.K, cam.w2c, 48, 40), mask, dilation=0)
    uv3, _ = cam.project(v3[f3].double().mean(1))
    assert 0 < len(f3) < len(f)
    assert (uv3[0, :, 0] < 24.0).all()
    # With dilation, more survives; with a second view that sees everything as object,
    # mode="all" keeps the faces seen by it.
    _, f4, _ = cull_by_masks(v, f, Cameras(cam.K, cam.w2c, 48, 40), mask, dilation=12)
    assert len(f4) > len(f3)
    cams2 = Cameras(torch.cat([cam.K, cam.K]), torch.cat([cam.w2c, cam.w2c]), 48, 40)
    masks2 = torch.cat([mask, torch.ones_like(mask)])
    _, f5, _ = cull_by_masks(v, f, cams2, masks2, dilation=0, mode="all")
    assert len(f5) == len(f)
    _, f6, _ = cull_by_masks(v, f, cams2, masks2, dilation=0, mode="any")
    assert len(f6) == len(f3)


def test_cull_unseen_keeps_the_seen_side_and_drops_hidden_cavities():
    """A sphere with a cavity inside, one camera in front: the half facing the camera stays,
    the far half and the cavity (hidden from the camera) go."""
    cam = look_at_camera((0.0, 0.0, -4.0), W=64, H=48, f=60.0)
    outer = sphere_sdf(r=1.0)
    cavity = sphere_sdf(r=0.4)
    v, f = extract_mesh(lambda x: torch.maximum(outer(x), -cavity(x)), bounds=1.2, resolution=40)
    depth = sphere_depth(cam, center=torch.zeros(3, dtype=torch.float64), radius=1.0)
    v2, f2, idx = cull_unseen(v, f, cam, depth[None], rel_tol=0.01)
    torch.testing.assert_close(v2, v[idx])
    c = v2[f2].double().mean(1)
    r = c.norm(dim=-1)
    assert (r > 0.9).all(), "a face of the cavity survived"
    assert (c[:, 2] < 0.2).all(), "a face on the far side survived"
    # the near cap is kept: faces of the original mesh with centroid z < -0.5 all survive
    c0 = v[f].double().mean(1)
    near = (c0[:, 2] < -0.5) & (c0.norm(dim=-1) > 0.9)
    assert len(f2) >= int(near.sum()) > 0
    # no depth anywhere: nothing is seen
    _, f3, _ = cull_unseen(v, f, cam, torch.zeros_like(depth)[None])
    assert len(f3) == 0
    with pytest.raises(ValueError, match="depths must be"):
        cull_unseen(v, f, cam, depth)


def test_save_mesh_ply_and_obj(tmp_path):
    v, f = extract_mesh(sphere_sdf(r=0.5), bounds=1.0, resolution=12)
    col = torch.full((len(v), 3), 200, dtype=torch.uint8)
    p = save_mesh(tmp_path / "m.ply", v, f, col)
    data = read_ply(p)
    got = data["vertices"] if "vertices" in data else data[next(iter(data))]
    assert np.asarray(got).shape[0] == len(v)
    o = save_mesh(tmp_path / "m.obj", v, f)
    text = o.read_text().splitlines()
    assert sum(t.startswith("f ") for t in text) == len(f)
    assert not list(tmp_path.glob("*.tmp"))
