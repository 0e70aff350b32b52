"""A training-free plane-sweep backbone: the default `MVSBackbone`.

Per reference view and stage k (1/4, 1/2 and full MVS size for k = 1, 2, 3; 192, 32 and 8
hypotheses, docs/method.md 2.5; the MVS size is ``scale`` = 2 x the working size, as the released
code runs CasMVSNet on images upsampled 2x, docs/method.md 9.2.2):

1. Hypotheses (`svolsdf.mvs.hypotheses`): planes over the view's depth range at stage 1, per-pixel
   ranges centred on the upsampled previous depth (or a guide depth, docs/method.md 6.1) later.
2. Matching cost per source view: 1 - ZNCC of the reference and the warped source image
   (`svolsdf.mvs.warping.homo_warp`, per-pixel homographies) over a square window on grayscale,
   and on the image gradients (``gradient_weight``). ZNCC is invariant to per-window gain and
   offset, so exposure differences between views do not matter.
3. Aggregation over sources, robust to a source that does not see the point: the mean of the best
   ``ceil(keep_fraction * n_valid)`` costs among the sources where the point projects inside the
   image (out-of-image samples are missing, not bad matches). With 2 sources this is their minimum.
4. Cost aggregation: an edge-aware guided filter (He et al. 2013) of every cost slice, guided by
   the reference image, so the support follows intensity edges of real objects instead of
   bleeding across depth discontinuities; ``filter="box"`` is the plain box baseline.
5. Probabilities: softmax over D of -cost / T (docs/method.md 2.4 replaces the network's regularized
   cost by -cost / T). T is calibrated from the cost statistics of each volume (``temperature``
   None): with g the median over pixels of (median_D cost - min_D cost), T = g / (ln D + m),
   ``m = temperature_margin``. At a typical pixel the D/2 hypotheses at the median cost then keep
   about D/2 · e^-(ln D + m) = e^-m / 2 of the mass (m = 4: ~1 %), so the distribution is peaked
   where the matching is distinctive and spread where it is not.
6. depth = expectation over the main mode (``depth_radius``; the full expectation of docs/method.md
   2.4 with None), confidence = 4-bin sum (docs/method.md 2.4).

Everything is vectorized in torch; warps, windows and filters are computed in chunks over depth.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import Tensor

from svolsdf.errors import InputError
from svolsdf.io.progress import progress_bar
from svolsdf.mvs.backbone import (
    MAX_SOURCES,
    MVSBackbone,
    check_depth_ranges,
    mvs_size,
    register_backbone,
    select_sources,
    stage_size,
    upsample_depth,
    volume_from_prob,
)
from svolsdf.mvs.hypotheses import stage_hypotheses
from svolsdf.mvs.sgm import sgm_aggregate
from svolsdf.mvs.volume import ProbabilityVolume
from svolsdf.mvs.warping import homo_warp
from svolsdf.scene.cameras import Cameras
from svolsdf.scene.scene import Scene

__all__ = [
    "PlaneSweepConfig",
    "PlaneSweepBackbone",
    "box_filter",
    "guided_filter",
    "zncc_cost",
    "aggregate_sources",
    "calibrate_temperature",
]

log = logging.getLogger(__name__)


@dataclass
class PlaneSweepConfig:
    """Configuration of the plane-sweep backbone."""

    ndepths: tuple[int, int, int] = (192, 32, 8)
    """Hypotheses per stage (docs/method.md 2.5)."""
    width: str = "paper"
    """Finer-stage search width: "paper" (r = 0.5, 0.5), "released" (the same) or
    "half-default" (r = 1, 0.5); see `svolsdf.mvs.hypotheses`."""
    inverse_depth: bool = False
    """Space stage-1 planes uniformly in inverse depth (unbounded scenes)."""
    max_sources: int = MAX_SOURCES
    """Source views per reference, the best by pair score (`select_sources`, docs/method.md 1.4: at
    most 4, as released); <= 0: every other loaded view."""
    window: tuple[int, int, int] = (5, 5, 5)
    """ZNCC window side (odd, pixels at the stage's resolution) per stage."""
    gradient_weight: float = 0.5
    """Weight of the ZNCC cost on x/y image gradients, added to the grayscale cost (0 = off).
    Gradients sharpen the cost at texture edges (benchmarks/results/history/mvs_planesweep.md)."""
    keep_fraction: float = 0.5
    """Fraction of the valid sources whose best costs are averaged (robustness to occlusion)."""
    filter: str = "guided"
    """Cost aggregation per slice: "guided" (edge-aware), "box", or "none"."""
    sgm: tuple[bool, bool, bool] = (True, True, True)
    """Per stage: semi-global aggregation (``sgm_directions`` scanlines) after the filter."""
    sgm_p1: float = 0.03
    """SGM penalty for a change of one hypothesis (cost units, cost in [0, 2])."""
    sgm_p2: float = 2.0
    """SGM penalty for larger jumps away from intensity edges (above the cost range [0, 2]:
    away from edges the depth may jump only where no smooth path explains the costs;
    benchmarks/results/history/mvs_planesweep.md, notes)."""
    sgm_sigma: float = 0.04
    """Intensity difference (on [0, 1]) over which the SGM jump penalty drops from P2 to P1."""
    sgm_directions: int = 8
    """SGM scanline directions: 4 (horizontal, vertical) or 8 (and the diagonals)."""
    filter_radius: tuple[int, int, int] = (2, 2, 2)
    """Radius of the aggregation filter per stage (pixels at the stage's resolution)."""
    filter_eps: float = 1e-3
    """Guided-filter regularizer (on [0, 1] grayscale; larger = closer to a box filter)."""
    missing_cost: float = 1.0
    """Cost where no source sees the hypothesis (1 - ZNCC of unrelated patches)."""
    temperature: float | None = None
    """Softmax temperature; None calibrates it per volume from the costs (module docstring)."""
    temperature_margin: float = 4.0
    """m in T = g / (ln D + m); larger = more peaked (m = 4: the hypotheses at the median cost keep
    ~1 % of the mass at a typical pixel)."""
    depth_chunk: int = 24
    """Hypotheses processed at once (memory)."""
    zncc_eps: float = 1e-5
    """Added to each window variance in ZNCC's denominator, ~ the squared image noise on [0, 1]
    (a flat patch gets cost ~1 instead of matching noise)."""
    depth_radius: int | None = 2
    """Depth estimate per pixel: the probability-weighted mean over the 2r+1 hypotheses around
    the most likely one (`svolsdf.mvs.backbone.mode_depth`); None = the full expectation of
    docs/method.md 2.4. A training-free cost often has a second, wrong match on textureless or
    repeated surfaces; the full expectation then lands between the two, on no surface, and the
    next stage searches around that."""
    min_depth_ratio: float = 0.05
    """Finer-stage hypotheses are clamped to >= this fraction of the view's near depth."""
    scale: float = 2.0
    """The stages run at ``scale`` x the working size (stage 3 at scale x, stage 1 at scale / 4
    x); images are resized from the working size (bicubic when upsampling, as the released
    code's x2_mvsres, docs/method.md 9.2.2) and the volumes, depth maps and fused points follow.
    2 against 1 on six synthetic scenes (768x576, 3 views): the backbone alone's points Chamfer
    up to 20 % lower (1 % higher on one scene), the fast preset's 9-26 % lower, for ~2.5 min
    more per three-view run (benchmarks/results/history/fast_preset.md, notes of commit ecd04c9)."""
    native_images: bool = False
    """Stages larger than the working size read the images again from their files when those are
    larger (`Scene.images_at`): a 1600x1200 DTU photo gives stage 3 its own detail at 1536x1152.
    False: the working-size images upsampled, as the released code (docs/method.md 9.2.2); the two
    score the same on dtu_scan65 (`svolsdf.config.MVSConfig.native_images`)."""
    crop_to_masks: int | None = None
    """Stages 2-3 (the per-pixel hypotheses) only inside the box around the reference's object
    mask dilated by this many pixels at the working size (`mvs.crop_to_masks`); outside it the
    stage's depth and confidence are 0 (no depth) and its probabilities 0. None, or a scene
    without masks: every pixel."""
    extra: dict = field(default_factory=dict)
    """Unused; room for experiments without changing the signature."""


# --------------------------------------------------------------------------- filters
def _window_sum(x: Tensor, radius: int, dim: int) -> Tensor:
    """Sum of ``x`` over [i - radius, i + radius] along ``dim``, entries outside left out."""
    n = x.shape[dim]
    if radius <= 0 or n <= 1:
        return x.clone()
    # the first add writes the output (x[i] + x[i-1], x[0] copied): one pass less than a clone
    # followed by the add, with the same sums in the same order
    out = torch.empty_like(x)
    torch.add(x.narrow(dim, 1, n - 1), x.narrow(dim, 0, n - 1), out=out.narrow(dim, 1, n - 1))
    out.narrow(dim, 0, 1).copy_(x.narrow(dim, 0, 1))
    out.narrow(dim, 0, n - 1).add_(x.narrow(dim, 1, n - 1))
    for s in range(2, min(radius, n - 1) + 1):
        out.narrow(dim, s, n - s).add_(x.narrow(dim, 0, n - s))
        out.narrow(dim, 0, n - s).add_(x.narrow(dim, s, n - s))
    return out


def _window_count(n: int, radius: int, dtype, device) -> Tensor:
    """(n,) number of entries of [i - radius, i + radius] inside [0, n)."""
    i = torch.arange(n, dtype=dtype, device=device)
    return (i + radius).clamp(max=n - 1) - (i - radius).clamp(min=0) + 1


def box_filter(x: Tensor, radius: int) -> Tensor:
    """Mean over a (2r+1)^2 window, shrinking at the borders (separable).

    Written as shifted adds rather than ``F.avg_pool2d(..., count_include_pad=False)`` (the
    same result to float rounding): on the CPU the pooling kernel was 4-8x slower at the
    plane sweep's sizes and a third of the MVS time (benchmarks/results/history/mvs_speed.md).
    kornia's box blur pads the border instead of shrinking the window.

    Args:
        x: (N, C, H, W).
        radius: r >= 0.

    Returns:
        (N, C, H, W).
    """
    if radius <= 0:
        return x
    H, W = x.shape[-2:]
    count = (_window_count(H, radius, x.dtype, x.device)[:, None]
             * _window_count(W, radius, x.dtype, x.device)[None, :])
    return _window_sum(_window_sum(x, radius, -1), radius, -2).div_(count)


def guided_filter(guide: Tensor, p: Tensor, radius: int, eps: float,
                  guide_stats: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """Gray-guided filter of each channel of ``p`` (He, Sun, Tang, TPAMI 2013, Alg. 1).

    a = cov(I, p) / (var(I) + eps), b = mean(p) - a mean(I), q = mean(a) I + mean(b).

    Args:
        guide: (1, 1, H, W) guide image I.
        p: (1, C, H, W) inputs (e.g. cost slices).
        radius: window radius.
        eps: regularizer.
        guide_stats: optional precomputed (mean(I), var(I)), each (1, 1, H, W).

    Returns:
        (1, C, H, W) filtered.
    """
    if guide_stats is None:
        mI = box_filter(guide, radius)
        vI = box_filter(guide * guide, radius) - mI * mI
    else:
        mI, vI = guide_stats
    if radius <= 0:  # the box filter returns its input: nothing may be written in place
        cov = guide * p - mI * p
        a = cov / (vI + eps)
        return a * guide + (p - a * mI)
    # in place where the old value is not needed again (the same operations in the same order)
    mp = box_filter(p, radius)
    t = guide * p
    cov = box_filter(t, radius)
    torch.mul(mI, mp, out=t)
    a = cov.sub_(t).div_(vI + eps)
    torch.mul(a, mI, out=t)
    b = mp.sub_(t)
    del t
    return box_filter(a, radius).mul_(guide).add_(box_filter(b, radius))


def zncc_cost(ref: Tensor, warped: Tensor, radius: int, eps: float,
              ref_stats: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """1 - windowed zero-mean normalized cross-correlation, in [0, 2].

    ZNCC = cov(R, S) / sqrt((var R + eps)(var S + eps)) over a (2 radius + 1)^2 window.

    Args:
        ref: (1, 1, H, W) reference image.
        warped: (1, D, H, W) source image warped to each hypothesis.
        radius: window radius.
        eps: added to var(ref) and var(src) in the denominator.
        ref_stats: optional precomputed (mean(ref), var(ref)).

    Returns:
        (1, D, H, W) cost.
    """
    if ref_stats is None:
        mR = box_filter(ref, radius)
        vR = (box_filter(ref * ref, radius) - mR * mR).clamp_min(0)
    else:
        mR, vR = ref_stats
    if radius <= 0:  # the box filter returns its input: nothing may be written in place
        vS = (warped * warped - warped * warped).clamp_min(0)
        cross = warped * ref - mR * warped
        return 1.0 - (cross / torch.sqrt((vR + eps) * (vS + eps))).clamp(-1, 1)
    # in place where the old value is not needed again: the same operations in the same order
    # as the out-of-place formula, without a fresh (D, H, W) allocation per step
    mS = box_filter(warped, radius)
    t = warped * warped
    vS = box_filter(t, radius)
    torch.mul(mS, mS, out=t)
    vS.sub_(t).clamp_min_(0)
    torch.mul(warped, ref, out=t)
    cross = box_filter(t, radius)
    torch.mul(mR, mS, out=t)
    cross.sub_(t)
    del t, mS
    vS.add_(eps).mul_(vR + eps).sqrt_()  # sqrt((var S + eps)(var R + eps)), a commuted product
    ncc = cross.div_(vS).clamp_(-1, 1)
    return ncc.neg_().add_(1.0)


def aggregate_sources(costs: Tensor, valid: Tensor, keep_fraction: float,
                      missing_cost: float) -> Tensor:
    """Mean of the best ceil(keep_fraction · n_valid) costs over the valid sources.

    Args:
        costs: (S, D, H, W) per-source costs.
        valid: (S, D, H, W) bool, the hypothesis projects inside source s.
        keep_fraction: in (0, 1].
        missing_cost: the result where no source is valid.

    Returns:
        (D, H, W) aggregated cost.
    """
    S = costs.shape[0]
    if S == 1:
        return torch.where(valid[0], costs[0], torch.full_like(costs[0], missing_cost))
    if S == 2 and keep_fraction <= 0.5:
        # k = 1 wherever a source is valid: the smaller valid cost, the value the sort below
        # gives, without sorting along a dimension of 2 (slow on large volumes)
        big = torch.finfo(costs.dtype).max / 4
        a = torch.where(valid[0], costs[0], torch.full_like(costs[0], big))
        b = torch.where(valid[1], costs[1], torch.full_like(costs[1], big))
        best = torch.minimum(a, b)
        return best.masked_fill_(best >= big, missing_cost)
    big = torch.finfo(costs.dtype).max / 4
    c = torch.where(valid, costs, torch.full_like(costs, big))
    c, _ = torch.sort(c, dim=0)
    n_valid = valid.sum(0)
    k = torch.ceil(keep_fraction * n_valid.to(costs.dtype)).clamp_min(1).long()  # (D, H, W)
    c = torch.where(c >= big, torch.zeros_like(c), c)
    csum = torch.cumsum(c, dim=0)
    best = torch.gather(csum, 0, (k - 1)[None])[0] / k.to(costs.dtype)
    return torch.where(n_valid > 0, best, torch.full_like(best, missing_cost))


def calibrate_temperature(cost: Tensor, margin: float, mask: Tensor | None = None) -> float:
    """T = median_pixels(median_D cost - min_D cost) / (ln D + margin) (module docstring, step 5).

    Args:
        cost: (D, H, W) aggregated cost.
        margin: m.
        mask: optional (H, W) bool pixels to take the statistics over.

    Returns:
        T > 0.
    """
    D = cost.shape[0]
    gap = cost.median(dim=0).values - cost.min(dim=0).values
    if mask is not None and mask.any():
        gap = gap[mask]
    g = float(gap.median()) if gap.numel() else 0.0
    return max(g, 1e-3) / (math.log(D) + margin)


# --------------------------------------------------------------------------- backbone
def _gray(images: Tensor) -> Tensor:
    """(V, 3, H, W) RGB -> (V, 1, H, W) luma."""
    w = torch.tensor([0.299, 0.587, 0.114], dtype=images.dtype, device=images.device)
    return (images * w.view(1, 3, 1, 1)).sum(1, keepdim=True)


def _gradients(gray: Tensor) -> Tensor:
    """(V, 1, H, W) -> (V, 2, H, W) central differences (x, y), replicate border."""
    p = F.pad(gray, (1, 1, 1, 1), mode="replicate")
    gx = 0.5 * (p[..., 1:-1, 2:] - p[..., 1:-1, :-2])
    gy = 0.5 * (p[..., 2:, 1:-1] - p[..., :-2, 1:-1])
    return torch.cat([gx, gy], dim=1)


@register_backbone("planesweep")
class PlaneSweepBackbone(MVSBackbone):
    """Training-free plane sweep with ZNCC, guided-filter aggregation and a calibrated softmax.

    See the module docstring for the method. ``PlaneSweepBackbone(**fields)`` takes the fields of
    `PlaneSweepConfig`, or ``config=PlaneSweepConfig(...)``; ``device`` is the torch device the
    sweep runs on (default the CPU); its volumes stay there.
    """

    name = "planesweep"
    config_class = PlaneSweepConfig
    signature_names = {"ndepths": "num_depths", "crop_to_masks": "crop_margin"}

    @classmethod
    def scale_problem(cls, scale: float | None) -> str | None:
        """None: the plane sweep runs at any ``mvs.scale`` > 0 (its ``scale``; the limit is the
        option's own, `svolsdf.config.schema.MVSConfig.scale`)."""
        return None

    @classmethod
    def options(cls, mvs) -> dict:
        """`MVSBackbone.options`, with ``scale`` when ``mvs.scale`` is set (the sweep runs at
        any scale; unset, its own default)."""
        kw = super().options(mvs)
        if mvs.scale is not None:
            kw["scale"] = float(mvs.scale)
        return kw

    def __init__(self, config: PlaneSweepConfig | None = None,
                 device: torch.device | str | None = None, **fields) -> None:
        if config is None:
            try:
                config = PlaneSweepConfig(**fields)
            except TypeError as e:
                raise InputError(f"planesweep backbone: {e}") from None
        elif fields:
            raise InputError("planesweep backbone: pass either config or fields, not both")
        if not config.scale > 0:
            raise InputError(f"planesweep: scale must be > 0, got {config.scale}")
        if config.filter not in ("guided", "box", "none"):
            raise InputError(f"planesweep: filter must be guided, box or none, got {config.filter}")
        self.cfg = config
        # where the sweep runs; not a config field: it does not change the volumes, so cached
        # volumes (keyed by the config, `MVSBackbone.signature`) stay valid on another device
        self.device = torch.device(device if device is not None else "cpu")
        self._cache: dict = {}

    # ------------------------------------------------------------------ inputs
    def _stage_inputs(self, scene: Scene, k: int) -> tuple[Tensor, Tensor, object]:
        """(V,C,Hk,Wk) matching channels, (V,1,Hk,Wk) guide gray, cameras at stage k."""
        if scene.images is None:
            raise InputError(f"{scene.path}: the scene was loaded without images")
        W, H = stage_size(k, *mvs_size(scene.width, scene.height, self.cfg.scale))
        key = (id(scene), id(scene.images), k)
        if key in self._cache:
            return self._cache[key]
        if any(c[:2] != key[:2] for c in self._cache):  # another scene: forget the old one
            self._cache = {}
        imgs = scene.images.float().to(self.device)
        # the files, or bicubic upsampling (docs/method.md 9.2.2)
        if W > scene.width or H > scene.height:
            imgs = scene.images_at(W, H, from_files=self.cfg.native_images).to(self.device)
        elif (W, H) != (scene.width, scene.height):
            imgs = F.interpolate(imgs, size=(H, W), mode="bilinear", align_corners=False,
                                 antialias=True)
        gray = _gray(imgs)
        chans = gray
        if self.cfg.gradient_weight > 0:
            chans = torch.cat([gray, _gradients(gray)], dim=1)
        cams = scene.cameras.resize(W, H).to(self.device)
        # every stage of the latest scene: a cascade run one view at a time alternates them
        self._cache[key] = (chans, gray, cams)
        return chans, gray, cams

    def _centre(self, k: int, vid: int, W: int, H: int, guide_depth, prev) -> Tensor:
        if guide_depth is not None and vid in guide_depth:
            g = torch.as_tensor(guide_depth[vid]).float()
            if g.ndim == 3 and g.shape[0] == 1:
                g = g[0]
            if g.ndim != 2:
                raise InputError(
                    f"guide depth of view {vid} must be (H, W), got {tuple(g.shape)}")
            return upsample_depth(g.to(self.device), W, H)
        if prev is None or vid not in prev:
            raise InputError(
                f"stage {k} of view {vid} needs the previous stage's volume or a guide depth")
        return upsample_depth(prev[vid].depth.float().to(self.device), W, H)

    # ------------------------------------------------------------------ stage
    def stage(
        self,
        k: int,
        scene: Scene,
        ref_ids: list[int] | None = None,
        guide_depth: dict[int, Tensor] | None = None,
        prev: dict[int, ProbabilityVolume] | None = None,
    ) -> list[ProbabilityVolume]:
        """Run stage ``k`` (see `MVSBackbone.stage`); volumes at 1/2^(3-k) of the MVS size,
        ``scale`` x the working size."""
        if not 1 <= k <= 3:
            raise ValueError(f"stage must be 1, 2 or 3, got {k}")
        ref_ids = list(scene.view_ids if ref_ids is None else ref_ids)
        check_depth_ranges(scene, ref_ids)
        if len(scene) < 2:
            raise InputError(f"{scene.path}: plane sweep needs at least 2 views, got {len(scene)}")
        chans, gray, cams = self._stage_inputs(scene, k)
        out = []
        for vid in progress_bar(ref_ids, desc=f"MVS stage {k} (plane sweep)"):
            r = scene.index(vid)
            near, far = (float(x) for x in scene.depth_range[r])
            if k == 1:
                depths = stage_hypotheses(1, near, far, cams.height, cams.width,
                                          num_depths=self.cfg.ndepths[0],
                                          inverse=self.cfg.inverse_depth,
                                          device=self.device).contiguous()
            else:
                centre = self._centre(k, vid, cams.width, cams.height, guide_depth, prev)
                depths = stage_hypotheses(k, near, far, cams.height, cams.width, guide=centre,
                                          num_depths=self.cfg.ndepths[k - 1],
                                          width_mode=self.cfg.width)
                depths = depths.clamp_min(self.cfg.min_depth_ratio * near)
            src = [scene.index(s) for s in select_sources(scene, vid, self.cfg.max_sources)]
            box = self._crop_box(scene, r, cams.width, cams.height) if k > 1 else None
            x0, y0, x1, y1 = box or (0, 0, cams.width, cams.height)
            cam_r = cams[r] if box is None else cams[r].crop(x0, y0, x1 - x0, y1 - y0)
            hyp = depths[:, y0:y1, x0:x1].contiguous()
            cost = self._cost_volume(k, chans[r:r + 1, :, y0:y1, x0:x1],
                                     gray[r:r + 1, :, y0:y1, x0:x1], cam_r.proj.float(),
                                     [(chans[j:j + 1], cams.proj[j:j + 1].float()) for j in src],
                                     hyp)
            T = self.cfg.temperature
            if T is None:
                T = calibrate_temperature(cost, self.cfg.temperature_margin)
            prob = torch.softmax(-cost / T, dim=0)
            log.debug("planesweep stage %d view %d: T = %.4g", k, vid, T)
            vol = volume_from_prob(prob, hyp, cam_r, vid, k,
                                   inverse_depth=self.cfg.inverse_depth and k == 1,
                                   depth_radius=self.cfg.depth_radius)
            out.append(vol if box is None else _uncrop(vol, depths, cams[r], box))
        return out

    def _crop_box(self, scene: Scene, r: int, W: int, H: int) -> tuple[int, int, int, int] | None:
        """(x0, y0, x1, y1) at the stage's size W x H: the box of view index r's object mask
        dilated by ``crop_to_masks`` working-size pixels; None without a margin, masks, or an
        object in the mask."""
        m = self.cfg.crop_to_masks
        if m is None or scene.masks is None:
            return None
        mask = scene.masks[r].reshape(scene.masks.shape[-2:]) > 0.5
        ys, xs = mask.nonzero(as_tuple=True)
        if len(xs) == 0:
            return None
        Hw, Ww = mask.shape
        sx, sy = W / Ww, H / Hw
        # working pixel x spans [x - 0.5, x + 0.5], i.e. stage pixels from (x + 0.5 - 0.5 - m) sx
        x0 = max(0, math.floor((int(xs.min()) - m) * sx))
        y0 = max(0, math.floor((int(ys.min()) - m) * sy))
        x1 = min(W, math.ceil((int(xs.max()) + 1 + m) * sx))
        y1 = min(H, math.ceil((int(ys.max()) + 1 + m) * sy))
        return None if (x0, y0, x1, y1) == (0, 0, W, H) else (x0, y0, x1, y1)

    def _cost_volume(self, k: int, ref: Tensor, g: Tensor, P_ref: Tensor,
                     sources: list[tuple[Tensor, Tensor]], depths: Tensor) -> Tensor:
        """(D, H, W) aggregated matching cost of the reference over its sources.

        Args:
            k: the stage.
            ref: (1, C, H, W) the reference's matching channels (its image or a crop of it).
            g: (1, 1, H, W) its gray image, the aggregation filter's guide.
            P_ref: (1, 3, 4) or (1, 4, 4) its projection at (W, H) (`Cameras.proj`).
            sources: per source, its (1, C, Hs, Ws) channels and (1, ., 4) projection.
            depths: (D, H, W) hypotheses.
        """
        cfg = self.cfg
        D, H, W = depths.shape
        rad = cfg.window[k - 1] // 2
        frad = cfg.filter_radius[k - 1]
        C = ref.shape[1]
        ref_stats = []
        for c in range(C):
            m = box_filter(ref[:, c:c + 1], rad)
            v = (box_filter(ref[:, c:c + 1] ** 2, rad) - m * m).clamp_min(0)
            ref_stats.append((m, v))
        mI = box_filter(g, frad)
        g_stats = (mI, box_filter(g * g, frad) - mI * mI)
        cost = torch.empty(D, H, W, dtype=torch.float32, device=depths.device)
        weights = [1.0] + [cfg.gradient_weight] * (C - 1)
        wsum = sum(weights)
        for d0 in range(0, D, cfg.depth_chunk):
            dh = depths[d0:d0 + cfg.depth_chunk][None]
            per_src = torch.empty(len(sources), *dh.shape[1:], dtype=torch.float32,
                                  device=depths.device)
            valids = torch.empty(per_src.shape, dtype=torch.bool, device=depths.device)
            for j, (src_chans, P_src) in enumerate(sources):
                warped, valid = homo_warp(src_chans, P_src, P_ref, dh, padding_mode="border")
                # sum_c w_c cost_c / sum_c w_c, accumulated in channel order
                c_s = None
                for c in range(C):
                    z = zncc_cost(ref[:, c:c + 1], warped[:, c], rad, cfg.zncc_eps, ref_stats[c])
                    if weights[c] != 1.0:
                        z.mul_(weights[c])
                    c_s = z if c_s is None else c_s.add_(z)
                del warped
                torch.div(c_s[0], wsum, out=per_src[j])
                valids[j] = valid[0]
            agg = aggregate_sources(per_src, valids, cfg.keep_fraction, cfg.missing_cost)
            if cfg.filter == "guided":
                agg = guided_filter(g, agg[None], frad, cfg.filter_eps, g_stats)[0]
            elif cfg.filter == "box":
                agg = box_filter(agg[None], frad)[0]
            cost[d0:d0 + dh.shape[1]] = agg
        if cfg.sgm[k - 1]:
            cost = sgm_aggregate(cost, g[0, 0], cfg.sgm_p1, cfg.sgm_p2, cfg.sgm_sigma,
                                 cfg.sgm_directions)
        return cost


def _uncrop(vol: ProbabilityVolume, depths: Tensor, cam: Cameras,
            box: tuple[int, int, int, int]) -> ProbabilityVolume:
    """The cropped stage volume ``vol`` placed in the full image: ``depths`` (D, H, W) the full
    hypotheses, ``cam`` the full reference camera; probabilities, depth and confidence 0
    outside ``box`` (no depth there)."""
    x0, y0, x1, y1 = box
    D, H, W = depths.shape
    prob = vol.prob.new_zeros(D, H, W)
    prob[:, y0:y1, x0:x1] = vol.prob
    depth = vol.depth.new_zeros(H, W)
    depth[y0:y1, x0:x1] = vol.depth
    conf = vol.confidence.new_zeros(H, W)
    conf[y0:y1, x0:x1] = vol.confidence
    return ProbabilityVolume(depths, prob, depth, conf, cam, vol.view_id, vol.stage,
                             vol.inverse_depth)
