"""The unit frame and per-view depth ranges for scenes whose files do not give them.

- `normalize_cameras`: VolSDF's ``normalize_cameras.py`` rule (docs/method.md 1.2): the centre is
  the least-squares point nearest all optical axes, s = 1.1 * (max camera distance to the centre) /
  3, so the cameras lie within radius 3 / 1.1 ~ 2.73 of the unit frame and the region of interest
  inside the sphere of radius 3.
- `normalization_from_points`: the same scale rule around a robust centre of sparse points.
- `sphere_depth_range`: z-depth range of the normalization sphere seen from each camera.
- `points_depth_range`: z-depth range of the sparse points seen by each camera.
"""

from __future__ import annotations

import logging

import torch
from torch import Tensor

from svolsdf.scene.cameras import Cameras
from svolsdf.scene.scene import Normalization

__all__ = [
    "axes_center",
    "normalization_from_points",
    "normalize_cameras",
    "points_depth_range",
    "sphere_depth_range",
]

log = logging.getLogger(__name__)


def axes_center(centers: Tensor, dirs: Tensor) -> Tensor:
    """The point nearest (in least squares) to all optical axes.

    Minimises sum_i ||(I - d_i d_i^T)(x - c_i)||^2, i.e. solves
    [sum_i (I - d_i d_i^T)] x = sum_i (I - d_i d_i^T) c_i (docs/method.md 1.2, VolSDF
    ``normalize_cameras.py``). When the axes are (nearly) parallel the system is singular; the
    minimum-norm least-squares solution relative to the mean camera centre is used and a warning
    is logged.

    Args:
        centers: (V, 3) camera centres.
        dirs: (V, 3) optical axes (normalised inside).

    Returns:
        (3,) float64 point.
    """
    if centers.ndim != 2 or centers.shape[-1] != 3 or dirs.shape != centers.shape:
        raise ValueError(f"axes_center expects (V, 3) centres and dirs, got "
                         f"{tuple(centers.shape)} and {tuple(dirs.shape)}")
    c = centers.double()
    d = dirs.double()
    d = d / d.norm(dim=-1, keepdim=True)
    eye = torch.eye(3, dtype=torch.float64)
    A = eye - d[:, :, None] * d[:, None, :]  # (V, 3, 3) projectors orthogonal to each axis
    lhs = A.sum(0)
    mean = c.mean(0)
    rhs = (A @ (c - mean)[..., None]).sum(0)[:, 0]
    evals = torch.linalg.eigvalsh(lhs)
    if evals[0] < 1e-6 * evals[-1]:
        log.warning("optical axes are nearly parallel; the scene centre is poorly determined")
    x = torch.linalg.lstsq(lhs, rhs[:, None], rcond=1e-6).solution[:, 0]
    return x + mean


def normalize_cameras(cameras: Cameras, radius: float = 3.0, margin: float = 1.1) -> Normalization:
    """VolSDF normalization from the cameras alone (docs/method.md 1.2).

    centre = `axes_center`, s = margin * max_i ||c_i - centre|| / radius, so every camera lies
    within radius / margin (2.73 for the defaults) of the unit frame's origin.

    Args:
        cameras: V cameras (world units).
        radius: radius of the region of interest in the unit frame (VolSDF: 3).
        margin: VolSDF's 1.1.

    Returns:
        `Normalization` with ``radius``.
    """
    center = axes_center(cameras.centers, cameras.view_dirs)
    return _scale_around(center, cameras, radius, margin)


def normalization_from_points(points: Tensor, cameras: Cameras, radius: float = 3.0,
                              margin: float = 1.1) -> Normalization:
    """Normalization centred on sparse points, with VolSDF's scale rule.

    The centre is the per-axis median of the points (robust to stray points, and defined for
    forward-facing captures where the optical axes do not meet); the scale follows docs/method.md
    1.2 (s = margin * max camera distance / radius), so the cameras lie within radius / margin.

    Args:
        points: (N, 3) sparse world points, N >= 1.
        cameras: V cameras.

    Returns:
        `Normalization` with ``radius``; the 99th-percentile point distance in unit-frame
        units is logged at debug level.
    """
    if points.ndim != 2 or points.shape[-1] != 3 or points.shape[0] == 0:
        raise ValueError(f"normalization_from_points expects (N>0, 3) points, got "
                         f"{tuple(points.shape)}")
    center = points.double().median(dim=0).values
    return _scale_around(center, cameras, radius, margin)


