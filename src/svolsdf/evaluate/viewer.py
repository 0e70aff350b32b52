"""The report's interactive 3D view: mesh, points and cameras as one plotly figure.

plotly is the choice because its wheel ships plotly.js, so the page can embed the library once and
open offline, and its WebGL traces (``mesh3d``, ``scatter3d``) rotate, zoom and toggle (legend
clicks) without a server. The figure is built as a plain dict (no per-element validation of
hundreds of thousands of values) with coordinates as base64 typed arrays (plotly.js >= 2.28), so a
200k-point cloud costs ~0.1 s to serialize rather than seconds of float formatting.

Display budget: the cloud is subsampled to ``max_points`` (random, seeded) and a mesh above
``max_faces`` is decimated by vertex clustering; the files on disk are never changed.
"""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass

import numpy as np

__all__ = ["ViewerConfig", "cluster_decimate", "frustum_lines", "scene_figure", "figure_div",
           "plotly_js", "subsample"]


@dataclass
class ViewerConfig:
    """Display budget and look of the 3D view."""

    max_points: int = 200_000
    """Points of points.ply shown (a random subset beyond that)."""
    max_error_points: int = 100_000
    """Points shown coloured by their distance to the ground truth."""
    max_faces: int = 300_000
    """Mesh faces shown (vertex-clustering decimation beyond that)."""
    point_size: float = 1.5
    """Marker size of the points, in pixels."""
    height: int = 640
    """Height of the view in pixels."""


def subsample(n: int, k: int, seed: int = 0) -> np.ndarray:
    """Sorted indices of at most ``k`` of ``n`` items (all of them when n <= k)."""
    if n <= k:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, k, replace=False))


def cluster_decimate(vertices: np.ndarray, faces: np.ndarray, max_faces: int,
                     colors: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Decimate a mesh to at most ~``max_faces`` faces by vertex clustering.

    Vertices are merged per cell of a cubic grid (their mean position and colour); faces whose
    corners fall in fewer than three cells vanish, duplicates are dropped. The cell size starts
    from sqrt(F / max_faces) times the mean edge length and grows until the budget holds.

    Args:
        vertices: (V, 3) float; faces: (F, 3) int; colors: (V, 3) uint8 or None.
        max_faces: the face budget.

    Returns:
        (V', 3) vertices, (F', 3) faces, (V', 3) colours or None.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if len(f) <= max_faces:
        return v, f, colors
    edge = float(np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1).mean())
    cell = max(edge, 1e-12) * np.sqrt(len(f) / max_faces)
    lo = v.min(0)
    for _ in range(12):
        ijk = np.floor((v - lo) / cell).astype(np.int64)
        dims = ijk.max(0) + 1
        key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]  # one int64 per cell
        _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
        inv = inv.ravel()
        nf = inv[f]
        ok = (nf[:, 0] != nf[:, 1]) & (nf[:, 1] != nf[:, 2]) & (nf[:, 0] != nf[:, 2])
        nf = nf[ok]
        s = np.sort(nf, axis=1)
        n = np.int64(len(counts))
        _, first = np.unique((s[:, 0] * n + s[:, 1]) * n + s[:, 2], return_index=True)
        nf = nf[np.sort(first)]  # one copy of each face, its original winding
        if len(nf) <= max_faces:
            break
        cell *= 1.25
    nv = np.stack([np.bincount(inv, weights=v[:, k]) for k in range(3)], 1) / counts[:, None]
    nc = None
    if colors is not None:
        c = np.asarray(colors, np.float64)
        nc = (np.stack([np.bincount(inv, weights=c[:, k]) for k in range(3)], 1)
              / counts[:, None] + 0.5).astype(np.uint8)
    return nv, nf, nc


def frustum_lines(K: np.ndarray, w2c: np.ndarray, width: int, height: int, depth: float
                  ) -> np.ndarray:
    """(16, 3) polyline of a camera frustum, NaN-separated: centre to the four image corners at
    z-depth ``depth`` and the corner loop (world units)."""
    corners = np.array([[0, 0], [width - 1, 0], [width - 1, height - 1], [0, height - 1]], float)
    cam = np.c_[corners, np.ones(4)] @ np.linalg.inv(K).T * depth
    R, t = w2c[:3, :3], w2c[:3, 3]
    world = (cam - t) @ R
    c = -R.T @ t
    nan = np.full(3, np.nan)
    seq = [c, world[0], nan, c, world[1], nan, c, world[2], nan, c, world[3], nan,
           world[0], world[1], world[2], world[3]]
    return np.vstack(seq + [world[0]])


def _typed(a: np.ndarray, dtype: str = "f4") -> dict:
    """A numpy array as plotly.js's base64 typed-array spec."""
    a = np.ascontiguousarray(a, dtype=np.dtype(dtype))
    return {"dtype": dtype, "bdata": base64.b64encode(a.tobytes()).decode("ascii")}


_HEX = np.array([f"{i:02x}" for i in range(256)])


