"""Mesh culling by the input views: frusta, object masks, visibility, and the sequence a
reconstruction's mesh goes through (`cull_to_views`).

Meshes are (vertices (V, 3) float32, faces (F, 3) int64) torch tensors on the CPU, in the world
frame of the cameras, as in `svolsdf.fusion.mesh_ops`.
"""

from __future__ import annotations

import logging

import torch
from torch import Tensor

from svolsdf.fusion.mesh_ops import _check_mesh, _in_image, largest_component, submesh
from svolsdf.geometry import dilate_mask
from svolsdf.scene.cameras import Cameras

__all__ = [
    "cull_by_frusta",
    "cull_by_masks",
    "cull_to_views",
    "cull_unseen",
    "mask_cull_dilation",
    "mesh_vertex_depths",
]

log = logging.getLogger(__name__)


def _centroids(vertices: Tensor, faces: Tensor) -> Tensor:
    return vertices.double()[faces].mean(dim=1)


def _pixel_at(cam: Cameras, points: Tensor, image: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Nearest-pixel value of ``image`` (H, W) at the projections of ``points`` (N, 3) into
    the one-view ``cam`` (resized to the image): (in_image (N,) bool, value (N,), z (N,))."""
    cam = cam.resize(image.shape[1], image.shape[0])
    uv, z = cam.project(points)
    uv, z = uv[0], z[0]
    ij = uv.round().long()
    ij[:, 0] = ij[:, 0].clamp(0, cam.width - 1)
    ij[:, 1] = ij[:, 1].clamp(0, cam.height - 1)
    return _in_image(uv, z, cam.width, cam.height), image[ij[:, 1], ij[:, 0]], z


def cull_by_frusta(
    vertices: Tensor, faces: Tensor, cameras: Cameras, near: float = 0.0
) -> tuple[Tensor, Tensor, Tensor]:
    """Remove faces whose centroid lies inside no view's frustum.

    Args:
        vertices: (V, 3) world points; faces: (F, 3).
        cameras: `Cameras` (any number of views) in the same world frame.
        near: least z-depth in front of a camera.

    Returns:
        vertices (V', 3), faces (F', 3), vertex_index (V',) as `submesh`.
    """
    vertices, faces = _check_mesh(vertices, faces)
    c = _centroids(vertices, faces)
    cams = cameras.to(dtype=torch.float64)
    uv, z = cams.project(c)
    inside = (_in_image(uv, z, cams.width, cams.height) & (z > near)).any(dim=0)
    log.info("frustum culling keeps %d of %d faces", int(inside.sum()), len(faces))
    return submesh(vertices, faces, inside)


def cull_by_masks(
    vertices: Tensor,
    faces: Tensor,
    cameras: Cameras,
    masks: Tensor,
    dilation: int = 12,
    mode: str = "any",
) -> tuple[Tensor, Tensor, Tensor]:
    """Remove faces whose centroid projects outside the (dilated) object mask.

    Only views whose frustum contains the centroid judge a face; faces seen by no view are kept
    (use `cull_by_frusta` to remove those).

    Args:
        vertices: (V, 3) world points; faces: (F, 3).
        cameras: `Cameras` with V views.
        masks: (V, 1, Hm, Wm) or (V, Hm, Wm) object masks (any resolution; 1 = object).
        dilation: disk radius in mask pixels (docs/method.md 6.3 uses 12).
        mode: "any" removes a face outside the mask in any view that sees it (strict);
            "all" removes it only if it is outside in every view that sees it.

    Returns:
        vertices (V', 3), faces (F', 3), vertex_index (V',) as `submesh`.
    """
    if mode not in ("any", "all"):
        raise ValueError(f"mode must be 'any' or 'all', got {mode!r}")
    vertices, faces = _check_mesh(vertices, faces)
    if masks.ndim == 4:
        masks = masks[:, 0]
    if masks.ndim != 3 or masks.shape[0] != len(cameras):
        raise ValueError(f"masks must be ({len(cameras)}, H, W), got {tuple(masks.shape)}")
    c = _centroids(vertices, faces)
    cams = cameras.to(dtype=torch.float64)
    seen = torch.zeros(len(cams), len(faces), dtype=torch.bool)
    outside = torch.zeros_like(seen)
    for v in range(len(cams)):
        s, inside, _ = _pixel_at(cams[v], c, dilate_mask(masks[v], dilation))
        seen[v] = s
        outside[v] = s & ~inside
    if mode == "any":
        remove = outside.any(dim=0)
    else:
        remove = seen.any(dim=0) & (outside | ~seen).all(dim=0)
    log.info("mask culling (%s) removes %d of %d faces", mode, int(remove.sum()), len(faces))
    return submesh(vertices, faces, ~remove)


def cull_unseen(
    vertices: Tensor,
    faces: Tensor,
    cameras: Cameras,
    depths: Tensor,
    rel_tol: float = 0.01,
) -> tuple[Tensor, Tensor, Tensor]:
    """Remove faces that no view sees: the centroid lies behind the view's surface depth.

    A face is kept when, in at least one view whose image contains its centroid, the
    centroid's z-depth is at most ``(1 + rel_tol)`` times that view's depth at the projected
    pixel (nearest pixel; a view without depth there, <= 0, does not see it). The depths are
    the field's rendered depths of the input views (OUT/field/render_depth), so what remains is
    the surface the views observe; parts hidden from every view, such as cavities inside the
    object that nothing constrains, go. A mask-free twin of the DTU evaluations' culling
    (docs/method.md 8.3) for surfaces occluded rather than outside the masks.

    Args:
        vertices: (V, 3) world points; faces: (F, 3).
        cameras: `Cameras` with N views.
        depths: (N, H, W) z-depth maps of those views (any resolution).
        rel_tol: relative depth slack (the rendered depth is an expectation, not the exact
            first hit).

    Returns:
        vertices (V', 3), faces (F', 3), vertex_index (V',) as `submesh`.
    """
    vertices, faces = _check_mesh(vertices, faces)
    if depths.ndim != 3 or depths.shape[0] != len(cameras):
        raise ValueError(f"depths must be ({len(cameras)}, H, W), got {tuple(depths.shape)}")
    c = _centroids(vertices, faces)
    cams = cameras.to(dtype=torch.float64)
    seen = torch.zeros(len(faces), dtype=torch.bool)
    for v in range(len(cams)):
        s, dv, z = _pixel_at(cams[v], c, depths[v].double())
        seen |= s & (dv > 0) & (z <= (1 + rel_tol) * dv)
    log.info("visibility culling keeps %d of %d faces", int(seen.sum()), len(faces))
    return submesh(vertices, faces, seen)


def mesh_vertex_depths(vertices: torch.Tensor, cameras, scale: float = 0.5) -> torch.Tensor:
    """(V, h, w) z-depth of a dense world mesh seen from each camera, at ``scale`` x the cameras'
    size: a z-buffer of its vertices (the nearest vertex per pixel; 0 where none falls).

    A marching-cubes mesh at the mesh resolution has several vertices per pixel at half the
    working size, so the vertex z-buffer is its depth map without rasterizing triangles.

    Args:
        vertices: (N, 3) world points.
        cameras: world `Cameras` of V views.
    """
    w = max(1, round(cameras.width * scale))
    h = max(1, round(cameras.height * scale))
    cams = cameras.resize(w, h).to(dtype=torch.float64)
    out = []
    for k in range(len(cams)):
        uv, z = cams[k].project(vertices.double()[None])
        uv, z = uv[0], z[0]
        px = uv.round().long()
        ok = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        idx = px[ok, 1] * w + px[ok, 0]
        buf = torch.full((h * w,), float("inf"), dtype=torch.float64)
        buf.scatter_reduce_(0, idx, z[ok], reduce="amin")
        out.append(torch.where(torch.isfinite(buf), buf, 0.0).reshape(h, w).float())
    return torch.stack(out)


def mask_cull_dilation(width: int) -> int:
    """Mask dilation (px) of the mesh culling at an image ``width``: docs/method.md 6.3's 12 px at
    1600 wide, scaled, at least 2."""
    return max(2, round(12 * width / 1600))


def cull_to_views(
    vertices: Tensor,
    faces: Tensor,
    cameras: Cameras,
    masks: Tensor | None = None,
    unseen: bool = False,
    depths: Tensor | str | None = "mesh",
    rel_tol: float = 0.01,
    largest: bool = True,
) -> tuple[Tensor, Tensor, Tensor]:
    """Keep what the input views can judge: faces inside some view's frustum, with ``masks``
    inside the dilated object mask of every view that sees them (the mesh culling of the DTU
    evaluations, docs/method.md 8.3), with ``largest`` the largest component, and with ``unseen``
    only faces some view sees (`cull_unseen`).

    Visibility comes after the largest component: culling splits the surface where no view
    looked, and the parts it leaves are all observed (benchmarks/results/history/fast_preset.md,
    notes of commit 9143dbd).

    Args:
        vertices: (V, 3) world points; faces: (F, 3).
        cameras: world `Cameras` of N views (the input views, at the masks' image size).
        masks: (N, 1, H, W) object masks, or None (no mask culling); dilated by
            `mask_cull_dilation` of the cameras' width.
        unseen: remove faces no view sees.
        depths: what the views see for ``unseen``: (N, H, W) z-depth maps (the field's rendered
            depth), "mesh" (the mesh's own vertex z-buffer, `mesh_vertex_depths`), or None (not
            available: a warning, and hidden faces are kept).
        rel_tol: `cull_unseen`'s relative depth slack.
        largest: keep only the largest connected component (docs/method.md 8.3, for a field's
            zero level, whose other components are floaters); False keeps every part.

    Returns:
        vertices (V', 3), faces (F', 3), vertex_index (V',) int64 indices of the kept vertices
        in the input, as `submesh`.
    """
    vw, f, index = cull_by_frusta(vertices, faces, cameras)
    if masks is not None:
        vw, f, idx = cull_by_masks(vw, f, cameras, masks,
                                   dilation=mask_cull_dilation(cameras.width))
        index = index[idx]
    if largest:
        vw, f, idx = largest_component(vw, f, return_index=True)
        index = index[idx]
    if unseen:
        if isinstance(depths, str):
            depths = mesh_vertex_depths(vw, cameras)
        if depths is None:
            log.warning("mesh: no rendered depth of the input views; faces hidden from every "
                        "view are kept")
        else:
            vw2, f2, idx = cull_unseen(vw, f, cameras, depths, rel_tol)
            if len(f2):
                vw, f, index = vw2, f2, index[idx]
            else:
                log.warning("mesh: no face is visible in the rendered depth; visibility culling "
                            "skipped")
    return vw, f, index
