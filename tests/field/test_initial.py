"""field/initial.py: the SDF grid initialised from (exact) MVS depth puts its zero level on the
surface, is a signed distance (|grad| ~ 1), and ignores inconsistent depth."""

from __future__ import annotations

import numpy as np
import torch
from tests.mvs.synth import make_cameras, raycast

from svolsdf.field.grid import GridFieldConfig, GridSDFField
from svolsdf.field.initial import init_grid_from_mvs, signed_distance_from_signs
from svolsdf.mvs.volume import ProbabilityVolume
from svolsdf.scene.scene import Normalization

R = 0.8  # sphere radius at the origin (world = unit frame here: centre 0, scale 1)


# two cameras see the front of the sphere; the third, opposite them, alone sees its back
ONE_SIDED = [(0.0, 0.0, -4.0), (1.2, 0.2, -3.8), (0.3, -0.2, 4.0)]


def _volumes(noise_view: int | None = None, eyes=None):
    eyes = eyes or [(0.0, 0.0, -4.0), (1.2, 0.2, -3.8), (-1.1, -0.4, -3.8)]
    cams = make_cameras(48, 36, eyes=eyes)
    _, depth, _ = raycast(cams, spheres=[((0.0, 0.0, 0.0), R)])
    vols = []
    for i in range(len(cams)):
        d = torch.where(torch.isfinite(depth[i]), depth[i], torch.full_like(depth[i], 6.0)).float()
        if i == noise_view:  # a view whose depth is garbage: fails the consistency check
            d = d * (1 + 0.3 * torch.rand_like(d))
        vols.append(ProbabilityVolume(depths=torch.stack([d * 0.99, d * 1.01]),
                                      prob=torch.full((2, *d.shape), 0.5), depth=d,
                                      confidence=torch.ones_like(d), cameras=cams[[i]],
                                      view_id=i))
    return vols


def _field():
    return GridSDFField(torch.tensor([[-1.2] * 3, [1.2] * 3]), GridFieldConfig(resolution=48))


def test_zero_level_on_the_seen_surface_and_unit_gradient():
    torch.manual_seed(0)
    model = _field()
    norm = Normalization(torch.zeros(3, dtype=torch.float64), 1.0, 3.0)
    share = init_grid_from_mvs(model, _volumes(), norm)
    assert 0.0 < share < 1.0
    cell = float(model.cell_size.mean())
    # points of the sphere facing the cameras (z < 0 side): |sdf| within about a cell
    g = torch.randn(2000, 3)
    p = g / g.norm(dim=-1, keepdim=True) * R
    front = p[p[:, 2] < -0.3]
    with torch.no_grad():
        s = model.sdf(front).abs()
    assert s.median() < 0.75 * cell and s.max() < 2.5 * cell, (s.median(), cell)
    # a signed distance: |grad| ~ 1 away from the surface inside the seen region
    q = front * 1.25
    _, grad, _ = model.sdf_and_grad(q, create_graph=False)
    assert (grad.norm(dim=-1) - 1).abs().median() < 0.1
    with torch.no_grad():
        assert (model.sdf(front * 0.5) < 0).all() and (model.sdf(front * 1.3) > 0).all()


def test_inconsistent_view_does_not_carve_the_surface():
    torch.manual_seed(0)
    norm = Normalization(torch.zeros(3, dtype=torch.float64), 1.0, 3.0)
    model = _field()
    init_grid_from_mvs(model, _volumes(noise_view=2), norm)
    g = torch.randn(2000, 3)
    p = g / g.norm(dim=-1, keepdim=True) * R
    front = p[p[:, 2] < -0.5]
    with torch.no_grad():
        s = model.sdf(front).abs()
    assert s.median() < float(model.cell_size.mean())


def test_signed_distance_from_signs_known_values():
    inside = np.zeros((5, 5, 9), bool)
    inside[:, :, :4] = True  # a wall at x between nodes 3 and 4
    d = signed_distance_from_signs(inside, (1.0, 1.0, 1.0))
    np.testing.assert_allclose(d[2, 2], [-3.5, -2.5, -1.5, -0.5, 0.5, 1.5, 2.5, 3.5, 4.5])


def test_unverified_depth_places_a_surface_only_one_view_sees():
    """With init_unverified_weight = 0 the back of the sphere (seen by one view) starts at the hull
    the front views leave (inside up to the box); with a small weight, on the surface."""
    torch.manual_seed(0)
    norm = Normalization(torch.zeros(3, dtype=torch.float64), 1.0, 3.0)
    g = torch.randn(4000, 3)
    p = g / g.norm(dim=-1, keepdim=True) * R
    back = p[p[:, 2] > 0.5]
    masks = torch.ones(3, 1, 36, 48)
    res = {}
    for w, m in ((0.0, masks), (0.05, masks), (0.05, None)):
        model = _field()
        init_grid_from_mvs(model, _volumes(eyes=ONE_SIDED), norm, masks=m, init_unverified_weight=w)
        with torch.no_grad():
            res[w, m is None] = (model.sdf(back).abs().median(), model.sdf(back * 1.3).median())
    cell = float(model.cell_size.mean())
    assert res[0.0, False][0] > 3 * cell and res[0.0, False][1] < 0  # filled beyond the back
    assert res[0.05, False][0] < cell and res[0.05, False][1] > 0, res
    # without masks the unconfirmed depths do not vote (they would be mostly background)
    assert res[0.05, True] == res[0.0, False]
