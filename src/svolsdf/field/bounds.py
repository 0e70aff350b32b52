"""The field's box: where the object is, in the unit frame, before the field is fitted."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from svolsdf.mvs.volume import ProbabilityVolume
from svolsdf.scene.scene import Scene

__all__ = ["field_bounds", "frusta_box"]


def field_bounds(scene: Scene, volumes: list[ProbabilityVolume] | None = None) -> torch.Tensor:
    """(2, 3) unit-frame box of the object: from stage-1 MVS depth where available (masked,
    percentiles, padded), else the intersection of the views' frusta and depth ranges.

    Args:
        scene: the input views (cameras, masks (V, 1, H, W) or None, normalization).
        volumes: the stage-1 volumes of the input views with their regressed depth (H', W')
            (`svolsdf.mvs.backbone.with_expected_depth`), or None (the frusta alone).
    """
    norm = scene.normalization
    pts = []
    for vol in volumes or []:
        cam = vol.cameras
        H, W = vol.depth.shape
        uv = cam.pixel_grid(dtype=torch.float64).reshape(1, -1, 2)
        conf = vol.confidence.reshape(-1)
        keep = conf >= torch.quantile(conf.float(), 0.5)
        if scene.masks is not None:
            i = scene.index(vol.view_id)
            m = F.interpolate(scene.masks[i:i + 1], size=(H, W), mode="bilinear")
            keep &= m.reshape(-1) > 0.5
        X = cam.to(dtype=torch.float64).unproject(uv, vol.depth.double().reshape(1, -1))[0]
        pts.append(norm.to_unit(X[keep]))
    if pts and sum(len(p) for p in pts) > 100:
        P = torch.cat(pts).float()
        lo = torch.quantile(P[torch.randperm(len(P))[:200000]], 0.01, dim=0)
        hi = torch.quantile(P[torch.randperm(len(P))[:200000]], 0.99, dim=0)
    else:
        lo, hi = frusta_box(scene)
    pad = 0.15 * (hi - lo).max()
    lo, hi = (lo - pad).clamp(-2.5, 2.5), (hi + pad).clamp(-2.5, 2.5)
    return torch.stack([lo, hi]).float()


def frusta_box(scene: Scene) -> tuple[torch.Tensor, torch.Tensor]:
    """(3,), (3,) unit-frame corners of the box of the points (on a 64^3 grid in [-2, 2]^3)
    that every input view sees within its depth range; [-1, 1]^3 when fewer than 8 do."""
    cams = scene.cameras_unit
    n = 64
    g = torch.linspace(-2.0, 2.0, n, dtype=torch.float64)
    X = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    uv, z = cams.project(X)
    nf = scene.depth_range / scene.normalization.scale
    ok = (z > nf[:, None, 0]) & (z < nf[:, None, 1]) & (uv[..., 0] >= 0) \
        & (uv[..., 0] <= cams.width - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= cams.height - 1)
    inside = ok.all(0)
    if inside.sum() < 8:
        return torch.full((3,), -1.0), torch.full((3,), 1.0)
    P = X[inside].float()
    return P.min(0).values, P.max(0).values