def _scale_around(center: Tensor, cameras: Cameras, radius: float, margin: float
                  ) -> Normalization:
    dist = (cameras.centers.double() - center).norm(dim=-1)
    scale = float(margin * dist.max() / radius)
    if not scale > 0:
        raise ValueError("cannot normalize: all cameras sit at the scene centre")
    return Normalization(center=center.double(), scale=scale, radius=float(radius))


def sphere_depth_range(cameras: Cameras, normalization: Normalization,
                       min_near: float = 0.01, radius: float = 1.0) -> Tensor:
    """z-depth range of the object sphere in each view.

    VolSDF's frame (docs/method.md 1.2) puts the cameras inside radius ~2.73 and the object inside
    the unit sphere; the radius-3 sphere bounds rays, not the object, and seen from a camera inside
    it spans z from ~0, which would waste most of the MVS planes. So the range is that of the
    sphere of unit-frame radius ``radius`` (default 1, the object sphere).

    z is linear along the optical axis, so the sphere of world radius r = radius * scale about
    the centre spans z in [z_c - r, z_c + r], z_c being the centre's z-depth. Cameras inside the
    sphere get near = ``min_near`` * z_c (at least ``min_near`` * r).

    Args:
        cameras: V cameras.
        normalization: the unit frame (centre, scale).
        min_near: smallest near plane as a fraction of the centre's depth.

    Returns:
        (V, 2) float64 [near, far] in world units.
    """
    r = radius * normalization.scale
    zc = cameras.world_to_camera(normalization.center.double()[None].to(cameras.w2c.dtype))
    zc = zc[:, 0, 2].double()
    floor = torch.clamp(min_near * zc, min=min_near * r)
    near = torch.maximum(zc - r, floor)
    far = torch.maximum(zc + r, near * 1.01)
    return torch.stack([near, far], dim=-1)


def points_depth_range(cameras: Cameras, points: Tensor, visibility: Tensor | None = None,
                       lo_q: float = 0.01, hi_q: float = 0.99, pad: float = 0.15,
                       near_scale: float = 0.8, min_points: int = 10) -> tuple[Tensor, Tensor]:
    """z-depth range of sparse points per view.

    The range is the [lo_q, hi_q] quantiles of the depths of the points the view sees, widened
    by ``pad`` times its span on each side, and near at most ``near_scale`` times the low
    quantile (kept >= half of it); this follows the percentile rule of MVSNet's
    ``colmap2mvsnet.py`` (near 0.75 x the 1 % quantile, far 1.25 x the 99 %) with a gentler
    far padding. The near side gets the wide margin because sparse points are sparse on what
    the camera sees at a grazing angle: on an object standing on a textured table (most points
    on the table) the 1 % quantile lay 5-10 % behind the object's nearest surface.

    Args:
        cameras: V cameras.
        points: (N, 3) world points.
        visibility: (N, V) bool, which views observe each point (COLMAP tracks); default: the
            points in front of the camera that project inside the image.
        min_points: views seeing fewer points get NaN (the caller falls back to the sphere).

    Returns:
        depth_range: (V, 2) float64 [near, far] (NaN where too few points).
        counts: (V,) number of points used per view.
    """
    uv, z = cameras.project(points.to(cameras.w2c.dtype))
    z = z.double()
    if visibility is None:
        inside = ((uv[..., 0] >= -0.5) & (uv[..., 0] <= cameras.width - 0.5)
                  & (uv[..., 1] >= -0.5) & (uv[..., 1] <= cameras.height - 0.5))
        vis = (inside & (z > 0)).T
    else:
        vis = visibility.bool() & (z > 0).T
    out = torch.full((len(cameras), 2), float("nan"), dtype=torch.float64)
    counts = vis.sum(0)
    for v in range(len(cameras)):
        if counts[v] < min_points:
            continue
        zs = z[v][vis[:, v]]
        q = torch.quantile(zs, torch.tensor([lo_q, hi_q], dtype=torch.float64))
        span = float(q[1] - q[0])
        near = max(min(float(q[0]) - pad * span, near_scale * float(q[0])), 0.5 * float(q[0]))
        far = float(q[1]) + pad * span
        out[v] = torch.tensor([near, max(far, near * 1.01)], dtype=torch.float64)
    return out, counts
