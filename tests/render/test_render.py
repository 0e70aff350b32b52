"""Rays, samplers and volume rendering on an analytic sphere (docs/method.md 5.4)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tests.field.analytic import SphereSDF

from svolsdf.render.rays import rays_from_cameras, sphere_intersections
from svolsdf.render.samplers import (
    ErrorBoundSamplerConfig,
    UniformRaySampler,
    error_bound_sample,
    interval_min_distance,
    opacity_error_bound,
    sample_pdf,
    uniform_sampler,
)
from svolsdf.render.volume import render_image, render_rays
from svolsdf.scene.cameras import Cameras


def _camera(W=16, H=12, f=20.0, dist=2.5):
    """One camera on the -z axis looking at the origin (OpenCV axes)."""
    K = torch.tensor([[f, 0.0, (W - 1) / 2], [0.0, f, (H - 1) / 2], [0.0, 0.0, 1.0]])[None]
    w2c = torch.eye(4)[None]
    w2c[0, 2, 3] = dist
    return Cameras(K, w2c, W, H)


def _true_hit(rays, r=1.0):
    """Distance to the first intersection with the sphere |x| = r, NaN on a miss."""
    od = (rays.origins * rays.dirs).sum(-1)
    disc = od**2 - (rays.origins**2).sum(-1) + r**2
    t = -od - disc.clamp_min(0).sqrt()
    return torch.where(disc > 0, t, torch.full_like(t, float("nan")))


def test_rays_unit_dirs_cos_and_far():
    cams = _camera()
    rays = rays_from_cameras(cams, 0)
    assert len(rays) == 16 * 12
    assert torch.allclose(rays.dirs.norm(dim=-1), torch.ones(len(rays)), atol=1e-6)
    centre = rays[5 * 16 + 7:5 * 16 + 8]  # a pixel near the principal point
    assert centre.cos.item() == pytest.approx(1.0, abs=0.01)
    # far on the sphere R = 3, and the fixed mode gives 2R
    p_far = rays.origins + rays.far[:, None] * rays.dirs
    assert torch.allclose(p_far.norm(dim=-1), torch.full((len(rays),), 3.0), atol=1e-4)
    rays2 = rays_from_cameras(cams, 0, far_mode="fixed")
    assert torch.allclose(rays2.far, torch.full_like(rays2.far, 6.0))
    assert torch.allclose(rays.near, torch.full_like(rays.near, 1e-4))
    # z-depth of a world point along the ray = cos * distance
    x = rays.origins + 1.7 * rays.dirs
    zc = cams.world_to_camera(x)[0, :, 2]
    assert torch.allclose(zc, 1.7 * rays.cos, atol=1e-5)
    t_in, t_out = sphere_intersections(rays.origins, rays.dirs, 3.0)
    assert (t_in < 0).all() and torch.allclose(t_out, rays.far)


def test_uniform_and_sample_pdf():
    near, far = torch.tensor([0.0, 1.0]), torch.tensor([1.0, 3.0])
    z = uniform_sampler(near, far, 5)
    assert torch.allclose(z[1], torch.tensor([1.0, 1.5, 2.0, 2.5, 3.0]))
    zs = uniform_sampler(near, far, 5, stratified=True)
    assert (zs[:, 1:] >= zs[:, :-1]).all() and (zs[:, 0] >= near).all() and (zs[:, -1] <= far).all()
    mids = 0.5 * (z[:, 1:] + z[:, :-1])
    assert ((zs[:, 1:-1] >= mids[:, :-1]) & (zs[:, 1:-1] <= mids[:, 1:])).all()
    # all mass in interval 2 of [0,1,2,3,4]: deterministic samples cover [2, 3] evenly
    bins = torch.tensor([[0.0, 1.0, 2.0, 3.0, 4.0]])
    s = sample_pdf(bins, torch.tensor([[0.0, 0.0, 1.0, 0.0]]), 5, det=True)
    assert torch.allclose(s[:, :4], torch.tensor([[2.0, 2.25, 2.5, 2.75]]), atol=1e-6)
    assert 3.0 <= s[0, 4] <= 4.0  # u = 1 lands past a flat CDF tail (searchsorted right=True)
    # zero weights: uniform fallback, no NaN
    s0 = sample_pdf(bins, torch.zeros(1, 4), 5, det=True)
    assert torch.allclose(s0, torch.linspace(0, 4, 5)[None], atol=1e-6)


def test_interval_min_distance_cases():
    z = torch.tensor([[0.0, 1.0], [0.0, 1.0], [0.0, 1.0], [0.0, 4.0], [0.0, 1.0]])
    sdf = torch.tensor([[0.5, 2.0], [3.0, 0.5], [1.0, 1.0], [1.0, 1.0], [1.0, -1.0]])
    d = interval_min_distance(z, sdf)[:, 0]
    # case 1: a^2 + b^2 <= c^2 -> b; case 2 -> c; case 3: Heron, isosceles 1,1,1 -> height
    assert d[0] == pytest.approx(0.5)
    assert d[1] == pytest.approx(0.5)
    assert d[2] == pytest.approx(np.sqrt(3) / 2, abs=1e-6)
    assert d[3] == pytest.approx(0.0)  # b + c <= a
    assert d[4] == pytest.approx(0.0)  # sign change


def _dense_opacity_error(model, rays, z, sdf, beta, n=32001):
    """max_i |O(z_i) - O_hat(z_i)| with O from a dense trapezoid integral (float64).

    The density has a kink at the surface; with beta = 0.005 a step of 0.15 beta (n=8001) leaves
    ~5e-4 trapezoid error, so the reference uses a step below 0.04 beta."""
    t = torch.linspace(0, 1, n, dtype=torch.float64)
    zd = rays.near.double()[:, None] + (rays.far - rays.near).double()[:, None] * t
    pts = rays.origins.double()[:, None] + zd[..., None] * rays.dirs.double()[:, None]
    s = (pts.norm(dim=-1) - model.r)
    sig = model.density(s, beta=beta.double()[:, None])
    cum = torch.cat([torch.zeros_like(zd[:, :1]),
                     torch.cumsum(0.5 * (sig[:, 1:] + sig[:, :-1]) * zd.diff(dim=-1), -1)], -1)
    true_int = torch.stack([torch.from_numpy(np.interp(z[r].double().numpy(), zd[r].numpy(),
                                                       cum[r].numpy())) for r in range(len(z))])
    sg = model.density(sdf.double(), beta=beta.double()[:, None])
    approx = torch.cat([torch.zeros_like(true_int[:, :1]),
                        torch.cumsum(z.double().diff(dim=-1) * sg[:, :-1], -1)], -1)
    return (torch.exp(-approx) - torch.exp(-true_int)).abs().max(-1).values


@pytest.mark.parametrize("beta", [0.05, 0.005])
def test_error_bound_sampler_bound_property(beta):
    """After the sampler, the true opacity error with the chosen beta is <= eps (VolSDF Thm 1);
    for converged rays that beta is the model's."""
    cams = _camera(W=8, H=7, f=8.0)
    rays = rays_from_cameras(cams, 0, far_mode="fixed")
    model = SphereSDF(1.0, beta=beta).eval()
    cfg = ErrorBoundSamplerConfig()
    out = error_bound_sample(model, rays, cfg)
    assert out.z.shape == (len(rays), 98)
    assert (out.z.diff(dim=-1) >= 0).all()
    assert out.eik_index.shape == (len(rays),) and out.eik_index.max() < 98
    E, _ = opacity_error_bound(model, out.sdf_eval, out.z_eval,
                               interval_min_distance(out.z_eval, out.sdf_eval), out.beta[:, None])
    assert (E <= cfg.eps + 1e-6).all()
    err = _dense_opacity_error(model, rays, out.z_eval, out.sdf_eval, out.beta)
    assert (err <= E.double() + 1e-4).all()
    assert (err <= cfg.eps).all()
    converged = out.beta <= out.beta0
    assert converged.float().mean() > 0.5
    # with beta the model's own, the converged rays meet the bound
    err0 = _dense_opacity_error(model, rays[converged], out.z_eval[converged],
                                out.sdf_eval[converged], out.beta0.expand(int(converged.sum())))
    assert (err0 <= cfg.eps).all()


