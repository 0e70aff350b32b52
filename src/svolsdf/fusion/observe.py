"""What the input views observed, for meshing: each view's final depth where fused points
confirm it, the mesh culling that follows from it (free space, support by the points), and the
final-stage depth step that sets its tolerances.

The standard visibility argument of MVS meshing (the free-space constraint behind
depth-map fusion, e.g. Curless and Levoy 1996, Merrell et al. 2007): a view that observed a
surface at depth d along a pixel's ray saw empty space in front of it, so a mesh face lying
clearly in front of d along that ray is not there. Only depths that the fused points confirm
count as observed (a pixel whose depth survived the multi-view filter, docs/method.md 6.3), so an
outlier of one depth map carves nothing.

Depth maps are (H, W) float z-depth in world units, 0 where there is none; points are (N, 3)
float world points; meshes are (vertices (V, 3) float32, faces (F, 3) int64) torch tensors, as
in `svolsdf.fusion.mesh`.
"""

from __future__ import annotations

import logging

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree
from torch import Tensor

from svolsdf.fusion.mesh_ops import _check_mesh, _in_image, submesh
from svolsdf.mvs.hypotheses import base_interval, interval_ratio
from svolsdf.scene.cameras import Cameras

__all__ = [
    "cull_free_space",
    "final_depth_step",
    "observed_depths",
    "point_spacing",
    "trim_by_support",
]

log = logging.getLogger(__name__)


def final_depth_step(depth_range: Tensor, width: str = "paper", stage: int = 3) -> Tensor:
    """(V,) depth step of the cascade's final stage per view: r Δ̄, Δ̄ = (d_max - d_min) / 192
    (docs/method.md 2.5; DTU: 0.5 x 2.64 = 1.32 mm).

    Args:
        depth_range: (V, 2) [near, far] z-depth per view, world units (`Scene.depth_range`).
        width: the cascade's width option (`svolsdf.mvs.hypotheses.WIDTHS`).
    """
    dr = torch.as_tensor(depth_range, dtype=torch.float64).reshape(-1, 2)
    return interval_ratio(stage, width) * base_interval(dr[:, 0], dr[:, 1])


def observed_depths(points: Tensor, cameras: Cameras, depth_sets: list[list[Tensor]],
                    rel_tol: float = 0.005) -> list[Tensor]:
    """Each view's depth where a fused point confirms it.

    A pixel of a view's depth map is observed when some fused point projects into it with a
    z-depth within ``rel_tol`` of the map's depth there. Where a view has several depth sets
    (the guided and the unguided stages), the first set that is confirmed at a pixel gives its
    depth.

    Args:
        points: (N, 3) fused world points.
        cameras: world `Cameras` of the V views (any size: resized to each map).
        depth_sets: for each of the V views, a list of (H, W) z-depth maps (0 = none).
        rel_tol: relative depth agreement of a point and the map.

    Returns:
        V (H, W) float32 maps: the observed z-depth, 0 where nothing was observed.
    """
    pts = torch.as_tensor(points, dtype=torch.float64).reshape(-1, 3)
    if len(depth_sets) != len(cameras):
        raise ValueError(f"depth_sets: {len(depth_sets)} views for {len(cameras)} cameras")
    out = []
    for k, maps in enumerate(depth_sets):
        h, w = maps[0].shape
        cam = cameras[[k]].resize(w, h).to(dtype=torch.float64)
        uv, z = cam.project(pts)
        uv, z = uv[0], z[0]
        ok = _in_image(uv, z, w, h) & (z > 0)
        px = uv[ok].round().long()
        px[:, 0].clamp_(0, w - 1)
        px[:, 1].clamp_(0, h - 1)
        idx, zk = px[:, 1] * w + px[:, 0], z[ok]
        obs = torch.zeros(h * w, dtype=torch.float64)
        for d in maps:
            if tuple(d.shape) != (h, w):
                d = F.interpolate(d[None, None].double(), size=(h, w), mode="nearest")[0, 0]
            dv = d.double().reshape(-1)
            di = dv[idx]
            agree = (di > 0) & ((zk - di).abs() <= rel_tol * di)
            hit = torch.zeros(h * w, dtype=torch.bool)
            hit[idx[agree]] = True
            obs = torch.where((obs == 0) & hit, dv, obs)
        out.append(obs.reshape(h, w).float())
    return out


def _window_min(depth: Tensor, radius: int) -> Tensor:
    """(H, W) least observed depth within ``radius`` pixels (inf where none is observed)."""
    d = torch.where(depth > 0, depth.double(), torch.tensor(float("inf"), dtype=torch.float64))
    if radius <= 0:
        return d
    return -F.max_pool2d(-d[None, None], 2 * radius + 1, stride=1, padding=radius)[0, 0]


