"""`select_views` (``--views auto``): a reference with sources on either side at useful
baselines, overlap required, clear errors."""

from __future__ import annotations

import math

import pytest
import torch

from svolsdf.scene.pairs import covisibility, select_views
from svolsdf.scene.scene import SceneError


def _ring(step_deg: float, n: int) -> torch.Tensor:
    """n camera centres on a circle around the origin, ``step_deg`` apart."""
    a = torch.arange(n, dtype=torch.float64) * math.radians(step_deg)
    return torch.stack([torch.cos(a), torch.sin(a), torch.zeros(n, dtype=torch.float64)], -1)


def _overlap(centers: torch.Tensor, reach_deg: float = 60.0) -> torch.Tensor:
    # views share points in proportion to how close they are (none beyond reach_deg)
    d = centers / centers.norm(dim=-1, keepdim=True)
    ang = torch.rad2deg(torch.arccos((d @ d.T).clamp(-1, 1)))
    return 1000.0 * (1 - ang / reach_deg).clamp_min(0)


def test_picks_a_reference_between_its_sources():
    c = _ring(5.0, 19)  # a 90 degree arc, a view every 5 degrees
    sel = select_views(_overlap(c), c, torch.zeros(3, dtype=torch.float64), 3)
    ref, a, b = sel
    ang = lambda i, j: abs(i - j) * 5.0  # noqa: E731
    assert 10 <= ang(ref, a) <= 35 and 10 <= ang(ref, b) <= 35
    assert (a - ref) * (b - ref) < 0  # on either side of the reference
    assert 4 <= ref <= 14  # not at an end of the arc


def test_needs_overlap_and_enough_views():
    c = _ring(5.0, 4)
    none = torch.zeros(4, 4, dtype=torch.float64)
    with pytest.raises(SceneError, match="no 3 views overlap"):
        select_views(none, c, torch.zeros(3, dtype=torch.float64), 3)
    with pytest.raises(SceneError, match="cannot pick 5 views from a scene of 4"):
        select_views(_overlap(c), c, torch.zeros(3, dtype=torch.float64), 5)


def test_covisibility_counts_shared_points():
    vis = torch.tensor([[1, 1, 0], [1, 1, 1], [0, 0, 1]], dtype=torch.bool)
    C = covisibility(vis)
    assert C[0, 1] == 2 and C[1, 2] == 1 and C[0, 2] == 1 and C[2, 2] == 2