def test_error_bound_sampler_training_single_iteration():
    cams = _camera(W=6, H=5, f=6.0)
    rays = rays_from_cameras(cams, 0)
    model = SphereSDF(1.0, beta=0.01).train()
    out = error_bound_sample(model, rays)
    assert out.iters == 1 and out.z_eval.shape[1] == 128 and out.z.shape[1] == 98
    assert torch.allclose(out.z[:, 0], rays.near) and torch.allclose(out.z[:, -1], rays.far)


def test_render_sphere_depth_and_opacity():
    cams = _camera(W=16, H=12, f=10.0)
    rays = rays_from_cameras(cams, 0)
    model = SphereSDF(1.0, beta=0.002).eval()
    s = error_bound_sample(model, rays)
    out = render_rays(model, rays, s.z)
    hit = _true_hit(rays)
    is_hit = ~torch.isnan(hit)
    # rays grazing the silhouette are ambiguous; keep clear hits and clear misses
    od = (rays.origins * rays.dirs).sum(-1)
    miss_dist = ((rays.origins**2).sum(-1) - od**2).sqrt()  # distance of the ray to the centre
    clear_hit, clear_miss = miss_dist < 0.9, miss_dist > 1.1
    assert clear_hit.sum() > 10 and clear_miss.sum() > 10
    assert torch.allclose(out.opacity[clear_hit], torch.ones(int(clear_hit.sum())), atol=1e-3)
    assert (out.opacity[clear_miss] < 1e-3).all()
    true_depth = hit[clear_hit] * rays.cos[clear_hit]
    assert (out.depth[clear_hit] - true_depth).abs().max() < 0.02
    assert torch.allclose(out.rgb[clear_hit], model.rgb.expand(int(clear_hit.sum()), 3), atol=1e-3)
    # normals point outward at the hit point
    n_true = (rays.origins + hit[:, None] * rays.dirs)[clear_hit]
    assert ((out.normals[clear_hit] * n_true).sum(-1) > 0.99).all()
    assert is_hit[clear_hit].all()
    assert out.weights.shape == out.sdf.shape == out.z.shape == (len(rays), 98)
    assert out.points.shape == (len(rays), 98, 3) and out.grad.shape == (len(rays), 98, 3)


