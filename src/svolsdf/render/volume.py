"""Volume rendering of a :class:`SurfaceModel` along rays (docs/method.md 5.4, 5.5).

Generic over any SurfaceModel (the paper MLP, grid fields, analytic test models) and over any
sampler returning sorted distances ``z`` (R, S). No Python loops over rays or samples.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor
from torch.profiler import record_function

from svolsdf.field.base import SurfaceModel
from svolsdf.render.rays import RayBundle, rays_from_cameras
from svolsdf.render.samplers import ErrorBoundSampler
from svolsdf.scene.cameras import Cameras

__all__ = ["RenderOutput", "composite", "render_rays", "render_image"]


@dataclass
class RenderOutput:
    """Per-ray results of :func:`render_rays` (S foreground samples).

    Attributes:
        rgb: (R, 3) composited colour (foreground + bg_transmittance * background).
        depth: (R,) foreground z-depth cos * sum_i w_i z_i / (sum_i w_i + 1e-8).
        weights: (R, S) foreground weights w_i = alpha_i T_i.
        opacity: (R,) sum_i w_i.
        normals: (R, 3) sum_i w_i grad_i / |grad_i| (world frame).
        sdf: (R, S) SDF at the samples (sphere-clamped).
        points: (R, S, 3) sample positions.
        grad: (R, S, 3) d sdf / dx at the samples (differentiable when ``create_graph``).
        z: (R, S) sample distances along the rays (ray distance).
        depth_all: (R,) z-depth including the background (= depth without one); docs/method.md 5.5.
        bg_transmittance: (R,) transmittance left after the foreground (zeros without background
            unless the last interval is bounded).
    """

    rgb: Tensor
    depth: Tensor
    weights: Tensor
    opacity: Tensor
    normals: Tensor
    sdf: Tensor
    points: Tensor
    grad: Tensor
    z: Tensor
    depth_all: Tensor
    bg_transmittance: Tensor


def composite(sigma: Tensor, deltas: Tensor) -> tuple[Tensor, Tensor]:
    """Alpha compositing (docs/method.md 5.4).

    alpha_i = 1 - exp(-sigma_i delta_i), T_i = exp(-sum_{j<i} sigma_j delta_j), w_i = alpha_i T_i.

    Args:
        sigma, deltas: (R, S).

    Returns:
        weights (R, S), transmittance after the last sample (R,).
    """
    with record_function("svolsdf.composite"):
        fe = sigma * deltas
        cum = torch.cumsum(fe, dim=-1)
        shifted = torch.cat([torch.zeros_like(cum[:, :1]), cum[:, :-1]], dim=-1)
        w = (1.0 - torch.exp(-fe)) * torch.exp(-shifted)
        return w, torch.exp(-cum[:, -1])


def render_rays(
    model: SurfaceModel,
    rays: RayBundle,
    z: Tensor,
    background: Callable | None = None,
    bounded_last: bool = False,
    create_graph: bool | None = None,
    colour_min_weight: float = 0.0,
) -> RenderOutput:
    """Render R rays at sample distances z (docs/method.md 5.4; background 5.5).

    delta_i = z_{i+1} - z_i with the last delta 1e10, or, when ``bounded_last`` or with a
    ``background``, the last entry of z is the far bound: it is not a sample, and the last delta
    is z_max - z_{S-1} (docs/method.md 5.5). rgb = sum_i w_i c_i (+ T_bg * rgb_bg);
    depth = cos * sum_i w_i z_i / (sum_i w_i + 1e-8).

    Args:
        model: the surface model.
        rays: R rays (unit frame).
        z: (R, S) sorted distances.
        background: optional callable ``background(rays, training) -> (rgb (R, 3),
            sum_k w_k t_k (R,), sum_k w_k (R,))`` with t_k background ray distances
            (see :class:`svolsdf.field.background.NeRFPlusPlusBackground`).
        bounded_last: see above (implied by ``background``).
        create_graph: keep the SDF gradient differentiable (default ``model.training``).
        colour_min_weight: > 0 evaluates the colour only at samples whose weight exceeds it
            (0 = every sample, exact). Without gradients any model; with ``create_graph``
            (training) models with ``sdf_grad`` and ``colour_features`` (the grid field), others
            take every sample.

    Returns:
        RenderOutput (its S excludes the far bound when the last interval is bounded).
    """
    R = len(rays)
    if z.ndim != 2 or z.shape[0] != R:
        raise ValueError(f"render_rays: z must be (R, S) with R = {R}, got {tuple(z.shape)}")
    create_graph = model.training if create_graph is None else create_graph
    bounded = bounded_last or background is not None
    if bounded:
        z_max = z[:, -1:]
        z = z[:, :-1]
    S = z.shape[1]
    points = rays.origins[:, None] + z[..., None] * rays.dirs[:, None]  # (R, S, 3)
    flat = points.reshape(-1, 3)
    view_dirs = rays.dirs[:, None].expand(R, S, 3).reshape(-1, 3)
    last = (z_max - z[:, -1:]) if bounded else torch.full_like(z[:, :1], 1e10)
    deltas = torch.cat([z[:, 1:] - z[:, :-1], last], dim=-1)
    if colour_min_weight > 0 and create_graph and _has_split_colour(model):
        # training (docs/method.md 5.4 compositing, train.colour_min_weight): the SDF and its
        # gradient at every sample (the weights, the eikonal sample and the normals need them),
        # the colour features and the colour network only where a sample's weight exceeds the
        # threshold; the dropped samples' colour terms w_i c_i sum to less than
        # S * colour_min_weight per ray, and their weights keep their gradient through the
        # transmittance of the kept ones
        sdf, grad = model.sdf_grad(flat, create_graph=True)
        sdf = sdf.reshape(R, S)
        w, t_after = composite(model.density(sdf), deltas)
        keep = (w.detach().reshape(-1) > colour_min_weight).nonzero()[:, 0]
        f_k = model.colour_features(flat[keep])
        rgb_k = model.colour(flat[keep], view_dirs[keep], grad[keep], f_k)
        rgb_s = torch.zeros(R * S, 3, dtype=rgb_k.dtype, device=w.device).index_copy(
            0, keep, rgb_k).reshape(R, S, 3)
    elif colour_min_weight > 0:
        # rendering: the weights need only the SDF; gradients, features and colour are then
        # evaluated only where a sample contributes (the dropped terms sum to less than
        # S * colour_min_weight per ray)
        sdf = model.sdf(flat).reshape(R, S)
        w, t_after = composite(model.density(sdf), deltas)
        keep = (w.reshape(-1) > colour_min_weight).nonzero()[:, 0]
        _, g_k, f_k = model.sdf_and_grad(flat[keep], create_graph=False)
        grad = torch.zeros(R * S, 3, dtype=w.dtype, device=w.device)
        grad[keep] = g_k.to(w.dtype)
        rgb_flat = torch.zeros(R * S, 3, dtype=w.dtype, device=w.device)
        rgb_flat[keep] = model.colour(flat[keep], view_dirs[keep], g_k, f_k).to(w.dtype)
        rgb_s = rgb_flat.reshape(R, S, 3)
    else:
        sdf, grad, feat = model.sdf_and_grad(flat, create_graph=create_graph)
        sdf = sdf.reshape(R, S)
        w, t_after = composite(model.density(sdf), deltas)
        rgb_s = model.colour(flat, view_dirs, grad, feat).reshape(R, S, 3)
    grad = grad.reshape(R, S, 3)
    opacity = w.sum(-1)
    rgb = (w[..., None] * rgb_s).sum(1)
    depth = rays.cos * (w * z).sum(-1) / (opacity + 1e-8)
    normals = (w[..., None] * grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-12)).sum(1)
    depth_all = depth
    if not bounded:
        t_after = torch.zeros_like(opacity)
    if background is not None:
        rgb_bg, wz_bg, wsum_bg = background(rays, model.training)
        rgb = rgb + t_after[:, None] * rgb_bg
        # expected z-depth over foreground weights and T_bg-scaled background weights (5.5)
        depth_all = rays.cos * ((w * z).sum(-1) + t_after * wz_bg) / (
            opacity + t_after * wsum_bg + 1e-8)
    return RenderOutput(rgb, depth, w, opacity, normals, sdf, points, grad, z, depth_all, t_after)


def _has_split_colour(model: SurfaceModel) -> bool:
    """The model computes the SDF's gradient without the colour features (``sdf_grad``) and
    the colour features on their own (``colour_features``): the grid field."""
    return callable(getattr(model, "sdf_grad", None)) and \
        callable(getattr(model, "colour_features", None))


def render_image(
    model: SurfaceModel,
    cameras: Cameras,
    view_index: int,
    chunk: int = 1024,
    sampler: Callable | None = None,
    background: Callable | None = None,
    near: float = 1e-4,
    far_mode: str = "sphere",
) -> dict[str, Tensor]:
    """Render a full image of view ``view_index`` in eval mode, ``chunk`` rays at a time.

    Memory is bounded by one chunk: no autograd graph is kept (the SDF gradient for normals is
    taken with grad enabled locally inside ``model.sdf_and_grad`` and detached). The model's
    training flag is restored afterwards.

    Args:
        model: the surface model.
        cameras: unit-frame cameras (``Scene.cameras_unit``).
        view_index: index into ``cameras``.
        chunk: rays per forward pass.
        sampler: ``sampler(model, rays, training=False)`` with a ``.z`` result (default: the
            error-bounded sampler, 5 iterations).
        background: optional background model (see :func:`render_rays`).
        near, far_mode: ray bounds (see :func:`rays_from_cameras`).

    Returns:
        dict with "rgb" (H, W, 3), "depth" (H, W) z-depth (unit frame), "depth_all" (H, W),
        "opacity" (H, W), "normals" (H, W, 3) (all detached, on the cameras' device).
    """
    if chunk < 1:
        raise ValueError(f"render_image: chunk must be >= 1, got {chunk}")
    sampler = sampler or ErrorBoundSampler()
    H, W = cameras.height, cameras.width
    rays = rays_from_cameras(cameras, int(view_index), radius=model.radius, near=near,
                             far_mode=far_mode)
    keys = ("rgb", "depth", "depth_all", "opacity", "normals")
    parts: dict[str, list[Tensor]] = {k: [] for k in keys}
    was_training = model.training
    model.eval()
    try:
        with torch.no_grad():
            for i in range(0, len(rays), chunk):
                rb = rays[i:i + chunk]
                s = sampler(model, rb, training=False)
                out = render_rays(model, rb, s.z, background=background, create_graph=False)
                for k in keys:
                    parts[k].append(getattr(out, k).detach())
    finally:
        model.train(was_training)
    res = {k: torch.cat(v, dim=0) for k, v in parts.items()}
    return {k: v.reshape(H, W, *v.shape[1:]) for k, v in res.items()}
