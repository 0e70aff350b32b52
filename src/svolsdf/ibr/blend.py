"""Image-based rendering: warp the input views to a target by depth and blend them
(docs/method.md 7).

For a target camera with a rendered z-depth map and a rendered (fallback) colour image, and V
source views with their images and rendered depths:

1. Geometric consistency of the target depth against each source depth (docs/method.md 7 step 1, the
   docs/method.md 6.3 procedure at 2 px / 1 %), through
   `svolsdf.geometry.reproject.check_geometric_consistency`.
2. Warped colour c_j: each source image sampled where the target pixels project (step 2).
3. View-direction cosine cos_j = <d_t, d_j> between the unit rays from the target and from
   source j to the target pixel's 3D point (step 3).
4. Per-pixel weights from a softmax of ``temperature * cos_j`` (step 4; temperature 20).
5. Filled candidates and blend masks (steps 5-6), then a 4-level Laplacian-pyramid blend of the
   candidates and the rendered colour (step 7).

Paper vs released code (docs/method.md 7 and 9.2.11). The paper states only: softmax over the
view-direction cosine at temperature 20, the rendered colour as the fallback, and 4-level
Laplacian blending. `IBRConfig()` implements that reading:

- W_j = m_j exp(20 cos_j) / sum_k m_k exp(20 cos_k) over the consistent sources (m_j = 1);
  the rendered colour takes weight 1 where no source is consistent, 0 elsewhere;
- candidate j is the warped colour where source j is consistent and the rendered colour
  elsewhere; blend masks M_j = W_j, M_render = 1 - sum_j W_j.

`IBRConfig.released()` reproduces the released ``simple_ibr.py`` (docs/method.md 7 steps 1-7): the
rendered colour is a fourth softmax candidate with constant score 0.2 and inconsistent sources
score 0 (not excluded), candidates are filled as img'_j = c_j W_j + rendered (1 - W_j), masks
are M_j = erode_5x5(W_j > 0.2) W_j and M_render = W_render + 0.01, and colours are warped
bicubically. The 2 px / 1 % thresholds are the released ones in both (the paper gives none).

Pyramids use kornia's ``pyrdown`` / ``pyrup`` (5x5 Gaussian; kornia's ``pyrdown`` resamples
bilinearly where OpenCV's decimates). Images are edge-padded to a multiple of 2^(levels - 1) so
that every level halves exactly, then cropped back.

Conventions: `svolsdf.scene.cameras` (OpenCV axes, integer pixel centres, z-depth in the
cameras' world units).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import Literal, NamedTuple

import torch
import torch.nn.functional as F
from kornia.geometry.transform import pyrdown, pyrup
from torch import Tensor

from svolsdf.geometry.reproject import check_geometric_consistency
from svolsdf.scene.cameras import Cameras

__all__ = [
    "IBRConfig",
    "IBRResult",
    "erode",
    "fill_candidates",
    "ibr_render",
    "laplacian_blend",
    "push_pull_fill",
    "view_softmax_weights",
    "warp_sources",
]

log = logging.getLogger(__name__)


@dataclass
class IBRConfig:
    """Image-based rendering with Laplacian-pyramid blending (docs/method.md 7).

    The defaults follow the paper; `IBRConfig.released` gives the released ``simple_ibr.py``.
    """

    dist_thresh: float = 2.0
    """Geometric check: largest forward-backward reprojection distance, in target pixels
    (docs/method.md 7 step 1; the released value, the paper gives none)."""

    rel_thresh: float = 0.01
    """Geometric check: largest relative depth difference |d' - d| / d (docs/method.md 7 step 1)."""

    temperature: float = 20.0
    """Softmax temperature: weights are softmax(temperature * cos) (docs/method.md 7 step 4)."""

    fallback: Literal["holes", "softmax"] = "holes"
    """How the rendered colour enters the weights. "holes" (paper): only where no source is
    consistent, with weight 1. "softmax" (released): as an extra softmax candidate with the
    constant score ``fallback_score``, inconsistent sources scoring 0."""

    fallback_score: float = 0.2
    """Constant cosine-like score of the rendered colour when ``fallback == "softmax"``
    (released: 0.2, so it gets e^4 / (3 + e^4) ~ 0.95 of the weight when all three sources fail)."""

    fill: Literal["replace", "weighted"] = "replace"
    """How each source candidate is completed before the pyramid blend. "replace" (ours, the
    paper is silent): the warped colour where the source is consistent, the rendered colour
    elsewhere. "weighted" (released, docs/method.md 7 step 5): c_j W_j + rendered (1 - W_j)."""

    colour_interp: Literal["bilinear", "bicubic"] = "bilinear"
    """Interpolation of the source colours at the warped positions (released: bicubic, like
    ``cv2.remap(INTER_CUBIC)``; torch's bicubic uses the same a = -0.75 kernel)."""

    mask_threshold: float = 0.0
    """Blend mask of source j: erode(W_j > mask_threshold) * W_j (released: 0.2; docs/method.md 7
    step 6). With 0 and no erosion the mask is W_j itself."""

    mask_erosion: int = 0
    """Side of the square structuring element eroding (W_j > mask_threshold); 0 or 1 = none
    (released: 5)."""

    fallback_mask_bias: float = 0.0
    """Added to the rendered colour's blend mask before normalization (released: 0.01)."""

    pyramid_levels: int = 4
    """Number of Laplacian-pyramid levels (docs/method.md 7 step 7: 4); 1 = plain per-pixel
    blend."""

    clip: bool = True
    """Clip the blended image to [0, 1] (docs/method.md 7 step 7)."""

    unseen: Literal["render", "inpaint"] = "render"
    """Colour of target pixels that have a surface (depth > 0) but no consistent source.
    "render" (paper): the volume-rendered colour. "inpaint": the sources' blended colour
    spread from the pixels some source sees by push-pull (`push_pull_fill`), an appearance
    smoothness prior for the surface no input view saw (docs/novel-views.md: on DTU that
    surface is a quarter of the test views' masks and holds about half of their error)."""

    hole_depth: Literal["none", "mesh"] = "none"
    """Depth where the field renders no surface: none (the paper: no depth, so the rendered
    colour shows, black where the field left the ray empty) or mesh (the run's mesh.ply gives
    the depth there, so the photos are warped onto it). Pixels of opacity below 0.5 of the
    target and of the sources are holes; `svolsdf render` fills them (`mesh_depth_fill`),
    `ibr_render` takes the depths it is given (docs/novel-views.md)."""

    inpaint_levels: int = 8
    """Pyramid levels of the push-pull fill (``unseen == "inpaint"``); 8 spreads colour about
    2^8 pixels, across any hole of a 768x576 view."""

    @classmethod
    def released(cls, **overrides) -> IBRConfig:
        """The released ``simple_ibr.py`` settings (docs/method.md 7 and 9.2.11), for reproducing
        its numbers."""
        base = cls(
            fallback="softmax",
            fallback_score=0.2,
            fill="weighted",
            colour_interp="bicubic",
            mask_threshold=0.2,
            mask_erosion=5,
            fallback_mask_bias=0.01,
        )
        return replace(base, **overrides)

    def __post_init__(self) -> None:
        if self.fallback not in ("holes", "softmax"):
            raise ValueError(
                f"IBRConfig.fallback must be 'holes' or 'softmax', got {self.fallback!r}"
            )
        if self.fill not in ("replace", "weighted"):
            raise ValueError(f"IBRConfig.fill must be 'replace' or 'weighted', got {self.fill!r}")
        if self.colour_interp not in ("bilinear", "bicubic"):
            raise ValueError(
                "IBRConfig.colour_interp must be 'bilinear' or 'bicubic', "
                f"got {self.colour_interp!r}"
            )
        if self.pyramid_levels < 1:
            raise ValueError(f"IBRConfig.pyramid_levels must be >= 1, got {self.pyramid_levels}")
        if self.unseen not in ("render", "inpaint"):
            raise ValueError(f"IBRConfig.unseen must be 'render' or 'inpaint', got {self.unseen!r}")
        if self.hole_depth not in ("none", "mesh"):
            raise ValueError("IBRConfig.hole_depth must be 'none' or 'mesh', "
                             f"got {self.hole_depth!r}")
        if self.inpaint_levels < 1:
            raise ValueError(f"IBRConfig.inpaint_levels must be >= 1, got {self.inpaint_levels}")


