"""Tests for svolsdf.fusion.filter on an analytic sphere seen by three cameras (the
reprojection check and the mask helpers it uses: tests/geometry)."""

from __future__ import annotations

import pytest
import torch
from fusion_synth import CENTER, RADIUS, look_at_camera, sphere_depth, three_cameras

from svolsdf.fusion.filter import FusionFilterConfig, fuse_depth_maps
from svolsdf.geometry.masks import dilate_mask, mask_to_depth_resolution
from svolsdf.geometry.reproject import check_geometric_consistency


def test_fusion_points_lie_on_the_sphere():
    cams = three_cameras()
    depths = {v: sphere_depth(c).float() for v, c in cams.items()}
    images = {v: torch.full((3, 40, 48), 0.25 * (v + 1)) for v in cams}
    out = fuse_depth_maps(depths, cams, images, cfg=FusionFilterConfig(estimate_normals=True))
    pts, cols, nrm, stats = out
    assert pts.shape[1] == 3 and pts.shape[0] > 1500
    r = (pts.double() - CENTER).norm(dim=-1)
    # The filter admits 1 % depth disagreement (~0.03 here), the average halves it; most
    # points are far more accurate.
    assert (r - RADIUS).abs().max() < 0.015
    assert (r - RADIUS).abs().median() < 1e-3
    assert cols.dtype == torch.uint8 and cols.shape == pts.shape
    # Colours come from the reference view of each point.
    n0 = stats[0]["points"]
    assert (cols[:n0] == round(0.25 * 255)).all()
    assert set(stats) == {0, 1, 2} and all(0 < s["kept"] <= s["valid"] for s in stats.values())
    # Normals point outwards on the visible sphere (towards the cameras).
    radial = (pts.double() - CENTER) / r[:, None]
    good = nrm.norm(dim=-1) > 0.5
    assert good.float().mean() > 0.8
    assert ((nrm.double()[good] * radial[good]).sum(-1) > 0.9).float().mean() > 0.95


def test_fusion_averages_and_min_consistent():
    cams = three_cameras()
    depths = {v: sphere_depth(c).float() for v, c in cams.items()}
    # View 2's depth is corrupted everywhere: a second consistent view is required -> fewer points
    depths[2] = depths[2] * 1.1
    one = fuse_depth_maps(depths, cams, cfg=FusionFilterConfig(min_views=1))
    two = fuse_depth_maps(depths, cams, cfg=FusionFilterConfig(min_views=2))
    assert one.colors is None and one.normals is None
    assert one.stats[2]["kept"] < 0.01  # (almost) nothing agrees with the corrupted view
    assert two.points.shape[0] < one.points.shape[0]
    assert two.stats[0]["points"] == 0  # view 0 can have at most one consistent source now


def test_fusion_depth_is_the_average_of_consistent_depths():
    cams = three_cameras()
    depths = {v: sphere_depth(c).float() for v, c in cams.items()}
    depths[1] = depths[1] * 1.004  # a bias inside the 1 % tolerance
    out = fuse_depth_maps(depths, cams)
    d0 = depths[0]
    num = d0.double().clone()
    cnt = torch.ones_like(num)
    for s in (1, 2):
        m, r, _ = check_geometric_consistency(d0, cams[0], depths[s], cams[s])
        num += torch.where(m, r.double(), torch.zeros_like(num))
        cnt += m.double()
    expected = (num / cnt)[cnt > 1]
    n0 = out.stats[0]["points"]
    assert n0 == int((cnt > 1).sum())
    _, z = cams[0].project(out.points[:n0].double())
    torch.testing.assert_close(z[0], expected, rtol=1e-5, atol=0)
    # The average moved the depths of view 0 towards the biased view 1 somewhere.
    assert (z[0] > d0.double()[cnt > 1] * 1.0005).any()


def test_fusion_confidence_and_masks():
    cams = three_cameras()
    depths = {v: sphere_depth(c).float() for v, c in cams.items()}
    conf = {v: torch.ones(40, 48) for v in cams}
    conf[0][:, :24] = 0.2
    out = fuse_depth_maps(depths, cams, confidences=conf, cfg=FusionFilterConfig(conf=0.5))
    ref = fuse_depth_maps(depths, cams)
    assert 0 < out.stats[0]["points"] < ref.stats[0]["points"]
    # Masks at twice the depth resolution, covering only a small square of view 0.
    masks = {v: torch.ones(80, 96) for v in cams}
    masks[0] = torch.zeros(80, 96)
    masks[0][36:44, 44:52] = 1
    cfg = FusionFilterConfig(mask_dilation=4)
    mo = fuse_depth_maps(depths, cams, masks=masks, cfg=cfg)
    keep0 = mask_to_depth_resolution(dilate_mask(masks[0], 4), 40, 48)
    assert mo.stats[0]["points"] <= int(keep0.sum())
    assert 0 < mo.stats[0]["points"]
    off = fuse_depth_maps(depths, cams, masks=masks, cfg=FusionFilterConfig(use_masks=False))
    assert off.stats[0]["points"] == ref.stats[0]["points"]


