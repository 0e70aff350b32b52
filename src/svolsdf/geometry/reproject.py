"""Forward-backward reprojection check of a depth map against another view's depth map.

Implements the geometric check of docs/method.md 6.3 (the released
``helpers/utils.py::check_geometric_consistency``), vectorized in torch: a reference pixel is
consistent with a source if its depth, carried to the source, sampled there (bilinear) and
carried back, lands within ``dist_thresh`` pixels of where it started and within a relative
depth difference ``rel_thresh``.

Fusion (`svolsdf.fusion.filter`), the field's initialisation (`svolsdf.field.initial`) and
image-based rendering (`svolsdf.ibr.blend`) all run this check, so it lives below them.

Depth is z-depth in the cameras' world units; pixel centres sit at integer coordinates
(`svolsdf.scene.cameras`).

``check_geometric_consistency_reference`` is a slow per-pixel twin of the vectorized check, kept
for the tests (docs/style.md habit 5).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from svolsdf.scene.cameras import Cameras

__all__ = [
    "check_geometric_consistency",
    "check_geometric_consistency_reference",
]


def _check_camera(cam: Cameras, name: str) -> None:
    if len(cam) != 1:
        raise ValueError(f"{name} must hold exactly one view, got {len(cam)}")


def _check_depth(depth: Tensor, name: str) -> None:
    if depth.ndim != 2:
        raise ValueError(f"{name} must be (H, W), got {tuple(depth.shape)}")


def _at_size(cam: Cameras, depth: Tensor) -> Cameras:
    """The camera resized to the depth map's size (no-op when they already agree)."""
    h, w = depth.shape
    return cam if (cam.width, cam.height) == (w, h) else cam.resize(w, h)


def check_geometric_consistency(
    depth_ref: Tensor,
    cam_ref: Cameras,
    depth_src: Tensor,
    cam_src: Cameras,
    dist_thresh: float = 1.0,
    rel_thresh: float = 0.01,
    pixels: Tensor | None = None,
) -> tuple[Tensor, Tensor, tuple[Tensor, Tensor]]:
    """Forward-backward depth consistency of a reference depth map against one source.

    docs/method.md 6.3, "Geometric check, per source": back-project every reference pixel (u, v)
    with its depth d, project into the source at (x_s, y_s), sample the source depth there
    bilinearly, back-project that source point and reproject it into the reference at (u', v') with
    z-depth d'. The pixel is consistent if ||(u', v') - (u, v)|| < dist_thresh and
    |d' - d| / d < rel_thresh.

    The bilinear sample counts as valid only if every source pixel with a non-zero bilinear weight
    lies inside the source image and has a positive depth (the released code blends with zeros
    outside the image and at holes, which fails the depth test in all but borderline cases).
    Cameras are resized to their depth map's size when they differ.

    Args:
        depth_ref: (H, W) reference z-depth, world units; <= 0 or non-finite = no depth.
        cam_ref: `Cameras` with one view (the reference).
        depth_src: (Hs, Ws) source z-depth.
        cam_src: `Cameras` with one view (the source).
        dist_thresh: reprojection distance threshold in reference pixels.
        rel_thresh: relative depth difference threshold.
        pixels: (K,) long flat indices (v * W + u) of the reference pixels to check; None:
            every pixel. Each pixel's result does not depend on the others: the checked ones
            get the values a full check gives them, the others False, 0 and NaN.

    Returns:
        mask: (H, W) bool, consistent pixels.
        depth_reproj: (H, W) d' (0 where the check is invalid), dtype of ``depth_ref``.
        (x_src, y_src): each (H, W), the projection of the reference pixels into the source.
    """
    _check_depth(depth_ref, "depth_ref")
    _check_depth(depth_src, "depth_src")
    _check_camera(cam_ref, "cam_ref")
    _check_camera(cam_src, "cam_src")
    if pixels is not None:
        return _check_pixels(depth_ref, cam_ref, depth_src, cam_src, dist_thresh, rel_thresh,
                             pixels)
    cam = _at_size(cam_ref, depth_ref)
    uv = cam.pixel_grid(device=depth_ref.device, dtype=torch.float64).reshape(-1, 2)
    return _check_rows(depth_ref, cam, uv, depth_src, cam_src, dist_thresh, rel_thresh)


