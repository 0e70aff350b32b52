"""Where a mesh's error sits: its surface split into extrapolated closure, outlier islands and
surface on the points, with a picture (issue 47).

For a finished run (its OUT/mesh.ply and OUT/points.ply) the mesh's surface is sampled as every
protocol samples it (`svolsdf.evaluate.chamfer.mesh_surface_points` at `mesh_density`, 0.1 % of
the reference's diagonal), each sample's distance to the reference is taken (clipped at 5 % of
the diagonal, as the protocols clip), and each sample is put in one class:

- "island": on a connected part of the mesh holding under 1 % of its area (outlier islands);
- "extrapolated": farther than the F-score threshold (0.5 % of the diagonal) from every fused
  point: surface the mesher made where no point is (closure over holes, past silhouettes);
- "on the points": the rest; its error is the points' own, or the mesher's smoothing of them.

The table gives each class's share of the surface and of the accuracy (the sum of the
distances), and its mean distance; the points' own accuracy is beside it. The picture shows the
samples from the first input view (and ``--view``), coloured by distance (top) and by class
(bottom).

The reference: a synthetic scene's observed ground truth without the table (as `svolsdf
evaluate` scores it), or a DTU scan's many-view pseudo ground truth (``--pgt DIR``, the cache of
benchmarks/dtu_pseudo_gt.py, as benchmarks/mesh_study.py reads it).

Usage:
    python benchmarks/mesh_error_map.py --run NAME=RUN [--pgt DIR] --png FILE.png
        [--results FILE.md]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

CLASSES = ("on the points", "extrapolated", "island")


def reference(run, pgt: Path | None) -> tuple[np.ndarray, float]:
    """(M, 3) reference points of the run's protocol (see the module docstring), and the height
    below which nothing is scored (a synthetic scene's table plane and the F-score threshold;
    -inf on DTU)."""
    from svolsdf.evaluate.synthetic import (
        _table_height,
        is_synthetic_scene,
        observed_gt_points,
    )

    scene_dir = Path(run.cfg.scene.path)
    if is_synthetic_scene(scene_dir):
        gt = observed_gt_points(scene_dir, run.views)
        diag = float(np.linalg.norm(gt.max(0) - gt.min(0)))
        table = _table_height(scene_dir)
        z_min = -np.inf if table is None else table + 0.005 * diag
        return gt[gt[:, 2] > z_min], z_min
    if pgt is None:
        sys.exit(f"{scene_dir}: not synthetic; give --pgt DIR")
    from mesh_study import _dtu_reference

    size = (run.load().width, run.load().height)
    ref, _ = _dtu_reference(run, pgt, size)
    return ref, -np.inf


def classify(vw: np.ndarray, faces: np.ndarray, points: np.ndarray, ref: np.ndarray,
             z_min: float = -np.inf) -> dict:
    """Samples of the mesh's surface with their distance to ``ref`` and their class (samples and
    points at or below ``z_min`` or outside the reference's box grown by the cut-off are not
    scored, as the protocols do)."""
    from scipy import sparse
    from scipy.sparse import csgraph
    from scipy.spatial import cKDTree

    from svolsdf.evaluate.chamfer import mesh_density, mesh_surface_points

    diag = float(np.linalg.norm(ref.max(0) - ref.min(0)))
    max_dist, thr = 0.05 * diag, 0.005 * diag
    lo, hi = ref.min(0) - max_dist, ref.max(0) + max_dist
    n = len(vw)
    rows = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    cols = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    adj = sparse.coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n, n))
    _, label = csgraph.connected_components(adj, directed=False)
    tri = vw[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    part_area = np.bincount(label[faces[:, 0]], weights=area, minlength=label.max() + 1)
    small = part_area < 0.01 * area.sum()
    samples = mesh_surface_points(vw, faces, mesh_density(diag))
    samples = samples[((samples >= lo) & (samples <= hi)).all(1) & (samples[:, 2] > z_min)]
    # a sample's part: that of its nearest vertex (the samples lie on the faces)
    _, nv = cKDTree(vw).query(samples, workers=2)
    island = small[label[nv]]
    d_ref = np.minimum(cKDTree(ref).query(samples, workers=2)[0], max_dist)
    d_pts = cKDTree(points).query(samples, distance_upper_bound=thr, workers=2)[0]
    cls = np.where(island, 2, np.where(np.isfinite(d_pts), 0, 1))
    p_in = points[((points >= lo) & (points <= hi)).all(1) & (points[:, 2] > z_min)]
    d_p = np.minimum(cKDTree(ref).query(p_in, workers=2)[0], max_dist)
    return {"samples": samples, "dist": d_ref, "cls": cls, "max_dist": max_dist,
            "threshold": thr, "points_accuracy": float(d_p.mean())}


def summary(c: dict) -> list[dict]:
    out = []
    total = c["dist"].sum()
    for i, name in enumerate(CLASSES):
        m = c["cls"] == i
        out.append({"class": name, "surface_share": float(m.mean()),
                    "accuracy_share": float(c["dist"][m].sum() / total) if total else 0.0,
                    "mean_distance": float(c["dist"][m].mean()) if m.any() else None})
    return out


def _view(ax, c: dict, cameras, i: int, by_class: bool):
    """The samples splatted into view ``i`` of ``cameras``, near ones drawn last."""
    idx = np.random.default_rng(0).permutation(len(c["samples"]))[:250_000]
    x = torch.from_numpy(c["samples"][idx])
    uv, z = cameras[i:i + 1].to(dtype=torch.float64).project(x)
    uv, z = uv[0].numpy(), z[0].numpy()
    order = np.argsort(-z)
    uv, d, k = uv[order], c["dist"][idx][order], c["cls"][idx][order]
    if by_class:
        colours = np.array([[0.6, 0.6, 0.6], [0.9, 0.2, 0.1], [0.1, 0.3, 0.9]])
        sc = ax.scatter(uv[:, 0], uv[:, 1], c=colours[k], s=0.2, rasterized=True, linewidths=0)
        for j, name in enumerate(CLASSES):
            ax.scatter([], [], color=colours[j], s=12, label=name)
        ax.legend(loc="lower right", fontsize=7, markerscale=1.5)
    else:
        sc = ax.scatter(uv[:, 0], uv[:, 1], c=d, s=0.2, cmap="inferno_r", vmin=0,
                        vmax=0.2 * c["max_dist"], rasterized=True, linewidths=0)
    ax.set_xlim(0, cameras.width)
    ax.set_ylim(cameras.height, 0)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    return sc


def picture(c: dict, cameras, names: list[str], path: Path, title: str) -> None:
    """Per camera of ``cameras`` (named ``names``): the samples coloured by distance (top) and
    by class (bottom)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(cameras)
    fig, ax = plt.subplots(2, n, figsize=(3.6 * n, 5.6), dpi=80, squeeze=False)
    for i in range(n):
        sc = _view(ax[0, i], c, cameras, i, by_class=False)
        _view(ax[1, i], c, cameras, i, by_class=True)
        ax[0, i].set_title(names[i], fontsize=8)
    fig.colorbar(sc, ax=list(ax[0]), fraction=0.03, label="distance to the reference")
    fig.suptitle(title, fontsize=9)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", required=True, metavar="NAME=DIR")
    ap.add_argument("--pgt", type=Path, default=None)
    ap.add_argument("--png", type=Path, required=True)
    ap.add_argument("--json", type=Path, default=None, help="the table as JSON")
    ap.add_argument("--view", type=int, default=None, help="also show the surface from this "
                    "view of the scene (e.g. a held-out view from another side)")
    args = ap.parse_args()
    from svolsdf.io.ply import read_ply
    from svolsdf.pipeline.loaded_run import Run

    name, _, d = args.run.rpartition("=")
    out = Path(d)
    run = Run.open(out, field=False)
    scene = run.load()  # sets run.views
    ref, z_min = reference(run, args.pgt)
    m = read_ply(out / "mesh.ply")
    pts = read_ply(out / "points.ply")["points"].astype(np.float64)
    c = classify(m["points"].astype(np.float64), m["faces"].astype(np.int64), pts, ref, z_min)
    rows = summary(c)
    acc = float(c["dist"].mean())
    print(f"{name}: mesh accuracy {acc:.3f}, points' {c['points_accuracy']:.3f} "
          f"(ratio {acc / c['points_accuracy']:.3f})")
    for r in rows:
        md = "-" if r["mean_distance"] is None else f"{r['mean_distance']:.3f}"
        print(f"  {r['class']}: {100 * r['surface_share']:.1f} % of the surface, "
              f"{100 * r['accuracy_share']:.1f} % of the accuracy sum, mean distance {md}")
    cams, names = scene.cameras[0:1], [f"input view {run.views[0]}"]
    if args.view is not None:  # a held-out view from another side
        from svolsdf.scene.loaders import load_scene

        cams = load_scene(run.cfg.scene.path, views=[run.views[0], args.view],
                          image_size=(scene.cameras.width, scene.cameras.height),
                          load_images=False).cameras
        names.append(f"view {args.view}")
    picture(c, cams, names, args.png, f"{name}: the mesh's surface; accuracy {acc:.2f} "
            f"(the points' {c['points_accuracy']:.2f})")
    if args.json:
        args.json.write_text(json.dumps({"run": name, "mesh_accuracy": acc,
                                         "points_accuracy": c["points_accuracy"],
                                         "classes": rows}, indent=1))


if __name__ == "__main__":
    main()
