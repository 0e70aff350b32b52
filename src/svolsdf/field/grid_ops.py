"""Pure tensor ops on dense voxel grids for the fast field (`svolsdf.field.grid`).

Grid convention (same as ``F.grid_sample(..., align_corners=True)``): a grid of shape
(C, Z, Y, X) spans an axis-aligned box [lo, hi]; node (i, j, k) = (x, y, z) index sits at
lo + (i, j, k) / ((X, Y, Z) - 1) * (hi - lo), so the box corners are nodes. Points are given in
continuous *index* coordinates u = (x, y, z) with u in [0, (X, Y, Z) - 1].

`trilinear_with_grad` is the fast op (8 gathers, value and analytic gradient in closed form,
differentiable to any order in the grid values); `trilinear_reference` is its slow, obviously
correct twin built on ``grid_sample`` + autograd, used by the tests.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "GradBuffers",
    "trilinear_sample",
    "trilinear_with_grad",
    "trilinear_reference",
    "resample_grid",
    "laplacian_loss",
    "total_variation_loss",
    "device_vector",
]


def device_vector(values: list[float], device, dtype) -> Tensor:
    """A small constant (len(values),) tensor made on ``device`` by fills, not by a copy.

    ``torch.tensor(values, device="cuda")`` copies host memory with a blocking copy, which
    synchronises the device; inside a training step that stalls the GPU queue every call.
    """
    out = torch.empty(len(values), device=device, dtype=dtype)
    for i, v in enumerate(values):
        out[i] = v  # a fill kernel on the device
    return out


def _check_grid_points(grid: Tensor, u: Tensor) -> None:
    if grid.dim() != 4:
        raise ValueError(f"grid must be (C, Z, Y, X), got shape {tuple(grid.shape)}")
    if min(grid.shape[1:]) < 2:
        raise ValueError(f"grid needs at least 2 nodes per axis, got shape {tuple(grid.shape)}")
    if u.dim() != 2 or u.shape[-1] != 3:
        raise ValueError(f"u must be (N, 3) index coordinates, got shape {tuple(u.shape)}")


def trilinear_with_grad(
    grid: Tensor, u: Tensor, with_grad: bool = True
) -> tuple[Tensor, Tensor | None]:
    """Trilinear interpolation of a dense grid and its analytic spatial gradient.

    Args:
        grid: (C, Z, Y, X) float node values.
        u: (N, 3) float continuous index coordinates (x, y, z); values outside
            [0, size - 1] are clamped (callers clamp points to the box first).
        with_grad: also return the gradient d value / d u.

    Returns:
        value: (N, C) interpolated values (equal to ``grid_sample(align_corners=True)``).
        grad: (N, C, 3) d value / d u in index units (x, y, z order), or None. Inside a cell
            the trilinear interpolant is smooth, so this is the exact derivative of `value`;
            on cell faces it is the one-sided derivative of the cell that holds the point.

    Both outputs are plain torch expressions of the 8 gathered corner values, hence
    differentiable to any order with respect to `grid` (the eikonal loss needs d grad / d grid)
    and once with respect to `u` through the fractional offsets.
    """
    _check_grid_points(grid, u)
    C = grid.shape[0]
    n = u.shape[0]
    idx, f = _corners(u, tuple(grid.shape[1:]))  # corner order: z, y, x (x fastest)
    c = grid.reshape(C, -1).index_select(1, idx.reshape(-1)).reshape(C, n, 2, 2, 2)
    c = c.permute(1, 0, 2, 3, 4)
    fx = f[:, 0].view(n, 1, 1, 1)
    fy = f[:, 1].view(n, 1, 1)
    fz = f[:, 2].view(n, 1)
    # Lerp along x, then y, then z; the derivatives follow the same factorization.
    c0, c1 = c[..., 0], c[..., 1]  # (N, C, 2, 2) over (z, y)
    cx = c0 + fx * (c1 - c0)
    cxy = cx[..., 0] + fy * (cx[..., 1] - cx[..., 0])  # (N, C, 2) over z
    value = cxy[..., 0] + fz * (cxy[..., 1] - cxy[..., 0])  # (N, C)
    if not with_grad:
        return value, None
    dx = c1 - c0  # d/dfx, (N, C, 2, 2)
    dx_y = dx[..., 0] + fy * (dx[..., 1] - dx[..., 0])  # (N, C, 2)
    gx = dx_y[..., 0] + fz * (dx_y[..., 1] - dx_y[..., 0])
    dy = cx[..., 1] - cx[..., 0]  # (N, C, 2)
    gy = dy[..., 0] + fz * (dy[..., 1] - dy[..., 0])
    gz = cxy[..., 1] - cxy[..., 0]
    return value, torch.stack([gx, gy, gz], dim=-1)


def _corners(u: Tensor, shape: tuple[int, int, int]) -> tuple[Tensor, Tensor]:
    """Corner indices and fractional offsets of points in a (Z, Y, X) grid.

    u: (N, 3) index coordinates (x, y, z), clamped to the grid -> idx (N, 8) long flat indices
    in corner order z, y, x (x fastest), f (N, 3) offsets in [0, 1] inside the cell.
    """
    Z, Y, X = shape
    size = device_vector([X, Y, Z], u.device, u.dtype)
    u = torch.minimum(torch.clamp(u, min=0.0), size - 1)
    i0 = torch.minimum(u.detach().floor(), size - 2)
    f = u - i0
    i0 = i0.long()
    base = (i0[:, 2] * Y + i0[:, 1]) * X + i0[:, 0]  # (N,)
    offs = device_vector(
        [0, 1, X, X + 1, X * Y, X * Y + 1, X * Y + X, X * Y + X + 1], u.device, torch.long
    )
    return base[:, None] + offs, f


class GradBuffers:
    """Dense gradient buffers handed back after an optimizer step, reused by the next backward
    of `trilinear_sample`.

    A fresh (C, M) zero gradient of a fine feature grid (52 MB at the fast preset's final
    resolution) is new memory every step: the allocator maps it and the zero fill pays a page
    fault per 4 kB, ~4x the cost of zeroing memory already in use
    (benchmarks/results/history/train_step_speed.md). The owner gives a gradient back only when
    nothing else refers to it (`svolsdf.field.grid.GridSDFField.recycle_grads`, called by the
    trainer before it clears the gradients).
    """

    def __init__(self) -> None:
        self._free: dict[tuple, list[Tensor]] = {}

    def give(self, t: Tensor) -> None:
        """Keep the contiguous tensor t (any shape) for a later `take` of its shape."""
        if t.is_contiguous():
            self._free.setdefault((tuple(t.shape), t.dtype, t.device), []).append(t.detach())

    def take(self, shape: tuple[int, ...], like: Tensor) -> Tensor:
        """A zeroed tensor of ``shape`` with ``like``'s dtype and device: a kept one (no longer
        kept) or a new one."""
        kept = self._free.get((tuple(shape), like.dtype, like.device))
        return kept.pop().zero_() if kept else like.new_zeros(shape)

    def clear(self) -> None:
        """Drop every kept tensor (e.g. after the grids changed shape)."""
        self._free.clear()


def trilinear_sample(grid: Tensor, u: Tensor, buffers: GradBuffers | None = None) -> Tensor:
    """Trilinear interpolation of a dense grid, as one weighted sum of the 8 gathered corners.

    Args:
        grid: (C, Z, Y, X) float node values.
        u: (N, 3) float continuous index coordinates (x, y, z), clamped to the grid.
        buffers: where the backward takes its (C, Z Y X) gradient from (`GradBuffers`);
            None: a new one.

    Returns:
        (N, C) values, equal to ``grid_sample(mode="bilinear", align_corners=True)``.

    Why not ``grid_sample``: on the CPU its 3-D kernels split the work over the batch only
    (``at::parallel_for(0, N, ...)`` in ATen's GridSampler.cpp), so one grid runs on one thread,
    and its backward was the slowest op of a training step. The gather and its backward (an
    index-add of N x 8 x C values) run multi-threaded, and the weights make the backward one
    product instead of the seven lerps' chain (benchmarks/results/history/train_step_speed.md).
    """
    _check_grid_points(grid, u)
    C = grid.shape[0]
    idx, f = _corners(u, tuple(grid.shape[1:]))
    # corner-major (8, N): every product and sum below runs along the N points
    wx, wy, wz = (torch.stack([1.0 - f[:, k], f[:, k]]) for k in range(3))  # (2, N)
    w = (wz[:, None, None] * wy[None, :, None] * wx[None, None, :]).reshape(8, -1)
    idx = idx.T.reshape(-1)  # (8 N,) corner k of point n at k N + n
    flat = grid.reshape(C, -1)
    if w.requires_grad and torch.is_grad_enabled():
        # d value / d u is wanted (the residual SDF's x-gradient): plain autograd
        return (flat.index_select(1, idx).view(C, 8, -1) * w).sum(1).T
    return _CornerSum.apply(flat, idx, w.detach(), buffers)


class _CornerSum(torch.autograd.Function):
    """out (N, C) = sum_k w[k, n] flat[:, idx[k N + n]] for flat (C, M), idx (8 N,), w (8, N).

    The autograd expression of `trilinear_sample` with a backward of one product on
    contiguous (C, 8, N) tensors and one index-add into the (C, M) gradient. Under autograd
    (corners last, (C, N, 8)) the transposed output's gradient reached the product in a
    strided layout, and the product and the view before the index-add made strided passes over
    C x N x 8 values (``aten::copy_`` and ``aten::mul``, then the largest ops of a training
    step; benchmarks/results/history/train_step_speed.md). The weights are constants here
    (callers that differentiate with respect to the points take the autograd expression); the
    backward is made of differentiable ops, so a gradient of the grid's gradient is still
    available.
    """

    @staticmethod
    def forward(ctx, flat: Tensor, idx: Tensor, w: Tensor, buffers: GradBuffers | None
                ) -> Tensor:
        ctx.save_for_backward(idx, w)
        ctx.n_nodes = flat.shape[1]
        ctx.buffers = buffers
        c = flat.index_select(1, idx).view(flat.shape[0], 8, -1)
        return (c * w).sum(1).T

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        idx, w = ctx.saved_tensors
        if not ctx.needs_input_grad[0]:
            return None, None, None, None
        C = grad_out.shape[1]
        gc = grad_out.T.contiguous()[:, None] * w  # (C, 8, N), contiguous
        if ctx.buffers is None or torch.is_grad_enabled():  # (create_graph: a new tensor)
            grad = gc.new_zeros(C, ctx.n_nodes)
        else:
            grad = ctx.buffers.take((C, ctx.n_nodes), gc)
        return grad.index_add_(1, idx, gc.view(C, -1)), None, None, None


def trilinear_reference(grid: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """Slow reference for `trilinear_with_grad`: ``grid_sample`` and an autograd gradient.

    grid: (C, Z, Y, X), u: (N, 3) index coordinates strictly inside the grid ->
    value (N, C), grad (N, C, 3) in index units.
    """
    _check_grid_points(grid, u)
    C, Z, Y, X = grid.shape
    size = torch.tensor([X, Y, Z], device=u.device, dtype=u.dtype)
    u = u.detach().clone().requires_grad_(True)
    g = (u / (size - 1) * 2 - 1).view(1, -1, 1, 1, 3)
    v = F.grid_sample(grid[None], g, align_corners=True).view(C, -1).T  # (N, C)
    grads = [
        torch.autograd.grad(v[:, k].sum(), u, retain_graph=True, create_graph=True)[0]
        for k in range(C)
    ]
    return v, torch.stack(grads, dim=1)


def resample_grid(grid: Tensor, size: tuple[int, int, int]) -> Tensor:
    """Resample a (C, Z, Y, X) grid to (C, *size) (size = (Z, Y, X)) by trilinear interpolation.

    With align_corners=True the box corners stay nodes, so the resampled grid represents the
    same function up to the interpolation error between old nodes (exactly the same function
    when every new size is k (old - 1) + 1 for an integer k).
    """
    if grid.dim() != 4:
        raise ValueError(f"grid must be (C, Z, Y, X), got shape {tuple(grid.shape)}")
    return F.interpolate(grid[None], size=tuple(size), mode="trilinear", align_corners=True)[0]


def laplacian_loss(grid: Tensor, n_samples: int | None = None) -> Tensor:
    """Mean squared discrete second derivative of a (C, Z, Y, X) grid along each axis.

    L = mean_{v, axis} (g[v + e_axis] - 2 g[v] + g[v - e_axis])^2, over interior nodes v.
    Unlike total variation this is zero for any linear function, so on an SDF grid it penalises
    curvature without fighting the eikonal constraint |grad f| = 1 (sparse views need it).

    Args:
        grid: (C, Z, Y, X) float.
        n_samples: if given, the mean over this many random interior nodes (cost O(n_samples),
            unbiased); if None, over all interior nodes.

    Returns:
        () scalar loss, in grid-value units squared.
    """
    if grid.dim() != 4 or min(grid.shape[1:]) < 3:
        raise ValueError(f"grid must be (C, Z, Y, X) with >= 3 nodes per axis, got {grid.shape}")
    C, Z, Y, X = grid.shape
    if n_samples is None:
        lz = grid[:, 2:] - 2 * grid[:, 1:-1] + grid[:, :-2]
        ly = grid[:, :, 2:] - 2 * grid[:, :, 1:-1] + grid[:, :, :-2]
        lx = grid[..., 2:] - 2 * grid[..., 1:-1] + grid[..., :-2]
        return (lz.square().mean() + ly.square().mean() + lx.square().mean()) / 3
    dev = grid.device
    z = torch.randint(1, Z - 1, (n_samples,), device=dev)
    y = torch.randint(1, Y - 1, (n_samples,), device=dev)
    x = torch.randint(1, X - 1, (n_samples,), device=dev)
    centre = (z * Y + y) * X + x
    steps = device_vector([1, X, X * Y], dev, torch.long)
    flat = grid.reshape(C, -1)
    plus_idx = (centre[:, None] + steps).reshape(-1)
    minus_idx = (centre[:, None] - steps).reshape(-1)
    idx = torch.cat([centre, plus_idx, minus_idx])
    v = flat.index_select(1, idx)
    c = v[:, :n_samples, None]
    plus = v[:, n_samples : 4 * n_samples].reshape(C, n_samples, 3)
    minus = v[:, 4 * n_samples :].reshape(C, n_samples, 3)
    return (plus - 2 * c + minus).square().mean()


def total_variation_loss(grid: Tensor) -> Tensor:
    """Mean squared first difference of a (C, Z, Y, X) grid along each axis -> () scalar.

    L = mean_{v, axis} (g[v + e_axis] - g[v])^2 (a smoothness prior for feature grids).
    """
    if grid.dim() != 4:
        raise ValueError(f"grid must be (C, Z, Y, X), got shape {tuple(grid.shape)}")
    dz = (grid[:, 1:] - grid[:, :-1]).square().mean()
    dy = (grid[:, :, 1:] - grid[:, :, :-1]).square().mean()
    dx = (grid[..., 1:] - grid[..., :-1]).square().mean()
    return (dz + dy + dx) / 3
