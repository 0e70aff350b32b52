"""Soft consistency lookup (docs/method.md 3) against the slow reference and known values."""

from __future__ import annotations

import pytest
import torch

from svolsdf.mvs.volume import ProbabilityVolume
from svolsdf.prior.consistency import MVSPrior, lookup_reference, p_prime
from svolsdf.scene.cameras import Cameras
from svolsdf.scene.scene import Normalization

CENTER = torch.tensor([10.0, -5.0, 3.0], dtype=torch.float64)
SCALE = 50.0


def _look_at(eye, target):
    eye = torch.as_tensor(eye, dtype=torch.float64)
    target = torch.as_tensor(target, dtype=torch.float64)
    z = target - eye
    z = z / z.norm()
    x = torch.linalg.cross(torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64), z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c


def _volumes(inverse=False, D=6, H=7, W=9, seed=0):
    g = torch.Generator().manual_seed(seed)
    vols = []
    for i, ang in enumerate([-0.4, 0.0, 0.5]):
        a = torch.tensor(ang, dtype=torch.float64)
        y = torch.tensor(0.3, dtype=torch.float64)
        eye = CENTER + SCALE * torch.stack([2.2 * a.sin(), y, -2.2 * a.cos()])
        w2c = _look_at(eye, CENTER)
        K = torch.tensor([[8.0, 0.3, 4.1], [0.0, 7.5, 3.2], [0.0, 0.0, 1.0]], dtype=torch.float64)
        cams = Cameras(K[None].float(), w2c[None].float(), W, H)
        near = SCALE * (1.4 + 0.2 * torch.rand(H, W, generator=g))
        far = SCALE * (2.9 + 0.3 * torch.rand(H, W, generator=g))
        t = torch.linspace(0, 1, D)[:, None, None]
        if inverse:
            depths = 1.0 / (1.0 / near + t * (1.0 / far - 1.0 / near))
        else:
            depths = near + t * (far - near)
        prob = torch.rand(D, H, W, generator=g)
        prob = prob / prob.sum(0, keepdim=True)
        vols.append(ProbabilityVolume(depths.float(), prob, (prob * depths).sum(0).float(),
                                      torch.ones(H, W), cams, view_id=i, inverse_depth=inverse))
    return vols


def _points(R=5, S=7, seed=1):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(R, S, 3, generator=g) - 0.5) * 1.6  # unit frame, around the object


@pytest.mark.parametrize("inverse", [False, True])
@pytest.mark.parametrize("quirk", [False, True])
def test_lookup_matches_reference(inverse, quirk):
    vols = _volumes(inverse)
    prior = MVSPrior(vols, Normalization(CENTER, SCALE), align_quirk=quirk)
    pts = _points()
    ref_view = torch.tensor([0, 1, 2, 1, 0])
    a = prior.lookup(pts, ref_view)
    b = lookup_reference(prior, pts, ref_view)
    assert a[2].equal(b[2])
    assert a[2].float().mean() > 0.3  # the test exercises valid points
    assert (a[1] > 0).any() and (a[0] > 0).any()
    assert torch.allclose(a[0], b[0], atol=1e-5)
    assert torch.allclose(a[1], b[1], atol=1e-5)
    assert not a[0].requires_grad


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_lookup_is_the_same_split_over_any_number_of_threads(threads):
    """The volume lookup splits the points into one batch entry per thread (odd counts padded)."""
    prior = MVSPrior(_volumes(), Normalization(CENTER, SCALE))
    pts = _points(R=7, S=5)
    ref_view = torch.tensor([0, 1, 2, 1, 0, 2, 2])
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(threads)
        a = prior.lookup(pts, ref_view)
        empty = prior.view_lookup(0, torch.zeros(0, 3))
    finally:
        torch.set_num_threads(before)
    b = lookup_reference(prior, pts, ref_view)
    assert a[2].equal(b[2]) and (a[0] > 0).any()
    torch.testing.assert_close(a[0], b[0], atol=1e-5, rtol=0)
    torch.testing.assert_close(a[1], b[1], atol=1e-5, rtol=0)
    assert empty[0].shape == (0,) and empty[1].shape == (0,)


def test_lookup_known_value_at_pixel_centre_and_quirk_drift():
    """A point on pixel (u, v)'s ray at hypothesis k's depth reads prob[k, v, u] exactly."""
    vols = _volumes(False)
    norm = Normalization(CENTER, SCALE)
    prior = MVSPrior(vols, norm)
    cams_u = vols[1].cameras.transformed(CENTER, SCALE)
    u, v, k = 7, 4, 3
    depth = vols[1].depths[k, v, u] / SCALE
    x = cams_u.unproject(torch.tensor([[[float(u), float(v)]]]), depth.reshape(1, 1))[0]
    cost, ok = prior.view_lookup(1, x)
    assert ok.item()
    assert cost.item() == pytest.approx(vols[1].prob[k, v, u].item(), abs=1e-5)
    # the released align_corners quirk samples somewhere else (docs/method.md 3, step 3)
    quirk = MVSPrior(vols, norm, align_quirk=True)
    cq, _ = quirk.view_lookup(1, x)
    assert abs(cq.item() - cost.item()) > 1e-4


