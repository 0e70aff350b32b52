"""`svolsdf.field.fit`: the grid's zero level moves onto trusted points and stays an SDF."""

from __future__ import annotations

import torch

from svolsdf.field.fit import fit_sdf_to_points
from svolsdf.field.grid import GridFieldConfig, GridSDFField


def _sphere_points(n: int, r: float, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g)
    return r * d / d.norm(dim=-1, keepdim=True)


def test_zero_level_moves_onto_the_points_and_far_outliers_are_ignored():
    torch.manual_seed(0)
    field = GridSDFField(torch.tensor([[-1.0] * 3, [1.0] * 3]),
                         GridFieldConfig(resolution=32, init_radius=0.5))
    cell = float(field.cell_size.mean())  # ~0.043
    target = _sphere_points(20_000, 0.5 + 1.5 * cell)  # 1.5 cells outside the initial sphere
    outliers = _sphere_points(500, 0.9, seed=1)  # far junk, as fusion leaves some
    before = field.sdf(target, clamp=False).abs().median()
    res = fit_sdf_to_points(field, torch.cat([target, outliers]), fit_points=120, lr=3e-3,
                            batch=2048)
    after = field.sdf(target, clamp=False).abs()
    assert before > 1.4 * cell
    assert after.median() < 0.25 * cell and res["median_after"] < 0.5
    # the outliers pulled no spike out: the field there is still far from zero
    assert field.sdf(outliers, clamp=False).abs().median() > 0.25
    # still a signed distance near the surface (eikonal)
    q = _sphere_points(5000, 0.5 + 1.5 * cell, seed=2) * 1.05
    _, g, _ = field.sdf_and_grad(q, create_graph=False, clamp=False)
    assert (g.norm(dim=-1) - 1).abs().median() < 0.2
    # only the SDF grid changed, and no gradient is left behind
    assert all(p.grad is None for p in field.parameters())
