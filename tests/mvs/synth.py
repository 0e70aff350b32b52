"""Tiny ray-cast synthetic scenes with exact z-depth, for the MVS tests and benchmark.

Surfaces carry a band-limited procedural texture (a sum of random 3D sinusoids), so that every
view sees the same colours at the same 3D points.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from svolsdf.scene.cameras import Cameras
from svolsdf.scene.scene import Normalization, Scene


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, -1.0, 0.0)) -> torch.Tensor:
    """(4, 4) float64 world-to-camera matrix of a camera at ``eye`` looking at ``target``."""
    eye = torch.tensor(eye, dtype=torch.float64)
    z = torch.tensor(target, dtype=torch.float64) - eye
    z = z / z.norm()
    x = torch.linalg.cross(z, torch.tensor(up, dtype=torch.float64))
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c


def make_cameras(W=64, H=48, eyes=None, focal_ratio=1.2) -> Cameras:
    """Cameras at ``eyes`` (default three on a small arc at distance ~4) looking at the origin."""
    if eyes is None:
        eyes = [(0.0, 0.0, -4.0), (0.7, 0.1, -3.95), (-0.6, -0.3, -3.95)]
    V = len(eyes)
    K = torch.zeros(V, 3, 3, dtype=torch.float64)
    K[:, 0, 0] = K[:, 1, 1] = focal_ratio * W
    K[:, 0, 2] = (W - 1) / 2
    K[:, 1, 2] = (H - 1) / 2
    K[:, 2, 2] = 1
    w2c = torch.stack([look_at(e) for e in eyes])
    return Cameras(K, w2c, W, H)


def texture(points: torch.Tensor, n: int = 48, seed: int = 3, fmin=3.0, fmax=25.0) -> torch.Tensor:
    """(N, 3) world points -> (N, 3) colours in [0, 1] from random 3D sinusoids."""
    g = torch.Generator().manual_seed(seed)
    dirs = torch.randn(n, 3, generator=g, dtype=torch.float64)
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    freq = fmin * (fmax / fmin) ** torch.rand(n, generator=g, dtype=torch.float64)
    phase = 2 * math.pi * torch.rand(n, 3, generator=g, dtype=torch.float64)
    amp = 1.0 / freq.sqrt()
    arg = (points.double() @ (dirs * freq[:, None]).T)[:, :, None] + phase  # (N, n, 3)
    c = (amp[None, :, None] * torch.sin(arg)).sum(1)
    c = c / amp.sum() * 8.0
    return (0.5 + 0.5 * torch.tanh(c)).float()


def raycast(cameras: Cameras, planes=(), spheres=()):
    """Render surfaces: planes as (normal n, offset o) with n·x = o, spheres as (centre, radius).

    Returns:
        images (V, 3, H, W), depth (V, H, W) z-depth (inf where nothing is hit), mask (V, 1, H, W).
    """
    origins, dirs, cos = cameras.rays()
    origins, dirs = origins.double(), dirs.double()
    t_best = torch.full(dirs.shape[:2], math.inf, dtype=torch.float64)
    for n, o in planes:
        n = torch.tensor(n, dtype=torch.float64)
        denom = dirs @ n
        t = (o - origins @ n) / denom
        t = torch.where((denom.abs() > 1e-9) & (t > 0), t, torch.full_like(t, math.inf))
        t_best = torch.minimum(t_best, t)
    for c, r in spheres:
        c = torch.tensor(c, dtype=torch.float64)
        oc = origins - c
        b = (dirs * oc).sum(-1)
        disc = b * b - (oc * oc).sum(-1) + r * r
        t = -b - disc.clamp_min(0).sqrt()
        t = torch.where((disc > 0) & (t > 0), t, torch.full_like(t, math.inf))
        t_best = torch.minimum(t_best, t)
    hit = torch.isfinite(t_best)
    pts = origins + dirs * torch.where(hit, t_best, torch.zeros_like(t_best))[..., None]
    V, H, W = len(cameras), cameras.height, cameras.width
    col = texture(pts.reshape(-1, 3)).reshape(V, H * W, 3)
    col = torch.where(hit[..., None], col, torch.zeros_like(col))
    depth = torch.where(hit, t_best * cos.double(), torch.full_like(t_best, math.inf))
    images = col.permute(0, 2, 1).reshape(V, 3, H, W)
    return images, depth.reshape(V, H, W).float(), hit.reshape(V, 1, H, W).float()


def make_scene(cameras: Cameras, planes=(), spheres=(), depth_range=(2.5, 6.0),
               path: Path | str = "synthetic") -> tuple[Scene, torch.Tensor]:
    """A `Scene` of the ray-cast surfaces, and its (V, H, W) ground-truth z-depth."""
    images, depth, mask = raycast(cameras, planes, spheres)
    V = len(cameras)
    scene = Scene(
        images=images,
        cameras=cameras.to(dtype=torch.float32),
        view_ids=list(range(V)),
        masks=mask,
        pairs={},
        depth_range=torch.tensor([depth_range] * V, dtype=torch.float64),
        normalization=Normalization(torch.zeros(3, dtype=torch.float64), 1.0),
        path=Path(path),
        format="synthetic",
    )
    return scene, depth


def plane_scene(W=64, H=48, slanted=False, depth_range=(2.5, 6.0)):
    """A textured plane filling the views: fronto-parallel at z = 0.3 or slanted by ~30 degrees."""
    cams = make_cameras(W, H)
    if slanted:
        n = (math.sin(0.5), 0.0, -math.cos(0.5))
        plane = (n, -0.2)
    else:
        plane = ((0.0, 0.0, 1.0), 0.3)
    return make_scene(cams, planes=[plane], depth_range=depth_range)
