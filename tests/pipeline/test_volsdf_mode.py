"""``--mode volsdf`` end to end on the tiny synthetic scene: VolSDF from its sphere with nothing
from MVS (the grid field and the MLP baseline), and its points under the multi-view rule. Whole
runs: the slow tests."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tiny_pipeline import make_tiny_scene, tiny_cfg

from svolsdf.config import load_config
from svolsdf.evaluate.synthetic import observed_gt_points, synthetic_chamfer
from svolsdf.io.ply import read_ply
from svolsdf.pipeline import Pipeline
from svolsdf.pipeline.builders import grid_schedule

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return make_tiny_scene(tmp_path_factory.mktemp("syn") / "scene")


@pytest.fixture(scope="module")
def volsdf_run(tiny_scene, tmp_path_factory):
    """A 40-step --mode volsdf run of the tiny scene, with its field before any step."""
    cfg = tiny_cfg(tiny_scene, steps=40)
    cfg.train.mode = "volsdf"
    cfg.train.checkpoint_every = 0
    out = tmp_path_factory.mktemp("volsdf") / "v"
    p = Pipeline(cfg, out, progress=False)
    p.load()
    init = p.build_model()
    return out, p.run(), p, init


def test_volsdf_mode_starts_from_a_sphere_with_nothing_from_mvs(volsdf_run, tiny_scene):
    """Issue 28: --mode volsdf is VolSDF: the sphere in the bounding sphere's box, a coarse-to-
    fine grid, the whole-grid eikonal term; no MVS stage, prior or MVS-derived box. Issue 38:
    no stage-1 file where the pipeline writes them (OUT/mvs/stage1), and the fit improves on
    its start."""
    out, summary, p, model = volsdf_run
    cfg = p.cfg
    assert torch.equal(model.bounds, torch.tensor([[-1.0] * 3, [1.0] * 3]))
    assert model.resolution == cfg.field.sphere_start_resolution == 16
    x = torch.tensor([[0.7, 0.0, 0.0], [0.0, -0.8, 0.1]])  # |x| - r, away from the centre's kink
    assert model.sdf(x).tolist() == pytest.approx((x.norm(dim=-1) - cfg.field.sphere_radius)
                                                  .tolist(), abs=0.02)
    assert not getattr(model, "mvs_initialised", False)
    # doublings to the final resolution, the last at 3/4 of the steps
    assert grid_schedule(p.cfg) == [(15, 32), (30, 64)]
    assert p.volumes1 is None and "mvs1" not in p.timing
    assert not any(p.dir.stage1_file(v).exists() for v in p.views)
    assert not (out / "mvs").exists()
    hist = (out / "field" / "losses.csv").read_text().splitlines()
    assert "grid_eikonal" in hist[0]
    assert summary["mesh"] is not None
    # quality: 40 steps bring the surface towards the object (measured: the median |SDF| at
    # the observed ground truth 9.8 mm from the sphere's 15.4; the mesh's Chamfer 7.5 mm)
    gt = observed_gt_points(tiny_scene, p.views)
    norm = p.load().normalization
    gt_u = norm.to_unit(torch.from_numpy(gt)).float()
    with torch.no_grad():
        start = model.sdf(gt_u).abs().median().item() * norm.scale
        fit = p.model().sdf(gt_u.to(p.device)).abs().median().item() * norm.scale
    assert fit < 0.8 * start, (fit, start)
    footprint = 600.0 / (1.8 * 160)  # mm per pixel at the object (SynthConfig defaults)
    mesh = synthetic_chamfer(read_ply(out / "mesh.ply")["points"], tiny_scene, p.views)
    assert mesh["overall"] < 5.0 * footprint, mesh


def test_volsdf_points_pass_the_multi_view_check(volsdf_run, tmp_path):
    """Issue 38: VolSDF's fused depth is its rendered guide; that guide is no consistent
    source for itself, and the pixels docs/method.md 6.1 fills with the map's maximum depth are no
    surface. A pixel only one view sees is dropped: with the other views' depth removed,
    nothing of the remaining view is kept (before, every valid pixel passed)."""
    import shutil

    from svolsdf.pipeline.fusion_stage import fuse
    from svolsdf.render.views import max_rule_filled

    out, _, p, _ = volsdf_run
    assert p.cfg.fusion.surface > 0 and p.cfg.fusion.min_views == 1
    n_all = len(read_ply(out / "points.ply")["points"])
    valid = 0
    for v in p.views:
        d = torch.from_numpy(np.load(out / "depth" / f"{v}.npy"))
        assert max_rule_filled(d).any()  # the fill is there, and fused as no depth
        valid += int(((d > 0) & ~max_rule_filled(d)).sum())
    assert 0 < n_all < valid
    copy = tmp_path / "one_view"
    shutil.copytree(out, copy)
    for v in p.views[1:]:
        np.save(copy / "depth" / f"{v}.npy", np.zeros_like(np.load(out / "depth" / f"{v}.npy")))
    p2 = Pipeline(load_config(out / "config.yaml"), copy, progress=False)
    p2.load()
    assert fuse(p2, copy / "points_one_view.ply")[0] == 0


def test_volsdf_with_the_mlp_field_is_the_mlp_baseline(tiny_scene, tmp_path):
    """`--mode volsdf --set field.kind=mlp`: VolSDF's MLP from its sphere, nothing from MVS,
    a mesh and points, named "VolSDF (MLP)" in tables; and what the baseline must get right
    (issue 50): it starts as VolSDF's sphere (|x| - 0.6, unit gradient; an MLP whose skip
    entered its last layer started with |grad| ~ 9), its optimization lowers the colour error
    of the input views at fixed pixels, and its SDF stays finite with its zero level inside the
    bounding sphere. A small MLP, image and 30 steps of 64 rays keep it cheap (~25 s)."""
    from svolsdf.commands.render import open_run
    from svolsdf.config import apply_overrides
    from svolsdf.evaluate.benchmark_tables import method_label
    from svolsdf.field.volsdf import VolSDFField
    from svolsdf.pipeline.builders import build_sampler
    from svolsdf.render.views import render_field_views

    cfg = apply_overrides(tiny_cfg(tiny_scene, steps=30), {
        "train.mode": "volsdf", "field.kind": "mlp", "field.mlp_depth": 5,
        "field.mlp_width": 64, "train.checkpoint_every": 0, "scene.image_size": [48, 36],
        "train.rays": 64, "train.samples_uniform": 16, "train.samples_fine": 16,
        # the paper's learned beta: an anneal over 30 steps would change the loss it lowers
        "train.beta_start": 0.0,
        "guide.mask_dilation": 0, "mesh.resolution": 32,
        # 30 steps leave depth that no second view confirms yet: every depth is fused, so that
        # the run ends (the multi-view rule has its own test above)
        "fusion.min_views": 0})
    out = tmp_path / "mlp"
    p = Pipeline(cfg, out, progress=False)
    scene = p.load()
    torch.manual_seed(cfg.train.seed)  # as the field stage builds its model
    start = p.build_model()
    summary = p.run()
    # VolSDF's sphere: sdf ~ |x| - 0.6 with a unit gradient (docs/method.md 5.2; IDR's init is
    # that only roughly at width 64: measured means -0.28 / 0.00 / 0.37 at r 0.3 / 0.6 / 1.0,
    # |grad| 0.9-1.1)
    for r, lo, hi in ((0.3, -0.45, -0.15), (0.6, -0.15, 0.15), (1.0, 0.2, 0.6)):
        x = torch.randn(300, 3)
        x = x / x.norm(dim=-1, keepdim=True) * r
        sdf, grad, _ = start.sdf_and_grad(x, create_graph=False)
        assert lo < sdf.mean().item() < hi, (r, sdf.mean().item())
        assert 0.75 < grad.norm(dim=-1).mean().item() < 1.25, (r, grad.norm(dim=-1).mean())
    # the fit: L1 colour error of the inputs at fixed pixels, rendered before and after
    pixels = torch.zeros(len(p.views), 36, 48, dtype=torch.bool)
    pixels[:, 1::3, 1::3] = True
    sampler = build_sampler(cfg, None, training=False)
    target = scene.images.permute(0, 2, 3, 1)[pixels]
    err = [(render_field_views(m, sampler, scene.cameras_unit, p.unit_near_far(), keys=("rgb",),
                               pixels=pixels)["rgb"][pixels] - target).abs().mean().item()
           for m in (start, p.model())]
    assert err[1] < 0.85 * err[0], err  # measured: 0.18 -> 0.12
    # a finite SDF whose zero level lies inside the bounding sphere (radius 3)
    g = torch.linspace(-2.9, 2.9, 24)
    grid = torch.cartesian_prod(g, g, g)
    grid = grid[grid.norm(dim=-1) < 2.9]
    with torch.no_grad():
        values = p.model().sdf(grid.to(p.device)).cpu()
    assert torch.isfinite(values).all() and values.min() < 0 < values.max()
    assert (values[grid.norm(dim=-1) > 2.0] > 0).all()  # the object is inside the unit sphere
    mesh = read_ply(out / "mesh.ply")
    inside = scene.normalization.to_unit(torch.from_numpy(mesh["points"]).double()).norm(dim=-1)
    assert len(mesh["faces"]) > 0 and inside.max() < 2.0, inside.max()
    # the run: the MLP, no MVS, a mesh and points, the label
    run = open_run(out)
    assert isinstance(run.model(), VolSDFField) and not (out / "mvs").exists()
    assert summary["mesh"] is not None and (out / "points.ply").is_file()
    assert "rgb" in (out / "field" / "losses.csv").read_text().splitlines()[0]
    assert method_label(run.cfg.train.mode, run.cfg.field.kind) == "VolSDF (MLP)"


def test_volsdf_depth_is_fused_within_svolsdfs_masks(volsdf_run, monkeypatch):
    """Issue 50: VolSDF's rendered depth is fused within the masks dilated by
    fusion.guided_dilation, as S-VolSDF's guided depth (before, the released 12 px whatever the
    option said); a wider dilation keeps more of the surface it fattens into the background."""
    import svolsdf.fusion.filter as fusion_filter
    from svolsdf.pipeline.fusion_stage import fuse

    out, _, p, _ = volsdf_run
    assert p.cfg.fusion.guided_dilation == 4
    seen = []
    real = fusion_filter.fuse_depth_maps

    def spy(*args, **kwargs):
        cfg = args[5]  # (depths, cams, images, confs, masks, cfg)
        seen.append(cfg.guided_dilation if cfg.guided_depths else None)
        return real(*args, **kwargs)

    monkeypatch.setattr(fusion_filter, "fuse_depth_maps", spy)
    n4 = fuse(p, out / "points_4px.ply")[0]
    p.cfg.fusion.guided_dilation = 12
    try:
        n12 = fuse(p, out / "points_12px.ply")[0]
    finally:
        p.cfg.fusion.guided_dilation = 4
    assert seen == [4, 12]
    assert n4 == len(read_ply(out / "points.ply")["points"]) and n4 <= n12