def _hex_colors(rgb: np.ndarray) -> list[str]:
    """(N, 3) uint8 -> ['#rrggbb', ...]."""
    rgb = np.asarray(rgb, np.uint8)
    s = np.char.add(np.char.add(np.char.add("#", _HEX[rgb[:, 0]]), _HEX[rgb[:, 1]]),
                    _HEX[rgb[:, 2]])
    return s.tolist()


def _xyz(p: np.ndarray, origin: np.ndarray) -> dict:
    # float32 after centring keeps sub-micrometre precision for scenes of metres
    q = (np.asarray(p, np.float64) - origin).astype(np.float32)
    return {"x": _typed(q[:, 0]), "y": _typed(q[:, 1]), "z": _typed(q[:, 2])}


def scene_figure(points: tuple[np.ndarray, np.ndarray | None] | None = None,
                 mesh: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None,
                 cameras: list[tuple[int, np.ndarray, np.ndarray, int, int]] | None = None,
                 point_errors: tuple[np.ndarray, np.ndarray, float] | None = None,
                 units: str = "", cfg: ViewerConfig | None = None,
                 gt_errors: tuple[np.ndarray, np.ndarray, float] | None = None
                 ) -> tuple[dict, list[str]]:
    """The 3D view as a plotly figure dict.

    Coordinates are shown relative to the centre of what is drawn (``layout.meta.origin`` holds
    it in world units); axes are equal.

    Args:
        points: (N, 3) world points and optional (N, 3) uint8 colours.
        mesh: (V, 3) vertices, (F, 3) faces, optional (V, 3) uint8 vertex colours.
        cameras: (view id, K (3, 3), w2c (4, 4), width, height) of the input views.
        point_errors: (M, 3) points, (M,) distances to the ground truth and the colour-scale
            maximum, for a layer of points coloured by distance (their accuracy).
        gt_errors: the same of ground-truth points and their distance to the reconstruction
            (its completeness): a layer beside the accuracy one, on the same colour scale.
        units: world units, for the colour bar's title.
        cfg: `ViewerConfig`.

    Returns:
        (figure dict, lines saying what was subsampled or decimated).
    """
    cfg = cfg or ViewerConfig()
    _check_inputs(points, mesh, point_errors)
    _check_inputs(None, None, gt_errors)
    notes: list[str] = []
    parts = [a for a in (points[0] if points else None, mesh[0] if mesh else None,
                         point_errors[0] if point_errors else None) if a is not None and len(a)]
    if parts:
        allp = np.concatenate([p[subsample(len(p), 20_000)] for p in parts])
        origin = (allp.min(0) + allp.max(0)) / 2
        extent = float(np.linalg.norm(allp.max(0) - allp.min(0)))
    else:
        origin, extent = np.zeros(3), 1.0
    data: list[dict] = []
    if mesh is not None and len(mesh[1]):
        v, f, c = mesh[0], mesh[1], mesh[2] if len(mesh) > 2 else None
        nf = len(f)
        v, f, c = cluster_decimate(v, f, cfg.max_faces, c)
        if len(f) < nf:
            notes.append(f"3D view: mesh decimated from {nf:,} to {len(f):,} faces.")
        tr = {"type": "mesh3d", "name": f"mesh ({nf:,} faces)", "showlegend": True,
              **_xyz(v, origin), "i": _typed(f[:, 0], "i4"), "j": _typed(f[:, 1], "i4"),
              "k": _typed(f[:, 2], "i4"), "flatshading": False, "hoverinfo": "skip",
              "lighting": {"ambient": 0.45, "diffuse": 0.7, "specular": 0.05, "roughness": 0.9},
              "lightposition": {"x": 1e5, "y": 1e5, "z": 1e5}}
        if c is not None:
            tr["vertexcolor"] = _hex_colors(c)
        else:
            tr["color"] = "#c8c8c8"
        data.append(tr)
    if points is not None and len(points[0]):
        p, c = points
        idx = subsample(len(p), cfg.max_points)
        if len(idx) < len(p):
            notes.append(f"3D view: {len(idx):,} of {len(p):,} points shown (random subset).")
        marker = {"size": cfg.point_size}
        marker["color"] = _hex_colors(c[idx]) if c is not None else "#3070b0"
        data.append({"type": "scatter3d", "mode": "markers", "name": f"points ({len(p):,})",
                     **_xyz(p[idx], origin), "marker": marker, "hoverinfo": "skip",
                     "visible": True if mesh is None else "legendonly"})
    if point_errors is not None and len(point_errors[0]):
        p, d, vmax = point_errors
        idx = subsample(len(p), cfg.max_error_points, seed=1)
        data.append({"type": "scatter3d", "mode": "markers",
                     "name": "points: distance to ground truth", **_xyz(p[idx], origin),
                     "visible": "legendonly", "hoverinfo": "skip",
                     "marker": {"size": cfg.point_size, "color": _typed(d[idx]),
                                "colorscale": "Viridis", "cmin": 0.0, "cmax": float(vmax),
                                "colorbar": {"title": {"text": f"distance ({units})" if units
                                                       else "distance"}, "len": 0.6}}})
    if gt_errors is not None and len(gt_errors[0]):
        p, d, vmax = gt_errors
        idx = subsample(len(p), cfg.max_error_points, seed=2)
        data.append({"type": "scatter3d", "mode": "markers",
                     "name": "ground truth: distance to the points (completeness)",
                     **_xyz(p[idx], origin), "visible": "legendonly", "hoverinfo": "skip",
                     "marker": {"size": cfg.point_size, "color": _typed(d[idx]),
                                "colorscale": "Viridis", "cmin": 0.0, "cmax": float(vmax),
                                "showscale": point_errors is None,
                                "colorbar": {"title": {"text": f"distance ({units})" if units
                                                       else "distance"}, "len": 0.6}}})
    frusta = []
    for vid, K, w2c, w, h in cameras or []:
        ln = frustum_lines(np.asarray(K, float), np.asarray(w2c, float), w, h, 0.15 * extent)
        ln = ln - origin
        frusta.append(ln)
        data.append({"type": "scatter3d", "mode": "lines+text", "name": f"camera {vid}",
                     "legendgroup": "cameras",
                     "x": np.where(np.isnan(ln[:, 0]), None, ln[:, 0]).tolist(),
                     "y": np.where(np.isnan(ln[:, 1]), None, ln[:, 1]).tolist(),
                     "z": np.where(np.isnan(ln[:, 2]), None, ln[:, 2]).tolist(),
                     "text": [str(vid)] + [""] * (len(ln) - 1), "textposition": "top center",
                     "line": {"color": "#d04020", "width": 3}, "hoverinfo": "name"})
    axis = {"showbackground": False, "title": {"text": ""}, "showspikes": False,
            "gridcolor": "#eeeeee"}
    up, eye = {"x": 0, "y": 0, "z": 1}, {"x": 1.25, "y": 1.25, "z": 1.25}  # plotly's default
    center = {"x": 0, "y": 0, "z": 0}
    if cameras and parts:
        # start where the first input camera stands, looking at the object, its "up" up.
        # plotly's camera lives in the data box scaled by its largest side, centred at 0
        drawn = np.concatenate([allp - origin] + frusta)
        drawn = drawn[np.isfinite(drawn).all(1)]
        lo, hi = drawn.min(0), drawn.max(0)
        mid, size = (lo + hi) / 2, max(float((hi - lo).max()), 1e-12)
        w2c = np.asarray(cameras[0][2], float)
        eye_w = -w2c[:3, :3].T @ w2c[:3, 3] - origin
        c, u = -mid / size, -w2c[1, :3]
        e = c + 0.75 * ((eye_w - mid) / size - c)  # a little nearer than the camera
        eye = {"x": float(e[0]), "y": float(e[1]), "z": float(e[2])}
        center = {"x": float(c[0]), "y": float(c[1]), "z": float(c[2])}
        up = {"x": float(u[0]), "y": float(u[1]), "z": float(u[2])}
    layout = {"height": cfg.height, "margin": {"l": 0, "r": 0, "t": 10, "b": 0},
              "legend": {"itemclick": "toggle", "y": 0.9,
                         "title": {"text": "click to show / hide"}},
              "scene": {"aspectmode": "data", "xaxis": axis, "yaxis": axis, "zaxis": axis,
                        "camera": {"up": up, "eye": eye, "center": center}},
              "meta": {"origin": [float(x) for x in origin]}, "uirevision": "keep"}
    return {"data": data, "layout": layout}, notes