def test_fusion_needs_two_depth_maps():
    with pytest.raises(ValueError, match="two depth maps"):
        fuse_depth_maps({0: torch.ones(4, 4)}, {0: look_at_camera((0, 0, -4.0))})


def test_fusion_surface_counts_as_one_source():
    """A pixel whose only support is the optimized surface's depth survives with the surface
    option, keeps its own depth, and a depth off the surface does not."""
    cams = three_cameras()
    depths = {v: sphere_depth(c).float() for v, c in cams.items()}
    depths[0] = depths[0] * (1 + 1e-4)  # near the surface, but its own estimate
    depths[1] = depths[1] * 1.1  # views 1 and 2 fail everywhere: no MVS support for view 0
    depths[2] = depths[2] * 0.9
    surface = {v: sphere_depth(c).float() for v, c in cams.items()}
    plain = fuse_depth_maps(depths, cams)
    assert plain.stats[0]["points"] == 0
    cfg = FusionFilterConfig(surface=0.002)
    out = fuse_depth_maps(depths, cams, cfg=cfg, surface_depths=surface)
    n0 = out.stats[0]["points"]
    valid0 = int((depths[0] > 0).sum())
    assert n0 == valid0 and out.stats[0]["surface_only"] == pytest.approx(valid0 / (40 * 48))
    _, z = cams[0].project(out.points[:n0].double())
    torch.testing.assert_close(z[0].float(), depths[0][depths[0] > 0], rtol=1e-5, atol=0)
    # views 1 and 2 are 10 % off the surface: rejected
    assert out.stats[1]["points"] == 0 and out.stats[2]["points"] == 0
    # off by default, and the surface option needs every view
    assert fuse_depth_maps(depths, cams, surface_depths=surface).stats[0]["points"] == 0
    with pytest.raises(ValueError, match="surface_depths"):
        fuse_depth_maps(depths, cams, cfg=cfg, surface_depths={0: surface[0]})
    # a surface at another size is resized (nearest) to each depth map's: twice the size,
    # each pixel repeated, gives back the same points
    big = {v: s.repeat_interleave(2, 0).repeat_interleave(2, 1) for v, s in surface.items()}
    out2 = fuse_depth_maps(depths, cams, cfg=cfg, surface_depths=big)
    assert torch.equal(out2.points, out.points)


def test_a_depth_map_is_not_its_own_consistent_source():
    """Issue 38: VolSDF's fused depth is its rendered surface; with that map as the surface
    every valid pixel passed. A map equal to its surface gets no support from it, so a pixel
    that only one view sees is dropped, and the multi-view check decides as for any map."""
    cams = three_cameras()
    depths = {v: sphere_depth(c).float() for v, c in cams.items()}
    cfg = FusionFilterConfig(surface=5e-4, min_views=1)
    alone = {0: depths[0], 1: torch.zeros_like(depths[1]), 2: torch.zeros_like(depths[2])}
    out = fuse_depth_maps(alone, cams, cfg=cfg, surface_depths=alone)
    assert out.stats[0]["points"] == 0 and out.stats[0]["surface_only"] == 0
    # seen by the other views too: the same pixels pass on their multi-view support alone
    both = fuse_depth_maps(depths, cams, cfg=cfg, surface_depths=depths)
    ref = fuse_depth_maps(depths, cams, cfg=cfg)
    assert torch.equal(both.points, ref.points) and both.stats[0]["points"] > 0
    # a network hypothesis that echoes its surface gets no support from it either
    extra = fuse_depth_maps(alone, cams, cfg=cfg, surface_depths=alone,
                            extra_depths={"echo": alone})
    assert extra.stats["0:echo"]["points"] == 0


