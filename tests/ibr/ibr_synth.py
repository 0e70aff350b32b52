"""Analytic test scenes for tests/ibr: a textured plane z = 0 (plus optional solid spheres) seen
by look-at cameras, ray-cast exactly (colour and z-depth)."""

from __future__ import annotations

import math

import torch

from svolsdf.scene.cameras import Cameras

RED = (1.0, 0.0, 0.0)


def look_at_camera(eye, target=(0.0, 0.0, 0.0), W=64, H=48, f=60.0, up=(0.0, -1.0, 0.0)):
    """One OpenCV camera at ``eye`` looking at ``target`` (world -y is the image's up)."""
    eye = torch.tensor(eye, dtype=torch.float64)
    target = torch.tensor(target, dtype=torch.float64)
    z = target - eye
    z = z / z.norm()
    upv = torch.tensor(up, dtype=torch.float64)
    x = torch.linalg.cross(-upv, z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    K = torch.tensor([[f, 0, (W - 1) / 2 + 0.3], [0, f, (H - 1) / 2 - 0.2], [0, 0, 1]],
                     dtype=torch.float64)
    return Cameras(K[None], w2c[None], W, H)


def stack_cameras(cams: list[Cameras]) -> Cameras:
    return Cameras(
        torch.cat([c.K for c in cams]), torch.cat([c.w2c for c in cams]),
        cams[0].width, cams[0].height,
    )


def texture(p: torch.Tensor) -> torch.Tensor:
    """(N, 3) world points on the plane -> (N, 3) smooth colours in [0.1, 0.9]."""
    x, y = p[:, 0], p[:, 1]
    r = 0.5 + 0.2 * torch.sin(7.0 * x + 2.0 * y) + 0.2 * torch.cos(5.0 * y - 1.0)
    g = 0.5 + 0.35 * torch.sin(4.0 * x - 6.0 * y + 0.5)
    b = 0.5 + 0.2 * torch.cos(6.5 * x) * torch.sin(5.5 * y + 0.3) + 0.15 * torch.sin(3 * x)
    return torch.stack([r, g, b], dim=-1)


def render(cam: Cameras, spheres=()) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact ray casting of the plane z = 0 and solid red spheres ((centre, radius) pairs).

    Returns:
        image (3, H, W) float32 and z-depth (H, W) float32 (0 where nothing is hit).
    """
    o, d, cos = cam.rays()
    o, d, cos = o[0], d[0], cos[0]
    t_plane = -o[:, 2] / d[:, 2]
    hit = torch.isfinite(t_plane) & (t_plane > 0)
    t = torch.where(hit, t_plane, torch.full_like(t_plane, math.inf))
    col = texture(o + t_plane[:, None] * d)
    for centre, radius in spheres:
        oc = o - torch.tensor(centre, dtype=o.dtype)
        b = (d * oc).sum(-1)
        c = (oc * oc).sum(-1) - radius**2
        disc = b * b - c
        ts = -b - torch.sqrt(disc.clamp_min(0))
        hs = (disc > 0) & (ts > 0) & (ts < t)
        t = torch.where(hs, ts, t)
        col = torch.where(hs[:, None], torch.tensor(RED, dtype=col.dtype), col)
    ok = torch.isfinite(t)
    depth = torch.where(ok, t * cos, torch.zeros_like(t))
    col = torch.where(ok[:, None], col, torch.zeros_like(col))
    H, W = cam.height, cam.width
    return (
        col.T.reshape(3, H, W).float(),
        depth.reshape(H, W).float(),
    )


def render_all(cams: Cameras, spheres=()) -> tuple[torch.Tensor, torch.Tensor]:
    """(V, 3, H, W) images and (V, H, W) depths."""
    out = [render(cams[i], spheres) for i in range(len(cams))]
    return torch.stack([o[0] for o in out]), torch.stack([o[1] for o in out])


def psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """PSNR in dB of (3, H, W) images in [0, 1], over the (H, W) mask."""
    err = (a - b) ** 2
    if mask is not None:
        err = err[:, mask]
    return float(-10 * torch.log10(err.mean()))