def cull_free_space(vertices: Tensor, faces: Tensor, cameras: Cameras, observed: list[Tensor],
                    tol: Tensor | float, radius: int = 2) -> tuple[Tensor, Tensor, Tensor]:
    """Remove faces that lie in space an input view saw as empty.

    A face goes when, in at least one view whose image contains its centroid, the centroid's
    z-depth is smaller than the least observed depth within ``radius`` pixels of its projection
    by more than ``tol``. The window keeps a face at a depth edge: it is compared with the
    nearest surface around it, so only faces clearly in front of everything the view saw
    there go. Faces behind the observed surface (occluded in that view) are never removed.

    Args:
        vertices: (V, 3) world points; faces: (F, 3).
        cameras: world `Cameras` of the N views.
        observed: N (H, W) observed z-depth maps (`observed_depths`; 0 = not observed).
        tol: depth tolerance in world units, a float or an (N,) tensor per view.
        radius: window radius in pixels of the observed maps.

    Returns:
        vertices (V', 3), faces (F', 3), vertex_index (V',) as `submesh`.
    """
    vertices, faces = _check_mesh(vertices, faces)
    tols = torch.as_tensor(tol, dtype=torch.float64).expand(len(cameras))
    c = vertices.double()[faces].mean(dim=1)
    remove = torch.zeros(len(faces), dtype=torch.bool)
    for k, obs in enumerate(observed):
        h, w = obs.shape
        cam = cameras[[k]].resize(w, h).to(dtype=torch.float64)
        uv, z = cam.project(c)
        uv, z = uv[0], z[0]
        inside = _in_image(uv, z, w, h) & (z > 0)
        px = uv.round().long()
        px[:, 0].clamp_(0, w - 1)
        px[:, 1].clamp_(0, h - 1)
        near = _window_min(obs, radius)[px[:, 1], px[:, 0]]
        remove |= inside & torch.isfinite(near) & (z < near - tols[k])
    log.info("free-space culling removes %d of %d faces", int(remove.sum()), len(faces))
    return submesh(vertices, faces, ~remove)


def point_spacing(points: np.ndarray, sample: int = 200_000, seed: int = 0) -> float:
    """Median distance from a fused point to its nearest neighbour (world units), from at most
    ``sample`` points of (N, 3) ``points``."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 2:
        raise ValueError(f"points: {len(pts)} point(s), need at least 2 for a spacing")
    tree = cKDTree(pts)
    q = pts if len(pts) <= sample else pts[
        np.random.default_rng(seed).choice(len(pts), sample, replace=False)]
    d, _ = tree.query(q, k=2)
    return float(np.median(d[:, 1]))


def trim_by_support(vertices: Tensor, faces: Tensor, points: np.ndarray, k: float,
                    spacing: float | None = None, workers: int = 1
                    ) -> tuple[Tensor, Tensor, Tensor]:
    """Remove faces farther than ``k`` point spacings from every fused point: surface that no
    point supports (a mesher's extrapolation over holes and past silhouettes).

    A face goes when its centroid and all three vertices are beyond the distance, so that
    a large face over a well-supported region stays.

    Args:
        vertices: (V, 3) world points; faces: (F, 3).
        points: (N, 3) fused world points.
        k: the distance in point spacings (> 0).
        spacing: the points' spacing (`point_spacing` when None).
        workers: threads of the neighbour queries.

    Returns:
        vertices (V', 3), faces (F', 3), vertex_index (V',) as `submesh`.
    """
    vertices, faces = _check_mesh(vertices, faces)
    if k <= 0:
        raise ValueError(f"k must be > 0, got {k}")
    pts = np.asarray(points, dtype=np.float64)
    s = point_spacing(pts) if spacing is None else float(spacing)
    r = k * s
    tree = cKDTree(pts)
    v = vertices.double().numpy()
    dv, _ = tree.query(v, distance_upper_bound=r, workers=workers)
    c = v[faces.numpy()].mean(axis=1)
    dc, _ = tree.query(c, distance_upper_bound=r, workers=workers)
    near_v = torch.from_numpy(np.isfinite(dv))
    keep = torch.from_numpy(np.isfinite(dc)) | near_v[faces].any(dim=1)
    log.info("support trimming (%.2f x %.4g spacing) keeps %d of %d faces", k, s,
             int(keep.sum()), len(faces))
    return submesh(vertices, faces, keep)