def test_guided_and_unguided_dilation_narrow_only_their_hypothesis():
    """guided_dilation: the references of ``depths`` are kept inside masks dilated by it,
    those of ``alt_depths`` inside masks dilated by mask_dilation (or unguided_dilation), each
    exactly the pixels of its own dilated mask (every depth is exact, so the geometry keeps
    them all); with guided_depths False ``depths`` take unguided_dilation too."""
    cams = three_cameras()
    exact = {v: sphere_depth(c).float() for v, c in cams.items()}
    masks = {v: torch.zeros(40, 48) for v in cams}
    for m in masks.values():
        m[18:22, 22:26] = 1  # a small square in the middle of the sphere in every view
    both = {v: d.clone() for v, d in exact.items()}
    cfg = FusionFilterConfig(mask_dilation=6, guided_dilation=1)
    out = fuse_depth_maps(exact, cams, masks=masks, cfg=cfg, alt_depths=both)
    for v in cams:
        wide = dilate_mask(masks[v], 6) & (exact[v] > 0)
        narrow = dilate_mask(masks[v], 1) & (exact[v] > 0)
        assert out.stats[v]["points"] == int(narrow.sum())  # the first hypothesis: 1 px
        assert out.stats[f"{v}:alt"]["points"] == int(wide.sum())  # the second: 6 px
        assert int(narrow.sum()) < int(wide.sum())
    # None (the default) dilates every reference alike, as released
    same = fuse_depth_maps(exact, cams, masks=masks, cfg=FusionFilterConfig(mask_dilation=6),
                           alt_depths=both)
    assert all(same.stats[v]["points"] == same.stats[f"{v}:alt"]["points"] for v in cams)
    # unguided_dilation narrows the second hypothesis alone
    cfg = FusionFilterConfig(mask_dilation=6, unguided_dilation=1)
    out = fuse_depth_maps(exact, cams, masks=masks, cfg=cfg, alt_depths=both)
    for v in cams:
        wide = dilate_mask(masks[v], 6) & (exact[v] > 0)
        narrow = dilate_mask(masks[v], 1) & (exact[v] > 0)
        assert out.stats[v]["points"] == int(wide.sum())
        assert out.stats[f"{v}:alt"]["points"] == int(narrow.sum())
    # ... and the first too when it is the MVS cascade's alone (mvs-only)
    cfg = FusionFilterConfig(mask_dilation=6, guided_dilation=3, unguided_dilation=1,
                             guided_depths=False)
    out = fuse_depth_maps(exact, cams, masks=masks, cfg=cfg)
    for v in cams:
        assert out.stats[v]["points"] == int((dilate_mask(masks[v], 1) & (exact[v] > 0)).sum())


def test_filter_from_the_fusion_section():
    """from_config: the filter reads the options of the fusion section under their names."""
    from svolsdf.config import FusionConfig

    f = FusionConfig(dist=0.5, rel=0.02, min_views=2, conf=0.1, surface=0.003,
                     guided_dilation=4, unguided_dilation=2)
    cfg = FusionFilterConfig.from_config(f, use_masks=False, guided_depths=False)
    assert (cfg.dist, cfg.rel, cfg.min_views, cfg.conf, cfg.surface) == (0.5, 0.02, 2, 0.1, 0.003)
    assert (cfg.guided_dilation, cfg.unguided_dilation) == (4, 2)
    assert (cfg.use_masks, cfg.guided_depths, cfg.mask_dilation) == (False, False, 12)
    # a field given instead of an option is taken, the option not read
    assert FusionFilterConfig.from_config(f, guided_dilation=None).guided_dilation is None


def test_fusion_extra_hypotheses_per_view():
    """extra_depths: a named third set is a reference too, a source agrees through it, and it
    takes the primary (guided) mask dilation."""
    cams = three_cameras()
    exact = {v: sphere_depth(c).float() for v, c in cams.items()}
    none = {v: torch.zeros_like(d) for v, d in exact.items()}
    first = {0: exact[0].clone(), 1: none[1], 2: none[2]}
    alt = {v: none[v] for v in cams}
    net = {0: none[0], 1: none[1], 2: exact[2].clone()}  # only view 2 has the third set
    two = fuse_depth_maps(first, cams, alt_depths=alt)
    assert two.points.shape[0] == 0
    out = fuse_depth_maps(first, cams, alt_depths=alt, extra_depths={"net": net})
    assert set(out.stats) == {0, 1, 2, "0:alt", "1:alt", "2:alt", "0:net", "1:net", "2:net"}
    assert out.stats[0]["points"] > 50 and out.stats["2:net"]["points"] > 50
    assert out.points.shape[0] == sum(s["points"] for s in out.stats.values())
    # its references take the primary dilation, as the first set's
    masks = {v: torch.zeros(40, 48) for v in cams}
    for m in masks.values():
        m[18:22, 22:26] = 1
    cfg = FusionFilterConfig(mask_dilation=6, guided_dilation=1)
    full = {v: d.clone() for v, d in exact.items()}
    out = fuse_depth_maps(full, cams, masks=masks, cfg=cfg, alt_depths=full,
                          extra_depths={"net": full})
    for v in cams:
        assert out.stats[f"{v}:net"]["points"] == out.stats[v]["points"]
        assert out.stats[f"{v}:net"]["points"] < out.stats[f"{v}:alt"]["points"]
    with pytest.raises(ValueError, match="extra_confidences"):
        fuse_depth_maps(first, cams, confidences={v: torch.ones(40, 48) for v in cams},
                        extra_depths={"net": net})
    with pytest.raises(ValueError, match="extra_depths"):
        fuse_depth_maps(first, cams, extra_depths={"net": {0: net[0]}})


