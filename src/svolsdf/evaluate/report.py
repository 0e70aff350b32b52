"""The run's HTML report: one self-contained page that opens offline.

Every picture is a PNG embedded as base64 (no external files, scripts, fonts or URLs). Plots are
made with matplotlib on the Agg backend. The page shows the inputs, depth and normal maps, renders
beside ground truth with error maps, point-cloud and mesh previews, the metrics table and timing.
"""

from __future__ import annotations

import base64
import html
import io
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from torch import Tensor

__all__ = ["ViewImages", "write_report"]

log = logging.getLogger(__name__)

_THUMB = 360  # width in pixels of embedded thumbnails
_MAX_POINTS = 20_000
_MAX_FACES = 6_000


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


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _fig_b64(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80, bbox_inches="tight")
    _plt().close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _array_b64(a: np.ndarray, width: int = _THUMB) -> str:
    """(H, W, 3|4) uint8 or (H, W) -> base64 PNG thumbnail of at most ``width`` pixels across."""
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
            return _array_b64(np.asarray(im.convert("RGB")))
    except Exception as e:  # a broken preview must not break the report
        log.warning("report: cannot read %s (%s)", path, e)
        return None


def _tensor_u8(x: Tensor) -> np.ndarray:
    return (x.detach().float().clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255 + 0.5).astype(
        np.uint8)


def _img(b64: str, caption: str) -> str:
    return (f'<figure><img src="data:image/png;base64,{b64}" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


def _fmt(v) -> str:
    if v is None:
        return "&ndash;"
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        return f"{v:.4g}" if abs(v) < 1e4 else f"{v:.0f}"
    return html.escape(str(v))


def _metrics_table(metrics: dict) -> str:
    rows = []
    ch = metrics.get("chamfer") or {}
    for k in ("accuracy", "completeness", "overall"):
        rows.append((f"Chamfer {k} (points)", ch.get(k)))
    chm = metrics.get("chamfer_mesh") or {}
    for k in ("accuracy", "completeness", "overall"):
        if chm.get(k) is not None:
            rows.append((f"Chamfer {k} (mesh)", chm.get(k)))
    thr = metrics.get("fscore_threshold")
    rows.append((f"F-score (threshold {_fmt(thr)})" if thr else "F-score", metrics.get("fscore")))
    for group, label in (("images", "volume rendering"), ("images_ibr", "IBR")):
        g = metrics.get(group) or {}
        for k in ("psnr", "ssim", "lpips"):
            m = g.get(k)
            if m is not None or group == "images":
                rows.append((f"{k.upper()} mean ({label})", (m or {}).get("mean")))
    body = "".join(f"<tr><td>{html.escape(a)}</td><td>{_fmt(b)}</td></tr>" for a, b in rows)
    return (f'<table id="metrics"><thead><tr><th>metric</th><th>value</th></tr></thead>'
            f"<tbody>{body}</tbody></table>")


def _per_view_table(views: list[ViewImages]) -> str:
    if not views:
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


def _view_figure(v: ViewImages) -> str:
    """Render | ground truth | per-pixel error (mean absolute over RGB, matplotlib's inferno map,
    scaled to [0, max(0.05, largest error)]; black outside the mask). Composed as one image
    strip rather than a matplotlib figure: it is ~100x faster and keeps full resolution."""
    from matplotlib import colormaps

    pred = v.pred.detach().float().clamp(0, 1).cpu()
    gt = v.gt.detach().float().clamp(0, 1).cpu()
    err = (pred - gt).abs().mean(0).numpy()
    inside = np.ones_like(err, dtype=bool)
    if v.mask is not None:
        inside = v.mask.reshape(err.shape).cpu().numpy() > 0.5
    vmax = max(0.05, float(err[inside].max()) if inside.any() else 0.0)
    heat = (colormaps["inferno"](np.clip(err / vmax, 0, 1))[..., :3] * 255).astype(np.uint8)
    heat[~inside] = 0
    gap = np.full((err.shape[0], 4, 3), 255, np.uint8)
    strip = np.concatenate([_tensor_u8(pred), gap, _tensor_u8(gt), gap, heat], axis=1)
    cap = ", ".join(f"{k} {_fmt(val)}" for k, val in v.metrics.items())
    b64 = _array_b64(strip, width=3 * _THUMB)
    return _img(b64, f"view {v.view_id} ({v.kind}): render | ground truth | |error| "
                     f"(0..{vmax:.3g}); {cap}")


def _subsample(n: int, k: int, seed: int = 0) -> np.ndarray:
    if n <= k:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, k, replace=False))


def _points_figure(points: np.ndarray, colors: np.ndarray | None, title: str) -> str:
    plt = _plt()
    idx = _subsample(len(points), _MAX_POINTS)
    p = points[idx]
    c = None if colors is None else colors[idx].astype(np.float32) / 255.0
    fig = plt.figure(figsize=(10, 3.4))
    for k, (elev, azim) in enumerate(((-70, -90), (0, -90), (-20, -30))):
        ax = fig.add_subplot(1, 3, k + 1, projection="3d")
        ax.scatter(p[:, 0], p[:, 1], p[:, 2], s=0.3, c=c if c is not None else p[:, 2],
                   cmap=None if c is not None else "viridis", linewidths=0)
        ax.view_init(elev=elev, azim=azim)
        _equal_axes(ax, p)
        ax.set_axis_off()
    fig.suptitle(f"{title}: {len(points):,} points ({len(idx):,} shown)", fontsize=9)
    return _img(_fig_b64(fig), title)


