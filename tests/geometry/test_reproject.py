"""The forward-backward reprojection check of depth maps (svolsdf.geometry.reproject) on an
analytic sphere seen by three cameras."""

from __future__ import annotations

import torch
from scipy import ndimage
from tests.fusion.fusion_synth import sphere_depth, three_cameras

from svolsdf.geometry.reproject import (
    check_geometric_consistency,
    check_geometric_consistency_reference,
)


def test_consistency_accepts_exact_and_rejects_perturbed():
    cams = three_cameras()
    d0, d1 = sphere_depth(cams[0]), sphere_depth(cams[1])
    mask, d_rep, (xs, ys) = check_geometric_consistency(d0, cams[0], d1, cams[1])
    assert mask.shape == d0.shape and mask.dtype == torch.bool
    # Exact depths: the pixels that are not near the silhouette are consistent.
    interior = torch.from_numpy(ndimage.binary_erosion((d0 > 0).numpy(), iterations=4))
    vis = interior & (xs > 1) & (xs < 46) & (ys > 1) & (ys < 38)
    assert vis.sum() > 200
    assert mask[vis].float().mean() > 0.97
    # Bilinear sampling of a sphere at ~28 px radius: < 0.5 % depth error inside the disk.
    torch.testing.assert_close(d_rep[mask & vis], d0[mask & vis], rtol=5e-3, atol=0)
    # No depth -> never consistent.
    assert not mask[d0 <= 0].any()
    # Perturb a block of the reference depth by +5 %: rejected (relative test).
    d0p = d0.clone()
    d0p[15:25, 18:28] *= 1.05
    mp, _, _ = check_geometric_consistency(d0p, cams[0], d1, cams[1])
    assert not mp[15:25, 18:28].any()
    # Perturb the source instead: the reprojection lands elsewhere / depth disagrees.
    d1p = d1.clone()
    d1p[10:30, 10:38] *= 0.9
    ms, _, (xs2, ys2) = check_geometric_consistency(d0, cams[0], d1p, cams[1])
    hit = (xs2 > 11) & (xs2 < 36) & (ys2 > 11) & (ys2 < 28) & vis
    assert hit.sum() > 50
    assert not ms[hit].any()


def test_consistency_rejects_out_of_source_image():
    cams = three_cameras()
    d0 = sphere_depth(cams[0])
    d1 = sphere_depth(cams[1])[:, :20].contiguous()  # a source that only sees its left part
    cam1 = cams[1].crop(0, 0, 20, 40)
    mask, d_rep, (xs, ys) = check_geometric_consistency(d0, cams[0], d1, cam1)
    assert not mask[xs > 19.0].any()
    assert (d_rep[xs > 19.5] == 0).all()


def test_vectorized_matches_reference():
    cams = three_cameras()
    g = torch.Generator().manual_seed(3)
    d0 = sphere_depth(cams[0])
    d1 = sphere_depth(cams[1])
    # Noise of ~1 % so that both outcomes of the tests occur, plus holes.
    d0 = d0 * (1 + 0.01 * torch.randn(d0.shape, generator=g, dtype=d0.dtype))
    d1 = d1 * (1 + 0.005 * torch.randn(d1.shape, generator=g, dtype=d1.dtype))
    d1[5:9, 20:26] = 0
    d0, d1 = d0.float(), d1.float()
    cam1 = cams[1].resize(36, 30)  # a source at another resolution
    d1 = torch.nn.functional.interpolate(d1[None, None], size=(30, 36), mode="nearest")[0, 0]
    m, r, (x, y) = check_geometric_consistency(d0, cams[0], d1, cam1, 1.0, 0.01)
    mr, rr, (xr, yr) = check_geometric_consistency_reference(d0, cams[0], d1, cam1, 1.0, 0.01)
    torch.testing.assert_close(x, xr, atol=1e-4, rtol=0)
    torch.testing.assert_close(y, yr, atol=1e-4, rtol=0)
    # Decisions may only differ where a quantity sits at its threshold.
    assert (m != mr).sum() <= 1
    assert m.sum() > 50 and (~m & (d0 > 0)).sum() > 50
    both = m & mr
    torch.testing.assert_close(r[both], rr[both], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close((r > 0), (rr > 0))


def test_chosen_pixels_get_the_full_checks_values():
    """pixels=: the checked pixels get exactly the full image check's mask, reprojected depth
    and source coordinates; the others False, 0 and NaN."""
    cams = three_cameras()
    g = torch.Generator().manual_seed(5)
    d0 = (sphere_depth(cams[0]) * (1 + 0.01 * torch.randn(40, 48, generator=g,
                                                           dtype=torch.float64))).float()
    d1 = sphere_depth(cams[1]).float()
    cam0 = cams[0].resize(24, 20)  # a reference depth at another size than its camera
    d0 = torch.nn.functional.interpolate(d0[None, None], size=(20, 24), mode="nearest")[0, 0]
    full = check_geometric_consistency(d0, cam0, d1, cams[1])
    pix = torch.randperm(20 * 24, generator=g)[:150]
    part = check_geometric_consistency(d0, cam0, d1, cams[1], pixels=pix)
    chosen = torch.zeros(20 * 24, dtype=torch.bool)
    chosen[pix] = True
    chosen = chosen.reshape(20, 24)
    assert full[0][chosen].any() and (~full[0][chosen]).any()
    assert torch.equal(part[0][chosen], full[0][chosen]) and not part[0][~chosen].any()
    assert torch.equal(part[1][chosen], full[1][chosen]) and (part[1][~chosen] == 0).all()
    for a, b in zip(part[2], full[2], strict=True):
        assert torch.equal(a[chosen], b[chosen]) and a[~chosen].isnan().all()
