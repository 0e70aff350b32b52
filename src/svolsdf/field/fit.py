"""Fit the optimized surface to the fused points: the cascade's finer depth applied back to the
field (ours, not in the paper).

S-VolSDF's optimized surface guides MVS stages 2-3, whose depth is finer than the surface that
guided them (docs/method.md 6.1-6.3): the fused points are more accurate than the field's zero
level, so a mesh marched from the field is less accurate than ``points.ply``. This module closes the
loop in the other direction: the SDF grid is refined so that its zero level passes through the fused
points, while it stays a signed distance (eikonal, docs/method.md 4.5) and smooth where no point
constrains it (`GridSDFField.smoothness_loss`).

Per step, on ``batch`` fused points p and the same points jittered along the field's normal:

    L = mean_{p: |f(p)| < tau} |f(p)|                      (surface term, L1)
      + w_eik * mean (|grad f(q)| - 1)^2                   (eikonal, q = p + N(0, sigma) n)
      + w_smooth * smoothness

Points whose distance to the current zero level exceeds ``tau`` (``trunc_cells`` grid cells) are
left out: fusion keeps some outliers, and a far outlier would otherwise pull a spike out of the
surface. Only ``sdf_grid`` changes; the colour features stay, so vertex colours still come from the
field. Written by hand: it is a few lines on top of the grid's closed-form gradient
(`svolsdf.field.grid_ops.trilinear_with_grad`), which no library offers for this grid.
"""

from __future__ import annotations

import logging

import torch
from torch import Tensor

__all__ = ["fit_sdf_to_points"]

log = logging.getLogger(__name__)


def fit_sdf_to_points(model, points: Tensor, fit_points: int = 300, lr: float = 5e-4,
                      batch: int = 32768, trunc_cells: float = 3.0,
                      eikonal_weight: float = 0.1, smooth_weight: float = 0.0,
                      seed: int = 0) -> dict[str, float]:
    """Refine ``model.sdf_grid`` in place so that the zero level passes through ``points``.

    Args:
        model: a `svolsdf.field.grid.GridSDFField` (anything with ``sdf_grid``, ``cell_size``,
            ``sdf_and_grad(x, create_graph, clamp)`` and ``smoothness_loss()``).
        points: (N, 3) float unit-frame points (the fused points, ``Normalization.to_unit``).
        fit_points: Adam steps (``mesh.fit_points``).
        lr: learning rate of the SDF grid (per node, unit-frame units; keep it well below a
            cell, as `TrainConfig.lr_sdf`).
        batch: points per step.
        trunc_cells: points farther than this many cells from the current zero level are
            treated as outliers at that step.
        eikonal_weight: weight of the eikonal term near the points.
        smooth_weight: weight of the grid's Laplacian smoothness term.
        seed: random seed of the point draws.

    Returns:
        {"median_before", "median_after"}: median |f(p)| over the points in cells, and
        "inliers": the share of points within ``trunc_cells`` at the end.
    """
    if points.ndim != 2 or points.shape[-1] != 3:
        raise ValueError(f"points must be (N, 3), got {tuple(points.shape)}")
    grid = getattr(model, "sdf_grid", None)
    if grid is None:
        raise ValueError("fit_sdf_to_points needs a grid field (sdf_grid)")
    dev = grid.device
    pts = points.to(dev, torch.float32)
    cell = float(model.cell_size.mean())
    tau = trunc_cells * cell
    gen = torch.Generator(device=dev).manual_seed(seed)

    def median_dist() -> float:
        with torch.no_grad():
            sub = pts[torch.randperm(len(pts), generator=gen, device=dev)[:200_000]]
            return float(model.sdf(sub, clamp=False).abs().median()) / cell

    before = median_dist()
    if len(pts) == 0 or fit_points <= 0:
        return {"median_before": before, "median_after": before, "inliers": 0.0}
    requires = {id(p): p.requires_grad for p in model.parameters()}
    for p in model.parameters():
        p.requires_grad_(p is grid)
    opt = torch.optim.Adam([grid], lr=lr)
    try:
        for _ in range(fit_points):
            idx = torch.randint(len(pts), (min(batch, len(pts)),), generator=gen, device=dev)
            p = pts[idx]
            s, g, _ = model.sdf_and_grad(p, create_graph=True, clamp=False)
            inl = s.detach().abs() < tau
            surf = (s.abs() * inl).sum() / inl.sum().clamp_min(1)
            n = g.detach() / g.detach().norm(dim=-1, keepdim=True).clamp_min(1e-6)
            q = p + n * torch.randn(len(p), 1, generator=gen, device=dev) * tau
            _, gq, _ = model.sdf_and_grad(q, create_graph=True, clamp=False)
            eik = ((gq.norm(dim=-1) - 1) ** 2).mean()
            loss = surf + eikonal_weight * eik
            if smooth_weight > 0:
                loss = loss + smooth_weight * model.smoothness_loss()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
    finally:
        for p in model.parameters():
            p.requires_grad_(requires[id(p)])
        grid.grad = None
    with torch.no_grad():
        sub = pts[torch.randperm(len(pts), generator=gen, device=dev)[:200_000]]
        d = model.sdf(sub, clamp=False).abs()
    after = float(d.median()) / cell
    inliers = float((d < tau).float().mean())
    log.info("surface fitted to %d fused points in %d steps: median distance %.2f -> %.2f "
             "cells, %.0f%% within %.0f cells", len(pts), fit_points, before, after, 100 * inliers,
             trunc_cells)
    return {"median_before": before, "median_after": after, "inliers": inliers}
