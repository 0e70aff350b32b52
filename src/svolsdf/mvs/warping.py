"""Differentiable homography warping of source features onto reference depth hypotheses.

docs/method.md 2.3: with P = [K·E_3x4; 0 0 0 1] for each view (`Cameras.proj`), M = P_src·P_ref⁻¹
with rotation part R_m and translation t_m. A reference pixel (x, y) (integer pixel centres) at
hypothesis depth d maps to q = R_m·[x, y, 1]ᵀ·d + t_m, (u, v) = (q₁/q₃, q₂/q₃) in the source.

Sampling: bilinear, zero padding. Our default normalizes û = 2u/(W - 1) - 1 and samples with
``align_corners=True``, so source pixel centre u lands exactly on column u. With
``align_corners_quirk=True`` it reproduces CasMVSNet (docs/method.md 2.3): û = u/((W - 1)/2) - 1
sampled with ``align_corners=False`` (a sub-pixel shift of up to half a pixel towards the image
centre that the released checkpoint was trained with).

Hypotheses are per pixel (B, D, H, W), so stage-1 planes are a special case.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["project_hypotheses", "homo_warp"]


def _check(name: str, t: Tensor, ndim: int) -> None:
    if t.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dims, got shape {tuple(t.shape)}")


def project_hypotheses(src_proj: Tensor, ref_proj: Tensor, depths: Tensor,
                       eps: float = 1e-6) -> tuple[Tensor, Tensor]:
    """Source pixel coordinates of every reference pixel at every hypothesis (docs/method.md 2.3).

    Args:
        src_proj: (B, 4, 4) source projection [K E; 0 0 0 1] at the source feature's size.
        ref_proj: (B, 4, 4) reference projection at the hypotheses' size (H, W).
        depths: (B, D, H, W) reference z-depths.
        eps: smallest source z treated as in front of the camera.

    Returns:
        uv: (B, D, H, W, 2) source pixel coordinates (u = column, v = row).
        z: (B, D, H, W) source-camera z-depth (<= eps: behind the camera).
    """
    _check("src_proj", src_proj, 3)
    _check("ref_proj", ref_proj, 3)
    _check("depths", depths, 4)
    B, D, H, W = depths.shape
    # M in float64: depths ~1e3 and pixel coordinates ~1e3 make float32 inversions lossy.
    M = (src_proj.double() @ torch.linalg.inv(ref_proj.double())).to(depths.dtype)
    R, t = M[:, :3, :3], M[:, :3, 3]
    y, x = torch.meshgrid(
        torch.arange(H, device=depths.device, dtype=depths.dtype),
        torch.arange(W, device=depths.device, dtype=depths.dtype),
        indexing="ij",
    )
    pix = torch.stack([x, y, torch.ones_like(x)]).reshape(3, -1)  # (3, HW)
    rays = R @ pix  # (B, 3, HW)
    q = rays[:, :, None, :] * depths.reshape(B, 1, D, H * W) + t[:, :, None, None]
    z = q[:, 2]
    zs = torch.where(z > eps, z, torch.full_like(z, eps))
    uv = (q[:, :2] / zs[:, None]).permute(0, 2, 3, 1)  # (B, D, HW, 2)
    return uv.reshape(B, D, H, W, 2), z.reshape(B, D, H, W)


def homo_warp(
    src_feat: Tensor,
    src_proj: Tensor,
    ref_proj: Tensor,
    depths: Tensor,
    align_corners_quirk: bool = False,
    padding_mode: str = "zeros",
) -> tuple[Tensor, Tensor]:
    """Warp source features onto the reference view's depth hypotheses (docs/method.md 2.3).

    Differentiable with respect to ``src_feat`` and ``depths``.

    Args:
        src_feat: (B, C, Hs, Ws) source features.
        src_proj: (B, 4, 4) source projection at (Ws, Hs), e.g. ``Cameras.proj``.
        ref_proj: (B, 4, 4) reference projection at the hypotheses' (W, H).
        depths: (B, D, H, W) reference z-depth hypotheses (world units).
        align_corners_quirk: reproduce CasMVSNet's normalization (module docstring).
        padding_mode: ``grid_sample`` padding ("zeros" as CasMVSNet, or "border").

    Returns:
        warped: (B, C, D, H, W) source features at each hypothesis.
        valid: (B, D, H, W) bool, the projection lies in front of the source camera and inside
            the hull of its pixel centres, 0 <= u <= Ws - 1 and 0 <= v <= Hs - 1.
    """
    _check("src_feat", src_feat, 4)
    B, C, Hs, Ws = src_feat.shape
    _, D, H, W = depths.shape
    if src_proj.shape[0] != B or ref_proj.shape[0] != B or depths.shape[0] != B:
        raise ValueError(
            f"batch sizes differ: src_feat {B}, src_proj {src_proj.shape[0]}, "
            f"ref_proj {ref_proj.shape[0]}, depths {depths.shape[0]}"
        )
    uv, z = project_hypotheses(src_proj, ref_proj, depths)
    u, v = uv[..., 0], uv[..., 1]
    valid = (z > 1e-6) & (u >= 0) & (u <= Ws - 1) & (v >= 0) & (v <= Hs - 1)
    # Keep far-off coordinates finite and outside [-1, 1] so they sample padding.
    gx = (u / ((Ws - 1) / 2) - 1).clamp(-2, 2)
    gy = (v / ((Hs - 1) / 2) - 1).clamp(-2, 2)
    grid = torch.stack([gx, gy], dim=-1).reshape(B, D * H, W, 2)
    warped = F.grid_sample(
        src_feat, grid.to(src_feat.dtype), mode="bilinear", padding_mode=padding_mode,
        align_corners=not align_corners_quirk,
    )
    return warped.reshape(B, C, D, H, W), valid
