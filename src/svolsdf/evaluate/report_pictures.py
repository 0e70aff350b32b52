"""The picture sections of the HTML report (`svolsdf.evaluate.report`): the input photos beside
the mesh seen from their cameras, depth maps and their error against ground-truth depth, the
field's normal maps, the mesh from an orbit, and one strip per evaluated view."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from svolsdf.errors import raise_if_interrupted
from svolsdf.evaluate.report_parts import (
    DEPTH_CMAP,
    ERROR_CMAP,
    THUMB,
    ViewImages,
    colorbar,
    colorize,
    figure,
    file_b64,
    fmt,
    png_b64,
    tensor_u8,
    units_label,
)
from svolsdf.io.runfolder import RunFolder

__all__ = ["depth_error", "depth_section", "gt_distance_summary", "inputs_section", "mesh_pictures",
           "normals_section", "novel_section", "orbit_section"]

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- pictures
def _display_cameras(cameras, width: int = THUMB):
    """The cameras resized to at most ``width`` pixels across (float64)."""
    import torch

    c = cameras.to(dtype=torch.float64)
    if c.width > width:
        c = c.resize(width, max(8, round(c.height * width / c.width)))
    return c


def mesh_pictures(mesh, cameras) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(shaded picture, normal map, depth) of the mesh from each camera."""
    from svolsdf.evaluate.raster import rasterize_mesh, shade, vertex_normals

    v, f = mesh[0], mesh[1]
    colors = mesh[2] if len(mesh) > 2 else None
    normals = vertex_normals(v, f)
    out = []
    for k in range(len(cameras)):
        K, w2c = cameras.K[k].numpy(), cameras.w2c[k].numpy()
        r = rasterize_mesh(v, f, K, w2c, cameras.width, cameras.height)
        pic, nmap = shade(r, f, normals, w2c, colors)
        out.append((pic, nmap, r.depth))
    return out


def _normal_key(size: int = 56) -> np.ndarray:
    """A sphere coloured by its camera-frame normals: the key to the normal maps."""
    t = (np.arange(size) + 0.5) / size * 2 - 1
    x, y = np.meshgrid(t, t)
    inside = x * x + y * y < 1
    z = -np.sqrt(np.clip(1 - x * x - y * y, 0, 1))
    rgb = ((np.stack([x, y, z], -1) + 1) / 2 * 255 + 0.5).astype(np.uint8)
    rgb[~inside] = 255
    return rgb


def inputs_section(inputs, cameras, mesh) -> str:
    """Input photos beside the mesh (shaded, and its normals) from the same cameras."""
    if not inputs:
        return ""
    shots = None
    if mesh is not None and cameras is not None and len(mesh[1]):
        shots = mesh_pictures(mesh, _display_cameras(cameras))
    rows = []
    for k, (vid, im) in enumerate(inputs):
        figs = [figure(png_b64(tensor_u8(im)), f"input view {vid}")]
        if shots is not None:
            figs.append(figure(png_b64(shots[k][0]), f"mesh seen from view {vid}"))
            figs.append(figure(png_b64(shots[k][1]), f"mesh normals, view {vid}"))
        rows.append(f"<div class='row'>{''.join(figs)}</div>")
    key = ""
    if shots is not None:
        key = (f"<div class='key'>{figure(png_b64(_normal_key()), 'normal key')} Normals are shown "
               "in the camera frame as RGB = (n + 1) / 2: red = right, green = down, blue = "
               "away from the camera, so a surface facing the camera is olive; the sphere is "
               "the colour key.</div>")
    title = "Input views and the mesh" if shots is not None else "Input views"
    return f"<h2>{title}</h2>{key}{''.join(rows)}"


