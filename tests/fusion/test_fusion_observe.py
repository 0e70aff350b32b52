"""Free-space culling, support trimming and the TSDF mesh on an exact sphere seen by three
cameras (tests/fusion/fusion_synth.py), with depth maps at the cameras' size and, as the pipeline
gives them (the MVS size), at twice it."""

from __future__ import annotations

import numpy as np
import torch
from tests.fusion.fusion_synth import CENTER, RADIUS, look_at_camera, sphere_depth

from svolsdf.fusion.mesh_ops import extract_mesh
from svolsdf.fusion.observe import (
    cull_free_space,
    final_depth_step,
    observed_depths,
    point_spacing,
    trim_by_support,
)
from svolsdf.fusion.tsdf import tsdf_mesh
from svolsdf.scene.cameras import Cameras

EYES = [(0.3, -0.2, -4.0), (2.2, 0.1, -3.4), (-2.0, -0.4, -3.5)]


def _cams(W=96, H=80, f=110.0) -> Cameras:
    cs = [look_at_camera(e, W=W, H=H, f=f) for e in EYES]
    return Cameras(torch.cat([c.K for c in cs]), torch.cat([c.w2c for c in cs]), W, H)


def _points(cams: Cameras, depths: list[torch.Tensor]) -> torch.Tensor:
    """Back-projections of every pixel with depth: the fused points of exact depth maps."""
    out = []
    for k, d in enumerate(depths):
        o, dirs, cos = cams[[k]].rays()
        t = d.reshape(-1).double() / cos[0]
        ok = d.reshape(-1) > 0
        out.append((o[0] + dirs[0] * t[:, None])[ok])
    return torch.cat(out)


def _sphere_mesh(radius: float, bulge: bool = False):
    """Marching cubes of the sphere, optionally with a bump towards camera 0 (space it saw)."""
    c = CENTER.float()

    def sdf(x):
        d = (x - c).norm(dim=-1) - radius
        if bulge:  # a blob 0.5 in front of the sphere, towards camera 0 (z < 0)
            b = (x - (c + torch.tensor([0.0, 0.0, -1.45]))).norm(dim=-1) - 0.3
            d = torch.minimum(d, b)
        return d

    return extract_mesh(sdf, 2.0, resolution=112)


def test_observed_depths_keep_only_what_points_confirm():
    cams = _cams()
    depths = [sphere_depth(cams[[k]]).float() for k in range(3)]
    pts = _points(cams, depths)
    noisy = [d.clone() for d in depths]
    noisy[0][40, 48] = 2.0  # an outlier no point supports
    keep = pts[(pts - _points(cams[[0]], [depths[0]])[0]).norm(dim=-1) > 1e-9]  # drop one
    obs = observed_depths(keep, cams, [[d] for d in noisy])
    assert obs[0][40, 48] != 2.0
    assert (obs[1] > 0).sum() == (depths[1] > 0).sum()  # every point confirmed its pixel
    torch.testing.assert_close(obs[1][depths[1] > 0], depths[1][depths[1] > 0])


def test_free_space_culling_removes_a_bulge_and_keeps_the_sphere():
    cams = _cams()
    depths = [sphere_depth(cams[[k]]).float() for k in range(3)]
    obs = observed_depths(_points(cams, depths), cams, [[d] for d in depths])
    v, f = _sphere_mesh(RADIUS, bulge=True)
    v0, f0 = _sphere_mesh(RADIUS)
    vk, fk, _ = cull_free_space(v, f, cams, obs, tol=0.05)
    # the bulge's vertices (within 0.35 of its centre) are gone; the sphere is kept
    blob = CENTER.float() + torch.tensor([0.0, 0.0, -1.45])
    assert ((v - blob).norm(dim=-1) < 0.35).sum() > 50
    assert ((vk - blob).norm(dim=-1) < 0.35).sum() == 0
    vs, fs, _ = cull_free_space(v0, f0, cams, obs, tol=0.05)
    assert len(fs) == len(f0)  # nothing of the true surface is in seen-empty space
    # a surface behind what a view saw (occluded there) is never removed: a smaller sphere
    vi, fi = _sphere_mesh(0.6)
    assert len(cull_free_space(vi, fi, cams, obs, tol=0.05)[1]) == len(fi)
    # without the tolerance the same test removes the sphere's own faces at grazing angles
    assert len(fk) < len(f)