def _check_rows(depth_ref: Tensor, cam_ref: Cameras, uv: Tensor, depth_src: Tensor,
                cam_src: Cameras, dist_thresh: float, rel_thresh: float
                ) -> tuple[Tensor, Tensor, tuple[Tensor, Tensor]]:
    """The check of reference pixels ``uv`` (H * W, 2) with depths ``depth_ref`` (H, W) (an
    image, or a (1, K) row of chosen pixels), ``cam_ref`` at the reference depth's size."""
    out_dtype = depth_ref.dtype if depth_ref.is_floating_point() else torch.float32
    device = depth_ref.device
    # Geometry in float64: DTU depths are ~600 mm and the test is at 1 % / 1 px.
    dt = torch.float64
    cam_ref = cam_ref.to(device=device, dtype=dt)
    cam_src = _at_size(cam_src, depth_src).to(device=device, dtype=dt)
    H, W = depth_ref.shape
    Hs, Ws = depth_src.shape
    d_ref = depth_ref.to(dt)
    d_src = depth_src.to(device=device, dtype=dt)
    ok_ref = torch.isfinite(d_ref) & (d_ref > 0)
    d_ref = torch.where(ok_ref, d_ref, torch.ones_like(d_ref))  # dummy depth, masked below
    ok_src = torch.isfinite(d_src) & (d_src > 0)
    d_src = torch.where(ok_src, d_src, torch.zeros_like(d_src))

    uv = uv.to(device=device, dtype=dt).reshape(1, -1, 2)  # (1, HW, 2)
    x_world = cam_ref.unproject(uv, d_ref.reshape(1, -1))  # (1, HW, 3)
    uv_s, z_s = cam_src.project(x_world)  # (1, HW, 2), (1, HW)

    # grid_sample with align_corners=True maps -1/+1 to the centres of the first/last pixels,
    # i.e. integer pixel centres (the convention of `Cameras`), like cv2.remap.
    gx = 2.0 * uv_s[..., 0] / max(Ws - 1, 1) - 1.0
    gy = 2.0 * uv_s[..., 1] / max(Hs - 1, 1) - 1.0
    grid = torch.stack([gx, gy], dim=-1).reshape(1, H, W, 2)
    grid = torch.nan_to_num(grid, nan=-4.0, posinf=-4.0, neginf=-4.0)
    stacked = torch.stack([d_src, ok_src.to(dt)], dim=0)[None]  # (1, 2, Hs, Ws)
    sampled = F.grid_sample(
        stacked, grid, mode="bilinear", padding_mode="zeros", align_corners=True
    )[0]
    d_s = sampled[0]  # (H, W)
    # All neighbours with weight > 0 inside and valid <=> the sampled validity is exactly 1.
    ok_s = (sampled[1] > 1.0 - 1e-9) & (z_s.reshape(H, W) > 0)

    uv_s_hw = uv_s.reshape(H, W, 2)
    d_s_safe = torch.where(ok_s, d_s, torch.ones_like(d_s))
    x_back = cam_src.unproject(uv_s_hw.reshape(1, -1, 2), d_s_safe.reshape(1, -1))
    uv_r, z_r = cam_ref.project(x_back)
    uv_r = uv_r.reshape(H, W, 2)
    z_r = z_r.reshape(H, W)

    dist = (uv_r - uv.reshape(H, W, 2)).norm(dim=-1)
    rel = (z_r - d_ref).abs() / d_ref
    valid = ok_ref & ok_s & (z_r > 0) & torch.isfinite(dist) & torch.isfinite(rel)
    mask = valid & (dist < dist_thresh) & (rel < rel_thresh)
    depth_reproj = torch.where(valid, z_r, torch.zeros_like(z_r)).to(out_dtype)
    return mask, depth_reproj, (
        uv_s_hw[..., 0].to(out_dtype),
        uv_s_hw[..., 1].to(out_dtype),
    )


