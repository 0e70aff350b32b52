"""Plane sweep: accuracy on ray-cast scenes with exact depth, volume shapes and hypotheses
(docs/method.md 2.5), probabilities, and the building blocks (ZNCC, source aggregation, SGM)."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from tests.mvs.synth import make_cameras, make_scene, plane_scene, raycast

from svolsdf.errors import InputError
from svolsdf.mvs.backbone import get_backbone, select_sources
from svolsdf.mvs.cascade import run_cascade
from svolsdf.mvs.hypotheses import base_interval
from svolsdf.mvs.planesweep import (
    PlaneSweepBackbone,
    aggregate_sources,
    box_filter,
    calibrate_temperature,
    guided_filter,
    zncc_cost,
)
from svolsdf.mvs.sgm import sgm_aggregate

RANGE = (2.5, 6.0)


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def sphere_run():
    """A textured sphere in front of a slanted textured plane, 3 views at 96x72, all stages."""
    cams = make_cameras(96, 72)
    sphere = ((0.0, 0.0, 0.2), 1.3)
    plane = ((math.sin(0.3), 0.0, -math.cos(0.3)), -1.2)
    scene, gt = make_scene(cams, planes=[plane], spheres=[sphere], depth_range=RANGE)
    _, _, sphere_mask = raycast(cams, spheres=[sphere])
    res = run_cascade(get_backbone("planesweep"), scene)
    return scene, gt, sphere_mask[:, 0] > 0, res


def _median_error(vol, gt, mask) -> float:
    """Median |depth - gt| inside ``mask`` as a fraction of the depth range."""
    H, W = vol.depth.shape
    g = F.interpolate(gt[None, None], size=(H, W), mode="nearest")[0, 0]
    m = F.interpolate(mask[None, None].float(), size=(H, W), mode="nearest")[0, 0] > 0
    return float((vol.depth - g).abs()[m].median()) / (RANGE[1] - RANGE[0])


def test_stage3_accuracy_on_object(sphere_run):
    scene, gt, mask, res = sphere_run
    errs = {k: [_median_error(v, gt[i], mask[i]) for i, v in enumerate(res[k])] for k in res}
    for i in range(3):
        assert errs[3][i] < 0.015, f"view {i}: stage-3 median error {errs[3][i]:.2%} of range"
        assert errs[3][i] < errs[1][i]
    assert sum(errs[3]) / 3 < 0.01


@pytest.mark.parametrize("slanted", [False, True])
def test_stage3_accuracy_on_planes(slanted):
    # 96x72 (stage 1 at 24x18): at 64x48 the image borders, where hypotheses leave the sources,
    # are a third of stage 1 and the median error says more about them than about the planes
    scene, gt = plane_scene(96, 72, slanted=slanted, depth_range=RANGE)
    res = run_cascade(PlaneSweepBackbone(), scene)
    for i, v in enumerate(res[3]):
        err = _median_error(v, gt[i], torch.ones_like(gt[i], dtype=torch.bool))
        assert err < 0.01, f"view {i}: {err:.2%}"


def test_volume_shapes_and_hypotheses(sphere_run):
    scene, _, _, res = sphere_run
    d_min, d_max = RANGE
    delta = base_interval(d_min, d_max)
    # the MVS size is 2x the working size (PlaneSweepConfig.scale)
    sizes = {1: (192, 36, 48), 2: (32, 72, 96), 3: (8, 144, 192)}
    for k, vols in res.items():
        assert [v.view_id for v in vols] == [0, 1, 2]
        for v in vols:
            assert tuple(v.prob.shape) == sizes[k] and v.depths.shape == v.prob.shape
            assert v.stage == k
            assert (v.cameras.width, v.cameras.height) == (sizes[k][2], sizes[k][1])
            assert torch.allclose(v.prob.sum(0), torch.ones_like(v.depth), atol=1e-5)
            assert (v.prob >= 0).all()
            assert (v.confidence >= 0).all() and (v.confidence <= 1 + 1e-5).all()
            assert (v.depths[1:] > v.depths[:-1]).all()
            # expectation lies inside each pixel's hypotheses
            assert (v.depth >= v.depths[0] - 1e-4).all() and (v.depth <= v.depths[-1] + 1e-4).all()
    # stage 1: 192 fronto-parallel planes over [d_min, d_max] (docs/method.md 2.5)
    planes = res[1][0].depths[:, 0, 0]
    assert torch.allclose(planes, torch.linspace(d_min, d_max, 192), atol=1e-5)
    assert torch.allclose(res[1][0].depths, planes[:, None, None].expand(-1, 36, 48))
    # stages 2-3: per-pixel, centred on the previous stage's upsampled depth, width D r Δ̄
    # (the default width, the paper's intervals 1, 0.5, 0.5)
    for k, (D, r) in {2: (32, 0.5), 3: (8, 0.5)}.items():
        for v, p in zip(res[k], res[k - 1], strict=True):
            H, W = v.depth.shape
            centre = F.interpolate(p.depth[None, None], size=(H, W), mode="bilinear",
                                   align_corners=False)[0, 0]
            assert torch.allclose(v.depths.mean(0), centre, atol=1e-4)
            width = v.depths[-1] - v.depths[0]
            # lower/upper = d -+ (D/2) r Δ̄, so the first and last hypotheses are D r Δ̄ apart
            assert torch.allclose(width, torch.full_like(width, D * r * delta), rtol=1e-4)


@pytest.mark.parametrize("scale", [2.0, 1.5])
def test_scale_runs_the_cascade_at_a_multiple_of_the_working_size(scale):
    """mvs.scale (docs/method.md 9.2.2, the released x2_mvsres): stage k at scale / 2^(3-k) x the
    working size, cameras resized with it (pixel-centre convention), depth still accurate."""
    scene, gt = plane_scene(48, 36, slanted=True, depth_range=RANGE)
    res = run_cascade(PlaneSweepBackbone(scale=scale), scene)
    for k, vols in res.items():
        W, H = round(48 * scale / 2 ** (3 - k)), round(36 * scale / 2 ** (3 - k))
        for v in vols:
            assert tuple(v.depth.shape) == (H, W) and tuple(v.prob.shape[1:]) == (H, W)
            K = scene.cameras.resize(W, H).K[scene.index(v.view_id)]
            assert torch.allclose(v.cameras.K.reshape(3, 3), K.reshape(3, 3))
    for i, v in enumerate(res[3]):
        # gt at 48x36, compared by nearest lookup: the slanted plane's depth changes within a
        # working pixel, so the bound is the scale-1 test's plus that footprint
        err = _median_error(v, gt[i], torch.ones_like(gt[i], dtype=torch.bool))
        assert err < 0.015, f"view {i}: {err:.2%}"
    with pytest.raises(InputError, match="scale"):
        PlaneSweepBackbone(scale=0.0)


def test_width_released_option():
    scene, _ = plane_scene(32, 24, depth_range=RANGE)
    bb = PlaneSweepBackbone(width="released")
    v1 = bb.stage(1, scene, ref_ids=[0])
    v2 = bb.stage(2, scene, ref_ids=[0], prev={0: v1[0]})[0]
    width = float((v2.depths[-1] - v2.depths[0]).mean())
    assert width == pytest.approx(32 * 0.5 * base_interval(*RANGE), rel=1e-4)


def test_guide_depth_centres_stage2():
    scene, gt = plane_scene(32, 24, depth_range=RANGE)
    guide = torch.full((12, 16), 4.0)  # any size: resized to the stage's
    v = PlaneSweepBackbone().stage(2, scene, ref_ids=[1], guide_depth={1: guide})[0]
    assert v.view_id == 1 and v.depths.shape == (32, 24, 32)  # stage 2 at 2x / 2
    assert torch.allclose(v.depths.mean(0), torch.full((24, 32), 4.0), atol=1e-5)


@pytest.mark.parametrize("max_sources, expected", [(2, 2), (0, 4), (9, 4)])
def test_max_sources_caps_the_sources_in_pair_order(monkeypatch, max_sources, expected):
    """docs/method.md 1.4: at most 4 sources, the best by pair score; <= 0 means every other
    view."""
    eyes = [(0.0, 0.0, -4.0), (0.7, 0.1, -3.95), (-0.6, -0.3, -3.95), (0.3, 0.6, -3.9),
            (-0.4, 0.5, -3.9)]
    plane = ((0.0, 0.0, -1.0), -0.5)
    scene, _ = make_scene(make_cameras(32, 24, eyes=eyes), planes=[plane], depth_range=RANGE)
    import svolsdf.mvs.planesweep as ps

    bb = PlaneSweepBackbone(max_sources=max_sources)
    seen, costs = [], []
    real, real_cost = ps.select_sources, bb._cost_volume

    def spy(scene, vid, n):
        seen.append((vid, real(scene, vid, n)))
        return seen[-1][1]

    def spy_cost(k, ref, g, P_ref, sources, depths):
        costs.append(len(sources))
        return real_cost(k, ref, g, P_ref, sources, depths)

    monkeypatch.setattr(ps, "select_sources", spy)
    monkeypatch.setattr(bb, "_cost_volume", spy_cost)
    bb.stage(1, scene, ref_ids=[0, 3])
    for vid, src in seen:
        assert src == scene.source_views(vid)[:expected]
    assert [v for v, _ in seen] == [0, 3] and costs == [expected, expected]
    assert select_sources(scene, 0, 2) == scene.source_views(0)[:2]
    assert select_sources(scene, 0, 0) == scene.source_views(0)


def test_bad_input():
    scene, _ = plane_scene(32, 24, depth_range=RANGE)
    bad = scene.depth_range.clone()
    bad[1] = torch.tensor([5.0, 5.0])
    from dataclasses import replace

    with pytest.raises(InputError, match="view 1"):
        PlaneSweepBackbone().stage(1, replace(scene, depth_range=bad))
    with pytest.raises(InputError, match="previous stage"):
        PlaneSweepBackbone().stage(2, scene)
    with pytest.raises(InputError, match="filter"):
        PlaneSweepBackbone(filter="median")
    with pytest.raises(InputError):
        get_backbone("planesweep", weights="x.pt")


# --------------------------------------------------------------------------- building blocks
def test_zncc_known_values():
    g = torch.Generator().manual_seed(0)
    ref = torch.rand(1, 1, 20, 20, generator=g)
    same = zncc_cost(ref, ref.clone(), 2, 1e-8)
    gain = zncc_cost(ref, 0.5 * ref + 0.2, 2, 1e-8)  # invariant to gain and offset
    neg = zncc_cost(ref, 1.0 - ref, 2, 1e-8)
    assert same.abs().max() < 1e-3 and gain.abs().max() < 1e-3
    assert (neg - 2).abs().max() < 1e-3
    flat = zncc_cost(ref, torch.full_like(ref, 0.5), 2, 1e-5)  # textureless source: ~1
    assert (flat - 1).abs().max() < 1e-3


@pytest.mark.parametrize("shape", [(1, 2, 15, 17), (2, 3, 4, 9), (1, 1, 1, 6)])
@pytest.mark.parametrize("radius", [1, 2, 5])
def test_box_filter_is_the_window_mean_shrinking_at_the_borders(shape, radius):
    x = torch.rand(*shape, generator=torch.Generator().manual_seed(0))
    k = 2 * radius + 1
    ref = F.avg_pool2d(x, (1, k), stride=1, padding=(0, radius), count_include_pad=False)
    ref = F.avg_pool2d(ref, (k, 1), stride=1, padding=(radius, 0), count_include_pad=False)
    assert torch.allclose(box_filter(x, radius), ref, atol=1e-6)
    H, W = shape[-2:]  # one corner by hand: the window holds rows/cols 0..radius only
    corner = x[..., :min(radius + 1, H), :min(radius + 1, W)].mean(dim=(-2, -1))
    assert torch.allclose(box_filter(x, radius)[..., 0, 0], corner, atol=1e-6)
    assert box_filter(x, 0) is x


def test_box_and_guided_filter():
    x = torch.rand(1, 2, 15, 17)
    b = box_filter(x, 2)
    ref = F.avg_pool2d(F.pad(x, (2, 2, 2, 2), mode="constant", value=0), 5, stride=1)
    assert torch.allclose(b[..., 2:-2, 2:-2], ref[..., 2:-2, 2:-2], atol=1e-6)
    # a constant input stays constant; with a flat guide the guided filter is a box filter
    c = torch.full((1, 1, 15, 17), 0.7)
    assert torch.allclose(guided_filter(torch.rand(1, 1, 15, 17), c, 2, 1e-3), c, atol=1e-5)
    flat = torch.full((1, 1, 15, 17), 0.3)
    assert torch.allclose(guided_filter(flat, x, 2, 1e-3), box_filter(box_filter(x, 2), 2),
                          atol=1e-5)


def test_aggregate_sources_robust_to_a_missing_view():
    costs = torch.tensor([0.2, 1.5, 0.4]).view(3, 1, 1, 1)
    all_valid = torch.ones(3, 1, 1, 1, dtype=torch.bool)
    # best ceil(0.5 * 3) = 2 costs: (0.2 + 0.4) / 2
    assert float(aggregate_sources(costs, all_valid, 0.5, 1.0)) == pytest.approx(0.3)
    one_out = all_valid.clone()
    one_out[0] = False  # the best source does not see the point: best 1 of the other 2
    assert float(aggregate_sources(costs, one_out, 0.5, 1.0)) == pytest.approx(0.4)
    none = torch.zeros_like(all_valid)
    assert float(aggregate_sources(costs, none, 0.5, 1.0)) == pytest.approx(1.0)


def test_sgm_without_penalties_is_identity_and_smooths_with_them():
    cost = torch.rand(6, 9, 11)
    g = torch.rand(9, 11)
    assert torch.allclose(sgm_aggregate(cost, g, 0.0, 0.0, 0.1), cost, atol=1e-6)
    # a single wrong pixel in a flat image is voted back to its neighbours' hypothesis
    c = torch.ones(5, 9, 9)
    c[2] = 0.0
    c[2, 4, 4], c[0, 4, 4] = 0.3, 0.0
    out = sgm_aggregate(c, torch.zeros(9, 9), 0.05, 0.5, 0.1)
    assert int(out[:, 4, 4].argmin()) == 2


def _sgm_reference(c, g, p1, p2, sigma, dy, dx):
    """Slow per-pixel SGM recursion along direction (dy, dx), for the tests."""
    D, H, W = c.shape
    L = torch.zeros_like(c)
    ys = range(H) if dy >= 0 else range(H - 1, -1, -1)
    xs = list(range(W)) if dx >= 0 else list(range(W - 1, -1, -1))
    for y in ys:
        for x in xs:
            py, px = y - dy, x - dx
            if not (0 <= py < H and 0 <= px < W):
                L[:, y, x] = c[:, y, x]
                continue
            P = L[:, py, px]
            m = P.min()
            pen = p1 + (p2 - p1) * math.exp(-abs(float(g[y, x] - g[py, px])) / sigma)
            for k in range(D):
                cand = [float(P[k]), float(m) + pen]
                if k > 0:
                    cand.append(float(P[k - 1]) + p1)
                if k < D - 1:
                    cand.append(float(P[k + 1]) + p1)
                L[k, y, x] = c[k, y, x] + min(cand) - m
    return L


@pytest.mark.parametrize("directions", [4, 8])
def test_sgm_matches_per_pixel_recursion(directions):
    torch.manual_seed(0)
    c, g = torch.rand(5, 6, 7), torch.rand(6, 7)
    dirs = [(0, 1), (0, -1), (1, 0), (-1, 0)]
    if directions == 8:
        dirs += [(1, 1), (-1, -1), (1, -1), (-1, 1)]
    ref = sum(_sgm_reference(c, g, 0.05, 0.5, 0.1, dy, dx) for dy, dx in dirs) / len(dirs)
    out = sgm_aggregate(c, g, 0.05, 0.5, 0.1, directions)
    assert torch.allclose(out, ref, atol=1e-5)
    with pytest.raises(ValueError, match="directions"):
        sgm_aggregate(c, g, 0.05, 0.5, 0.1, 6)
    with pytest.raises(ValueError, match="penalties"):
        sgm_aggregate(c, g, -0.05, 0.5, 0.1, directions)


@pytest.mark.parametrize("shape", [(3, 1, 5), (4, 9, 2), (2, 3, 3)])
def test_sgm_matches_per_pixel_recursion_on_thin_volumes(shape):
    # one-row / one-column / square slices: every diagonal predecessor falls off the edge
    torch.manual_seed(1)
    c, g = torch.rand(*shape), torch.rand(*shape[1:])
    dirs = [(0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (-1, -1), (1, -1), (-1, 1)]
    ref = sum(_sgm_reference(c, g, 0.1, 0.7, 0.2, dy, dx) for dy, dx in dirs) / len(dirs)
    assert torch.allclose(sgm_aggregate(c, g, 0.1, 0.7, 0.2, 8), ref, atol=1e-5)


def test_calibrated_temperature():
    cost = torch.rand(32, 10, 10)
    T = calibrate_temperature(cost, 4.0)
    gap = (cost.median(0).values - cost.min(0).values).median()
    assert T == pytest.approx(float(gap) / (math.log(32) + 4.0), rel=1e-5)
    assert calibrate_temperature(torch.zeros(8, 3, 3), 2.0) > 0


def test_crop_to_masks_runs_stages_2_3_in_the_mask_box_only(sphere_run, monkeypatch):
    """crop_to_masks: stages 2-3 cost only the box around the dilated object mask; the depth
    there is the full run's (the same hypotheses, a little less context for the aggregation),
    outside it depth and confidence are 0; stage 1 is not cropped."""
    import dataclasses

    scene, gt, mask, full = sphere_run
    masked = dataclasses.replace(scene, masks=mask[:, None].float())
    bb = PlaneSweepBackbone(crop_to_masks=4)
    shapes = []
    real = bb._cost_volume

    def spy(k, ref, g, P_ref, sources, depths):
        shapes.append((k, tuple(depths.shape[1:])))
        return real(k, ref, g, P_ref, sources, depths)

    monkeypatch.setattr(bb, "_cost_volume", spy)
    res = run_cascade(bb, masked)
    for k, (h, w) in shapes:
        H, W = res[k][0].depth.shape
        assert (h, w) == (H, W) if k == 1 else h * w < H * W, (k, h, w, H, W)
    for i in range(3):
        v3, f3 = res[3][i], full[3][i]
        H, W = v3.depth.shape
        m = F.interpolate(mask[i][None, None].float(), size=(H, W), mode="nearest")[0, 0] > 0
        ys, xs = m.nonzero(as_tuple=True)
        s = W // mask.shape[-1]  # stage 3 at the MVS scale (2x here)
        yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
        far = (xx < int(xs.min()) - 5 * s) | (xx > int(xs.max()) + 5 * s) | \
            (yy < int(ys.min()) - 5 * s) | (yy > int(ys.max()) + 5 * s)
        assert (v3.depth[far] == 0).all() and (v3.confidence[far] == 0).all()
        assert far.any() and v3.depth.shape == f3.depth.shape
        d = (v3.depth - f3.depth).abs()[m]
        assert float(d.median()) < 0.002 * (RANGE[1] - RANGE[0])
        assert _median_error(v3, gt[i], mask[i]) < 0.015
