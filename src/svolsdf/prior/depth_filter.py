"""The stage-1 MVS depth, filtered by the geometric-consistency test of fusion (docs/method.md
6.3) at the stage-1 resolution: the start of the grid field (`svolsdf.field.initial`) and the
depth the "mse" and "no-prob-volume" ablations fit the field to, in place of the probability
volume (docs/method.md 0)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from svolsdf.mvs.volume import ProbabilityVolume

__all__ = ["consistent_depths", "filtered_depth_maps"]


def consistent_depths(volumes: list[ProbabilityVolume], masks: Tensor | None = None,
                      min_views: int = 1, unverified_weight: float = 0.0
                      ) -> tuple[list[Tensor], list[Tensor]]:
    """Stage-1 depths with the inconsistent pixels removed or down-weighted.

    Args:
        volumes: V stage-1 `ProbabilityVolume` (depth (H, W) world z-depth, confidence, cameras).
        masks: optional (V, 1, Hm, Wm) object masks in [0, 1] of the same views.
        min_views: consistent source views a pixel needs (docs/method.md 6.3).
        unverified_weight: 0 removes the pixels that fail the test; w > 0 keeps those inside
            the (dilated) mask with weight w * confidence. Needs ``masks``: without them the
            unconfirmed depths are mostly background, which would vote for surfaces in empty
            space, so they are removed as with 0.

    Returns:
        depths: V tensors (H, W), 0 where rejected; weights: V tensors (H, W) confidence.
    """
    from svolsdf.geometry import check_geometric_consistency, dilate_mask

    depths, weights = [], []
    for i, v in enumerate(volumes):
        cnt = torch.zeros_like(v.depth, dtype=torch.long)
        for j, u in enumerate(volumes):
            if i != j:
                ok = check_geometric_consistency(v.depth, v.cameras, u.depth, u.cameras)[0]
                cnt += ok.long()
        keep = cnt >= min_views
        inside = torch.ones_like(keep)
        if masks is not None:
            m = F.interpolate(masks[i:i + 1].float(), size=v.depth.shape, mode="bilinear",
                              align_corners=False)[0, 0] > 0.5
            inside = dilate_mask(m, 2)
        keep &= inside
        w = torch.where(keep, v.confidence.clamp_min(1e-3), torch.zeros_like(v.depth))
        if unverified_weight > 0 and masks is not None:
            extra = inside & ~keep & torch.isfinite(v.depth) & (v.depth > 0)
            w = torch.where(extra, unverified_weight * v.confidence.clamp_min(1e-3), w)
            keep |= extra
        depths.append(torch.where(keep, v.depth, torch.zeros_like(v.depth)))
        weights.append(w)
    return depths, weights


def filtered_depth_maps(volumes: list[ProbabilityVolume], height: int, width: int) -> Tensor:
    """(V, H, W) stage-1 depth (world z-depth) of ``volumes`` where at least one other view
    confirms it (`consistent_depths`), 0 where rejected, resized (nearest) to ``height`` x
    ``width``: the ablations' depth target (docs/method.md 0)."""
    depths, _ = consistent_depths(volumes)  # >= 1 consistent source (docs/method.md 6.3)
    return torch.stack([F.interpolate(d[None, None], size=(height, width),
                                      mode="nearest")[0, 0] for d in depths])