def depth_error(depth: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """|depth - ground truth| at the ground truth's pixels, and where it counts.

    Args:
        depth: (h, w) the run's z-depth (0 or non-finite: none), any size: read at the ground
            truth's pixels (nearest, so no mixing across edges).
        gt: (H, W) ground-truth z-depth (0: none).
        mask: (H', W') object mask (any size, > 0.5 = object) or None: with one, only pixels
            inside it count, so that the background (a table, the far wall) does not swamp the
            object's error.

    Returns:
        (H, W) float64 absolute error and the (H, W) bool pixels where it counts.
    """
    def at_gt(a: np.ndarray) -> np.ndarray:
        ys = ((np.arange(gt.shape[0]) + 0.5) * a.shape[0] / gt.shape[0]).astype(int)
        xs = ((np.arange(gt.shape[1]) + 0.5) * a.shape[1] / gt.shape[1]).astype(int)
        return a[np.ix_(ys, xs)]

    dd = at_gt(depth)
    valid = (gt > 0) & np.isfinite(dd) & (dd > 0)
    if mask is not None:
        valid &= at_gt(np.asarray(mask, np.float64).reshape(mask.shape[-2:])) > 0.5
    err = np.where(valid, np.abs(np.where(np.isfinite(dd), dd, 0.0) - gt), 0.0)
    return err, valid


def depth_section(out_dir: Path, view_ids: list[int], gt_depth: dict | None,
                  units: str | None, masks: dict | None = None) -> str:
    """Depth maps of the run (depth/<id>.npy) with a colour bar; with ground-truth depth, the
    per-view absolute error with its own colour bar, inside the object mask of ``masks`` (view
    id -> (H, W) mask) where the scene has one (`depth_error`), as each caption says."""
    u = units_label(units)
    rows = []
    depth_dir = RunFolder(out_dir).depth_dir
    npys = {v: depth_dir / f"{v}.npy" for v in view_ids}
    npys = {v: p for v, p in npys.items() if p.is_file()}
    if not npys:  # e.g. a run folder without .npy depth: show the previews as they are
        files = sorted(depth_dir.glob("*.png")) if depth_dir.is_dir() else []
        figs = [figure(b, p.stem) for p in files if (b := file_b64(p)) is not None]
        return f"<h2>Depth maps</h2><div class='grid'>{''.join(figs)}</div>" if figs else ""
    for vid, p in npys.items():
        try:
            d = np.load(p).astype(np.float64)
        except Exception as e:
            raise_if_interrupted()
            log.warning("report: cannot read %s (%s)", p, e)
            continue
        d = d.reshape(d.shape[-2:])
        valid = np.isfinite(d) & (d > 0)
        if not valid.any():
            continue
        lo, hi = np.percentile(d[valid], [1, 99])
        figs = [figure(png_b64(colorize(d, valid, DEPTH_CMAP, lo, hi)),
                     f"view {vid}: z-depth ({valid.mean():.0%} of pixels)",
                     colorbar(DEPTH_CMAP, lo, hi, f"z-depth ({u})"))]
        g = (gt_depth or {}).get(vid)
        if g is not None:
            m = (masks or {}).get(vid)
            err, both = depth_error(d, np.asarray(g, np.float64), m)
            if both.any():
                where = ("inside the object mask" if m is not None else
                         "over every pixel with ground truth: no object mask")
                vmax = float(np.percentile(err[both], 95)) or 1e-9
                figs.append(figure(
                    png_b64(colorize(err, both, ERROR_CMAP, 0.0, vmax)),
                    f"view {vid}: |depth - ground truth| {where}, median "
                    f"{np.median(err[both]):.3g} {u}",
                    colorbar(ERROR_CMAP, 0.0, vmax, f"absolute depth error ({u}; clipped at "
                                                    "the 95th percentile)")))
        rows.append(f"<div class='row'>{''.join(figs)}</div>")
    title = "Depth maps and depth error" if gt_depth else "Depth maps"
    return (f"<h2>{title}</h2><p>The fused depth of each input view (depth/&lt;view&gt;.npy); "
            f"grey: no depth.</p>{''.join(rows)}") if rows else ""


def normals_section(out_dir: Path) -> str:
    folder = RunFolder(out_dir).normals_dir
    files = sorted(folder.glob("*.png")) if folder.is_dir() else []
    figs = [figure(b, f"view {p.stem}") for p in files if (b := file_b64(p)) is not None]
    if not figs:
        return ""
    return ("<h2>Normal maps of the field</h2><div class='key'>"
            f"{figure(png_b64(_normal_key()), 'normal key')} Camera-frame normals as RGB = "
            "(n + 1) / 2 (red = right, green = down, blue = away from the camera); the sphere is "
            f"the colour key.</div><div class='grid'>{''.join(figs)}</div>")


def orbit_section(mesh, cameras, frames: int) -> str:
    if mesh is None or cameras is None or len(cameras) < 2 or frames < 2 or not len(mesh[1]):
        return ""
    from svolsdf.ibr.path import orbit_cameras

    try:
        cams = orbit_cameras(_display_cameras(cameras, 280), frames + 1, closed=True)[
            list(range(frames))]
    except ValueError as e:  # e.g. a camera centre on the look-at point
        log.warning("report: no orbit (%s)", e)
        return ""
    figs = [figure(png_b64(pic, 280), f"orbit {k + 1}/{frames}")
            for k, (pic, _, _) in enumerate(mesh_pictures(mesh, cams))]
    return ("<h2>The mesh from an orbit through the input views</h2>"
            f"<div class='grid'>{''.join(figs)}</div>")


def novel_section(views: list[ViewImages]) -> str:
    """One strip per evaluated view: ground truth | volume rendering | IBR | |error| of each,
    with one error scale per strip (mean absolute error over RGB inside the object mask, black
    outside it). Novel (held-out) views and input views rendered back go to two sections, so
    that a training view copied back is never shown as a novel one."""
    novel = _strips([v for v in views if v.role == "novel"])
    inputs = _strips([v for v in views if v.role != "novel"])
    out = ""
    if novel:
        out += "<h2>Novel views: ground truth, volume rendering, IBR, error</h2>" + novel
    if inputs:
        out += ("<h2>Input views rendered back: ground truth, volume rendering, IBR, error</h2>"
                "<p>The run trained on these views: their renders show how well it fits its "
                "inputs, not how it renders an unseen view, and no novel-view number counts "
                "them.</p>" + inputs)
    return out


def _strips(views: list[ViewImages]) -> str:
    if not views:
        return ""
    by_id: dict[int, dict[str, ViewImages]] = {}
    for v in views:
        by_id.setdefault(v.view_id, {})[v.kind] = v
    strips = []
    for vid, kinds in sorted(by_id.items()):
        first = next(iter(kinds.values()))
        gt = first.gt.detach().float().clamp(0, 1).cpu()
        inside = np.ones(gt.shape[-2:], bool)
        if first.mask is not None:
            inside = first.mask.reshape(gt.shape[-2:]).cpu().numpy() > 0.5
        errs = {}
        for kind, v in kinds.items():
            errs[kind] = (v.pred.detach().float().clamp(0, 1).cpu() - gt).abs().mean(0).numpy()
        vmax = max([0.05] + [float(e[inside].max()) for e in errs.values() if inside.any()])
        where = ("inside the object mask" if first.mask is not None else
                 "over all pixels: the scene has no object mask")
        tiles = [tensor_u8(gt)] + [tensor_u8(kinds[k].pred) for k in ("volume", "ibr")
                                    if k in kinds]
        tiles += [colorize(errs[k], inside, ERROR_CMAP, 0, vmax) for k in ("volume", "ibr")
                  if k in errs]
        for t in tiles[1 + len(errs):]:
            t[~inside] = 0
        gap = np.full((gt.shape[1], 4, 3), 255, np.uint8)
        strip = np.concatenate([x for t in tiles for x in (t, gap)][:-1], axis=1)
        names = ["ground truth"] + [n for k, n in (("volume", "volume rendering"),
                                                   ("ibr", "IBR")) if k in kinds]
        names += [f"|error| {n}" for k, n in (("volume", "volume"), ("ibr", "IBR"))
                  if k in kinds]
        cap = "; ".join(f"{k}: " + ", ".join(f"{m} {fmt(x)}" for m, x in v.metrics.items())
                        for k, v in kinds.items() if v.metrics)
        strips.append(figure(png_b64(strip, width=min(len(tiles), 5) * 240),
                           f"view {vid}: {' | '.join(names)}" + (f"; {cap}" if cap else ""),
                           colorbar(ERROR_CMAP, 0.0, vmax, f"mean absolute RGB error ({where})")))
    return "".join(strips)


def gt_distance_summary(point_errors, units: str | None) -> str:
    if point_errors is None or not len(point_errors[1]):
        return ""
    d = point_errors[1]
    q = np.percentile(d, [50, 90, 99])
    return (f"<p>Distance of the reconstructed points to the ground truth ({units_label(units)}): "
            f"median {q[0]:.3g}, 90th percentile {q[1]:.3g}, 99th {q[2]:.3g} (over "
            f"{len(d):,} points; the layer 'points: distance to ground truth' shows them "
            "coloured).</p>")
