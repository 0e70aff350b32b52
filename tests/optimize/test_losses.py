"""Losses (docs/method.md 4) against hand-computed values and gradient identities."""

from __future__ import annotations

import math

import pytest
import torch

from svolsdf.optimize.losses import (
    depth_mse_loss,
    eikonal_loss,
    gce_weight_loss,
    onehot_label,
    rgb_l1_loss,
    sparse_loss,
    sparse_weight_at,
    warmup_ray_mask,
    warmup_rgb_target,
)


def test_gce_paper_and_released_known_values():
    w = torch.tensor([[0.25, 0.64], [0.5, 0.5]])
    p = torch.tensor([[1.0, 0.5], [0.0, 1e-4]])  # ray 1 is below the 1e-3 support threshold
    # paper: ray 0 = 1*(1-0.5)/0.5 + 0.5*(1-0.8)/0.5 = 1.0 + 0.2; mean over 2 rays
    assert gce_weight_loss(w, p, 0.5, "paper").item() == pytest.approx(1.2 / 2, rel=1e-6)
    # released: -(1*0.5*log(0.25) + 0.5*0.8*log(0.64)) / 2
    exp = -(0.5 * math.log(0.25 + 1e-8) + 0.4 * math.log(0.64 + 1e-8)) / 2
    assert gce_weight_loss(w, p, 0.5, "released").item() == pytest.approx(exp, rel=1e-6)
    # q = 1: paper P'(1 - w); released -P' w
    assert gce_weight_loss(w, p, 1.0, "paper").item() == pytest.approx((0.75 + 0.18) / 2, rel=1e-6)
    assert gce_weight_loss(w, p, 1.0, "released").item() == pytest.approx(-(0.25 + 0.32) / 2,
                                                                          rel=1e-6)


def test_gce_gradient_paper_equals_released():
    g = torch.Generator().manual_seed(0)
    w0 = torch.rand(6, 9, generator=g) * 0.9 + 0.05
    p = torch.rand(6, 9, generator=g) * 0.3
    p[0] = 0.0  # an unsupported ray
    for q in (0.5, 0.3, 0.8, 1.0):
        wa = w0.clone().requires_grad_(True)
        wb = w0.clone().requires_grad_(True)
        gce_weight_loss(wa, p, q, "paper").backward()
        gce_weight_loss(wb, p, q, "released").backward()
        assert torch.allclose(wa.grad, wb.grad, rtol=1e-5, atol=1e-7), q
        assert (wa.grad[0] == 0).all()
        # and both equal -P' w^(q-1) / R on supported rays
        assert torch.allclose(wa.grad[1:], -p[1:] * w0[1:] ** (q - 1) / 6, rtol=1e-5)


def test_gce_q_to_zero_is_cross_entropy():
    g = torch.Generator().manual_seed(1)
    w = torch.rand(4, 5, generator=g) * 0.9 + 0.05
    p = torch.rand(4, 5, generator=g)
    ce = (-(p * torch.log(w + 1e-8)).sum(-1)).mean()
    for form in ("paper", "released"):
        assert gce_weight_loss(w, p, 0.0, form).item() == pytest.approx(ce.item(), rel=1e-6)
    # the paper form tends to CE as q -> 0
    assert gce_weight_loss(w, p, 1e-4, "paper").item() == pytest.approx(ce.item(), rel=1e-3)
    with pytest.raises(ValueError):
        gce_weight_loss(w, p, 0.5, "other")


def test_sparse_loss_normalization():
    depth = torch.tensor([1.0, 2.0, 0.5, 3.0])
    p = torch.zeros(4, 3)
    p[0, 1] = 0.5  # ray 0 supported; rays 1-3 in Q
    s = 1 / (2.0 + 1e-3) + 1 / (0.5 + 1e-3) + 1 / (3.0 + 1e-3)
    assert sparse_loss(depth, p).item() == pytest.approx(s / 3, rel=1e-6)
    assert sparse_loss(depth, p, normalize="all").item() == pytest.approx(s / 4, rel=1e-6)
    full = torch.ones(4, 3)
    assert sparse_loss(depth, full).item() == 0.0
    d = depth.clone().requires_grad_(True)
    sparse_loss(d, p).backward()
    assert d.grad[0] == 0 and d.grad[1] == pytest.approx(-1 / (2.001**2) / 3, rel=1e-5)


