"""NeRF++ inverted-sphere background (docs/method.md 5.5): the parameterisation, compositing in
`render_rays`, gradients, checkpoints, and a pipeline run with ``field.background``."""

from __future__ import annotations

import json

import numpy as np
import torch
from tests.field.analytic import SphereSDF

from svolsdf.config import TrainConfig, preset
from svolsdf.field.background import (
    BackgroundConfig,
    NeRFPlusPlusBackground,
    SphereMapBackground,
    inverted_sphere_points,
    sphere_exit,
)
from svolsdf.field.grid import GridFieldConfig, GridSDFField
from svolsdf.optimize.trainer import TrainData, Trainer
from svolsdf.pipeline import Pipeline
from svolsdf.render.guided import GuidedSamplerConfig, MVSGuidedSampler
from svolsdf.render.rays import rays_from_cameras
from svolsdf.render.samplers import uniform_sampler
from svolsdf.render.volume import render_rays
from svolsdf.scene.cameras import Cameras
from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

R_SPHERE = 3.0


def _tiny_bg(seed=0) -> NeRFPlusPlusBackground:
    torch.manual_seed(seed)
    return NeRFPlusPlusBackground(BackgroundConfig(
        n_samples=8, radius=R_SPHERE, multires=3, n_layers=2, d_hidden=16, skip_in=(),
        feature_dim=8, multires_view=2, colour_hidden=8))


def _camera(W=16, H=12, f=20.0, dist=2.5):
    """One camera on the -z axis looking at the origin (OpenCV axes), inside the sphere."""
    K = torch.tensor([[f, 0.0, (W - 1) / 2], [0.0, f, (H - 1) / 2], [0.0, 0.0, 1.0]])[None]
    w2c = torch.eye(4)[None]
    w2c[0, 2, 3] = dist
    return Cameras(K, w2c, W, H)


def test_inverted_sphere_points_lie_on_the_ray_at_radius_one_over_u():
    g = torch.Generator().manual_seed(0)
    n, k = 64, 9
    o = torch.randn(n, 3, generator=g, dtype=torch.float64)
    o = o / o.norm(dim=-1, keepdim=True) * 2.5 * torch.rand(n, 1, generator=g, dtype=torch.float64)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    u = torch.rand(n, k, generator=g, dtype=torch.float64) / R_SPHERE
    u[:, 0] = 1.0 / R_SPHERE  # on the sphere itself
    u[:, -1] = 0.0  # at infinity
    pts, dist = inverted_sphere_points(o, d, u, R_SPHERE)
    assert pts.shape == (n, k, 4) and dist.shape == (n, k)
    # 4-d point (unit direction, u): |xyz| = 1, u in [0, 1/R]
    torch.testing.assert_close(pts[..., :3].norm(dim=-1), torch.ones(n, k, dtype=torch.float64))
    assert torch.equal(pts[..., 3], u) and (u >= 0).all() and (u <= 1 / R_SPHERE).all()
    # the ray point at that distance has radius 1/u and the direction xyz (u > 0)
    x = o[:, None] + dist[..., None] * d[:, None]
    fin = u > 0.02
    torch.testing.assert_close(x.norm(dim=-1)[fin], (1.0 / u)[fin], rtol=1e-4, atol=0)
    # (1e-5: the distance uses 1 / (u + 1e-6), docs/method.md 5.5)
    torch.testing.assert_close((x / x.norm(dim=-1, keepdim=True))[fin], pts[..., :3][fin],
                               atol=1e-5, rtol=0)
    # u = 1/R: the sphere hit; distances grow as u falls
    torch.testing.assert_close(x[:, 0].norm(dim=-1), torch.full((n,), R_SPHERE,
                                                               dtype=torch.float64), rtol=1e-5,
                               atol=0)
    assert (dist[:, 1:-1] >= dist[:, :1]).all() and (dist[:, -1] > 1e5).all()


def _rays():
    rays = rays_from_cameras(_camera(), 0, radius=R_SPHERE, far_mode="sphere")
    z = uniform_sampler(rays.near, rays.far, 256)  # the last entry is the far bound
    return rays, z


def test_empty_foreground_shows_the_background_and_opaque_hides_it():
    bg = _tiny_bg().eval()
    rays, z = _rays()
    rgb_bg, _, _ = bg(rays, False)
    empty = SphereSDF(radius=0.01, center=(0.0, 2.0, 0.0), beta=0.01).eval()
    out = render_rays(empty, rays, z, background=bg, create_graph=False)
    torch.testing.assert_close(out.bg_transmittance, torch.ones(len(rays)), atol=1e-5, rtol=0)
    torch.testing.assert_close(out.rgb, rgb_bg, atol=1e-5, rtol=0)
    assert out.weights.shape == (len(rays), z.shape[1] - 1)  # the far bound is not a sample

    solid = SphereSDF(radius=0.6, beta=0.005, colour=(0.8, 0.4, 0.2)).eval()
    od = (rays.origins * rays.dirs).sum(-1)
    disc = od**2 - (rays.origins**2).sum(-1) + 0.36
    hit, miss = disc > 0.02, disc < -0.15  # clear hits; misses by > 20 beta
    out = render_rays(solid, rays, z, background=bg, create_graph=False)
    assert hit.sum() > 20 and miss.sum() > 20
    assert (out.bg_transmittance[hit] < 1e-4).all()
    torch.testing.assert_close(out.rgb[hit], torch.tensor([0.8, 0.4, 0.2]).expand(
        int(hit.sum()), 3), atol=1e-3, rtol=0)
    torch.testing.assert_close(out.rgb[miss], rgb_bg[miss], atol=1e-4, rtol=0)
    # depth_all moves towards the background where it is seen, depth stays foreground-only
    assert (out.depth_all[miss] > out.depth[miss]).all()


