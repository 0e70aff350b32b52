"""Initialise the fast preset's SDF grid from the stage-1 MVS depth (not in the paper).

The paper starts VolSDF from a sphere (geometric init, docs/method.md 5.2) and needs tens of
thousands of steps to carve it. On a CPU the `fast` preset cannot afford that, and MVS already
knows roughly where the surface is. So, before the S-VolSDF losses run, the SDF grid is set to a
signed distance built from the stage-1 depth maps:

1. Each view's expected depth (docs/method.md 2.4) is kept where it is geometrically consistent with
   at least one other view (the fusion test of docs/method.md 6.3, at the stage-1 resolution) and,
   when the scene has them, inside the (dilated) object mask. With ``init_unverified_weight``
   w > 0 (the fast preset) and masks, the depths inside the mask that fail the test still vote,
   with w times their confidence (without masks they would be mostly background): a part
   of the object that only one view sees has no consistent depth, and without its own votes it
   starts at the hull the other views' free space leaves, in front of the true surface, where
   three views' losses cannot move it (benchmarks/results/history/fast_preset.md, notes of
   commit 9143dbd).
2. Truncated signed-distance fusion (Curless and Levoy 1996): every grid node projects into each
   view; s = d(u, v) - z is its signed distance along the ray to that view's surface (> 0 in
   front, i.e. outside). Views where the node lies more than ``trunc`` behind the surface do not
   vote (it may be hidden); the others vote clamp(s, -trunc, trunc) weighted by the MVS
   confidence. A node no view votes on is inside when some view saw it behind its surface,
   else outside.
3. Only the sign of the fused value is kept; the grid becomes the Euclidean signed distance to
   that sign change (scipy.ndimage.distance_transform_edt on both sides, at the grid spacing), so
   the initial field already meets the eikonal constraint |grad f| = 1 (docs/method.md 4.5).

The losses then refine this surface exactly as they would refine the sphere.
"""

from __future__ import annotations

import logging

import numpy as np
import torch
from torch import Tensor

from svolsdf.mvs.volume import ProbabilityVolume
from svolsdf.prior.depth_filter import consistent_depths
from svolsdf.scene.scene import Normalization

__all__ = ["tsdf_signs", "signed_distance_from_signs", "init_grid_from_mvs"]

log = logging.getLogger(__name__)


def tsdf_signs(nodes: Tensor, volumes: list[ProbabilityVolume], depths: list[Tensor],
               weights: list[Tensor], trunc: float) -> Tensor:
    """Fused truncated signed distance at world points (module docstring, step 2).

    Args:
        nodes: (N, 3) float64 world points.
        volumes: V volumes (their ``cameras`` match the depth maps' size).
        depths: V (H, W) world z-depths, 0 = no measurement.
        weights: V (H, W) vote weights.
        trunc: truncation distance, world units.

    Returns:
        (N,) float32 fused value in [-trunc, trunc] (> 0 outside).
    """
    N = nodes.shape[0]
    num = torch.zeros(N, dtype=torch.float64)
    den = torch.zeros(N, dtype=torch.float64)
    behind = torch.zeros(N, dtype=torch.bool)
    for v, d, w in zip(volumes, depths, weights, strict=True):
        cam = v.cameras.to(dtype=torch.float64)
        uv, z = cam.project(nodes[None])
        uv, z = uv[0], z[0]
        H, W = d.shape
        u = torch.round(uv[:, 0]).long()
        r = torch.round(uv[:, 1]).long()
        inside = (u >= 0) & (u < W) & (r >= 0) & (r < H) & (z > 0)
        idx = (r.clamp(0, H - 1) * W + u.clamp(0, W - 1))
        dd = d.reshape(-1).double()[idx]
        ww = w.reshape(-1).double()[idx]
        valid = inside & (dd > 0)
        s = dd - z
        vote = valid & (s >= -trunc)
        behind |= valid & (s < -trunc)
        num += torch.where(vote, ww * s.clamp(-trunc, trunc), torch.zeros_like(s))
        den += torch.where(vote, ww, torch.zeros_like(s))
    fused = torch.where(den > 0, num / den.clamp_min(1e-12),
                        torch.where(behind, torch.full_like(num, -trunc),
                                    torch.full_like(num, trunc)))
    return fused.float()


def signed_distance_from_signs(inside: np.ndarray, spacing: tuple[float, float, float]
                               ) -> np.ndarray:
    """Euclidean signed distance (> 0 outside) to the boundary of a boolean grid.

    Args:
        inside: (Z, Y, X) bool.
        spacing: (sz, sy, sx) node spacing.

    Returns:
        (Z, Y, X) float32; the zero level sits halfway between inside and outside nodes.
    """
    from scipy.ndimage import distance_transform_edt

    if inside.all() or not inside.any():
        raise ValueError("the MVS depth gives no surface inside the field's box")
    d_out = distance_transform_edt(~inside, sampling=spacing)  # outside nodes: distance to inside
    d_in = distance_transform_edt(inside, sampling=spacing)
    half = 0.5 * min(spacing)
    return np.where(inside, -(d_in - half), d_out - half).astype(np.float32)


@torch.no_grad()
def init_grid_from_mvs(model, volumes: list[ProbabilityVolume], normalization: Normalization,
                       masks: Tensor | None = None, trunc_cells: float = 4.0,
                       chunk: int = 1 << 18, init_unverified_weight: float = 0.0) -> float:
    """Set ``model.sdf_grid`` (a `GridSDFField`) from stage-1 MVS depth (module docstring).

    Args:
        model: `svolsdf.field.grid.GridSDFField`.
        volumes: stage-1 volumes of the input views.
        normalization: the scene's unit frame.
        masks: optional (V, 1, H, W) masks of the same views.
        trunc_cells: truncation in grid cells.
        chunk: nodes per projection batch.
        init_unverified_weight: vote weight (times the confidence) of the depths that fail the
            consistency test (module docstring, step 1); 0 = they do not vote.

    Returns:
        the share of nodes inside the initial surface.
    """
    depths, weights = consistent_depths(volumes, masks,
                                        unverified_weight=init_unverified_weight)
    cell = float(model.cell_size.mean())
    trunc = trunc_cells * cell * normalization.scale
    shape = model.grid_shape
    nodes = model._node_coords(shape).reshape(-1, 3).double()
    fused = torch.empty(nodes.shape[0])
    for s in range(0, nodes.shape[0], chunk):
        world = normalization.to_world(nodes[s:s + chunk].to(normalization.center.device))
        fused[s:s + chunk] = tsdf_signs(world.cpu(), volumes, depths, weights, trunc)
    inside = (fused < 0).reshape(shape).numpy()
    cs = model.cell_size.tolist()  # (x, y, z)
    sdf = signed_distance_from_signs(inside, (cs[2], cs[1], cs[0]))
    model.sdf_grid.data.copy_(torch.from_numpy(sdf)[None].to(model.sdf_grid))
    model.mvs_initialised = True  # the trainer refines it with TrainConfig.lr_sdf
    share = float(inside.mean())
    log.info("SDF grid initialised from stage-1 MVS depth (%.1f%% of nodes inside)", 100 * share)
    return share