def check_geometric_consistency_reference(
    depth_ref: Tensor,
    cam_ref: Cameras,
    depth_src: Tensor,
    cam_src: Cameras,
    dist_thresh: float = 1.0,
    rel_thresh: float = 0.01,
) -> tuple[Tensor, Tensor, tuple[Tensor, Tensor]]:
    """Slow per-pixel twin of `check_geometric_consistency` (same arguments and returns).

    Loops over the reference pixels with explicit matrices and a hand-written bilinear
    interpolation; only for tests on tiny depth maps.
    """
    _check_depth(depth_ref, "depth_ref")
    _check_depth(depth_src, "depth_src")
    cam_ref = _at_size(cam_ref, depth_ref)
    cam_src = _at_size(cam_src, depth_src)
    Kr = cam_ref.K[0].double().cpu().numpy()
    Er = cam_ref.w2c[0].double().cpu().numpy()
    Ks = cam_src.K[0].double().cpu().numpy()
    Es = cam_src.w2c[0].double().cpu().numpy()
    Kr_inv, Ks_inv = np.linalg.inv(Kr), np.linalg.inv(Ks)
    Er_inv, Es_inv = np.linalg.inv(Er), np.linalg.inv(Es)
    dr = depth_ref.double().cpu().numpy()
    ds = depth_src.double().cpu().numpy()
    H, W = dr.shape
    Hs, Ws = ds.shape
    mask = np.zeros((H, W), bool)
    depth_reproj = np.zeros((H, W))
    xs = np.zeros((H, W))
    ys = np.zeros((H, W))

    def src_depth_at(x: float, y: float) -> float | None:
        x0, y0 = math.floor(x), math.floor(y)
        total = 0.0
        for yy, wy in ((y0, 1 - (y - y0)), (y0 + 1, y - y0)):
            for xx, wx in ((x0, 1 - (x - x0)), (x0 + 1, x - x0)):
                w = wx * wy
                if w <= 1e-12:
                    continue
                if not (0 <= xx < Ws and 0 <= yy < Hs):
                    return None
                d = ds[yy, xx]
                if not (np.isfinite(d) and d > 0):
                    return None
                total += w * d
        return total

    for v in range(H):
        for u in range(W):
            d = dr[v, u]
            ok = np.isfinite(d) and d > 0
            dd = d if ok else 1.0
            cam = Kr_inv @ np.array([u, v, 1.0]) * dd
            world = Er_inv @ np.append(cam, 1.0)
            cs = (Es @ world)[:3]
            zs = cs[2]
            p = Ks @ cs
            x, y = p[0] / zs, p[1] / zs
            xs[v, u], ys[v, u] = x, y
            if not ok or zs <= 0 or not (np.isfinite(x) and np.isfinite(y)):
                continue
            d_s = src_depth_at(x, y)
            if d_s is None:
                continue
            cam_s = Ks_inv @ np.array([x, y, 1.0]) * d_s
            world_s = Es_inv @ np.append(cam_s, 1.0)
            cr = (Er @ world_s)[:3]
            if cr[2] <= 0:
                continue
            pr = Kr @ cr
            ur, vr = pr[0] / cr[2], pr[1] / cr[2]
            depth_reproj[v, u] = cr[2]
            dist = math.hypot(ur - u, vr - v)
            rel = abs(cr[2] - d) / d
            mask[v, u] = dist < dist_thresh and rel < rel_thresh
    dt = depth_ref.dtype
    return (
        torch.from_numpy(mask),
        torch.from_numpy(depth_reproj).to(dt),
        (torch.from_numpy(xs).to(dt), torch.from_numpy(ys).to(dt)),
    )


def _check_pixels(depth_ref: Tensor, cam_ref: Cameras, depth_src: Tensor, cam_src: Cameras,
                  dist_thresh: float, rel_thresh: float, pixels: Tensor
                  ) -> tuple[Tensor, Tensor, tuple[Tensor, Tensor]]:
    """`check_geometric_consistency` at the reference pixels ``pixels`` (K,) only: the same
    arithmetic on a (1, K) row of pixels instead of the (H, W) image, scattered back."""
    H, W = depth_ref.shape
    K = int(pixels.numel())
    row_ref = depth_ref.reshape(-1)[pixels].reshape(1, K)
    cam_row = _at_size(cam_ref, depth_ref)
    grid = cam_row.pixel_grid(device=depth_ref.device, dtype=torch.float64).reshape(-1, 2)
    m, d, (xs, ys) = _check_rows(row_ref, cam_row, grid[pixels], depth_src, cam_src,
                                 dist_thresh, rel_thresh)
    out_dtype = d.dtype
    mask = torch.zeros(H * W, dtype=torch.bool, device=depth_ref.device)
    rep = torch.zeros(H * W, dtype=out_dtype, device=depth_ref.device)
    x_src = torch.full((H * W,), float("nan"), dtype=out_dtype, device=depth_ref.device)
    y_src = x_src.clone()
    mask[pixels], rep[pixels], x_src[pixels], y_src[pixels] = m[0], d[0], xs[0], ys[0]
    return mask.reshape(H, W), rep.reshape(H, W), (x_src.reshape(H, W), y_src.reshape(H, W))
