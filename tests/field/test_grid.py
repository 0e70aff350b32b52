"""Tests for the fast grid field (`svolsdf.field.grid`) and its ops (`svolsdf.field.grid_ops`)."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from svolsdf.field.density import laplace_density
from svolsdf.field.grid import GridFieldConfig, GridSDFField, beta_schedule
from svolsdf.field.grid_ops import (
    laplacian_loss,
    resample_grid,
    total_variation_loss,
    trilinear_reference,
    trilinear_sample,
    trilinear_with_grad,
)

BOX = torch.tensor([[-1.0, -0.8, -0.9], [1.0, 0.8, 0.9]])


def _torus(x: torch.Tensor, big: float = 0.5, small: float = 0.2) -> torch.Tensor:
    q = torch.stack([x[:, [0, 2]].norm(dim=-1) - big, x[:, 1]], dim=-1)
    return q.norm(dim=-1) - small


def _random_field(res: int = 17, residual: bool = False, clamp: float | None = None):
    cfg = GridFieldConfig(resolution=res, sdf_residual=residual, sphere_clamp_scale=clamp)
    f = GridSDFField(BOX, cfg).double()
    with torch.no_grad():  # a non-trivial function: sphere + noise, random MLP residual
        f.sdf_grid.add_(0.01 * torch.randn_like(f.sdf_grid))
        for g in f.feature_grids:
            g.normal_()
        if f.residual_net is not None:
            f.residual_net[-1].weight.normal_(0, 0.05)
    return f


# ----------------------------------------------------------------------------- ops
def test_trilinear_matches_grid_sample_reference_values_grads_and_double_backward():
    grid = torch.randn(2, 5, 6, 7, dtype=torch.float64, requires_grad=True)
    u = torch.rand(50, 3, dtype=torch.float64) * torch.tensor([6.0, 5.0, 4.0], dtype=torch.float64)
    v, g = trilinear_with_grad(grid, u)
    vr, gr = trilinear_reference(grid, u)
    torch.testing.assert_close(v, vr)
    torch.testing.assert_close(g, gr)
    # d(eikonal-like loss)/d grid: closed form vs grid_sample's double backward.
    (a,) = torch.autograd.grad((g.norm(dim=-1) - 1).square().sum() + v.sum(), grid)
    (b,) = torch.autograd.grad((gr.norm(dim=-1) - 1).square().sum() + vr.sum(), grid)
    torch.testing.assert_close(a, b)


def test_trilinear_sample_is_grid_sample_with_the_same_grid_gradient():
    grid = torch.randn(3, 5, 6, 7, dtype=torch.float64, requires_grad=True)
    size = torch.tensor([7.0, 6.0, 5.0], dtype=torch.float64)
    u = torch.rand(80, 3, dtype=torch.float64) * (size - 1)
    u[:4] = torch.tensor([[0.0, 0.0, 0.0], [6.0, 5.0, 4.0], [6.0, 0.0, 2.5], [3.5, 5.0, 0.0]],
                         dtype=torch.float64)  # corners and faces of the box
    w = torch.randn(80, 3, dtype=torch.float64)
    g = (u / (size - 1) * 2 - 1).view(1, -1, 1, 1, 3)
    ref = F.grid_sample(grid[None], g, mode="bilinear", align_corners=True).view(3, -1).T
    v = trilinear_sample(grid, u)
    torch.testing.assert_close(v, ref)
    (a,) = torch.autograd.grad((v * w).sum(), grid)
    (b,) = torch.autograd.grad((ref * w).sum(), grid)
    torch.testing.assert_close(a, b)
    # outside the grid the index is clamped: grid_sample's "border" padding
    far = (torch.rand(60, 3, dtype=torch.float64) * 3 - 1) * (size - 1)
    gb = (far / (size - 1) * 2 - 1).view(1, -1, 1, 1, 3)
    border = F.grid_sample(grid[None], gb, mode="bilinear", padding_mode="border",
                           align_corners=True).view(3, -1).T
    torch.testing.assert_close(trilinear_sample(grid, far), border)


def _trilinear_autograd(grid: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """`trilinear_sample` as plain autograd ops (its expression before the custom backward)."""
    from svolsdf.field.grid_ops import _corners

    C = grid.shape[0]
    idx, f = _corners(u, tuple(grid.shape[1:]))
    wx, wy, wz = (torch.stack([1.0 - f[:, k], f[:, k]], dim=-1) for k in range(3))
    w = (wz[:, :, None, None] * wy[:, None, :, None] * wx[:, None, None, :]).reshape(1, -1, 8)
    c = grid.reshape(C, -1).index_select(1, idx.reshape(-1)).view(C, -1, 8)
    return (c * w).sum(-1).T


def test_trilinear_sample_backward_is_autograd_and_twice_differentiable():
    grid = torch.randn(4, 5, 6, 7, dtype=torch.float64, requires_grad=True)
    u = torch.rand(90, 3, dtype=torch.float64) * torch.tensor([6.0, 5.0, 4.0],
                                                              dtype=torch.float64)
    w = torch.randn(90, 4, dtype=torch.float64)
    v = trilinear_sample(grid, u)
    ref = _trilinear_autograd(grid, u)
    torch.testing.assert_close(v, ref, rtol=1e-12, atol=1e-12)  # (corner-major sums)
    (a,) = torch.autograd.grad((v * w).sum(), grid)
    (b,) = torch.autograd.grad((ref * w).sum(), grid)
    torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    assert torch.autograd.gradcheck(lambda g: trilinear_sample(g, u), (grid,))
    assert torch.autograd.gradgradcheck(lambda g: trilinear_sample(g, u).square(), (grid,))
    # points that need a gradient (the residual SDF's x-gradient) take the autograd path
    ur = u.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: trilinear_sample(grid.detach(), x), (ur,))


def test_recycled_feature_gradients_reuse_their_memory_with_the_same_values():
    f = _random_field()
    x = torch.randn(300, 3, dtype=torch.float64) * 0.6
    w = torch.randn(300, f.feature_dim, dtype=torch.float64)

    def grads():
        _, _, feat = f.sdf_and_grad(x)
        (feat * w).sum().backward()
        return [g.grad for g in f.feature_grids]

    first = [g.clone() for g in grads()]
    ptrs = [g.grad.data_ptr() for g in f.feature_grids]
    f.recycle_grads()
    assert all(g.grad is None for g in f.feature_grids)
    again = grads()
    # the same memory, zeroed and refilled (levels of equal shapes may swap buffers)
    assert sorted(g.data_ptr() for g in again) == sorted(ptrs)
    for a, b in zip(first, again, strict=True):
        assert a.equal(b)
    f.recycle_grads()
    f.upsample(13)  # new grids: the kept buffers are dropped
    assert not f._grad_buffers._free


def test_sdf_grad_is_sdf_and_grad_without_features():
    for residual in (False, True):
        f = _random_field(residual=residual, clamp=20.0)
        x = torch.randn(40, 3, dtype=torch.float64) * 0.8
        for clamp in (False, True):
            s, g = f.sdf_grad(x, create_graph=True, clamp=clamp)
            s2, g2, _ = f.sdf_and_grad(x, create_graph=True, clamp=clamp)
            torch.testing.assert_close(s, s2, rtol=0, atol=0)
            torch.testing.assert_close(g, g2, rtol=0, atol=0)
            (a,) = torch.autograd.grad(g.square().sum(), f.sdf_grid)
            (b,) = torch.autograd.grad(g2.square().sum(), f.sdf_grid)
            torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_trilinear_at_nodes_returns_node_values():
    grid = torch.randn(1, 4, 4, 4, dtype=torch.float64)
    u = torch.tensor([[0.0, 0.0, 0.0], [3.0, 3.0, 3.0], [1.0, 2.0, 3.0]], dtype=torch.float64)
    v, _ = trilinear_with_grad(grid, u, with_grad=False)
    expected = torch.stack([grid[0, 0, 0, 0], grid[0, 3, 3, 3], grid[0, 3, 2, 1]])
    torch.testing.assert_close(v[:, 0], expected)


def test_resample_exact_on_refinement_and_laplacian_zero_on_linear():
    grid = torch.randn(1, 5, 5, 5, dtype=torch.float64)
    fine = resample_grid(grid, (9, 9, 9))
    u = torch.rand(100, 3, dtype=torch.float64) * 4
    torch.testing.assert_close(
        trilinear_with_grad(grid, u, False)[0], trilinear_with_grad(fine, u * 2, False)[0]
    )
    z, y, x = torch.meshgrid(*[torch.arange(6.0, dtype=torch.float64)] * 3, indexing="ij")
    lin = (0.3 * x - 0.2 * y + 0.7 * z + 1)[None]
    assert laplacian_loss(lin).item() < 1e-20
    assert laplacian_loss(lin, n_samples=100).item() < 1e-20
    assert total_variation_loss(lin).item() > 0
    rnd = torch.randn(1, 12, 12, 12, dtype=torch.float64)
    full, sampled = laplacian_loss(rnd).item(), laplacian_loss(rnd, n_samples=200_000).item()
    assert abs(sampled - full) < 0.05 * full


def test_ops_reject_bad_shapes():
    with pytest.raises(ValueError, match="grid must be"):
        trilinear_with_grad(torch.zeros(4, 4, 4), torch.zeros(3, 3))
    with pytest.raises(ValueError, match="u must be"):
        trilinear_with_grad(torch.zeros(1, 4, 4, 4), torch.zeros(3, 2))


# --------------------------------------------------------------------------- field
def test_init_is_sphere_sdf_and_shapes():
    f = GridSDFField(BOX, GridFieldConfig(resolution=33))
    x = (torch.rand(200, 3) * 2 - 1) * BOX[1] * 0.95
    s, g, feat = f.sdf_and_grad(x)
    assert s.shape == (200,) and g.shape == (200, 3) and feat.shape == (200, f.feature_dim)
    torch.testing.assert_close(s, x.norm(dim=-1) - 0.6, atol=0.01, rtol=0)
    far = x.norm(dim=-1) > 0.3  # away from the kink at the centre
    gn = g[far].norm(dim=-1)
    assert (gn - 1).abs().max() < 0.1 and (gn - 1).abs().mean() < 0.02
    torch.testing.assert_close(f.sdf(x), s)
    assert f.grid_shape == (30, 27, 33)  # cubic cells in a non-cubic box
    torch.testing.assert_close(f.cell_size, torch.full((3,), 2.0 / 32))
    assert ((f.bounds[0] <= BOX[0]) & (f.bounds[1] >= BOX[1])).all()
    assert ((f.bounds[1] - f.bounds[0]) - (BOX[1] - BOX[0]) < 2.0 / 32).all()


@pytest.mark.parametrize("residual", [False, True])
def test_sdf_and_grad_matches_finite_differences(residual):
    f = _random_field(residual=residual, clamp=20.0)
    f.radius = 1.6  # puts the sphere clamp inside the test region
    lo, hi = f.bounds
    x = torch.rand(300, 3, dtype=torch.float64) * (hi - lo) * 1.6 + lo * 1.6  # in and out of box
    s, g, _ = f.sdf_and_grad(x, create_graph=False)
    # Central differences, keeping only points whose stencil stays in one trilinear cell
    # and on one side of the box faces and of the clamp.
    h = 1e-6
    eye = torch.eye(3, dtype=torch.float64) * h
    with torch.no_grad():
        fd = torch.stack([(f.sdf(x + e) - f.sdf(x - e)) / (2 * h) for e in eye], dim=-1)
        u = (x - lo) / f.cell_size
        frac = u - u.floor()
        inside = (x > lo) & (x < hi)
        off_face = ((x - lo).abs() > 1e-3) & ((x - hi).abs() > 1e-3)
        safe = (off_face & (~inside | ((frac > 1e-3) & (frac < 1 - 1e-3)))).all(-1)
        raw = f.sdf(x, clamp=False)
        bound = 20.0 * (f.radius - x.norm(dim=-1))
        safe &= (raw - bound).abs() > 1e-3
    assert safe.sum() > 200
    assert not g.requires_grad
    torch.testing.assert_close(g[safe], fd[safe], atol=1e-5, rtol=1e-5)
    clamped = safe & (bound < raw)
    assert clamped.any()


def test_eikonal_gradient_reaches_grid_and_mlps():
    f = GridSDFField(BOX, GridFieldConfig(resolution=9, sdf_residual=True))
    x = torch.rand(64, 3) * 2 - 1
    s, g, feat = f.sdf_and_grad(x, create_graph=True)
    rgb = f.colour(x, torch.nn.functional.normalize(torch.randn(64, 3), dim=-1), g, feat)
    ((g.norm(dim=-1) - 1).square().mean() + rgb.mean() + s.mean()).backward()
    for name, p in f.named_parameters():
        if name != "laplace.beta_param":
            assert p.grad is not None and torch.isfinite(p.grad).all(), name


def test_upsample_preserves_function():
    f = _random_field(res=17)
    x = torch.rand(500, 3, dtype=torch.float64) * (BOX[1] - BOX[0]).double() + BOX[0].double()
    view = torch.nn.functional.normalize(torch.randn(500, 3, dtype=torch.float64), dim=-1)
    with torch.no_grad():
        s0, g0, f0 = f.sdf_and_grad(x)
        c0 = f.colour(x, view, g0, f0)
        shape0 = f.grid_shape
        f.upsample(2 * 17 - 1)  # node count 2(n - 1) + 1 on the longest axis: exact refinement
        s1 = f.sdf(x)
        f.upsample(50)  # not a refinement: approximately the same function
        s2, g2, f2 = f.sdf_and_grad(x)
        c2 = f.colour(x, view, g2, f2)
    assert f.grid_shape[2] == 50 and f.grid_shape != shape0
    torch.testing.assert_close(s1, s0)
    assert (s2 - s0).abs().max() < 0.03 and (s2 - s0).abs().mean() < 0.005
    assert (c2 - c0).abs().mean() < 0.02
    groups = f.param_groups(1e-2, 1e-3)
    ids = [id(p) for grp in groups for p in grp["params"]]
    assert sorted(ids) == sorted(id(p) for p in f.parameters())
    assert f.sdf_grid in groups[0]["params"]


def test_outside_box_is_positive_and_growing():
    f = GridSDFField(BOX, GridFieldConfig(resolution=17, init_radius=0.5))
    d = torch.nn.functional.normalize(torch.randn(100, 3), dim=-1)
    r = torch.tensor([1.5, 2.0, 2.4, 2.7])  # inside the clamp radius 3
    s = torch.stack([f.sdf(d * ri) for ri in r], dim=0)  # (4, 100), beyond the box
    assert (s > 0).all()
    assert (s[1:] > s[:-1]).all()
    # Distance outside the box adds one-for-one along the face normal.
    x = torch.tensor([[1.0, 0.1, 0.2], [1.7, 0.1, 0.2]])
    torch.testing.assert_close(f.sdf(x)[1] - f.sdf(x)[0], torch.tensor(0.7), atol=1e-5, rtol=0)
    # The sphere clamp (docs/method.md 5.2) makes the SDF negative past radius 3.
    assert (f.sdf(d * 3.2) < 0).all() and (f.sdf(d * 3.2, clamp=False) > 0).all()


def test_colour_range_and_checks():
    f = GridSDFField(BOX, GridFieldConfig(resolution=9))
    with torch.no_grad():
        for g in f.feature_grids:
            g.normal_(0, 100.0)
    x = torch.rand(100, 3) * 2 - 1
    s, g, feat = f.sdf_and_grad(x)
    rgb = f.colour(x, torch.randn(100, 3), g, feat)
    assert rgb.shape == (100, 3) and (rgb >= 0).all() and (rgb <= 1).all()
    with pytest.raises(ValueError, match="feature must be"):
        f.colour(x, x, g, feat[:, :3])
    with pytest.raises(ValueError, match="must be \\(N, 3\\)"):
        f.sdf(x[:, :2])
    with pytest.raises(ValueError, match="lo < hi"):
        GridSDFField(torch.tensor([[0.0, 0, 0], [1.0, -1, 1]]))


def test_density_beta_and_schedule():
    f = GridSDFField(BOX, GridFieldConfig(resolution=9, beta_init=0.1))
    s = torch.linspace(-1, 1, 11)
    torch.testing.assert_close(f.density(s), laplace_density(s, 0.1 + 1e-4))
    torch.testing.assert_close(f.density(s, beta=torch.tensor(0.05)), laplace_density(s, 0.05))
    f.beta_min = 0.2
    assert abs(f.beta.item() - 0.3) < 1e-6
    with pytest.raises(ValueError):
        f.beta_min = -1.0
    assert beta_schedule(0, 100, 0.1, 0.001) == pytest.approx(0.1)
    assert beta_schedule(50, 100, 0.1, 0.001) == pytest.approx(0.01)
    assert beta_schedule(500, 100, 0.1, 0.001) == pytest.approx(0.001)


def test_smoothness_losses():
    f = GridSDFField(BOX, GridFieldConfig(resolution=17, init_radius=0.5))
    smooth = f.smoothness_loss(None).item()
    with torch.no_grad():
        f.sdf_grid.add_(0.05 * torch.randn_like(f.sdf_grid))
    assert f.smoothness_loss(None).item() > 10 * smooth
    f.smoothness_loss(4096).backward()
    assert f.sdf_grid.grad is not None and f.sdf_grid.grad.abs().sum() > 0
    assert f.feature_tv_loss().item() > 0


def test_fits_analytic_torus():
    """Direct SDF supervision + eikonal, with one coarse-to-fine step: the error must drop."""
    cfg = GridFieldConfig(resolution=25, sphere_clamp_scale=None)
    f = GridSDFField(torch.tensor([[-1.0] * 3, [1.0] * 3]), cfg)
    xt = torch.rand(4000, 3) * 1.6 - 0.8
    with torch.no_grad():
        err0 = (f.sdf(xt) - _torus(xt)).abs().mean().item()
    opt = torch.optim.Adam(f.param_groups(0.02, 1e-3))
    for it in range(200):
        if it == 100:
            f.upsample(49)
            opt = torch.optim.Adam(f.param_groups(0.01, 1e-3))
        x = torch.rand(1024, 3) * 2 - 1
        s, g, _ = f.sdf_and_grad(x)
        loss = (s - _torus(x)).abs().mean() + 0.02 * (g.norm(dim=-1) - 1).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        err = (f.sdf(xt) - _torus(xt)).abs().mean().item()
        # Points on the torus surface: the zero level of the fit lies near them.
        phi, theta = torch.rand(2, 2000) * 2 * torch.pi
        ring = 0.5 + 0.2 * torch.cos(theta)
        on = torch.stack([ring * torch.cos(phi), 0.2 * torch.sin(theta), ring * torch.sin(phi)], -1)
        surf = f.sdf(on).abs().mean().item()
    assert err0 > 0.1
    assert err < min(0.03, 0.2 * err0), f"mean |sdf - torus| = {err:.4f} (start {err0:.4f})"
    assert surf < 0.03, f"mean |sdf| on the torus = {surf:.4f}"


def test_loading_a_checkpoint_takes_its_box_and_grid_shapes():
    """A field built for another box (e.g. the stage-1 volumes were deleted) still loads a
    checkpoint, and then evaluates exactly as the saved field."""
    torch.manual_seed(0)
    saved = GridSDFField(torch.tensor([[-0.4, -0.3, -0.2], [0.5, 0.3, 0.4]]),
                         GridFieldConfig(resolution=17))
    saved.upsample(33)
    with torch.no_grad():
        saved.sdf_grid.add_(0.01 * torch.randn_like(saved.sdf_grid))
    state = saved.state_dict()
    other = GridSDFField(torch.tensor([[-1.0] * 3, [1.0] * 3]), GridFieldConfig(resolution=17))
    assert other.grid_shape != saved.grid_shape
    other.load_state_dict(state)
    assert other.grid_shape == saved.grid_shape and other.resolution == saved.resolution
    assert torch.equal(other.bounds, saved.bounds)
    x = torch.rand(200, 3) * 1.4 - 0.7
    assert torch.allclose(other.sdf(x), saved.sdf(x))
    s1, g1, f1 = saved.sdf_and_grad(x, create_graph=False)
    s2, g2, f2 = other.sdf_and_grad(x, create_graph=False)
    assert torch.allclose(g1, g2) and torch.allclose(f1, f2)
    # a missing key is still an error
    del state["sdf_grid"]
    with pytest.raises(RuntimeError, match="sdf_grid"):
        other.load_state_dict(state)