class IBRResult(NamedTuple):
    """The result of `ibr_render`; H x W is the target camera's size, V the number of sources.

    Attributes:
        rgb: (3, H, W) float, the Laplacian-blended image in [0, 1] (docs/method.md 7 step 7).
        composite: (3, H, W) float, the same blend without the pyramid (sum_j M_j img'_j).
        weights: (V, H, W) float, softmax weights W_j of the sources.
        weight_sum: (H, W) float, sum_j W_j: the share of the colour taken from the sources
            (1 - the rendered colour's weight).
        valid: (V, H, W) bool, source j passed the geometric consistency check.
        n_valid: (H, W) int64, number of consistent sources.
        cos: (V, H, W) float, view-direction cosines (0 where the target depth is invalid).
    """

    rgb: Tensor
    composite: Tensor
    weights: Tensor
    weight_sum: Tensor
    valid: Tensor
    n_valid: Tensor
    cos: Tensor


# ---------------------------------------------------------------------------------------------
# pieces


def _as_float_image(img: Tensor) -> Tensor:
    """uint8 images -> float32 in [0, 1]; float images unchanged."""
    return img if img.is_floating_point() else img.float() / 255.0


def _grid(uv: Tensor, width: int, height: int) -> Tensor:
    """(..., 2) pixel coordinates -> grid_sample coordinates for align_corners=True (integer
    pixel centres, like ``cv2.remap``); non-finite values go far outside."""
    gx = 2.0 * uv[..., 0] / max(width - 1, 1) - 1.0
    gy = 2.0 * uv[..., 1] / max(height - 1, 1) - 1.0
    g = torch.stack([gx, gy], dim=-1)
    return torch.nan_to_num(g, nan=-4.0, posinf=-4.0, neginf=-4.0)