def _twice(cams: Cameras) -> Cameras:
    """The cameras of depth maps at twice the size of ``cams``, as the pipeline's MVS stage 3
    makes them (the plane sweep's and CasMVSNet's 2x; docs/method.md 9.2.2): focal lengths and
    skew doubled, the principal point c' = 2 (c + 0.5) - 0.5 (docs/architecture.md
    "Conventions"). Written out here, not through `Cameras.resize`, so that a mistake in that
    scaling cannot cancel on both sides."""
    K = cams.K.clone()
    K[:, 0, :2] *= 2.0  # fx, skew
    K[:, 1, 1] *= 2.0  # fy
    K[:, :2, 2] = 2.0 * (K[:, :2, 2] + 0.5) - 0.5
    return Cameras(K, cams.w2c.clone(), 2 * cams.width, 2 * cams.height)


def test_maps_at_twice_the_camera_size_are_read_where_they_were_made():
    """Issue 50: the pipeline hands `observed_depths` and `cull_free_space` the final depth at
    the MVS size (twice the working size) with the cameras at the working size, which they
    rescale to each map. Exact depth maps made by the 2x cameras: every pixel is confirmed by
    its own point (a half-pixel error in the scaling moves points to the neighbouring pixels),
    and culling acts as with maps at the cameras' size."""
    cams = _cams()
    big = _twice(cams)
    assert (big.width, big.height) == (192, 160)
    depths = [sphere_depth(big[[k]]).float() for k in range(3)]
    assert depths[0].shape == (160, 192)
    obs = observed_depths(_points(big, depths), cams, [[d] for d in depths])
    for k in range(3):
        assert obs[k].shape == depths[k].shape
        valid = depths[k] > 0
        assert int((obs[k] > 0).sum()) == int(valid.sum()) > 1000, k
        torch.testing.assert_close(obs[k][valid], depths[k][valid])
    v, f = _sphere_mesh(RADIUS, bulge=True)
    vk, fk, _ = cull_free_space(v, f, cams, obs, tol=0.05)
    blob = CENTER.float() + torch.tensor([0.0, 0.0, -1.45])
    assert ((v - blob).norm(dim=-1) < 0.35).sum() > 50
    assert ((vk - blob).norm(dim=-1) < 0.35).sum() == 0  # the bulge in seen-empty space goes
    v0, f0 = _sphere_mesh(RADIUS)
    assert len(cull_free_space(v0, f0, cams, obs, tol=0.05)[1]) == len(f0)  # the surface stays
    vi, fi = _sphere_mesh(0.6)  # behind what the views saw: never removed
    assert len(cull_free_space(vi, fi, cams, obs, tol=0.05)[1]) == len(fi)


def test_trim_by_support_drops_what_no_point_supports():
    cams = _cams()
    depths = [sphere_depth(cams[[k]]).float() for k in range(3)]
    pts = _points(cams, depths).numpy()
    s = point_spacing(pts)
    assert 0 < s < 0.1
    v, f = _sphere_mesh(RADIUS)
    vk, fk, _ = trim_by_support(v, f, pts, k=4, spacing=s)
    # the back of the sphere (z > 0.6 in front of no camera) has no points: trimmed
    assert (v[:, 2] > 0.8).any() and not (vk[:, 2] > 0.8).any()
    # the side the cameras see is kept
    front = (v[:, 2] < -0.8).sum()
    assert (vk[:, 2] < -0.8).sum() == front
    assert len(trim_by_support(v, f, pts, k=1e6, spacing=s)[1]) == len(f)


def test_tsdf_mesh_of_exact_depths_lies_on_the_sphere():
    cams = _cams(W=160, H=128, f=180.0)
    depths = [sphere_depth(cams[[k]]).float() for k in range(3)]
    pts = _points(cams, depths)
    obs = observed_depths(pts, cams, [[d] for d in depths])
    v, f = tsdf_mesh(pts.numpy(), obs, cams, trunc=0.06, resolution=96)
    r = np.linalg.norm(v - CENTER.numpy(), axis=1)
    assert len(f) > 1000
    assert np.abs(r - RADIUS).max() < 0.02  # a fifth of the voxel-free truncation 0.06
    # only the observed front: no vertex on the far side of the sphere
    assert (v[:, 2] > 0.6).sum() == 0
    # faces point outwards (towards the cameras)
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    out = tri.mean(1) - CENTER.numpy()
    assert (np.einsum("ij,ij->i", n, out) > 0).mean() > 0.99


def test_final_depth_step_is_half_the_base_interval():
    step = final_depth_step(torch.tensor([[425.0, 931.15]], dtype=torch.float64))
    assert abs(float(step[0]) - 0.5 * (931.15 - 425.0) / 192) < 1e-9