def test_eikonal_and_rgb():
    g = torch.tensor([[3.0, 4.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    assert eikonal_loss(g).item() == pytest.approx((16 + 0 + 1) / 3)
    pred = torch.tensor([[0.0, 0.5, 1.0], [1.0, 1.0, 1.0]])
    tgt = torch.tensor([[0.0, 0.0, 0.0], [0.7, 1.0, 1.0]])
    assert rgb_l1_loss(pred, tgt).item() == pytest.approx((1.5 + 0.3) / 6)
    mask = torch.tensor([False, True])
    assert rgb_l1_loss(pred, tgt, mask).item() == pytest.approx(0.1 / 2)


def test_warmup_schedule_target_and_mask():
    assert sparse_weight_at(0, 1.0) == 1.0
    assert sparse_weight_at(100, 1.0) == pytest.approx(0.5)
    assert sparse_weight_at(200, 1.0) == 0.0
    assert sparse_weight_at(150, 0.1, decay="constant") == pytest.approx(0.1)
    assert sparse_weight_at(10, 0.0) == 0.0
    img = torch.rand(2, 3, 40, 50)
    out = warmup_rgb_target(img)
    assert out.shape == img.shape
    # sigma 90 on a 31 window is nearly a box filter: interior pixel ~ 31x31 mean
    box = img[:, :, 20 - 15:20 + 16, 25 - 15:25 + 16].mean(dim=(-1, -2))
    assert torch.allclose(out[:, :, 20, 25], box, atol=2e-3)
    p = torch.zeros(3, 4)
    p[1, 2] = 1e-3
    assert warmup_ray_mask(p).tolist() == [True, False, True]
    assert warmup_ray_mask(p, "all").all()


def test_depth_mse_and_onehot():
    d = torch.tensor([1.0, 2.0, 3.0])
    m = torch.tensor([1.5, 0.0, 2.0])
    v = torch.tensor([True, False, True])
    assert depth_mse_loss(d, m, v).item() == pytest.approx((0.25 + 1.0) / 2)
    assert depth_mse_loss(d, m, torch.zeros(3, dtype=torch.bool)).item() == 0.0
    z = torch.tensor([[0.0, 1.0, 2.0, 3.0], [0.0, 1.0, 2.0, 3.0], [0.0, 2.0, 4.0, 6.0]])
    lab = onehot_label(z, torch.tensor([1.2, 0.0, 2.9]), cos=torch.tensor([1.0, 1.0, 0.5]))
    assert lab.tolist() == [[0, 1, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]]
    # fed to the GCE loss it supervises the labelled sample only
    w = torch.full((3, 4), 0.25, requires_grad=True)
    gce_weight_loss(w, lab, 0.5).backward()
    assert (w.grad[0, [0, 2, 3]] == 0).all() and w.grad[0, 1] < 0 and (w.grad[1] == 0).all()


def test_gce_gradient_is_finite_at_zero_weights():
    """Empty samples have w = 0 exactly; d(w^q)/dw must not turn the step's gradient NaN."""
    w = torch.tensor([[0.0, 0.3, 0.0, 0.7]], requires_grad=True)
    p = torch.tensor([[0.0, 0.5, 0.2, 0.3]])
    for form in ("paper", "released"):
        for q in (0.0, 0.5, 1.0):
            w.grad = None
            gce_weight_loss(w, p, q=q, form=form).backward()
            assert torch.isfinite(w.grad).all(), (form, q, w.grad)
            if form == "paper" or q == 0.0:  # released: sg(w)^q = 0 stops it at w = 0
                assert w.grad[0, 2] < 0  # labelled empty sample is pulled up
