"""Positional encoding, Laplace density and the VolSDF MLP (docs/method.md 5.1-5.4)."""

from __future__ import annotations

import math

import pytest
import torch

from svolsdf.field.density import LaplaceDensity, laplace_density
from svolsdf.field.embedding import PositionalEncoding, positional_encoding
from svolsdf.field.volsdf import VolSDFField, VolSDFFieldConfig


def test_positional_encoding_layout():
    x = torch.tensor([[0.1, -0.2, 0.3]])
    e = positional_encoding(x, 2)
    assert e.shape == (1, 3 + 2 * 3 * 2)
    assert torch.allclose(e[0, :3], x[0])
    assert torch.allclose(e[0, 3:6], torch.sin(x[0]))
    assert torch.allclose(e[0, 6:9], torch.cos(x[0]))
    assert torch.allclose(e[0, 9:12], torch.sin(2 * x[0]))
    assert torch.allclose(e[0, 12:15], torch.cos(2 * x[0]))
    assert PositionalEncoding(3, 6).out_dim == 39 and PositionalEncoding(3, 1).out_dim == 9
    assert positional_encoding(x, 0) is x


def test_laplace_density_branches_and_continuity():
    beta = 0.2
    s = torch.tensor([0.3, -0.3, 0.0, 1e-7, -1e-7])
    sig = laplace_density(s, beta)
    assert sig[0].item() == pytest.approx(0.5 * math.exp(-0.3 / beta) / beta, rel=1e-6)  # outside
    assert sig[1].item() == pytest.approx((1 - 0.5 * math.exp(-0.3 / beta)) / beta, rel=1e-6)
    assert sig[2].item() == pytest.approx(0.5 / beta)
    assert sig[3].item() == pytest.approx(0.5 / beta, rel=1e-5)
    assert sig[4].item() == pytest.approx(0.5 / beta, rel=1e-5)
    # high inside (sdf < 0), monotone decreasing in sdf, bounded by 1/beta
    grid = torch.linspace(-2, 2, 401)
    d = laplace_density(grid, beta)
    assert (d.diff() <= 0).all() and d.max() <= 1 / beta and d.min() >= 0
    # per-ray beta broadcasting
    b = torch.tensor([[0.1], [0.2]])
    assert torch.allclose(laplace_density(torch.zeros(2, 3), b), (0.5 / b).expand(2, 3))


def test_laplace_module_beta():
    m = LaplaceDensity()
    assert m.get_beta().item() == pytest.approx(0.1 + 1e-4)
    with torch.no_grad():
        m.beta_param.fill_(-0.05)
    assert m.get_beta().item() == pytest.approx(0.05 + 1e-4)
    assert [n for n, _ in m.named_parameters()] == ["beta_param"]
    s = torch.tensor([0.01])
    assert torch.allclose(m(s), laplace_density(s, 0.05 + 1e-4))


def test_geometric_init_is_sphere_of_radius_bias():
    torch.manual_seed(0)
    m = VolSDFField()
    net = m.sdf_net
    assert len(net.layers) == 9
    # skip: lin3 outputs 256 - 39, lin4 sees 256; geometric-init zero columns (docs/method.md 5.2)
    assert net.layers[3].weight.shape == (217, 256) and net.layers[4].weight.shape == (256, 256)
    assert (net.layers[0].weight[:, 3:] == 0).all() and (net.layers[0].weight[:, :3] != 0).any()
    w4 = net.layers[4].weight
    assert (w4[:, -36:] == 0).all() and (w4[:, -39:-36] != 0).any()
    assert torch.allclose(net.layers[8].bias, torch.full((257,), -0.6))
    assert hasattr(net.layers[0], "parametrizations")  # weight norm
    assert m.colour_net.d_in == 271
    for r in (0.6, 1.0, 1.5):
        x = torch.randn(300, 3)
        x = x / x.norm(dim=-1, keepdim=True) * r
        s, g, f = m.sdf_and_grad(x, create_graph=False)
        assert (s.mean() - (r - 0.6)).abs() < 0.1, r  # on average |x| - 0.6
        assert (s - (r - 0.6)).abs().mean() < 0.2, r
        assert (g.norm(dim=-1).mean() - 1.0).abs() < 0.2, r
        assert f.shape == (300, 256)
    assert m.sdf(torch.zeros(1, 3)).item() < -0.2  # inside at the origin


def test_sdf_and_grad_matches_finite_differences_and_clamp():
    torch.manual_seed(0)
    cfg = VolSDFFieldConfig(mlp_depth=3, mlp_width=64, skip_in=(2,), multires=2, feature_dim=8)
    m = VolSDFField(cfg).double()
    x = torch.randn(5, 3, dtype=torch.float64) * 0.7
    s, g, _ = m.sdf_and_grad(x, create_graph=False)
    h = 1e-6
    fd = torch.stack([(m.sdf(x + h * e) - m.sdf(x - h * e)) / (2 * h)
                      for e in torch.eye(3, dtype=torch.float64)], -1)
    assert torch.allclose(g, fd, atol=1e-6)
    # the sphere clamp: near |x| = 3 the clamped sdf is 20 (3 - |x|); raw is unclamped
    xo = torch.tensor([[2.99, 0.0, 0.0]], dtype=torch.float64)
    assert m.sdf(xo).item() == pytest.approx(min(m.sdf(xo, clamp=False).item(), 20 * 0.01))
    _, graw, _ = m.sdf_and_grad(torch.tensor([[0.0, 0.0, 2.999]], dtype=torch.float64),
                                create_graph=False, clamp=False)
    _, gcl, _ = m.sdf_and_grad(torch.tensor([[0.0, 0.0, 2.999]], dtype=torch.float64),
                               create_graph=False)
    assert gcl[0, 2].item() == pytest.approx(-20.0) and graw.norm() < 5
    # no grad mode still returns the gradient; create_graph keeps it differentiable
    with torch.no_grad():
        _, g2, _ = m.sdf_and_grad(x, create_graph=False)
    assert torch.allclose(g2, g)
    _, g3, _ = m.sdf_and_grad(x, create_graph=True)
    ((g3.norm(dim=-1) - 1) ** 2).mean().backward()
    assert m.sdf_net.layers[0].parametrizations.weight.original1.grad is not None


def test_colour_and_density_interfaces():
    cfg = VolSDFFieldConfig(mlp_depth=2, mlp_width=64, skip_in=(), feature_dim=16,
                            render_layers=2, render_hidden=32)
    m = VolSDFField(cfg)
    x = torch.randn(7, 3)
    s, g, f = m.sdf_and_grad(x, create_graph=False)
    rgb = m.colour(x, torch.nn.functional.normalize(torch.randn(7, 3), dim=-1), g, f)
    assert rgb.shape == (7, 3) and ((rgb > 0) & (rgb < 1)).all()
    assert torch.allclose(m.density(s), laplace_density(s, m.beta))
    assert m.beta.item() == pytest.approx(0.1001)
