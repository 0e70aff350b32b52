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

import html
import logging
import time
from pathlib import Path

import numpy as np
from torch import Tensor

from svolsdf.evaluate.report_parts import ViewImages, fmt, units_label
from svolsdf.evaluate.report_pictures import (
    depth_section,
    gt_distance_summary,
    inputs_section,
    normals_section,
    novel_section,
    orbit_section,
)
from svolsdf.evaluate.report_run import (
    config_section,
    loss_curves_section,
    run_section,
    stage_time_section,
)
from svolsdf.evaluate.run_outputs import protocol_label
from svolsdf.io.runfolder import RunFolder, atomic_write

__all__ = ["ViewImages", "METRIC_INFO", "write_report"]

log = logging.getLogger(__name__)

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



# --------------------------------------------------------------------------- tables
def _blendedmvs_rows(b: dict | None, u: str) -> list[tuple]:
    """The BlendedMVS protocol's rows beside the unmasked Chamfer (`chamfer`): the masked
    score, the VolSDF run's and the relative improvement over it."""
    if not b:
        return []
    rows = []
    masked = b["masked"]
    proto = f"; protocol: {protocol_label('blendedmvs-masked')}"
    for k in ("accuracy", "completeness", "overall"):
        rows.append((f"Chamfer {k} (points, masked)", masked.get(k), u,
                     METRIC_INFO[k] + proto if masked.get("overall") is not None else
                     str(masked.get("missing"))))
    v = b.get("volsdf")
    if v:
        for key in ("unmasked", "masked"):
            rows.append((f"VolSDF Chamfer overall ({key})", v[key].get("overall"), u,
                         f"the VolSDF run {v['run']} scored the same way"))
        for key, x in (b.get("relative_improvement") or {}).items():
            rows.append((f"relative improvement over VolSDF ({key})", x, "ratio",
                         "(VolSDF - run) / VolSDF of the overall Chamfer, the paper's "
                         "BlendedMVS number (positive: better than VolSDF)"))
    return rows


def _metrics_table(metrics: dict, units: str | None) -> str:
    u = units_label(units)
    rows = []
    msrc = metrics.get("mesh_source")
    mesh_label = f"mesh: {msrc}" if msrc else "mesh"
    for key, src in (("chamfer", "points"), ("chamfer_mesh", mesh_label)):
        blk = metrics.get(key) or {}
        if key == "chamfer_mesh" and blk.get("overall") is None:
            continue
        proto = f"; protocol: {protocol_label(blk.get('protocol'))}" if blk.get(
            "overall") is not None else ""
        for k in ("accuracy", "completeness", "overall"):
            rows.append((f"Chamfer {k} ({src})", blk.get(k), u, METRIC_INFO[k] + proto))
    rows += _blendedmvs_rows(metrics.get("blendedmvs"), u)
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
    at = f" at {fmt(thr)} {u}" if thr else ""
    rows.append((f"F-score{at}", metrics.get("fscore"), "0..1", METRIC_INFO["fscore"]))
    for k in ("precision", "recall"):
        if metrics.get(k) is not None:
            rows.append((f"{k.capitalize()}{at}", metrics.get(k), "0..1", METRIC_INFO[k]))
    unit = {"psnr": "dB", "ssim": "0..1", "lpips": "0..1"}
    region = (metrics.get("settings") or {}).get("image_region") or "region not recorded"
    for group, label in (("images", "novel views, volume rendering"),
                         ("images_ibr", "novel views, IBR"),
                         ("images_input_views", "input views, volume rendering"),
                         ("images_ibr_input_views", "input views, IBR")):
        g = metrics.get(group) or {}
        for k in ("psnr", "ssim", "lpips"):
            m = (g.get(k) or {}).get("mean")
            if m is not None or group == "images":
                why = METRIC_INFO[k] + f"; {region}"
                if group.endswith("_input_views"):
                    why += ("; views the run trained on, rendered back: not a novel-view "
                            "score")
                rows.append((f"{k.upper()} mean ({label})", m, unit[k], why))
    body = "".join(f"<tr><td>{html.escape(a)}</td><td>{fmt(b)}</td><td>{html.escape(c)}</td>"
                   f"<td class='why'>{html.escape(d)}</td></tr>" for a, b, c, d in rows)
    return (f'<table id="metrics"><thead><tr><th>metric</th><th>value</th><th>unit</th>'
            f"<th class='why'>meaning</th></tr></thead><tbody>{body}</tbody></table>")