def test_render_image_chunked_equals_unchunked():
    cams = _camera(W=7, H=5, f=5.0)
    model = SphereSDF(1.0, beta=0.01)
    sampler = UniformRaySampler(64)
    a = render_image(model, cams, 0, chunk=4, sampler=sampler)
    b = render_image(model, cams, 0, chunk=1000, sampler=sampler)
    for k in ("rgb", "depth", "opacity", "normals"):
        assert a[k].shape[:2] == (5, 7)
        assert torch.allclose(a[k], b[k], atol=1e-6), k
    # the error-bound sampler converges per chunk; results agree to the sampling accuracy
    c = render_image(model, cams, 0, chunk=18)
    d = render_image(model, cams, 0, chunk=1000)
    m = d["opacity"] > 0.99
    assert (c["depth"][m] - d["depth"][m]).abs().max() < 1e-2
    assert model.training  # restored


def test_max_rule_filled_finds_the_low_weight_pixels():
    """`max_rule_filled` recovers the pixels `guide_depths`' "max" rule filled (weight < 0.2),
    with the covered pixels at exactly the maximum; VolSDF's fusion drops them (issue 38)."""
    from svolsdf.render.views import guide_depths, max_rule_filled

    g = torch.Generator().manual_seed(0)
    depth = 1.0 + torch.rand(1, 12, 16, generator=g)
    opacity = torch.rand(1, 12, 16, generator=g)
    guide = guide_depths(depth, opacity, [3], 2.0, "max")[3]
    low = opacity[0] < 0.2
    at_max = (~low) & (depth[0] == depth[0][~low].max())
    assert low.any() and torch.equal(max_rule_filled(guide), low | at_max)
    assert max_rule_filled(torch.zeros(4, 5)).all()  # nothing covered: all fill
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        max_rule_filled(guide[None])


def _grid_sphere_field():
    """A grid field holding the SDF of a sphere of radius 0.5, random colour features and
    colour network (seeded)."""
    from svolsdf.field.grid import GridFieldConfig, GridSDFField

    torch.manual_seed(3)
    model = GridSDFField(torch.tensor([[-1.0] * 3, [1.0] * 3]), GridFieldConfig(resolution=32))
    Z, Y, X = model.grid_shape
    lo, hi = model.bounds
    axes = [torch.linspace(float(lo[i]), float(hi[i]), n)
            for i, n in zip((2, 1, 0), (Z, Y, X), strict=True)]
    zz, yy, xx = torch.meshgrid(*axes, indexing="ij")
    with torch.no_grad():
        model.sdf_grid.copy_((torch.stack([xx, yy, zz], -1).norm(dim=-1) - 0.5)[None])
        for fg in model.feature_grids:
            fg.normal_(0.0, 0.5)
    model.beta_min = 1e-4
    return model.train()


def test_training_colour_only_where_it_counts_matches_every_sample():
    """render_rays with create_graph and colour_min_weight: the colour network sees only the
    samples whose weight exceeds the threshold; the colour, depth and the gradients of the SDF
    grid, the feature grids and the colour network stay those of every sample within the
    bound (the dropped colour terms sum to < S x threshold per ray)."""
    cams = _camera(W=12, H=9, f=9.0)
    rays = rays_from_cameras(cams, 0)
    model = _grid_sphere_field()
    z = uniform_sampler(rays.near, rays.far, 96, stratified=False)
    calls = []
    colour = model.colour
    model.colour = lambda x, *a: (calls.append(len(x)), colour(x, *a))[1]
    outs, grads = [], []
    for tau in (0.0, 1e-4):
        model.zero_grad()
        calls.clear()
        out = render_rays(model, rays, z, create_graph=True, colour_min_weight=tau)
        (out.rgb.sum() + out.depth.sum()).backward()
        outs.append((out, list(calls)))
        grads.append({n: p.grad.clone() for n, p in model.named_parameters()
                      if p.grad is not None})
    (full, n_full), (part, n_part) = outs
    assert n_full == [len(rays) * 96] and 0 < n_part[0] < 0.5 * n_full[0], (n_full, n_part)
    bound = 96 * 1e-4
    assert (part.rgb - full.rgb).abs().max() < bound
    assert torch.equal(part.weights, full.weights) and torch.equal(part.depth, full.depth)
    assert grads[0].keys() == grads[1].keys() and "sdf_grid" in grads[0]
    for name, g in grads[0].items():
        rel = (grads[1][name] - g).norm() / g.norm().clamp_min(1e-12)
        # beta's gradient sums over every sample, the dropped ones' colour terms included
        assert rel < (0.05 if "beta" in name else 0.01), (name, float(rel))
