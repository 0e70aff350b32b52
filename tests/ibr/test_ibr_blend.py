"""Tests for svolsdf.ibr.blend: IBR on an analytic textured plane (docs/method.md 7)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from ibr_synth import look_at_camera, psnr, render, render_all, stack_cameras
from scipy import ndimage

from svolsdf.ibr import (
    IBRConfig,
    erode,
    fill_candidates,
    ibr_render,
    laplacian_blend,
    push_pull_fill,
    view_softmax_weights,
    warp_sources,
)

SRC_EYES = [(1.3, 0.1, -2.8), (-1.1, 0.4, -2.9), (0.1, -1.2, -2.9)]
# a small red sphere a third of the way from source 0 to the plane, outside the target's view
OCCLUDER = [((1.3 * 0.7, 0.1 * 0.7, -2.8 * 0.7), 0.12)]


@pytest.fixture(scope="module")
def scene():
    tgt = look_at_camera((0.3, -0.2, -3.0))
    # wider sources (f = 45 < 60) so that they cover the whole target view
    srcs = stack_cameras([look_at_camera(e, f=45.0) for e in SRC_EYES])
    img_t, d_t = render(tgt)
    imgs, ds = render_all(srcs)
    return tgt, img_t, d_t, srcs, imgs, ds


def test_held_out_view_high_psnr(scene):
    tgt, img_t, d_t, srcs, imgs, ds = scene
    grey = torch.full_like(img_t, 0.5)  # a wrong fallback: the colour must come from the sources
    r = ibr_render(tgt, d_t, grey, imgs, srcs, ds)
    assert r.rgb.shape == (3, 48, 64) and r.valid.shape == (3, 48, 64)
    assert bool((r.n_valid == 3).all())  # exact depths: every source consistent everywhere
    assert torch.allclose(r.weight_sum, torch.ones_like(r.weight_sum), atol=1e-5)
    assert psnr(r.rgb, img_t) > 40.0
    assert psnr(r.composite, img_t) > 40.0
    assert psnr(grey, img_t) < 15.0


def test_released_config_with_good_fallback(scene):
    tgt, img_t, d_t, srcs, imgs, ds = scene
    # The released fill (c W + rendered (1 - W)) leans on the rendered colour; with a rendered
    # colour that is right up to noise the blend must still be close to the truth.
    noisy = (img_t + 0.05 * torch.randn_like(img_t)).clamp(0, 1)
    r = ibr_render(tgt, d_t, noisy, imgs, srcs, ds, IBRConfig.released())
    assert psnr(r.rgb, img_t) > psnr(noisy, img_t) + 3.0
    assert psnr(r.rgb, img_t) > 30.0


def test_occluded_source_is_rejected(scene):
    tgt, img_t, d_t, srcs, _, _ = scene
    imgs, ds = render_all(srcs, OCCLUDER)
    img_t2, _ = render(tgt, OCCLUDER)
    assert torch.equal(img_t2, img_t)  # the sphere is outside the target's view
    grey = torch.full_like(img_t, 0.5)

    r = ibr_render(tgt, d_t, grey, imgs, srcs, ds)
    # Ground truth of the occlusion: the segment from source 0's centre to the target pixel's
    # plane point hits the sphere.
    uv = tgt.pixel_grid(dtype=torch.float64).reshape(1, -1, 2)
    x = tgt.unproject(uv, d_t.double().reshape(1, -1))[0]
    c0 = srcs.centers[0]
    centre = torch.tensor(OCCLUDER[0][0], dtype=torch.float64)
    seg = x - c0
    s = ((centre - c0) @ seg.T / (seg * seg).sum(-1)).clamp(0, 1)
    closest = c0 + s[:, None] * seg
    dist = (closest - centre).norm(dim=-1).reshape(48, 64)
    hidden = dist < OCCLUDER[0][1] - 0.02
    seen = dist > OCCLUDER[0][1] + 0.05
    assert int(hidden.sum()) > 50
    assert not bool(r.valid[0][hidden].any())
    assert float(r.valid[0][seen].float().mean()) > 0.98
    assert bool(r.valid[1:].all())
    assert psnr(r.rgb, img_t) > 38.0

    # without the check the red sphere leaks into the target
    loose = ibr_render(tgt, d_t, grey, imgs, srcs, ds, IBRConfig(dist_thresh=1e9, rel_thresh=1e9))
    assert bool(loose.valid[0][hidden].all())
    assert psnr(loose.rgb, img_t) < psnr(r.rgb, img_t) - 10.0


def test_corrupted_depth_is_rejected(scene):
    tgt, img_t, d_t, srcs, imgs, ds = scene
    ds = ds.clone()
    imgs = imgs.clone()
    ds[1, :, :32] *= 1.03  # 3 % depth error on the left half of source 1: inconsistent
    imgs[1, :, :, :32] = torch.tensor([0.0, 1.0, 0.0])[:, None, None]
    r = ibr_render(tgt, d_t, torch.zeros_like(img_t), imgs, srcs, ds)
    _, _, (xs, _) = _projection_into(tgt, d_t, srcs, 1)
    assert not bool(r.valid[1][xs < 31].any())
    assert float(r.valid[1][xs > 33].float().mean()) > 0.99
    assert psnr(r.rgb, img_t) > 38.0


def _projection_into(tgt, d_t, srcs, j):
    from svolsdf.geometry.reproject import check_geometric_consistency

    return check_geometric_consistency(d_t, tgt, torch.ones(48, 64), srcs[j])


def test_invalid_target_depth_uses_fallback(scene):
    tgt, img_t, d_t, srcs, imgs, ds = scene
    d = d_t.clone()
    d[10:40, 20:50] = 0.0  # no surface here: the rendered colour must be used
    fb = torch.full_like(img_t, 0.25)
    r = ibr_render(tgt, d, fb, imgs, srcs, ds)
    hole = torch.zeros(48, 64, dtype=torch.bool)
    hole[10:40, 20:50] = True
    assert bool((r.n_valid[hole] == 0).all())
    assert torch.all(r.weight_sum[hole] == 0)
    assert torch.allclose(r.composite[:, hole], fb[:, hole])
    inner = torch.zeros_like(hole)
    inner[18:32, 28:42] = True  # > 8 px (one coarse pyramid cell) inside the hole
    # the coarse pyramid levels spread the seam over a few pixels: close, not exact
    assert torch.allclose(r.rgb[:, inner], fb[:, inner], atol=0.06)
    assert float((r.rgb[:, inner] - fb[:, inner]).abs().mean()) < 0.03
    far = torch.zeros_like(hole)
    far[:, :4] = True
    assert psnr(r.rgb, img_t, far) > 35.0


def test_softmax_weights_known_values():
    cos = torch.tensor([1.0, 0.9, 0.5]).reshape(3, 1, 1)
    valid = torch.tensor([True, True, False]).reshape(3, 1, 1)
    w, wr = view_softmax_weights(cos, valid, IBRConfig())
    e = math.exp(-20 * 0.1)
    assert torch.allclose(w[:, 0, 0], torch.tensor([1 / (1 + e), e / (1 + e), 0.0]), atol=1e-6)
    assert float(wr) == 0.0

    # no consistent source: all weight on the rendered colour (paper)
    w, wr = view_softmax_weights(cos, torch.zeros_like(valid), IBRConfig())
    assert float(w.abs().sum()) == 0.0 and float(wr) == 1.0

    # released: rendered colour scores 0.2, inconsistent sources score 0 (docs/method.md 7 step 4)
    w, wr = view_softmax_weights(cos, torch.zeros_like(valid), IBRConfig.released())
    assert math.isclose(float(wr), math.exp(4) / (3 + math.exp(4)), rel_tol=1e-5)
    assert torch.allclose(w[:, 0, 0], torch.full((3,), 1 / (3 + math.exp(4))), atol=1e-6)
    w, wr = view_softmax_weights(cos, valid, IBRConfig.released())
    z = math.exp(20) + math.exp(18) + 1 + math.exp(4)
    ref = torch.tensor([math.exp(20), math.exp(18), 1.0]) / z
    assert torch.allclose(w[:, 0, 0], ref, rtol=1e-5)
    assert math.isclose(float(wr), math.exp(4) / z, rel_tol=1e-4)


def test_weights_favour_closest_direction():
    tgt = look_at_camera((1.0, 0.2, -2.9))  # close to source 0's direction
    srcs = stack_cameras([look_at_camera(e, f=45.0) for e in SRC_EYES])
    img_t, d_t = render(tgt)
    imgs, ds = render_all(srcs)
    colours, valid, cos = warp_sources(tgt, d_t, imgs, srcs, ds)
    full = valid.all(0)
    assert float(full.float().mean()) > 0.8
    assert bool((cos[0] > cos[1]).all()) and bool((cos[0] > cos[2]).all())
    w, wr = view_softmax_weights(cos, valid)
    assert bool((w[0][full] > 0.5).all())
    assert bool((w[0][full] > w[1][full]).all()) and bool((w[0][full] > w[2][full]).all())
    assert torch.allclose(w.sum(0) + wr, torch.ones(48, 64), atol=1e-6)
    # the cosine is the one between the rays to the 3D point: check one pixel by hand
    uv = torch.tensor([[[10.0, 30.0]]], dtype=torch.float64)
    x = tgt.unproject(uv, d_t[30, 10].double().reshape(1, 1))[0, 0]
    a = (x - tgt.centers[0]) / (x - tgt.centers[0]).norm()
    b = (x - srcs.centers[2]) / (x - srcs.centers[2]).norm()
    assert math.isclose(float(cos[2, 30, 10]), float(a @ b), abs_tol=1e-6)


def test_warped_colours_match_truth(scene):
    tgt, img_t, d_t, srcs, imgs, ds = scene
    for interp in ("bilinear", "bicubic"):
        colours, valid, _ = warp_sources(tgt, d_t, imgs, srcs, ds, IBRConfig(colour_interp=interp))
        for j in range(3):
            assert psnr(colours[j], img_t) > 35.0


def test_fill_candidates_modes():
    V, H, W = 2, 3, 4
    c = torch.rand(V, 3, H, W)
    valid = torch.rand(V, H, W) > 0.5
    w = torch.rand(V, H, W)
    rend = torch.rand(3, H, W)
    out = fill_candidates(c, valid, w, rend, IBRConfig())
    assert torch.equal(out[valid[:, None].expand_as(c)], c[valid[:, None].expand_as(c)])
    inv = ~valid[0]
    assert torch.equal(out[0][:, inv], rend[:, inv])
    out = fill_candidates(c, valid, w, rend, IBRConfig.released())
    assert torch.allclose(out, c * w[:, None] + rend[None] * (1 - w[:, None]))


def test_erode_matches_scipy():
    m = torch.rand(2, 23, 31) > 0.2
    for size in (3, 5):
        ref = np.stack([
            ndimage.binary_erosion(mi, structure=np.ones((size, size)), border_value=1)
            for mi in m.numpy()
        ])
        assert np.array_equal(erode(m, size).numpy(), ref)
    assert torch.equal(erode(m, 1), m)


@pytest.mark.parametrize("shape", [(48, 64), (37, 29)])
def test_laplacian_blend_of_identical_images_is_identity(shape):
    img = torch.rand(3, *shape, dtype=torch.float64)
    masks = torch.rand(4, *shape, dtype=torch.float64)
    out = laplacian_blend(img[None].expand(4, -1, -1, -1), masks, levels=4)
    assert out.shape == img.shape
    assert torch.allclose(out, img, atol=1e-10)


def test_laplacian_blend_single_level_is_weighted_sum():
    imgs = torch.rand(3, 3, 20, 24, dtype=torch.float64)
    masks = torch.rand(3, 20, 24, dtype=torch.float64)
    out = laplacian_blend(imgs, masks, levels=1)
    m = masks / masks.sum(0)
    assert torch.allclose(out, (m[:, None] * imgs).sum(0))


def test_laplacian_blend_smooths_seams():
    H, W = 32, 64
    a = torch.zeros(1, H, W, dtype=torch.float64)
    b = torch.ones(1, H, W, dtype=torch.float64)
    left = torch.zeros(H, W, dtype=torch.float64)
    left[:, :32] = 1
    out = laplacian_blend(torch.stack([a, b]), torch.stack([left, 1 - left]), levels=4)
    row = out[0, H // 2]
    hard = (1 - left)[H // 2]
    # far from the seam the images are untouched; at the seam the step is spread over pixels
    assert torch.allclose(row[:4], hard[:4], atol=1e-3)
    assert torch.allclose(row[-4:], hard[-4:], atol=1e-3)
    assert float((row[1:] - row[:-1]).abs().max()) < 0.5
    assert bool(((row > 0.05) & (row < 0.95)).sum() >= 4)
    # a detail present only in image a survives where a's mask is 1
    a2 = a.clone()
    a2[0, 10:12, 10:12] = 1.0
    out2 = laplacian_blend(torch.stack([a2, b]), torch.stack([left, 1 - left]), levels=4)
    assert float(out2[0, 10:12, 10:12].min()) > 0.9


def test_input_checks(scene):
    tgt, img_t, d_t, srcs, imgs, ds = scene
    with pytest.raises(ValueError, match="target_depth"):
        ibr_render(tgt, d_t[:-1], img_t, imgs, srcs, ds)
    with pytest.raises(ValueError, match="src_images"):
        ibr_render(tgt, d_t, img_t, imgs[:2], srcs, ds)
    with pytest.raises(ValueError, match="fallback"):
        IBRConfig(fallback="nope")


def test_released_masks_and_blend_wiring(scene):
    # docs/method.md 7 steps 4-7 written out by hand from the pieces, on a scene with partial
    # validity
    tgt, img_t, d_t, srcs, imgs, ds = scene
    ds = ds.clone()
    ds[0, 10:30, 10:40] *= 1.05
    rend = (img_t * 0.8 + 0.1).clamp(0, 1)
    cfg = IBRConfig.released()
    r = ibr_render(tgt, d_t, rend, imgs, srcs, ds, cfg)
    colours, valid, cos = warp_sources(tgt, d_t, imgs, srcs, ds, cfg)
    assert not bool(valid.all()) and bool(valid.any(0).all())
    w, wr = view_softmax_weights(cos, valid, cfg)
    cand = torch.cat([colours * w[:, None] + rend * (1 - w[:, None]), rend[None]])
    m = torch.cat([erode(w > 0.2, 5).float() * w, (wr + 0.01)[None]])
    m = m / m.sum(0)
    assert torch.allclose(r.composite, (m[:, None] * cand).sum(0).clamp(0, 1), atol=1e-6)
    assert torch.allclose(r.rgb, laplacian_blend(cand, m, 4).clamp(0, 1), atol=1e-6)


def test_source_depths_at_lower_resolution_and_uint8(scene):
    tgt, img_t, d_t, srcs, imgs, _ = scene
    # depths rendered at half resolution with the resized cameras (Cameras.resize convention)
    _, ds_half = render_all(srcs.resize(32, 24))
    imgs_u8 = (imgs * 255).round().to(torch.uint8)
    r = ibr_render(tgt, d_t, torch.full_like(img_t, 0.5), imgs_u8, srcs, ds_half)
    assert float((r.n_valid > 0).float().mean()) > 0.95
    assert psnr(r.rgb, img_t, r.n_valid > 0) > 35.0


def test_push_pull_fill_keeps_known_and_fills_from_neighbours():
    img = torch.zeros(3, 40, 60)
    img[0, :, :30] = 1.0  # red left half, blue right half
    img[2, :, 30:] = 1.0
    known = torch.ones(40, 60, dtype=torch.bool)
    known[10:30, 5:20] = False  # a hole inside the red half
    garbage = torch.where(known[None], img, torch.full_like(img, 0.5))
    out = push_pull_fill(garbage, known, levels=6)
    assert torch.equal(out[:, known], img[:, known])
    hole = ~known
    assert float(out[0, hole].min()) > 0.7  # filled red, mostly from its own side
    assert float(out[2, hole].max()) < 0.3
    const = push_pull_fill(torch.full((3, 40, 60), 0.3) * known, known, levels=6)
    assert torch.allclose(const, torch.full_like(const, 0.3) * 1, atol=1e-6)
    nothing = torch.zeros(40, 60, dtype=torch.bool)  # nothing known: the image unchanged
    assert torch.equal(push_pull_fill(garbage, nothing), garbage)
    with pytest.raises(ValueError):
        push_pull_fill(img, known[:, :10])


def test_unseen_inpaint_replaces_the_render_only_where_no_source_sees(scene):
    tgt, img_t, d_t, srcs, imgs, ds = scene
    d_src = ds
    wrong = torch.zeros_like(img_t)  # a black render: what the field shows where it saw nothing
    # hide a block of the target from every source: corrupt the target depth there (still > 0)
    d = d_t.clone()
    d[16:32, 24:40] *= 1.3
    r_paper = ibr_render(tgt, d, wrong, imgs, srcs, d_src)
    r_fill = ibr_render(tgt, d, wrong, imgs, srcs, d_src, IBRConfig(unseen="inpaint"))
    block = torch.zeros(48, 64, dtype=torch.bool)
    block[16:32, 24:40] = True
    assert bool((r_paper.n_valid[block] == 0).all())
    # paper: the black render shows through; inpaint: the seen colours around the block
    assert psnr(r_fill.rgb, img_t, block) > psnr(r_paper.rgb, img_t, block) + 3.0
    far = torch.zeros_like(block)
    far[:, :6] = True  # seen pixels away from the block are unchanged
    assert torch.allclose(r_fill.rgb[:, far], r_paper.rgb[:, far], atol=1e-5)
    no_surface = d.clone()
    no_surface[16:32, 24:40] = 0.0  # no depth: the render stays, as in the paper
    r_bg = ibr_render(tgt, no_surface, wrong, imgs, srcs, d_src, IBRConfig(unseen="inpaint"))
    assert torch.allclose(r_bg.composite[:, block], wrong[:, block])
    with pytest.raises(ValueError):
        IBRConfig(unseen="nearest")