def test_fusion_second_hypothesis_per_view():
    """alt_depths: each view's second depth map is a reference too, and a source view agrees
    when either of its maps does (counted once)."""
    cams = three_cameras()
    exact = {v: sphere_depth(c).float() for v, c in cams.items()}
    # first maps: view 0 right on its left half only (no depth elsewhere), views 1 and 2 empty
    none = {v: torch.zeros_like(d) for v, d in exact.items()}
    first = {0: exact[0].clone(), 1: none[1], 2: none[2]}
    first[0][:, 24:] = 0
    # second maps: view 1 right, views 0 and 2 empty
    alt = {0: none[0], 1: exact[1].clone(), 2: none[2]}
    plain = fuse_depth_maps(first, cams)
    assert plain.points.shape[0] == 0  # no two first maps overlap
    out = fuse_depth_maps(first, cams, alt_depths=alt)
    assert set(out.stats) == {0, 1, 2, "0:alt", "1:alt", "2:alt"}
    # view 0's first map agrees with view 1's second on its left half, not its right
    assert out.stats[0]["points"] > 50
    n0 = out.stats[0]["points"]
    u, _ = cams[0].project(out.points[:n0].double())
    assert (u[0, :, 0] < 24.5).all()
    # view 1's second map is the reference too and agrees with view 0's first
    assert out.stats["1:alt"]["points"] > 50
    assert out.stats[2]["points"] == 0 and out.stats["2:alt"]["points"] == 0
    assert out.points.shape[0] == sum(s["points"] for s in out.stats.values())
    # a source view counts once: with min_views 2, view 1's second map needs views 0 and 2
    two = fuse_depth_maps(first, cams, alt_depths=alt, cfg=FusionFilterConfig(min_views=2))
    assert two.stats["1:alt"]["points"] == 0
    with pytest.raises(ValueError, match="alt_confidences"):
        fuse_depth_maps(first, cams, confidences={v: torch.ones(40, 48) for v in cams},
                        alt_depths=alt)


def test_checking_only_the_kept_pixels_keeps_the_same_points(monkeypatch):
    """The sources are checked only at the pixels the confidence and the mask keep: the fused
    points (positions, colours, order) are those of checking every pixel."""
    import svolsdf.fusion.filter as filt

    cams = three_cameras()
    g = torch.Generator().manual_seed(2)
    depths = {v: (sphere_depth(c) * (1 + 0.004 * torch.randn(40, 48, generator=g,
                                                              dtype=torch.float64))).float()
              for v, c in cams.items()}
    conf = {v: torch.rand(40, 48, generator=g) for v in cams}
    masks = {v: torch.zeros(80, 96) for v in cams}
    for v in cams:
        masks[v][20:60, 30:70] = 1
    images = {v: torch.rand(3, 40, 48, generator=g) for v in cams}
    cfg = FusionFilterConfig(conf=0.3, mask_dilation=2, surface=0.01)
    kw = dict(images=images, confidences=conf, masks=masks, cfg=cfg,
              surface_depths={v: d * 1.001 for v, d in depths.items()})
    fast = fuse_depth_maps(depths, cams, **kw)
    every = []

    def full_check(*a, pixels=None, **k):
        every.append(pixels)
        return check_geometric_consistency(*a, **k)

    monkeypatch.setattr(filt, "check_geometric_consistency", full_check)
    slow = fuse_depth_maps(depths, cams, **kw)
    assert all(p is not None for p in every)  # the fast run did choose pixels
    assert 0 < len(fast.points) and torch.equal(fast.points, slow.points)
    assert torch.equal(fast.colors, slow.colors)
    assert fast.stats == slow.stats