def test_gradients_reach_the_background():
    bg = _tiny_bg().train()
    rays, z = _rays()
    model = SphereSDF(radius=0.01, center=(0.0, 2.0, 0.0)).train()
    out = render_rays(model, rays, z, background=bg, create_graph=True)
    ((out.rgb - 0.3) ** 2).mean().backward()
    for name, p in bg.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert all(p.grad.abs().sum() > 0 for p in bg.colour_net.parameters())
    assert sum(float(p.grad.abs().sum()) for p in bg.net.parameters()) > 0


def _data(V=2, W=12, H=9):
    cams = _camera(W, H, f=15.0)
    cams = Cameras(cams.K.expand(V, 3, 3).clone(), cams.w2c.expand(V, 4, 4).clone(), W, H)
    return TrainData(torch.rand(V, 3, H, W), cams, torch.tensor([[1.5, 3.5]]).expand(V, 2).clone())


def _bg_trainer(out_dir, seed=0):
    torch.manual_seed(seed)
    model = GridSDFField(torch.tensor([[-0.8] * 3, [0.8] * 3]),
                         GridFieldConfig(resolution=8, sphere_clamp_scale=None))
    model.background = _tiny_bg(seed)
    cfg = TrainConfig(mode="volsdf", steps=2, rays=16, checkpoint_every=0)
    sampler = MVSGuidedSampler(None, GuidedSamplerConfig(samples_coarse=8, samples_uniform=4,
                                                         samples_fine=4))
    return Trainer(model, _data(), cfg, sampler=sampler, out_dir=out_dir)


def test_trainer_optimizes_and_checkpoints_the_background(tmp_path):
    a = _bg_trainer(tmp_path)
    in_opt = {id(p): g["lr"] for g in a.optimizer.param_groups for p in g["params"]}
    assert all(in_opt.get(id(p)) == a.cfg.lr for p in a.model.background.parameters())
    before = [p.detach().clone() for p in a.model.background.parameters()]
    a.fit(progress=False)
    assert any(not torch.equal(p, q) for p, q in zip(before, a.model.background.parameters(),
                                                     strict=True))
    path = a.save_checkpoint()
    keys = torch.load(path, weights_only=False)["model_state_dict"].keys()
    assert any(k.startswith("background.net.") for k in keys)
    assert any(k.startswith("background.colour_net.") for k in keys)
    b = _bg_trainer(tmp_path, seed=1)
    assert b.load_checkpoint() and b.step == 2
    for (n, p), (_, q) in zip(a.model.named_parameters(), b.model.named_parameters(),
                              strict=True):
        assert torch.equal(p, q), n


def test_pipeline_runs_with_background(tmp_path):
    scene = tmp_path / "scene"
    make_synthetic_scene(scene, SynthConfig(views=3, width=48, height=36, seed=2,
                                            object="blobs", supersample=1, gt_points=2000))
    cfg = preset("fast")
    cfg.scene.path = str(scene)
    cfg.train.mode = "volsdf"
    cfg.train.steps = 3
    cfg.train.rays = 32
    cfg.train.checkpoint_every = 0
    cfg.field.background = True
    cfg.field.grid_start_resolution = cfg.field.grid_resolution = 12
    cfg.field.sphere_start_resolution = 8  # volsdf starts from the sphere
    cfg.mesh.resolution = 24
    p = Pipeline(cfg, tmp_path / "out", progress=False)
    p.run()
    model = p.model()
    assert isinstance(model.background, NeRFPlusPlusBackground)
    assert model.config.sphere_clamp_scale is None  # docs/method.md 5.5: no clamp
    state = torch.load(tmp_path / "out" / "field" / "model.pt", weights_only=False)
    assert any(k.startswith("background.") for k in state["model_state_dict"])
    v = json.loads((tmp_path / "out" / "views.json").read_text())["inputs"][0]
    assert np.isfinite(np.load(tmp_path / "out" / "depth" / f"{v}.npy")).all()
    # a rerun loads the saved field, background included
    p2 = Pipeline(cfg, tmp_path / "out", progress=False)
    p2.run()
    assert "field" not in p2.timing
    for (n, a), (_, b) in zip(model.state_dict().items(), p2.model().state_dict().items(),
                              strict=True):
        assert torch.equal(a.cpu(), b.cpu()), n


