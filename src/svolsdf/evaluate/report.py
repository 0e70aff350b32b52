"""The run's HTML report: one self-contained page that opens offline.

The page holds, in order: an interactive 3D view (`svolsdf.evaluate.viewer`: the mesh with its
vertex colours, the points subsampled, the input cameras as frusta, and with ground truth the
points coloured by their distance to it; plotly.js is embedded once, so no network is needed);
the metrics with units and what each means; the input photos beside pictures of the mesh seen
from the same cameras (`svolsdf.evaluate.raster`, a CPU z-buffer) and its normals; depth maps
and, with ground-truth depth, per-view depth error maps, each with a colour bar; the mesh from an
orbit through the inputs; one strip per novel view (ground truth, volume rendering, IBR, errors);
the run's config and timings. Pictures are PNGs embedded as base64; colour bars are CSS
gradients of the same colour maps.
"""

from __future__ import annotations

import base64
import html
import io
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from torch import Tensor

from svolsdf.errors import raise_if_interrupted
from svolsdf.io.runfolder import RunFolder, atomic_write

__all__ = ["ViewImages", "METRIC_INFO", "write_report"]

log = logging.getLogger(__name__)

_THUMB = 360  # width in pixels of embedded pictures
_DEPTH_CMAP = "viridis"
_ERROR_CMAP = "inferno"

METRIC_INFO = {
    "accuracy": "mean distance from the reconstruction to the nearest ground-truth point "
                "(lower is better)",
    "completeness": "mean distance from the ground truth to the nearest reconstructed point "
                    "(lower is better)",
    "overall": "mean of accuracy and completeness: the Chamfer distance (lower is better)",
    "fscore": "harmonic mean of precision and recall at the threshold (higher is better)",
    "precision": "fraction of reconstructed points within the threshold of the ground truth",
    "recall": "fraction of ground-truth points within the threshold of the reconstruction",
    "psnr": "peak signal-to-noise ratio of the render against the held-out photo, inside the "
            "object mask (higher is better)",
    "ssim": "structural similarity of render and photo, 1 = identical (higher is better)",
    "lpips": "learned perceptual distance (deep features) of render and photo (lower is better)",
}
"""One line per metric: what it measures (the report's metrics table)."""


@dataclass
class ViewImages:
    """One evaluated novel view.

    Attributes:
        view_id: the view id.
        pred: (3, H, W) float rendering in [0, 1].
        gt: (3, H, W) float ground truth in [0, 1].
        mask: (1, H, W) object mask or None.
        metrics: metric name -> value for this view.
        kind: which renderer ("volume" or "ibr").
    """

    view_id: int
    pred: Tensor
    gt: Tensor
    mask: Tensor | None = None
    metrics: dict = field(default_factory=dict)
    kind: str = "volume"


# --------------------------------------------------------------------------- small helpers
def _png_b64(a: np.ndarray, width: int = _THUMB) -> str:
    """(H, W, 3|4) uint8 or (H, W) -> base64 PNG of at most ``width`` pixels across."""
    from PIL import Image

    im = Image.fromarray(a)
    if im.width > width:
        im = im.resize((width, max(1, round(im.height * width / im.width))), Image.LANCZOS)
    buf = io.BytesIO()
    im.save(buf, format="PNG")
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _file_b64(path: Path) -> str | None:
    from PIL import Image

    try:
        with Image.open(path) as im:
            return _png_b64(np.asarray(im.convert("RGB")))
    except Exception as e:  # a broken preview must not break the report
        raise_if_interrupted()
        log.warning("report: cannot read %s (%s)", path, e)
        return None


def _tensor_u8(x: Tensor) -> np.ndarray:
    return (x.detach().float().clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255 + 0.5).astype(
        np.uint8)