def _per_view_table(views: list[ViewImages]) -> str:
    if not views or not any(v.metrics for v in views):
        return ""
    keys = sorted({k for v in views for k in v.metrics})
    head = "".join(f"<th>{html.escape(k)}</th>" for k in keys)
    role = {"novel": "novel (held out)", "input": "input view (trained on)"}
    body = "".join(
        f"<tr><td>{v.view_id}</td><td>{html.escape(role.get(v.role, v.role))}</td>"
        f"<td>{html.escape(v.kind)}</td>"
        + "".join(f"<td>{fmt(v.metrics.get(k))}</td>" for k in keys) + "</tr>" for v in views)
    return (f'<table id="per-view"><thead><tr><th>view</th><th>role</th><th>renderer</th>'
            f"{head}</tr></thead><tbody>{body}</tbody></table>")


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
    body = "".join(f"<tr><td>{html.escape(k)}</td><td>{fmt(v)}</td></tr>" for k, v in flat)
    return f'<table id="timing"><tbody>{body}</tbody></table>'


_CSS = """
body{font-family:sans-serif;margin:1.5em;max-width:1400px;color:#222}
h1{font-size:1.4em}h2{font-size:1.15em;border-bottom:1px solid #ccc;margin-top:1.6em}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #bbb;padding:3px 8px;
font-size:.9em;text-align:right}td:first-child,th:first-child{text-align:left}
td.why{text-align:left;color:#555;font-size:.82em}
details summary{cursor:pointer;color:#335}.charts figure img{width:560px}
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
                 masks: dict | None = None, run_info: dict | None = None,
                 losses: dict | None = None,
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
        masks: view id -> (H, W) object mask of the inputs: depth errors count inside it.
        run_info: OUT/run.json (command, version, device, date).
        losses: optimization name -> rows of its losses.csv: the loss curves.
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
    point_errors = gt_errors = None
    if gt_points is not None and points is not None and len(gt_points):
        point_errors = _point_errors(points[0], gt_points, metrics, viewer)
        # the ground truth by its distance to the points (completeness), on the same scale
        gt_errors = _point_errors(gt_points, points[0], metrics, viewer)
        gt_errors = (gt_errors[0], gt_errors[1], point_errors[2])
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
    fig, more = scene_figure(points, mesh, cams3d, point_errors, units_label(units), viewer,
                             gt_errors=gt_errors)
    view_notes += more
    t_fig = time.perf_counter()
    view = ""
    if fig["data"]:
        view = ("<h2>3D view</h2><p>Drag to rotate, scroll to zoom, right-drag to pan; click a "
                "legend entry to show or hide that layer.</p>" + figure_div(fig)
                + "".join(f"<p class='note'>{html.escape(n)}</p>" for n in view_notes)
                + gt_distance_summary(point_errors, units))
    inputs_html = inputs_section(inputs, cameras, mesh)
    parts = [f"<h1>{html.escape(title)}</h1>"]
    parts += [f"<p>{html.escape(n)}</p>" for n in notes]
    parts.append(view)
    parts.append("<h2>Metrics</h2>" + _metrics_table(metrics, units))
    parts.append(_per_view_table(views or []))
    parts.append(run_section(run_info, config_text))
    parts.append(loss_curves_section(losses or {}))
    parts.append(stage_time_section(metrics.get("timing")))
    parts.append(inputs_html)
    parts.append(depth_section(out_dir, [vid for vid, _ in inputs or []]
                               or _depth_ids(out_dir), gt_depth, units, masks))
    parts.append(normals_section(out_dir))
    parts.append(orbit_section(mesh, cameras, orbit_frames))
    parts.append(novel_section(views or []))
    parts.append(config_section(config_text))
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
