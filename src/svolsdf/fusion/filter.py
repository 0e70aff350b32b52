"""Geometric-consistency filtering of depth maps and their fusion into a coloured point cloud.

Implements docs/method.md 6.3 (the released ``runner.py::filter_depth`` and
``helpers/utils.py::check_geometric_consistency``), vectorized in torch:

1. Each view is the reference once; every other view is a source.
2. A reference pixel is consistent with a source if its depth, carried to the source, sampled
   there (bilinear) and carried back, lands within ``dist`` pixels of where it started and
   within a relative depth difference ``rel`` (`svolsdf.geometry.reproject`).
3. Optionally (not in docs/method.md; the fast preset's ``fusion.surface``), a pixel whose
   depth lies on the optimized surface (its rendered depth in the reference view, within a
   relative tolerance) counts as one more consistent source; not for a depth map that is the
   surface's own depth.
4. Pixels with at least ``min_views`` consistent sources, a confidence above
   ``conf`` and inside the dilated object mask are kept; their depth is the average of the
   reference depth and the consistent reprojected depths, back-projected to world coordinates
   and coloured from the reference image.

Depth is z-depth in the cameras' world units; pixel centres sit at integer coordinates
(`svolsdf.scene.cameras`).

The reprojection check (`svolsdf.geometry.reproject.check_geometric_consistency`) and the mask
helpers (`svolsdf.geometry.masks`) live in `svolsdf.geometry`, below every stage that uses them.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from svolsdf.geometry.masks import dilate_mask, mask_to_depth_resolution
from svolsdf.geometry.reproject import (
    _at_size,
    _check_camera,
    _check_depth,
    check_geometric_consistency,
)
from svolsdf.io.progress import progress_bar
from svolsdf.scene.cameras import Cameras

__all__ = ["FusionFilterConfig", "FusedPoints", "fuse_depth_maps"]

log = logging.getLogger(__name__)


@dataclass
class FusionFilterConfig:
    """Depth-map filtering and fusion (docs/method.md 6.3)."""

    dist: float = 1.0
    """Largest reprojection distance, in pixels of the reference depth map, for a source to count
    as consistent (the released ``filter_dist``)."""

    rel: float = 0.01
    """Largest relative depth difference |d_reproj - d| / d for a source to count as consistent
    (the released ``filter_diff``)."""

    min_views: int = 1
    """Least number of consistent source views for a pixel to be kept (the released
    ``thres_view``; with three input views each reference has two sources)."""

    conf: float = 0.0
    """Photometric filter: keep pixels whose confidence is strictly greater than this. The default
    0 reproduces the released code, where conf > 0 removes (almost) nothing (docs/method.md 9.2.9);
    the paper's probability-based check needs a positive value, e.g. 0.3 for conf1*conf2*conf3.
    Ignored when no confidences are given."""

    use_masks: bool = True
    """Keep only pixels inside the (dilated) object mask of the reference view when masks are
    given (the released ``eval_mask = true``)."""

    mask_dilation: int = 12
    """Radius in pixels of the disk the masks are dilated with, at the mask's native resolution,
    before they are resized to the depth resolution (docs/method.md 6.3)."""

    guided_dilation: int | None = None
    """Dilation radius for the references of a depth a guide made (``fusion.guided_dilation``):
    ``depths`` (the first hypothesis) with ``guided_depths``, and every set of
    ``extra_depths``; None = ``mask_dilation``. The pipeline's field-guided stages 2-3 and
    the field's rendered depth: near the silhouette they inherit the field's errors, which are
    one 3D surface and so pass the multi-view check."""

    unguided_dilation: int | None = None
    """Dilation radius for the references of the MVS cascade's own depth
    (``fusion.unguided_dilation``): ``alt_depths`` (the second hypothesis), and ``depths``
    without ``guided_depths``; None = ``mask_dilation``. The fast preset narrows it: as a
    second hypothesis beside the guided depth, the unguided points in the rim between the
    object and the dilated mask were mostly background."""

    guided_depths: bool = True
    """``depths`` were made from a guide (MVS stages 2-3 centred on it, or a field's rendered
    depth itself) and take ``guided_dilation``; False: the MVS cascade's alone (the pipeline's
    mvs-only mode), which take ``unguided_dilation``."""

    surface: float = 0.0
    """With ``surface_depths`` (the optimized surface's depth rendered in each reference view): a
    pixel whose depth lies within this relative difference of the surface's depth counts as one
    more consistent source (its fused depth is not changed by it). The surface is fitted to all
    views at once, so agreeing with it is multi-view evidence where the other views' depth maps
    failed (rims, occlusion borders). 0 = off (the released fusion). It is no source for a
    depth map equal to it (VolSDF's rendered depth): that map would pass at every pixel."""

    estimate_normals: bool = False
    """Also return per-point normals, from finite differences of the fused depth map's
    back-projected points, oriented towards the reference camera."""

    @classmethod
    def from_config(cls, fusion, **fields) -> FusionFilterConfig:
        """The filter of a run's fusion section ``fusion`` (a `svolsdf.config.FusionConfig`):
        every option of the section that is a field here, under the same name (``dist``,
        ``rel``, ``min_views``, ``conf``, ``surface``, ``guided_dilation``,
        ``unguided_dilation``), and ``fields`` for the others (``use_masks``,
        ``guided_depths``) or instead of an option (which is then not read)."""
        own = {f.name: getattr(fusion, f.name) for f in dataclasses.fields(cls)
               if f.name not in fields and hasattr(fusion, f.name)}
        return cls(**own, **fields)


class FusedPoints(NamedTuple):
    """The result of `fuse_depth_maps`.

    Attributes:
        points: (N, 3) float32 world points.
        colors: (N, 3) uint8 colours from the reference images, or None without images.
        normals: (N, 3) float32 unit normals, or None unless ``estimate_normals``.
        stats: view id -> {"valid", "geo" (consistent; checked only at the pixels the
            confidence and the mask keep), "surface_only" (geometric only thanks to the surface),
            "photo", "mask", "kept": share of the depth map's pixels; "points": number of points
            contributed}.
    """

    points: Tensor
    colors: Tensor | None
    normals: Tensor | None
    stats: dict


# ---------------------------------------------------------------------------------------------
# fusion


def _normals_from_points(pts: Tensor, center: Tensor) -> Tensor:
    """(H, W, 3) point map -> (H, W, 3) unit normals facing ``center`` (zeros where undefined)."""
    du = torch.zeros_like(pts)
    dv = torch.zeros_like(pts)
    du[:, 1:-1] = pts[:, 2:] - pts[:, :-2]
    dv[1:-1] = pts[2:] - pts[:-2]
    n = torch.cross(du, dv, dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    to_cam = center.to(pts) - pts
    flip = (n * to_cam).sum(-1, keepdim=True) < 0
    return torch.where(flip, -n, n)


def _same_map(a: Tensor, b: Tensor) -> bool:
    """Two depth maps hold the same values (the same size, equal where either is finite)."""
    return a is b or (tuple(a.shape) == tuple(b.shape)
                      and torch.equal(torch.nan_to_num(a.float()),
                                      torch.nan_to_num(b.float().to(a.device))))


def _image_at(image: Tensor, height: int, width: int) -> Tensor:
    """(3, H, W) image resized to (3, height, width) (bilinear, antialiased when shrinking)."""
    if tuple(image.shape[-2:]) == (height, width):
        return image
    shrink = height < image.shape[-2] or width < image.shape[-1]
    return F.interpolate(
        image[None].float(), size=(height, width), mode="bilinear", align_corners=False,
        antialias=shrink,
    )[0]


def fuse_depth_maps(
    depths: dict[int, Tensor],
    cameras: dict[int, Cameras],
    images: dict[int, Tensor] | None = None,
    confidences: dict[int, Tensor] | None = None,
    masks: dict[int, Tensor] | None = None,
    cfg: FusionFilterConfig | None = None,
    surface_depths: dict[int, Tensor] | None = None,
    alt_depths: dict[int, Tensor] | None = None,
    alt_confidences: dict[int, Tensor] | None = None,
    extra_depths: dict[str, dict[int, Tensor]] | None = None,
    extra_confidences: dict[str, dict[int, Tensor]] | None = None,
    device: torch.device | str | None = None,
) -> FusedPoints:
    """Filter every depth map against the others and fuse the survivors (docs/method.md 6.3).

    Each view is the reference once with all other views as sources. A pixel survives if
    ``#consistent >= cfg.min_views`` (geometric), ``conf > cfg.conf`` (photometric,
    when confidences are given) and it lies in the reference's dilated mask (when masks are given
    and ``cfg.use_masks``). Its fused depth is
    (d_ref + sum of consistent reprojected d) / (1 + #consistent), back-projected with the
    reference camera into world coordinates (the cameras' units).

    With ``alt_depths`` every view has a second depth hypothesis (the pipeline's unguided MVS
    stages 2-3, ``fusion.unguided``; an extension of docs/method.md 6.3). Each hypothesis
    of each view is a reference in turn; a source view is consistent when either of its
    hypotheses agrees (it still counts once, and its reprojected depth is the first hypothesis
    that agrees, ``depths`` before ``alt_depths``). The points of both are returned, the
    ``depths`` references' first. ``extra_depths`` adds further named hypotheses the same way
    (after ``alt_depths``; the pipeline's ``fusion.network``); they are guided by the
    field, so their references take ``cfg.guided_dilation`` (when set) as ``depths`` does;
    ``alt_depths``' references take ``cfg.unguided_dilation`` (when set).

    Depth maps may be at another resolution than the cameras, images and masks: cameras are
    resized to the depth size (`Cameras.resize`), masks are dilated at their own resolution and
    then resized bilinearly and thresholded at > 0, images are resized to the depth size before
    the colours are read.

    Args:
        depths: view id -> (H, W) z-depth in world units (<= 0 = no depth).
        cameras: view id -> `Cameras` with one view (any resolution).
        images: view id -> (3, Hi, Wi) float in [0, 1] (or uint8), or None.
        confidences: view id -> (H, W) confidence at the depth resolution, or None.
        masks: view id -> (Hm, Wm) or (1, Hm, Wm) object masks, or None.
        cfg: `FusionFilterConfig`; defaults reproduce the released settings.
        surface_depths: view id -> (Hs, Ws) z-depth of the optimized surface (<= 0 = none),
            used when ``cfg.surface > 0``; resized (nearest, so that no depth mixes
            across an edge) to each hypothesis' depth size.
        alt_depths: view id -> (H2, W2) second z-depth hypothesis, or None.
        alt_confidences: view id -> (H2, W2) confidence of ``alt_depths``; needed with
            ``alt_depths`` when ``confidences`` are given.
        extra_depths: name -> (view id -> (H3, W3) z-depth), further hypotheses, or None.
        extra_confidences: name -> (view id -> (H3, W3) confidence); needed with
            ``extra_depths`` when ``confidences`` are given.
        device: where the filtering runs (the depth maps, confidences and surface depths are
            moved there; cameras, images and masks follow each reference's depth); None: where
            ``depths`` are. The returned points are on the CPU either way.

    Returns:
        `FusedPoints` (points (N, 3), colors (N, 3) uint8 or None, normals (N, 3) or None,
        stats: keyed by view id, by "<view id>:alt" for the second hypotheses and by
        "<view id>:<name>" for ``extra_depths``).
    """
    cfg = cfg or FusionFilterConfig()
    ids = list(depths)
    if len(ids) < 2:
        raise ValueError(f"fusion needs at least two depth maps, got {len(ids)}")
    use_surface = surface_depths is not None and cfg.surface > 0
    if alt_depths is not None and confidences is not None and alt_confidences is None:
        raise ValueError("alt_depths with confidences needs alt_confidences")
    use_alt = alt_depths is not None
    extra_depths = extra_depths or {}
    if extra_depths and confidences is not None and (
            extra_confidences is None or set(extra_confidences) != set(extra_depths)):
        raise ValueError("extra_depths with confidences needs extra_confidences of the same sets")
    extras = [(f"extra_depths[{k!r}]", d) for k, d in extra_depths.items()]
    if confidences is not None:
        extras += [(f"extra_confidences[{k!r}]", extra_confidences[k]) for k in extra_depths]
    for name, d in (("cameras", cameras), ("images", images), ("confidences", confidences),
                    ("masks", masks), ("surface_depths", surface_depths if use_surface else None),
                    ("alt_depths", alt_depths),
                    ("alt_confidences", alt_confidences if confidences is not None and use_alt
                     else None), *extras):
        if d is not None and any(v not in d for v in ids):
            missing = [v for v in ids if v not in d]
            raise ValueError(f"{name} has no entry for view(s) {missing}")
    for v in ids:
        _check_depth(depths[v], f"depths[{v}]")
        _check_camera(cameras[v], f"cameras[{v}]")
        if use_alt:
            _check_depth(alt_depths[v], f"alt_depths[{v}]")
        for k, d in extra_depths.items():
            _check_depth(d[v], f"extra_depths[{k!r}][{v}]")
    if device is not None:
        dev = torch.device(device)

        def move(d):
            return None if d is None else {v: t.to(dev) for v, t in d.items()}

        depths, confidences, alt_depths, alt_confidences = (
            move(depths), move(confidences), move(alt_depths), move(alt_confidences))
        surface_depths = move(surface_depths)
        extra_depths = {k: move(d) for k, d in extra_depths.items()}
        if extra_confidences is not None:
            extra_confidences = {k: move(d) for k, d in extra_confidences.items()}
    # view id -> its hypotheses, primary first; each set's stats suffix and its mask dilation
    # (the field-guided sets take the primary one)
    guided = cfg.mask_dilation if cfg.guided_dilation is None else cfg.guided_dilation
    second = cfg.mask_dilation if cfg.unguided_dilation is None else cfg.unguided_dilation
    primary = guided if cfg.guided_depths else second
    sets = [("", primary)] + ([(":alt", second)] if use_alt else []) + \
        [(f":{k}", primary) for k in extra_depths]
    hyps = {v: [depths[v]] + ([alt_depths[v]] if use_alt else [])
            + [d[v] for d in extra_depths.values()] for v in ids}
    confs = {v: [confidences[v]] + ([alt_confidences[v]] if use_alt else [])
             + [extra_confidences[k][v] for k in extra_depths]
             for v in ids} if confidences is not None else None

    all_pts, all_cols, all_nrm = [], [], []
    stats: dict = {}
    jobs = [(h, suffix, radius, ref) for h, (suffix, radius) in enumerate(sets) for ref in ids]
    for h, suffix, radius, ref in progress_bar(jobs, desc="fusion"):
        key = ref if h == 0 else f"{ref}{suffix}"
        r = _fuse_reference(ref, h, hyps, cameras, images, confs, masks, cfg,
                            surface_depths if use_surface else None, radius)
        all_pts.append(r["points"])
        if r["colors"] is not None:
            all_cols.append(r["colors"])
        if r["normals"] is not None:
            all_nrm.append(r["normals"])
        stats[key] = r["stats"]
        log.info("fusion: view %s keeps %.1f%% of pixels (valid %.1f%%, geometric %.1f%%)",
                 key, 100 * r["stats"]["kept"], 100 * r["stats"]["valid"],
                 100 * r["stats"]["geo"])
    points = torch.cat(all_pts, 0).cpu()
    colors = torch.cat(all_cols, 0).cpu() if images is not None else None
    normals = torch.cat(all_nrm, 0).cpu() if cfg.estimate_normals else None
    return FusedPoints(points, colors, normals, stats)


def _fuse_reference(ref: int, h: int, hyps: dict[int, list[Tensor]],
                    cameras: dict[int, Cameras], images: dict[int, Tensor] | None,
                    confs: dict[int, list[Tensor]] | None, masks: dict[int, Tensor] | None,
                    cfg: FusionFilterConfig, surface_depths: dict[int, Tensor] | None,
                    radius: int) -> dict:
    """Hypothesis ``h`` of view ``ref`` as the reference of `fuse_depth_maps`: its kept points
    (N, 3), colours (N, 3) uint8 or None, normals (N, 3) or None and stats. ``radius``: the
    dilation of its mask, in pixels."""
    d_ref = hyps[ref][h].float()
    H, W = d_ref.shape
    cam_ref = _at_size(cameras[ref], d_ref)
    valid = torch.isfinite(d_ref) & (d_ref > 0)
    photo = torch.ones_like(valid)
    if confs is not None:
        conf = confs[ref][h].to(d_ref.device)
        conf = conf.reshape(conf.shape[-2:])
        if tuple(conf.shape) != (H, W):
            raise ValueError(f"the confidence of hypothesis {h} of view {ref} is "
                             f"{tuple(conf.shape)} but its depth map is {(H, W)}")
        photo = conf > cfg.conf
    inside = torch.ones_like(valid)
    if masks is not None and cfg.use_masks:
        dil = dilate_mask(masks[ref], radius)
        inside = mask_to_depth_resolution(dil, H, W).to(d_ref.device)
    # the sources are checked only at the pixels the photometric test and the mask keep
    # (each pixel's check is its own, `check_geometric_consistency`): the same points, a
    # fraction of the work where the object fills a fraction of the image
    cand = valid & photo & inside
    pixels = None if bool(cand.all()) else cand.reshape(-1).nonzero()[:, 0]
    count = torch.zeros(H, W, dtype=torch.int32, device=d_ref.device)
    d_sum = torch.where(valid, d_ref, torch.zeros_like(d_ref)).double()
    for src in hyps:
        if src == ref:
            continue
        agree = torch.zeros_like(valid)  # a source view counts once, whichever hypothesis agrees
        for d_src in hyps[src]:
            m, d_rep, _ = check_geometric_consistency(
                d_ref, cam_ref, d_src.float().to(d_ref.device), cameras[src],
                cfg.dist, cfg.rel, pixels=pixels,
            )
            new = m & ~agree
            d_sum += torch.where(new, d_rep.double(), torch.zeros_like(d_sum))
            agree |= m
        count += agree.int()
    support = count
    on_surface = torch.zeros_like(valid)
    if surface_depths is not None:
        ds = surface_depths[ref].to(d_ref.device).float()
        if tuple(ds.shape) != (H, W):  # hypotheses may differ in size; nearest: no mixing
            ds = F.interpolate(ds[None, None], size=(H, W), mode="nearest")[0, 0]
        # a hypothesis that is the surface's own depth (VolSDF's rendered depth, a network
        # echoing its guide) would lie on it at every pixel: the surface is no source for it
        if not _same_map(ds, d_ref):
            on_surface = (ds > 0) & ((d_ref - ds).abs() < cfg.surface * d_ref)
        support = count + on_surface.int()
    geo = cand & (support >= cfg.min_views)
    keep = geo
    fused = (d_sum / (1 + count).double()).float()  # docs/method.md 6.3, "Fused depth"

    uv = cam_ref.pixel_grid(device=d_ref.device, dtype=torch.float64).reshape(1, -1, 2)
    cam64 = cam_ref.to(device=d_ref.device, dtype=torch.float64)
    pts_map = cam64.unproject(uv, fused.double().reshape(1, -1))[0].reshape(H, W, 3)
    col = nrm = None
    if images is not None:
        img = images[ref]
        if img.dtype == torch.uint8:
            img = img.float() / 255.0
        img = _image_at(img.to(d_ref.device), H, W)
        col = (img.permute(1, 2, 0)[keep].clamp(0, 1) * 255.0).round().to(torch.uint8)
    if cfg.estimate_normals:
        pm = torch.where(keep[..., None], pts_map, torch.full_like(pts_map, float("nan")))
        nrm = torch.nan_to_num(_normals_from_points(pm, cam64.centers[0])[keep], nan=0.0).float()
    n = H * W
    stats = {
        "valid": float(valid.sum()) / n,
        "geo": float(geo.sum()) / n,
        "surface_only": float((cand & on_surface & (count < cfg.min_views)).sum()) / n,
        "photo": float((photo & valid).sum()) / n,
        "mask": float((inside & valid).sum()) / n,
        "kept": float(keep.sum()) / n,
        "points": int(keep.sum()),
    }
    return {"points": pts_map[keep].float(), "colors": col, "normals": nrm, "stats": stats}