def _img(b64: str, caption: str, extra: str = "") -> str:
    return (f'<figure><img src="data:image/png;base64,{b64}" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption>{extra}</figure>")


def _fmt(v) -> str:
    if v is None:
        return "&ndash;"
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        return f"{v:.4g}" if abs(v) < 1e4 else f"{v:.0f}"
    return html.escape(str(v))


def _colorize(values: np.ndarray, valid: np.ndarray, cmap: str, vmin: float, vmax: float
              ) -> np.ndarray:
    """(H, W) values -> (H, W, 3) uint8 through a matplotlib colour map; invalid pixels grey."""
    from matplotlib import colormaps

    t = np.clip((values - vmin) / max(vmax - vmin, 1e-12), 0, 1)
    rgb = (colormaps[cmap](t)[..., :3] * 255 + 0.5).astype(np.uint8)
    rgb[~valid] = 200
    return rgb


def _colorbar(cmap: str, vmin: float, vmax: float, label: str) -> str:
    """A horizontal colour bar as a CSS gradient with min / middle / max ticks."""
    from matplotlib import colormaps

    cm = colormaps[cmap]
    stops = ",".join(
        "rgb({},{},{}) {:.0f}%".format(*(int(255 * x + 0.5) for x in cm(t)[:3]), 100 * t)
        for t in np.linspace(0, 1, 11))
    ticks = "".join(f"<span>{v:.4g}</span>" for v in (vmin, (vmin + vmax) / 2, vmax))
    return (f'<div class="cbar"><div class="grad" style="background:linear-gradient(to right,'
            f'{stops})"></div><div class="ticks">{ticks}</div>'
            f'<div class="cbl">{html.escape(label)}</div></div>')


def _units(units: str | None) -> str:
    return units if units and units != "unknown" else "world units"


# --------------------------------------------------------------------------- tables
def _metrics_table(metrics: dict, units: str | None) -> str:
    u = _units(units)
    rows = []
    msrc = metrics.get("mesh_source")
    mesh_label = f"mesh: {msrc}" if msrc else "mesh"
    for key, src in (("chamfer", "points"), ("chamfer_mesh", mesh_label)):
        blk = metrics.get(key) or {}
        if key == "chamfer_mesh" and blk.get("overall") is None:
            continue
        for k in ("accuracy", "completeness", "overall"):
            rows.append((f"Chamfer {k} ({src})", blk.get(k), u, METRIC_INFO[k]))
    ratio = metrics.get("mesh_over_points") or {}
    for k in ("accuracy", "completeness", "overall"):
        if ratio.get(k) is not None:
            rows.append((f"mesh / points, {k}", ratio[k], "ratio",
                         "the mesh's score over the points' (1 = as good; above 1 the mesh "
                         "carries error the points do not)"))
    cm = metrics.get("chamfer_mesh") or {}
    if cm.get("overall") is not None:
        d = cm.get("density")
        how = (f"its surface, sampled every {d:.3g} {u}" if cm.get("sampled") == "surface"
               and d is not None else "its vertices (metrics of an older version)")
        rows.append(("mesh scored by", how, "",
                     "the mesh's Chamfer counts its triangles by their area, at the protocol's "
                     "density (DTU 0.2 mm, otherwise 0.1 % of the ground truth's diagonal), so "
                     "surface over a hole or past a silhouette counts however few its vertices"))
    if msrc:
        rows.append(("mesh.ply is", msrc, "",
                     "which surface the mesh is: the field's zero level, the Poisson surface "
                     "of the points or the TSDF of the depth; a failed method says so"))
    thr = metrics.get("fscore_threshold")
    at = f" at {_fmt(thr)} {u}" if thr else ""
    rows.append((f"F-score{at}", metrics.get("fscore"), "0..1", METRIC_INFO["fscore"]))
    for k in ("precision", "recall"):
        if metrics.get(k) is not None:
            rows.append((f"{k.capitalize()}{at}", metrics.get(k), "0..1", METRIC_INFO[k]))
    unit = {"psnr": "dB", "ssim": "0..1", "lpips": "0..1"}
    for group, label in (("images", "volume rendering"), ("images_ibr", "IBR")):
        g = metrics.get(group) or {}
        for k in ("psnr", "ssim", "lpips"):
            m = (g.get(k) or {}).get("mean")
            if m is not None or group == "images":
                rows.append((f"{k.upper()} mean ({label})", m, unit[k], METRIC_INFO[k]))
    body = "".join(f"<tr><td>{html.escape(a)}</td><td>{_fmt(b)}</td><td>{html.escape(c)}</td>"
                   f"<td class='why'>{html.escape(d)}</td></tr>" for a, b, c, d in rows)
    return (f'<table id="metrics"><thead><tr><th>metric</th><th>value</th><th>unit</th>'
            f"<th class='why'>meaning</th></tr></thead><tbody>{body}</tbody></table>")


def _per_view_table(views: list[ViewImages]) -> str:
    if not views or not any(v.metrics for v in views):
        return ""
    keys = sorted({k for v in views for k in v.metrics})
    head = "".join(f"<th>{html.escape(k)}</th>" for k in keys)
    body = "".join(
        f"<tr><td>{v.view_id}</td><td>{html.escape(v.kind)}</td>"
        + "".join(f"<td>{_fmt(v.metrics.get(k))}</td>" for k in keys) + "</tr>" for v in views)
    return (f'<table id="per-view"><thead><tr><th>view</th><th>renderer</th>{head}</tr></thead>'
            f"<tbody>{body}</tbody></table>")


def _timing_table(timing: dict | None) -> str:
    if not timing:
        return "<p>No timing recorded.</p>"
    flat = []

    def walk(prefix, d):
        for k, v in d.items():
            if isinstance(v, dict):
                walk(f"{prefix}{k}.", v)
            else:
                flat.append((f"{prefix}{k}", v))

    walk("", timing)
    body = "".join(f"<tr><td>{html.escape(k)}</td><td>{_fmt(v)}</td></tr>" for k, v in flat)
    return f'<table id="timing"><tbody>{body}</tbody></table>'


# --------------------------------------------------------------------------- pictures
def _display_cameras(cameras, width: int = _THUMB):
    """The cameras resized to at most ``width`` pixels across (float64)."""
    import torch

    c = cameras.to(dtype=torch.float64)
    if c.width > width:
        c = c.resize(width, max(8, round(c.height * width / c.width)))
    return c


def _mesh_pictures(mesh, cameras) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
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


def _inputs_section(inputs, cameras, mesh) -> str:
    """Input photos beside the mesh (shaded, and its normals) from the same cameras."""
    if not inputs:
        return ""
    shots = None
    if mesh is not None and cameras is not None and len(mesh[1]):
        shots = _mesh_pictures(mesh, _display_cameras(cameras))
    rows = []
    for k, (vid, im) in enumerate(inputs):
        figs = [_img(_png_b64(_tensor_u8(im)), f"input view {vid}")]
        if shots is not None:
            figs.append(_img(_png_b64(shots[k][0]), f"mesh seen from view {vid}"))
            figs.append(_img(_png_b64(shots[k][1]), f"mesh normals, view {vid}"))
        rows.append(f"<div class='row'>{''.join(figs)}</div>")
    key = ""
    if shots is not None:
        key = (f"<div class='key'>{_img(_png_b64(_normal_key()), 'normal key')} Normals are shown "
               "in the camera frame as RGB = (n + 1) / 2: red = right, green = down, blue = "
               "away from the camera, so a surface facing the camera is olive; the sphere is "
               "the colour key.</div>")
    title = "Input views and the mesh" if shots is not None else "Input views"
    return f"<h2>{title}</h2>{key}{''.join(rows)}"


def _depth_section(out_dir: Path, view_ids: list[int], gt_depth: dict | None,
                   units: str | None) -> str:
    """Depth maps of the run (depth/<id>.npy) with a colour bar; with ground-truth depth, the
    per-view absolute error with its own colour bar."""
    u = _units(units)
    rows = []
    depth_dir = RunFolder(out_dir).depth_dir
    npys = {v: depth_dir / f"{v}.npy" for v in view_ids}
    npys = {v: p for v, p in npys.items() if p.is_file()}
    if not npys:  # e.g. a run folder without .npy depth: show the previews as they are
        files = sorted(depth_dir.glob("*.png")) if depth_dir.is_dir() else []
        figs = [_img(b, p.stem) for p in files if (b := _file_b64(p)) is not None]
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
        figs = [_img(_png_b64(_colorize(d, valid, _DEPTH_CMAP, lo, hi)),
                     f"view {vid}: z-depth ({valid.mean():.0%} of pixels)",
                     _colorbar(_DEPTH_CMAP, lo, hi, f"z-depth ({u})"))]
        g = (gt_depth or {}).get(vid)
        if g is not None:
            g = np.asarray(g, np.float64)
            # the run's depth at the ground truth's pixels (nearest: no mixing across edges)
            ys = ((np.arange(g.shape[0]) + 0.5) * d.shape[0] / g.shape[0]).astype(int)
            xs = ((np.arange(g.shape[1]) + 0.5) * d.shape[1] / g.shape[1]).astype(int)
            dd = d[np.ix_(ys, xs)]
            both = (g > 0) & np.isfinite(dd) & (dd > 0)
            if both.any():
                err = np.abs(dd - g)
                vmax = float(np.percentile(err[both], 95)) or 1e-9
                figs.append(_img(
                    _png_b64(_colorize(err, both, _ERROR_CMAP, 0.0, vmax)),
                    f"view {vid}: |depth - ground truth|, median {np.median(err[both]):.3g} {u}",
                    _colorbar(_ERROR_CMAP, 0.0, vmax, f"absolute depth error ({u}; clipped at "
                                                      "the 95th percentile)")))
        rows.append(f"<div class='row'>{''.join(figs)}</div>")
    title = "Depth maps and depth error" if gt_depth else "Depth maps"
    return (f"<h2>{title}</h2><p>The fused depth of each input view (depth/&lt;view&gt;.npy); "
            f"grey: no depth.</p>{''.join(rows)}") if rows else ""


def _normals_section(out_dir: Path) -> str:
    folder = RunFolder(out_dir).normals_dir
    files = sorted(folder.glob("*.png")) if folder.is_dir() else []
    figs = [_img(b, f"view {p.stem}") for p in files if (b := _file_b64(p)) is not None]
    if not figs:
        return ""
    return ("<h2>Normal maps of the field</h2><div class='key'>"
            f"{_img(_png_b64(_normal_key()), 'normal key')} Camera-frame normals as RGB = "
            "(n + 1) / 2 (red = right, green = down, blue = away from the camera); the sphere is "
            f"the colour key.</div><div class='grid'>{''.join(figs)}</div>")


def _orbit_section(mesh, cameras, frames: int) -> str:
    if mesh is None or cameras is None or len(cameras) < 2 or frames < 2 or not len(mesh[1]):
        return ""
    from svolsdf.ibr.path import orbit_cameras

    try:
        cams = orbit_cameras(_display_cameras(cameras, 280), frames + 1, closed=True)[
            list(range(frames))]
    except ValueError as e:  # e.g. a camera centre on the look-at point
        log.warning("report: no orbit (%s)", e)
        return ""
    figs = [_img(_png_b64(pic, 280), f"orbit {k + 1}/{frames}")
            for k, (pic, _, _) in enumerate(_mesh_pictures(mesh, cams))]
    return ("<h2>The mesh from an orbit through the input views</h2>"
            f"<div class='grid'>{''.join(figs)}</div>")


def _novel_section(views: list[ViewImages]) -> str:
    """One strip per novel view: ground truth | volume rendering | IBR | |error| of each, with
    one error scale per strip (mean absolute error over RGB, black outside the mask)."""
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
        tiles = [_tensor_u8(gt)] + [_tensor_u8(kinds[k].pred) for k in ("volume", "ibr")
                                    if k in kinds]
        tiles += [_colorize(errs[k], inside, _ERROR_CMAP, 0, vmax) for k in ("volume", "ibr")
                  if k in errs]
        for t in tiles[1 + len(errs):]:
            t[~inside] = 0
        gap = np.full((gt.shape[1], 4, 3), 255, np.uint8)
        strip = np.concatenate([x for t in tiles for x in (t, gap)][:-1], axis=1)
        names = ["ground truth"] + [n for k, n in (("volume", "volume rendering"),
                                                   ("ibr", "IBR")) if k in kinds]
        names += [f"|error| {n}" for k, n in (("volume", "volume"), ("ibr", "IBR"))
                  if k in kinds]
        cap = "; ".join(f"{k}: " + ", ".join(f"{m} {_fmt(x)}" for m, x in v.metrics.items())
                        for k, v in kinds.items() if v.metrics)
        strips.append(_img(_png_b64(strip, width=min(len(tiles), 5) * 240),
                           f"view {vid}: {' | '.join(names)}" + (f"; {cap}" if cap else ""),
                           _colorbar(_ERROR_CMAP, 0.0, vmax, "mean absolute RGB error")))
    return ("<h2>Novel views: ground truth, volume rendering, IBR, error</h2>"
            + "".join(strips))


def _gt_distance_summary(point_errors, units: str | None) -> str:
    if point_errors is None or not len(point_errors[1]):
        return ""
    d = point_errors[1]
    q = np.percentile(d, [50, 90, 99])
    return (f"<p>Distance of the reconstructed points to the ground truth ({_units(units)}): "
            f"median {q[0]:.3g}, 90th percentile {q[1]:.3g}, 99th {q[2]:.3g} (over "
            f"{len(d):,} points; the layer 'points: distance to ground truth' shows them "
            "coloured).</p>")


_CSS = """
body{font-family:sans-serif;margin:1.5em;max-width:1400px;color:#222}
h1{font-size:1.4em}h2{font-size:1.15em;border-bottom:1px solid #ccc;margin-top:1.6em}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #bbb;padding:3px 8px;
font-size:.9em;text-align:right}td:first-child,th:first-child{text-align:left}
td.why{text-align:left;color:#555;font-size:.82em}
.grid,.row{display:flex;flex-wrap:wrap;gap:8px;margin-bottom:8px}figure{margin:0}
figcaption{font-size:.8em;color:#555;max-width:1200px}img{max-width:100%}
.view3d{width:100%;border:1px solid #ddd}
.row figure img{width:300px;height:auto}th.why{text-align:left}
.cbar{width:300px;font-size:.75em;color:#444;margin-top:2px}.grad{height:10px}
.ticks{display:flex;justify-content:space-between}.cbl{text-align:center}
.key{display:flex;align-items:center;gap:10px;font-size:.85em}.key figure img{width:56px}
.key figcaption{display:none}pre{background:#f6f6f6;padding:.6em;font-size:.8em;overflow:auto}
"""


def write_report(out_dir: str | Path, metrics: dict, views: list[ViewImages] | None = None,
                 inputs: list[tuple[int, Tensor]] | None = None,
                 points: tuple[np.ndarray, np.ndarray | None] | None = None,
                 mesh: tuple | None = None, title: str = "svolsdf run",
                 notes: list[str] | None = None, *, cameras=None,
                 gt_points: np.ndarray | None = None, gt_depth: dict | None = None,
                 units: str | None = None, config_text: str | None = None,
                 orbit_frames: int = 8, viewer=None) -> Path:
    """Write ``out_dir/report.html``.

    Args:
        out_dir: the run folder; ``depth/<id>.npy`` (else ``depth/*.png``) and ``normals/*.png``
            under it are shown.
        metrics: the ``metrics.json`` content (`svolsdf.evaluate.scoring`).
        views: evaluated novel views (render, ground truth, mask, per-view metrics).
        inputs: (view id, (3, H, W) image in [0, 1]) of the input views.
        points: (N, 3) points and optional (N, 3) uint8 colours of the fused cloud.
        mesh: (V, 3) vertices, (F, 3) faces and optionally (V, 3) uint8 vertex colours.
        title: the page title.
        notes: extra lines shown under the title (e.g. what was not computable and why).
        cameras: `svolsdf.scene.Cameras` of ``inputs`` (same order, world units): frusta in the
            3D view, pictures of the mesh from the inputs and from an orbit.
        gt_points: (M, 3) ground-truth points: the points' distances to them are shown.
        gt_depth: view id -> (H, W) ground-truth z-depth (0 = none): per-view depth error maps.
        units: world units ("mm", ...).
        config_text: the run's config.yaml, shown verbatim.
        orbit_frames: pictures of the mesh along the orbit (0: none).
        viewer: `svolsdf.evaluate.viewer.ViewerConfig` (display budget of the 3D view).

    Returns:
        the written path.
    """
    from svolsdf.evaluate.viewer import (
        ViewerConfig,
        cluster_decimate,
        figure_div,
        plotly_js,
        scene_figure,
    )

    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    notes = list(notes or [])
    if points is not None and not len(points[0]):
        points = None
    if mesh is not None and not len(mesh[1]):
        mesh = None
    point_errors = None
    if gt_points is not None and points is not None and len(gt_points):
        point_errors = _point_errors(points[0], gt_points, metrics, viewer)
    cams3d = None
    if cameras is not None and inputs:
        import torch

        c = cameras.to(dtype=torch.float64)
        cams3d = [(vid, c.K[k].numpy(), c.w2c[k].numpy(), c.width, c.height)
                  for k, (vid, _) in enumerate(inputs)]
    view_notes = []
    if mesh is not None:  # one decimated mesh for the 3D view and the pictures
        nf = len(mesh[1])
        mesh = cluster_decimate(mesh[0], mesh[1], (viewer or ViewerConfig()).max_faces,
                                mesh[2] if len(mesh) > 2 else None)
        if len(mesh[1]) < nf:
            view_notes.append(f"Mesh decimated for display from {nf:,} to {len(mesh[1]):,} "
                              "faces (vertex clustering); mesh.ply is unchanged.")
    fig, more = scene_figure(points, mesh, cams3d, point_errors, _units(units), viewer)
    view_notes += more
    t_fig = time.perf_counter()
    view = ""
    if fig["data"]:
        view = ("<h2>3D view</h2><p>Drag to rotate, scroll to zoom, right-drag to pan; click a "
                "legend entry to show or hide that layer.</p>" + figure_div(fig)
                + "".join(f"<p class='note'>{html.escape(n)}</p>" for n in view_notes)
                + _gt_distance_summary(point_errors, units))
    inputs_html = _inputs_section(inputs, cameras, mesh)
    parts = [f"<h1>{html.escape(title)}</h1>"]
    parts += [f"<p>{html.escape(n)}</p>" for n in notes]
    parts.append(view)
    parts.append("<h2>Metrics</h2>" + _metrics_table(metrics, units))
    parts.append(_per_view_table(views or []))
    parts.append(inputs_html)
    parts.append(_depth_section(out_dir, [vid for vid, _ in inputs or []]
                                or _depth_ids(out_dir), gt_depth, units))
    parts.append(_normals_section(out_dir))
    parts.append(_orbit_section(mesh, cameras, orbit_frames))
    parts.append(_novel_section(views or []))
    if config_text:
        parts.append(f"<h2>Run configuration</h2><pre>{html.escape(config_text)}</pre>")
    parts.append("<h2>Timing (seconds)</h2>" + _timing_table(metrics.get("timing")))
    t_pics = time.perf_counter()
    script = ""
    if view:
        script = f"<script>{plotly_js()}</script>"
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}"
            f"</title><style>{_CSS}</style>{script}</head><body>{''.join(parts)}</body></html>")
    path = RunFolder(out_dir).report_file

    atomic_write(path, lambda tmp: tmp.write_text(page, encoding="utf-8"))
    log.info("report: 3D view %.1f s, pictures %.1f s, total %.1f s (%.1f MB)",
             t_fig - t0, t_pics - t_fig, time.perf_counter() - t0, len(page) / 1e6)
    return path


def _depth_ids(out_dir: Path) -> list[int]:
    d = RunFolder(out_dir).depth_dir
    return sorted(int(p.stem) for p in d.glob("*.npy") if p.stem.isdigit()) if d.is_dir() else []


def _point_errors(points: np.ndarray, gt: np.ndarray, metrics: dict, viewer
                  ) -> tuple[np.ndarray, np.ndarray, float]:
    """A subset of the points with their distance to the nearest ground-truth point, and the
    colour-scale maximum (the evaluation's cut-off when it had one, else the 95th percentile)."""
    from scipy.spatial import cKDTree

    from svolsdf.evaluate.viewer import ViewerConfig, subsample

    cfg = viewer or ViewerConfig()
    p = points[subsample(len(points), cfg.max_error_points, seed=1)]
    # an unbalanced tree: ~5x faster queries from points far off the ground truth (a table)
    tree = cKDTree(np.asarray(gt, np.float64), balanced_tree=False, compact_nodes=False)
    d, _ = tree.query(p, workers=-1)
    cut = ((metrics.get("settings") or {}).get("synthetic") or {}).get("max_dist")
    vmax = float(cut) if cut else float(np.percentile(d, 95))
    return p, d.astype(np.float32), max(vmax, 1e-12)
