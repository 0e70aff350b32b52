"""Analytic test scenes for tests/fusion: look-at cameras and exact sphere depth maps."""

from __future__ import annotations

import math

import torch

from svolsdf.scene.cameras import Cameras

CENTER = torch.tensor([0.1, -0.05, 0.0], dtype=torch.float64)
RADIUS = 1.0


def look_at_camera(eye, target=(0.0, 0.0, 0.0), W=48, H=40, f=55.0) -> Cameras:
    """One OpenCV camera at ``eye`` looking at ``target`` (y down)."""
    eye = torch.tensor(eye, dtype=torch.float64)
    target = torch.tensor(target, dtype=torch.float64)
    z = target - eye
    z = z / z.norm()
    up = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    x = torch.linalg.cross(up, z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])  # rows: camera axes in world
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    K = torch.tensor([[f, 0, (W - 1) / 2 + 0.3], [0, f, (H - 1) / 2 - 0.2], [0, 0, 1]],
                     dtype=torch.float64)
    return Cameras(K[None], w2c[None], W, H)


def sphere_depth(cam: Cameras, center=CENTER, radius=RADIUS) -> torch.Tensor:
    """(H, W) exact z-depth of the sphere (0 where the ray misses)."""
    o, d, cos = cam.rays()
    o, d, cos = o[0], d[0], cos[0]
    oc = o - center
    b = (d * oc).sum(-1)
    c = (oc * oc).sum(-1) - radius**2
    disc = b * b - c
    t = -b - torch.sqrt(disc.clamp_min(0))
    z = torch.where(disc > 0, t * cos, torch.zeros_like(t))
    return z.reshape(cam.height, cam.width)


def three_cameras() -> dict[int, Cameras]:
    """Three cameras 4 units from the origin looking at it, about 20 degrees apart."""
    return {
        0: look_at_camera((0.0, 0.0, -4.0)),
        1: look_at_camera((4.0 * math.sin(0.35), 0.2, -4.0 * math.cos(0.35))),
        2: look_at_camera((-4.0 * math.sin(0.3), -0.3, -4.0 * math.cos(0.3))),
    }
