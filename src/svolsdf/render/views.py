"""A fitted field rendered for whole cameras (guide depth, novel views, previews), and the
guide-depth rule of docs/method.md 6.1 for pixels the field barely covers.

Depths here are unit-frame z-depths unless a function says world; the renderer works in ray
distance inside (`svolsdf.render.volume`).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from svolsdf.io.progress import progress_bar
from svolsdf.mvs.volume import ProbabilityVolume
from svolsdf.scene.cameras import Cameras

__all__ = ["guide_depths", "guide_pixels", "max_rule_filled", "render_field_views"]


@torch.no_grad()
def render_field_views(model, sampler, cameras_unit: Cameras,
                       near_far: torch.Tensor | None = None, chunk: int = 4096,
                       keys=("depth", "opacity", "rgb", "normals"),
                       pixels: torch.Tensor | None = None,
                       device=None, desc: str = "render the field") -> dict[str, torch.Tensor]:
    """Render every camera of ``cameras_unit`` with the field (``sampler``: the eval-mode one).

    ``chunk`` rays at a time: 4096 rendered the fast field ~10 % faster than 2048 or 8192
    on two cores (benchmarks/results/history/train_step_speed.md, commit c3e3801).

    Args:
        model: the `SurfaceModel` (put in eval mode here); its ``background`` (docs/method.md 5.5)
            when it has one.
        sampler: ``sampler(model, rays, training=False)`` -> samples with ``z`` (R, S).
        cameras_unit: V unit-frame cameras of size (W, H).
        near_far: optional (V, 2) unit-frame z-depth range per camera; rays are clipped to it
            (without a background also at the far end) and to the field's bounding sphere.
        pixels: optional (V, H, W) bool; only these pixels are rendered, the others get 0
            in every map (depth, opacity, colour and normal).
        device: where the field renders.
        desc: the name of its progress bar (shown for more than one camera).

    Returns:
        dict of (V, H, W, ...) tensors on the CPU: depth (unit-frame z-depth), opacity, rgb,
        normals.
    """
    from svolsdf.render.rays import rays_from_cameras
    from svolsdf.render.volume import render_rays

    model.eval()
    background = model.get_background()
    cams = cameras_unit.to(device, dtype=torch.float32)
    H, W = cams.height, cams.width
    res = {k: [] for k in keys}
    for t in progress_bar(range(len(cams)), desc=desc, show=None if len(cams) > 1 else False):
        rays = rays_from_cameras(cams, t, radius=float(model.radius))
        if near_far is not None:
            rays.near = torch.maximum(rays.near, near_far[t, 0] / rays.cos)
            # with a background the foreground ends at the sphere (docs/method.md 5.5)
            far = rays.far if background is not None else torch.minimum(
                rays.far, near_far[t, 1] / rays.cos)
            rays.far = torch.maximum(far, rays.near + 1e-3)
        sel = None  # (R,) indices of the rendered pixels, on the CPU
        if pixels is not None:
            sel = pixels[t].reshape(-1).nonzero()[:, 0].cpu()
            rays = rays[sel.to(device)]
        parts = {k: [] for k in keys}
        for i in range(0, len(rays), chunk):
            rb = rays[i:i + chunk]
            s = sampler(model, rb, training=False)
            o = render_rays(model, rb, s.z, background=background, create_graph=False,
                            colour_min_weight=1e-4)
            for k in keys:
                parts[k].append(getattr(o, k).detach().cpu())
        for k in keys:
            v = torch.cat(parts[k])
            if sel is not None:
                full = v.new_zeros((H * W, *v.shape[1:]))
                full[sel] = v
                v = full
            res[k].append(v.reshape(H, W, *v.shape[1:]))
    return {k: torch.stack(v) for k, v in res.items()}


def guide_pixels(masks: torch.Tensor | None, mask_dilation: int | None) -> torch.Tensor | None:
    """(V, H, W) bool: the pixels whose guide depth is rendered, the object masks dilated by
    ``mask_dilation`` px (``guide.mask_dilation``; None: every pixel, as released; also
    without masks).

    Args:
        masks: (V, 1, H, W) object masks at the cameras' size, or None.
    """
    if mask_dilation is None or masks is None:
        return None
    from svolsdf.geometry import dilate_mask

    m = masks[:, 0] > 0.5  # (V, H, W) at the working size, as the cameras
    # a view whose mask is empty is rendered whole (its guide then follows the rule alone)
    return torch.stack([dilate_mask(m[i], int(mask_dilation)) if bool(m[i].any())
                        else torch.ones_like(m[i]) for i in range(len(m))])


def guide_depths(depth: torch.Tensor, opacity: torch.Tensor, view_ids: list[int], scale: float,
                 low_weight_rule: str, volumes: list[ProbabilityVolume] | None = None
                 ) -> dict[int, torch.Tensor]:
    """The guide z-depth (world) of each input view from its rendering, with docs/method.md 6.1's
    rule for pixels of accumulated weight < 0.2.

    Args:
        depth: (V, H, W) rendered unit-frame z-depth; opacity: (V, H, W) sum of the weights.
        view_ids: the V views' ids.
        scale: the normalization's scale (unit -> world).
        low_weight_rule: ``guide.low_weight_rule``: "max" (the map's maximum depth,
            docs/method.md 6.1), "mvs" (the stage-1 MVS depth of ``volumes``) or anything else
            (kept as rendered).
        volumes: the V stage-1 volumes with their regressed depth, for "mvs" (None: kept).

    Returns:
        {view id: (H, W) float32 world z-depth}.
    """
    guide = {}
    for i, v in enumerate(view_ids):
        d = depth[i] * scale
        low = opacity[i] < 0.2
        if low_weight_rule == "max":
            # docs/method.md 6.1: pixels with sum w < 0.2 get the map's maximum depth
            d = torch.where(low, d[~low].max() if (~low).any() else d.max(), d)
        elif low_weight_rule == "mvs" and volumes is not None:
            m = volumes[i].depth[None, None]
            m = F.interpolate(m, size=d.shape, mode="bilinear")[0, 0]
            d = torch.where(low, m, d)
        guide[v] = d.float()
    return guide


def max_rule_filled(guide: torch.Tensor) -> torch.Tensor:
    """(H, W) bool: the pixels of a guide made with `guide_depths`' "max" rule that hold its
    fill, the map's maximum depth (docs/method.md 6.1: accumulated weight < 0.2, or not rendered),
    not a depth of the field's surface. The fill is the largest depth of the covered pixels, so
    the few covered pixels at exactly that depth are counted too; a map without a finite
    positive depth is all fill.

    Args:
        guide: (H, W) world z-depth from `guide_depths` with rule "max".
    """
    if guide.ndim != 2:
        raise ValueError(f"max_rule_filled: expected an (H, W) depth map, got "
                         f"{tuple(guide.shape)}")
    ok = torch.isfinite(guide) & (guide > 0)
    if not ok.any():
        return torch.ones_like(ok)
    return guide == guide[ok].max()