def _mesh_figure(vertices: np.ndarray, faces: np.ndarray, title: str) -> str:
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    plt = _plt()
    idx = _subsample(len(faces), _MAX_FACES)
    tri = vertices[faces[idx]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
    shade = 0.35 + 0.65 * np.abs(n @ np.array([0.3, -0.5, -0.8]) / np.linalg.norm([0.3, .5, .8]))
    fig = plt.figure(figsize=(10, 3.4))
    for k, (elev, azim) in enumerate(((-70, -90), (0, -90), (-20, -30))):
        ax = fig.add_subplot(1, 3, k + 1, projection="3d")
        col = Poly3DCollection(tri, facecolors=np.c_[np.repeat(shade[:, None], 3, 1),
                                                     np.ones(len(tri))], linewidths=0)
        ax.add_collection3d(col)
        ax.view_init(elev=elev, azim=azim)
        _equal_axes(ax, tri.reshape(-1, 3))
        ax.set_axis_off()
    fig.suptitle(f"{title}: {len(vertices):,} vertices, {len(faces):,} faces "
                 f"({len(idx):,} shown)", fontsize=9)
    return _img(_fig_b64(fig), title)


def _equal_axes(ax, p: np.ndarray) -> None:
    if len(p) == 0:
        return
    lo, hi = p.min(0), p.max(0)
    c, r = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-9)
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)


def _folder_images(folder: Path, title: str) -> str:
    files = sorted(p for p in folder.glob("*.png")) if folder.is_dir() else []
    if not files:
        return ""
    figs = [_img(b, p.stem) for p in files if (b := _file_b64(p)) is not None]
    return f"<h2>{html.escape(title)}</h2><div class='grid'>{''.join(figs)}</div>"


_CSS = """
body{font-family:sans-serif;margin:1.5em;max-width:1200px;color:#222}
h1{font-size:1.4em}h2{font-size:1.15em;border-bottom:1px solid #ccc;margin-top:1.6em}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #bbb;padding:3px 8px;
font-size:.9em;text-align:right}td:first-child,th:first-child{text-align:left}
.grid{display:flex;flex-wrap:wrap;gap:8px}figure{margin:0}figcaption{font-size:.8em;color:#555}
img{max-width:100%}
"""


def write_report(out_dir: str | Path, metrics: dict, views: list[ViewImages] | None = None,
                 inputs: list[tuple[int, Tensor]] | None = None,
                 points: tuple[np.ndarray, np.ndarray | None] | None = None,
                 mesh: tuple[np.ndarray, np.ndarray] | None = None,
                 title: str = "svolsdf run", notes: list[str] | None = None) -> Path:
    """Write ``out_dir/report.html``.

    Args:
        out_dir: the run folder; ``depth/*.png`` and ``normals/*.png`` under it are embedded.
        metrics: the ``metrics.json`` content (`svolsdf.evaluate.run`).
        views: evaluated views (render, ground truth, mask, per-view metrics).
        inputs: (view id, (3, H, W) image in [0, 1]) of the input views.
        points: (N, 3) points and optional (N, 3) uint8 colours of the fused cloud.
        mesh: (V, 3) vertices and (F, 3) faces.
        title: the page title.
        notes: extra lines shown under the title (e.g. what was not computable and why).

    Returns:
        the written path.
    """
    out_dir = Path(out_dir)
    parts = [f"<h1>{html.escape(title)}</h1>"]
    parts += [f"<p>{html.escape(n)}</p>" for n in (notes or [])]
    parts.append("<h2>Metrics</h2>" + _metrics_table(metrics))
    parts.append(_per_view_table(views or []))
    parts.append("<h2>Timing (seconds)</h2>" + _timing_table(metrics.get("timing")))
    if inputs:
        figs = "".join(_img(_array_b64(_tensor_u8(im)), f"input view {vid}")
                       for vid, im in inputs)
        parts.append(f"<h2>Inputs</h2><div class='grid'>{figs}</div>")
    parts.append(_folder_images(out_dir / "depth", "Depth maps"))
    parts.append(_folder_images(out_dir / "normals", "Normal maps"))
    if views:
        parts.append("<h2>Novel views: render, ground truth, error</h2>"
                     + "".join(_view_figure(v) for v in views))
    if points is not None and len(points[0]):
        parts.append("<h2>Point cloud</h2>" + _points_figure(points[0], points[1], "points.ply"))
    if mesh is not None and len(mesh[1]):
        parts.append("<h2>Mesh</h2>" + _mesh_figure(mesh[0], mesh[1], "mesh.ply"))
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}"
            f"</title><style>{_CSS}</style></head><body>{''.join(parts)}</body></html>")
    path = out_dir / "report.html"
    tmp = path.with_suffix(".html.tmp")
    tmp.write_text(page, encoding="utf-8")
    tmp.replace(path)
    return path