# --------------------------------------------------------------------------- the sphere map
def test_sphere_exit_lies_on_the_sphere_along_the_ray():
    torch.manual_seed(0)
    o = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1) * 2.5 * torch.rand(64, 1)
    d = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1)
    p, t = sphere_exit(o, d, R_SPHERE)
    torch.testing.assert_close(p.norm(dim=-1), torch.full((64,), R_SPHERE), atol=1e-5, rtol=0)
    torch.testing.assert_close(p, o + t[:, None] * d, atol=1e-6, rtol=0)
    assert (t > 0).all()


def test_sphere_map_learns_a_colour_per_direction_and_trains_at_the_grid_rate(tmp_path):
    bg = SphereMapBackground(R_SPHERE, resolutions=(4, 16))
    rays, _ = _rays()
    target = torch.where(rays.dirs[:, :1] > 0, torch.tensor([0.9, 0.2, 0.1]),
                         torch.tensor([0.1, 0.3, 0.8]))  # two colours by side
    rgb0, t, w = bg(rays, True)
    torch.testing.assert_close(rgb0, torch.full_like(rgb0, 0.5))  # starts grey
    assert (w == 1).all() and (t > 0).all()
    opt = torch.optim.Adam(bg.grid_parameters(), lr=0.1)
    for _ in range(200):
        opt.zero_grad()
        ((bg(rays, True)[0] - target) ** 2).mean().backward()
        opt.step()
    assert float((bg(rays, False)[0] - target).abs().mean()) < 0.05
    # beside the grid field, the optimizer puts the maps in the grid group (train.lr_grid)
    model = GridSDFField(torch.tensor([[-0.8] * 3, [0.8] * 3]),
                         GridFieldConfig(resolution=8, sphere_clamp_scale=None))
    model.background = SphereMapBackground(R_SPHERE)
    tr = Trainer(model, _data(), TrainConfig(mode="volsdf", steps=1, rays=16,
                                             checkpoint_every=0),
                 sampler=MVSGuidedSampler(None, GuidedSamplerConfig(
                     samples_coarse=8, samples_uniform=4, samples_fine=4)),
                 out_dir=tmp_path)
    lr = {id(p): g["lr"] for g in tr.optimizer.param_groups for p in g["params"]}
    assert all(lr[id(p)] == tr.cfg.lr_grid for p in model.background.parameters())
    tr.fit(progress=False)
    assert any(float(m.abs().sum()) > 0 for m in model.background.maps)


def test_empty_foreground_shows_the_sphere_map():
    bg = SphereMapBackground(R_SPHERE, resolutions=(4,))
    with torch.no_grad():
        bg.maps[0].fill_(1.0)
    rays, z = _rays()
    empty = SphereSDF(radius=0.01, center=(0.0, 2.0, 0.0), beta=0.01).eval()
    out = render_rays(empty, rays, z, background=bg, create_graph=False)
    torch.testing.assert_close(out.rgb, torch.full_like(out.rgb, float(torch.sigmoid(
        torch.tensor(1.0)))), atol=1e-4, rtol=0)


# --------------------------------------------------------------------------- colour steps
def test_colour_steps_train_only_the_colour_and_give_the_model_back_whole(tmp_path):
    torch.manual_seed(0)
    model = GridSDFField(torch.tensor([[-0.8] * 3, [0.8] * 3]),
                         GridFieldConfig(resolution=8, sphere_clamp_scale=None))
    model.background = SphereMapBackground(R_SPHERE)
    cfg = TrainConfig(mode="volsdf", steps=2, rays=16, colour_steps=3, colour_rays=32,
                      checkpoint_every=0, beta_start=0.05, beta_end=0.01)
    tr = Trainer(model, _data(), cfg,
                 sampler=MVSGuidedSampler(None, GuidedSamplerConfig(
                     samples_coarse=8, samples_uniform=4, samples_fine=4)),
                 out_dir=tmp_path)
    tr.fit(steps=2, progress=False)
    sdf, beta = model.sdf_grid.detach().clone(), model.beta.detach().clone()
    feats = [g.detach().clone() for g in model.feature_grids]
    tr.fit(progress=False)  # the colour steps: 2 -> 5
    assert tr.step == 5 and "colour_rgb" in tr.history[-1]
    assert torch.equal(model.sdf_grid.detach(), sdf)  # the surface did not move
    assert torch.equal(model.beta.detach(), beta)  # the density too (beta is not annealed on)
    assert any(not torch.equal(a, g.detach()) for a, g in zip(feats, model.feature_grids,
                                                              strict=True))
    assert all(p.requires_grad for p in model.parameters())  # given back trainable


def test_colour_steps_are_refused_for_the_mlp_field():
    from svolsdf.config import validate_config
    from svolsdf.errors import InputError

    cfg = preset("paper")
    cfg.train.colour_steps = 10
    try:
        validate_config(cfg)
    except InputError as e:
        assert "train.colour_steps" in str(e)
    else:
        raise AssertionError("colour_steps with the MLP field was accepted")