def test_validity_rules_and_accumulation():
    vols = _volumes(False)
    prior = MVSPrior(vols, Normalization(CENTER, SCALE))
    # behind all cameras / far outside: invalid, zero
    far_pts = torch.full((1, 2, 3), 100.0)
    p_ref, p_src, valid = prior.lookup(far_pts, torch.tensor([0]))
    assert not valid.any() and (p_ref == 0).all() and (p_src == 0).all()
    # accumulation: P_src is the sum of the other views' costs, P_ref the own view's
    pts = _points(2, 4)
    costs = [prior.view_lookup(i, pts.reshape(-1, 3)) for i in range(3)]
    p_ref, p_src, valid = prior.lookup(pts, torch.tensor([2, 2]))
    exp_src = (costs[0][0] + costs[1][0]).reshape(2, 4)
    exp_valid = (costs[0][1] | costs[1][1]).reshape(2, 4)
    assert torch.allclose(p_src, exp_src) and valid.equal(exp_valid)
    assert torch.allclose(p_ref, torch.where(exp_valid, costs[2][0].reshape(2, 4), 0.0))
    assert torch.allclose(p_prime(p_ref, p_src), p_ref * p_src)
    pp, vv = prior.p_prime(pts, torch.tensor([2, 2]))
    assert torch.allclose(pp, p_ref * p_src) and vv.equal(valid)


@pytest.mark.parametrize("ref_view", [[0, 1, 2, 1, 0, 2, 2], [1] * 7])
def test_label_is_lookups_p_prime_and_reads_sources_only_where_p_ref_counts(ref_view):
    """MVSPrior.label: P' = P_ref * sum P_src bit for bit where P_ref > prior_floor (with the
    default 0: everywhere), 0 elsewhere; the source views are read only at those points."""
    vols = _volumes()
    for i, v in enumerate(vols):  # zero stretches, as a volume far from its peak has
        v.prob[:, :, : 3 + i] = 0.0
    prior = MVSPrior(vols, Normalization(CENTER, SCALE))
    pts = _points(R=7, S=40)
    ref = torch.tensor(ref_view)
    p_ref, p_src, _ = prior.lookup(pts, ref)
    exact = p_ref * p_src
    read = []
    view_lookup = prior.view_lookup
    prior.view_lookup = lambda i, q: (read.append(len(q)), view_lookup(i, q))[1]
    assert torch.equal(prior.label(pts, ref), exact)
    zero = int((p_ref == 0).sum())
    assert 0 < zero < p_ref.numel()
    n = p_ref.numel()
    others = 2 if len(set(ref_view)) == 1 else 3  # a single ray view is not its own source
    assert sum(read) == n + others * (n - zero), (read, n, zero)
    floor = float(p_ref[p_ref > 0].median())
    prior.prior_floor = floor
    lab = prior.label(pts, ref)
    keep = p_ref > floor
    assert torch.equal(lab[keep], exact[keep]) and (lab[~keep] == 0).all()
    assert (exact[~keep] <= floor * 2 + 1e-7).all()


def test_selected_sources_sum_only_their_volumes_in_lookup_and_label():
    """sources: a ray's P_src sums only its view's listed sources, in `lookup` and `label`
    alike; None is every other view (the paper's sum)."""
    vols = _volumes()
    norm = Normalization(CENTER, SCALE)
    pts = _points(R=6, S=30)
    ref = torch.tensor([0, 1, 2, 0, 1, 2])
    full = MVSPrior(vols, norm)
    assert torch.equal(MVSPrior(vols, norm, sources=[[1, 2], [0, 2], [0, 1]]).lookup(pts, ref)[1],
                       full.lookup(pts, ref)[1])
    sel = MVSPrior(vols, norm, sources=[[1], [2], [0]])
    one = [full.view_lookup(i, pts.reshape(-1, 3))[0].reshape(6, 30) for i in range(3)]
    want = torch.stack([one[[1, 2, 0][int(r)]][k] for k, r in enumerate(ref)])
    p_ref, p_src, valid = sel.lookup(pts, ref)
    assert torch.equal(p_src, want) and (p_src != full.lookup(pts, ref)[1]).any()
    assert torch.equal(sel.label(pts, ref), p_ref * p_src)
    with pytest.raises(ValueError, match="sources"):
        MVSPrior(vols, norm, sources=[[0], [2], [0]])  # a view is not its own source