def warp_sources(
    target_cam: Cameras,
    target_depth: Tensor,
    src_images: Tensor,
    src_cams: Cameras,
    src_depths: Tensor,
    cfg: IBRConfig | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Warp every source image to the target by the target depth (docs/method.md 7 steps 1-3).

    Args:
        target_cam: `Cameras` with one view, size W x H.
        target_depth: (H, W) target z-depth in world units; <= 0 or non-finite = none.
        src_images: (V, 3, Hs, Ws) source images at ``src_cams``' size, float in [0, 1] (uint8
            is divided by 255).
        src_cams: `Cameras` with V views, size Ws x Hs.
        src_depths: (V, Hd, Wd) source z-depths (any size; the cameras are rescaled to it).
        cfg: `IBRConfig` (thresholds and colour interpolation).

    Returns:
        colours: (V, 3, H, W) warped source colours (meaningful where valid).
        valid: (V, H, W) bool, geometric consistency at cfg.dist_thresh px / cfg.rel_thresh.
        cos: (V, H, W) cosine between the unit rays from the target centre and from source j's
            centre to the target pixel's 3D point; 0 where the target depth is invalid.
    """
    cfg = cfg or IBRConfig()
    V = len(src_cams)
    H, W = target_cam.height, target_cam.width
    dev = target_depth.device
    src_images = _as_float_image(src_images)
    dt = src_images.dtype
    g64 = torch.float64  # geometry in float64 (DTU depths ~600 mm, thresholds at 1 %)
    tcam = target_cam.to(device=dev, dtype=g64)
    scams = src_cams.to(device=dev, dtype=g64)

    d_t = target_depth.to(g64)
    ok_t = torch.isfinite(d_t) & (d_t > 0)
    d_safe = torch.where(ok_t, d_t, torch.ones_like(d_t))
    uv_t = tcam.pixel_grid(device=dev, dtype=g64).reshape(1, -1, 2)
    x = tcam.unproject(uv_t, d_safe.reshape(1, -1))[0]  # (HW, 3)

    uv_s, z_s = scams.project(x)  # (V, HW, 2), (V, HW)
    grid = _grid(uv_s, scams.width, scams.height).reshape(V, H, W, 2).to(dt)
    colours = F.grid_sample(
        src_images.to(device=dev, dtype=dt), grid, mode=cfg.colour_interp,
        padding_mode="border", align_corners=True,
    )

    valid = torch.zeros(V, H, W, dtype=torch.bool, device=dev)
    for j in range(V):  # V is small (3 in the headline case); each check is vectorized
        m, _, _ = check_geometric_consistency(
            target_depth, target_cam, src_depths[j], src_cams[j],
            dist_thresh=cfg.dist_thresh, rel_thresh=cfg.rel_thresh,
        )
        valid[j] = m.to(dev)
    valid &= ok_t[None] & (z_s.reshape(V, H, W) > 0)

    # docs/method.md 7 step 3: the released code samples the source ray-direction map at (x_s, y_s);
    # the ray through that point is the ray to x itself, computed here exactly.
    d_tgt = F.normalize(x - tcam.centers[0], dim=-1)  # (HW, 3)
    d_src = F.normalize(x[None] - scams.centers[:, None], dim=-1)  # (V, HW, 3)
    cos = (d_src * d_tgt[None]).sum(-1).reshape(V, H, W)
    cos = torch.where(ok_t[None] & torch.isfinite(cos), cos, torch.zeros_like(cos))
    return colours, valid, cos.to(dt)


def view_softmax_weights(
    cos: Tensor, valid: Tensor, cfg: IBRConfig | None = None
) -> tuple[Tensor, Tensor]:
    """Per-pixel blending weights from the view-direction cosines (docs/method.md 7 step 4).

    ``cfg.fallback == "holes"`` (paper):
        W_j = m_j exp(T cos_j) / sum_k m_k exp(T cos_k), W_render = 0 where some m_k = 1;
        W_j = 0, W_render = 1 where no source is consistent.
    ``cfg.fallback == "softmax"`` (released):
        [W_1..W_V, W_render] = softmax(T [m_1 cos_1, ..., m_V cos_V, s_render]),
        with s_render = cfg.fallback_score (0.2) and m_j in {0, 1}.
    T = cfg.temperature (20).

    Args:
        cos: (V, H, W) view-direction cosines.
        valid: (V, H, W) bool, consistent sources m_j.
        cfg: `IBRConfig`.

    Returns:
        W: (V, H, W) source weights.
        W_render: (H, W) weight of the rendered colour; W.sum(0) + W_render = 1.
    """
    cfg = cfg or IBRConfig()
    if cos.ndim != 3 or cos.shape != valid.shape:
        raise ValueError(
            f"cos and valid must both be (V, H, W), got {tuple(cos.shape)} and {tuple(valid.shape)}"
        )
    valid = valid.bool()
    T = cfg.temperature
    if cfg.fallback == "softmax":
        score = torch.where(valid, cos, torch.zeros_like(cos))
        fb = torch.full_like(cos[:1], cfg.fallback_score)
        w = torch.softmax(T * torch.cat([score, fb], dim=0), dim=0)
        return w[:-1], w[-1]
    logits = torch.where(valid, T * cos, torch.full_like(cos, -torch.inf))
    any_valid = valid.any(0)
    logits = torch.where(any_valid[None], logits, torch.zeros_like(logits))  # no NaN rows
    w = torch.softmax(logits, dim=0) * any_valid[None]
    return w, (~any_valid).to(cos.dtype)


def fill_candidates(
    colours: Tensor, valid: Tensor, W: Tensor, rendered: Tensor, cfg: IBRConfig | None = None
) -> Tensor:
    """Complete each warped source with the rendered colour (docs/method.md 7 step 5).

    "replace": img'_j = c_j where m_j, rendered elsewhere. "weighted" (released):
    img'_j = c_j W_j + rendered (1 - W_j).

    Args:
        colours: (V, 3, H, W) warped colours c_j.
        valid: (V, H, W) bool consistency m_j.
        W: (V, H, W) source weights.
        rendered: (3, H, W) fallback colour.
        cfg: `IBRConfig`.

    Returns:
        (V, 3, H, W) candidates img'_j.
    """
    cfg = cfg or IBRConfig()
    r = rendered[None].to(colours.dtype)
    if cfg.fill == "weighted":
        w = W[:, None].to(colours.dtype)
        return colours * w + r * (1 - w)
    return torch.where(valid[:, None], colours, r.expand_as(colours))


def push_pull_fill(image: Tensor, known: Tensor, levels: int = 8) -> Tensor:
    """Fill the unknown pixels of an image from the known ones by push-pull (the pyramid hole
    filling of Gortler et al., "The Lumigraph", 1996): average the known pixels down a 2x2
    pyramid, then, coming back up, give each unknown pixel the bilinearly upsampled average of
    the coarser level. Known pixels keep their value. No library fills by known-pixel weights on
    a pyramid (OpenCV's and scikit-image's inpainting solve a PDE per pixel, far slower here).

    Args:
        image: (C, H, W) float.
        known: (H, W) bool, the pixels to spread from.
        levels: number of pyramid levels (the fill reaches about 2^levels pixels).

    Returns:
        (C, H, W): ``image`` where ``known``, the fill elsewhere (``image`` itself where nothing
        is known within reach, e.g. an image with no known pixel).
    """
    if image.ndim != 3 or known.shape != image.shape[-2:]:
        raise ValueError(f"push_pull_fill: image (C, H, W) and known (H, W), got "
                         f"{tuple(image.shape)} and {tuple(known.shape)}")
    w = known.to(image.dtype)[None]
    num, den = [image * w], [w]
    for _ in range(levels):  # push: sums of known values and of their weights, 2x2 at a time
        if min(num[-1].shape[-2:]) < 2:
            break
        num.append(F.avg_pool2d(num[-1][None], 2, ceil_mode=True)[0])
        den.append(F.avg_pool2d(den[-1][None], 2, ceil_mode=True)[0])
    est = num[-1] / den[-1].clamp_min(1e-12)
    have = den[-1] > 0
    for n, d in zip(reversed(num[:-1]), reversed(den[:-1]), strict=True):  # pull: coarse->fine
        up = F.interpolate(est[None], size=n.shape[-2:], mode="bilinear",
                           align_corners=False)[0]
        hup = F.interpolate(have[None].to(image.dtype), size=n.shape[-2:], mode="bilinear",
                            align_corners=False)[0] > 0
        own = d > 0
        est = torch.where(own, n / d.clamp_min(1e-12), up)
        have = own | hup
    return torch.where(known[None] | ~have, image, est)  # ~have: nothing within reach


def erode(mask: Tensor, size: int) -> Tensor:
    """Binary erosion with a ``size`` x ``size`` square; the outside of the image does not erode
    (as ``cv2.erode`` with its default border).

    Args:
        mask: (..., H, W) bool.
        size: side of the structuring element (odd; <= 1 returns the mask).

    Returns:
        (..., H, W) bool.
    """
    if size <= 1:
        return mask.bool().clone()
    if size % 2 == 0:
        raise ValueError(f"erosion size must be odd, got {size}")
    shape = mask.shape
    m = mask.reshape(-1, 1, *shape[-2:]).float()
    # min-pool as -maxpool(-x); max_pool2d pads with -inf, i.e. the border counts as inside.
    e = -F.max_pool2d(-m, kernel_size=size, stride=1, padding=size // 2)
    return (e > 0.5).reshape(shape)


def _pad_to_multiple(x: Tensor, k: int) -> tuple[Tensor, int, int]:
    H, W = x.shape[-2:]
    ph, pw = (-H) % k, (-W) % k
    if ph or pw:
        x = F.pad(x, (0, pw, 0, ph), mode="replicate")
    return x, H, W


def laplacian_blend(images: Tensor, masks: Tensor, levels: int = 4) -> Tensor:
    """Multi-band (Laplacian-pyramid) blend of N images with per-pixel masks (docs/method.md 7 step
    7).

    Gaussian pyramids G_0..G_{L-1} of each image (``kornia`` ``pyrdown``); Laplacian stack
    [G_{L-1}, G_{L-2} - up(G_{L-1}), ..., G_0 - up(G_1)]; the masks' Gaussian pyramids weight
    each level, sum_j G_k(M_j) L_k(img_j); the blended stack is collapsed by up-and-add
    (``pyrup``). The masks are normalized to sum to 1 per pixel first (pixels where all are 0
    get equal weights). With identical images the result is that image (the blend is linear
    and the Gaussian pyramid of a constant is that constant).

    Args:
        images: (N, C, H, W) float.
        masks: (N, H, W) or (N, 1, H, W) non-negative weights.
        levels: number of pyramid levels L >= 1 (1 = per-pixel weighted sum).

    Returns:
        (C, H, W) blended image (not clipped).
    """
    if images.ndim != 4:
        raise ValueError(f"images must be (N, C, H, W), got {tuple(images.shape)}")
    if masks.ndim == 3:
        masks = masks[:, None]
    if masks.shape != (images.shape[0], 1, *images.shape[-2:]):
        raise ValueError(
            f"masks must be (N, H, W) matching images {tuple(images.shape)}, "
            f"got {tuple(masks.shape)}"
        )
    if levels < 1:
        raise ValueError(f"levels must be >= 1, got {levels}")
    masks = masks.to(images.dtype).clamp_min(0)
    total = masks.sum(0, keepdim=True)
    n = images.shape[0]
    masks = torch.where(total > 0, masks / total.clamp_min(1e-12), torch.full_like(masks, 1 / n))

    x, H, W = _pad_to_multiple(images, 2 ** (levels - 1))
    m, _, _ = _pad_to_multiple(masks, 2 ** (levels - 1))
    gi, gm = [x], [m]
    for _ in range(levels - 1):
        gi.append(pyrdown(gi[-1]))
        gm.append(pyrdown(gm[-1]))
    out = (gm[-1] * gi[-1]).sum(0, keepdim=True)  # coarsest level: Gaussian G_{L-1}
    for k in range(levels - 2, -1, -1):
        lap = gi[k] - pyrup(gi[k + 1])
        out = pyrup(out) + (gm[k] * lap).sum(0, keepdim=True)
    return out[0, :, :H, :W]


# ---------------------------------------------------------------------------------------------
# the whole step


def _check_inputs(target_cam, target_depth, fallback_rgb, src_images, src_cams, src_depths):
    if len(target_cam) != 1:
        raise ValueError(f"target_cam must hold one view, got {len(target_cam)}")
    H, W = target_cam.height, target_cam.width
    if tuple(target_depth.shape) != (H, W):
        raise ValueError(
            f"target_depth must be (H, W) = {(H, W)} (the target camera's size), "
            f"got {tuple(target_depth.shape)}"
        )
    if tuple(fallback_rgb.shape) != (3, H, W):
        raise ValueError(f"fallback_rgb must be (3, {H}, {W}), got {tuple(fallback_rgb.shape)}")
    V = len(src_cams)
    if V < 1:
        raise ValueError("ibr_render needs at least one source view")
    Hs, Ws = src_cams.height, src_cams.width
    if tuple(src_images.shape) != (V, 3, Hs, Ws):
        raise ValueError(
            f"src_images must be (V, 3, Hs, Ws) = {(V, 3, Hs, Ws)} (src_cams' count and size), "
            f"got {tuple(src_images.shape)}"
        )
    if src_depths.ndim != 3 or src_depths.shape[0] != V:
        raise ValueError(f"src_depths must be (V={V}, Hd, Wd), got {tuple(src_depths.shape)}")


def ibr_render(
    target_cam: Cameras,
    target_depth: Tensor,
    fallback_rgb: Tensor,
    src_images: Tensor,
    src_cams: Cameras,
    src_depths: Tensor,
    cfg: IBRConfig | None = None,
) -> IBRResult:
    """Image-based rendering of one target view from V source views (docs/method.md 7).

    Steps 1-7 of docs/method.md 7: geometric consistency of the target depth against each source
    depth (``cfg.dist_thresh`` px, ``cfg.rel_thresh``), warped colours, view-direction cosines,
    softmax weights at temperature ``cfg.temperature`` with the rendered colour as the fallback
    (`view_softmax_weights`), filled candidates (`fill_candidates`), blend masks, and a
    ``cfg.pyramid_levels``-level Laplacian blend (`laplacian_blend`) of the V candidates and the
    rendered colour, clipped to [0, 1].

    Args:
        target_cam: `Cameras` with one view, size W x H.
        target_depth: (H, W) rendered z-depth of the target, world units (the cameras' units);
            <= 0 or non-finite = no surface (the rendered colour is used there).
        fallback_rgb: (3, H, W) float in [0, 1] (or uint8), the volume-rendered colour of the
            target.
        src_images: (V, 3, Hs, Ws) float in [0, 1] (or uint8), the input images at
            ``src_cams``' size.
        src_cams: `Cameras` with V views, size Ws x Hs.
        src_depths: (V, Hd, Wd) rendered z-depths of the sources (any resolution; cameras are
            rescaled to it for the consistency check).
        cfg: `IBRConfig`; default = the paper, `IBRConfig.released()` = the released code.

    Returns:
        `IBRResult` (rgb (3, H, W), composite (3, H, W), weights (V, H, W), weight_sum (H, W),
        valid (V, H, W), n_valid (H, W), cos (V, H, W)), on ``target_depth``'s device.
    """
    cfg = cfg or IBRConfig()
    _check_inputs(target_cam, target_depth, fallback_rgb, src_images, src_cams, src_depths)
    dev = target_depth.device
    dt = _as_float_image(src_images[:1]).dtype
    rendered = _as_float_image(fallback_rgb).to(device=dev, dtype=dt)

    colours, valid, cos = warp_sources(
        target_cam, target_depth, src_images, src_cams, src_depths, cfg
    )
    W, W_r = view_softmax_weights(cos, valid, cfg)
    if cfg.unseen == "inpaint":
        # the surface no source sees takes the seen colour spread by push-pull, not the render
        seen = valid.any(0)
        w_seen = W / W.sum(0, keepdim=True).clamp_min(1e-12)
        blended = (w_seen[:, None].to(colours.dtype) * colours).sum(0)
        # one pass: a 4th channel that is 1 where seen comes out 1 where the fill reached
        filled = push_pull_fill(torch.cat([blended, seen[None].to(blended.dtype)]), seen,
                                cfg.inpaint_levels)
        surface = torch.isfinite(target_depth) & (target_depth > 0)
        use = (surface & ~seen & (filled[3] > 0.5))[None]
        rendered = torch.where(use, filled[:3].to(rendered.dtype), rendered)
    cands = fill_candidates(colours, valid, W, rendered, cfg)

    # docs/method.md 7 step 6: M_j = erode(W_j > thr) W_j, M_render = W_render + bias, normalized.
    m_src = erode(W > cfg.mask_threshold, cfg.mask_erosion).to(dt) * W
    m_r = W_r + cfg.fallback_mask_bias
    masks = torch.cat([m_src, m_r[None]], dim=0)
    masks = masks / masks.sum(0, keepdim=True).clamp_min(1e-12)
    images = torch.cat([cands, rendered[None]], dim=0)

    composite = (masks[:, None] * images).sum(0)
    rgb = laplacian_blend(images, masks, cfg.pyramid_levels)
    if cfg.clip:
        rgb = rgb.clamp(0, 1)
        composite = composite.clamp(0, 1)
    n_valid = valid.sum(0)
    log.debug(
        "ibr: %.1f%% of target pixels have a consistent source",
        100.0 * float((n_valid > 0).float().mean()),
    )
    return IBRResult(
        rgb=rgb, composite=composite, weights=W, weight_sum=W.sum(0), valid=valid,
        n_valid=n_valid, cos=cos,
    )