def _check_inputs(points, mesh, point_errors) -> None:
    def rows(a, name, cols=3):
        a = np.asarray(a)
        if a.ndim != 2 or a.shape[1] != cols:
            raise ValueError(f"scene_figure: {name} must be (N, {cols}), got {a.shape}")
        return len(a)

    if points is not None:
        n = rows(points[0], "points")
        if points[1] is not None and rows(points[1], "point colours") != n:
            raise ValueError(f"scene_figure: {n} points but {len(points[1])} colours")
    if mesh is not None:
        n = rows(mesh[0], "mesh vertices")
        rows(mesh[1], "mesh faces")
        if len(mesh) > 2 and mesh[2] is not None and rows(mesh[2], "vertex colours") != n:
            raise ValueError(f"scene_figure: {n} vertices but {len(mesh[2])} vertex colours")
    if point_errors is not None and rows(point_errors[0], "error points") != len(
            point_errors[1]):
        raise ValueError(f"scene_figure: {len(point_errors[0])} error points but "
                         f"{len(point_errors[1])} distances")


def plotly_js() -> str:
    """The plotly.js bundle shipped in the plotly wheel (text of a <script>)."""
    from plotly.offline import get_plotlyjs

    return get_plotlyjs()


def figure_div(fig: dict, div_id: str = "view3d") -> str:
    """HTML of a div plus the script that draws ``fig`` into it (plotly.js loaded separately)."""
    spec = json.dumps(fig, separators=(",", ":"), allow_nan=False)
    spec = spec.replace("</", "<\\/")  # never close the <script> early
    config = json.dumps({"responsive": True, "displaylogo": False, "scrollZoom": True})
    return (f'<div id="{div_id}" class="view3d"></div>'
            f"<script>(function(){{var f={spec};"
            f"Plotly.newPlot('{div_id}',f.data,f.layout,{config});}})();</script>")
