"""Geometry evaluation on synthetic scenes (``svolsdf synth``): Chamfer against the part of the
ground-truth surface that the input views observe.

DTU evaluates only where its scanner observed the object (the ObsMask, docs/method.md 8.1). A
synthetic scene's ``gt_points.ply`` samples the whole object, including its back, which three
frontal views never see; scoring completeness against it would measure the camera layout, not the
method. The analogue of the ObsMask here: a ground-truth point counts when at least one input view
sees it, i.e. it projects inside the image and its depth agrees with that view's ``gt_depth`` map
within a few pixel footprints. Accuracy and completeness are two-way nearest-neighbour means with a
cut-off, in world units (millimetres for generated scenes). By default a distance beyond the
cut-off counts as the cut-off (clipped), so holes are paid for; ``rule="exclude"`` leaves such
distances out of the means as the DTU and BlendedMVS evaluations do (docs/method.md 8.1, 8.2).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from svolsdf.errors import InputError

__all__ = ["observed_gt_points", "synthetic_chamfer", "truncated_chamfer", "is_synthetic_scene"]


def is_synthetic_scene(scene_dir: str | Path) -> bool:
    """Whether ``scene_dir`` has the ground truth that `svolsdf synth` writes."""
    d = Path(scene_dir)
    return (d / "gt_points.ply").is_file() and (d / "gt_depth").is_dir()


def observed_gt_points(scene_dir: str | Path, views: list[int], tol_px: float = 3.0,
                       tol_rel: float = 0.002) -> np.ndarray:
    """Ground-truth surface points seen by at least one of ``views``.

    Args:
        scene_dir: a synthetic scene folder (gt_points.ply, gt_depth/<NNN>.npy, cameras).
        views: input view ids.
        tol_px: depth tolerance in pixel footprints (z / fx per pixel).
        tol_rel: additional relative depth tolerance.

    Returns:
        (N, 3) float64 world points.
    """
    from svolsdf.io.ply import read_ply
    from svolsdf.scene.loaders import load_scene

    d = Path(scene_dir)
    if not is_synthetic_scene(d):
        raise InputError(f"{d}: not a synthetic scene (needs gt_points.ply and gt_depth/)")
    from svolsdf.evaluate.points import checked_ground_truth

    pts = checked_ground_truth(read_ply(d / "gt_points.ply")["points"], d / "gt_points.ply")
    scene = load_scene(d, views=views, load_images=False)
    cams = scene.cameras.to(dtype=torch.float64)
    uv, z = cams.project(torch.from_numpy(pts))  # (V, N, 2), (V, N)
    seen = torch.zeros(len(pts), dtype=torch.bool)
    for i, v in enumerate(views):
        f = d / "gt_depth" / f"{v:03d}.npy"
        if not f.is_file():
            raise InputError(f"{f}: ground-truth depth of view {v} is missing")
        dm = torch.from_numpy(np.load(f)).to(torch.float64)
        if dm.shape != (cams.height, cams.width):
            raise InputError(f"{f}: depth map is {tuple(dm.shape)}, cameras are "
                             f"{cams.height}x{cams.width}")
        u = torch.round(uv[i, :, 0]).long()
        w = torch.round(uv[i, :, 1]).long()
        inside = (u >= 0) & (u < cams.width) & (w >= 0) & (w < cams.height) & (z[i] > 0)
        dd = torch.zeros_like(z[i])
        dd[inside] = dm[w[inside], u[inside]]
        tol = tol_px * z[i] / float(cams.K[i, 0, 0]) + tol_rel * z[i]
        seen |= inside & (dd > 0) & ((z[i] - dd).abs() < tol)
    return pts[seen.numpy()]


def _table_height(scene_dir: str | Path) -> float | None:
    """World z of the synthetic table top (scene.json), or None."""
    import json

    f = Path(scene_dir) / "scene.json"
    if not f.is_file():
        return None
    t = json.loads(f.read_text()).get("table")
    try:
        plane = t["plane_world"]
        if abs(float(plane["normal"][2])) > 0.999:  # horizontal table (svolsdf synth)
            return float(plane["point"][2])
    except (KeyError, TypeError, IndexError):
        pass
    return None


def synthetic_chamfer(points: np.ndarray, scene_dir: str | Path, views: list[int],
                      max_dist: float | None = None, threshold: float | None = None,
                      on_empty: str = "raise", rule: str = "clip",
                      faces: np.ndarray | None = None) -> dict:
    """Chamfer and F-score of ``points`` against the observed ground truth (docs/method.md 8.2).

    A mesh (``faces`` given) is scored by its surface, never by its vertices:
    `svolsdf.evaluate.chamfer.mesh_surface_points` at `svolsdf.evaluate.chamfer.mesh_density`
    of the observed ground truth's diagonal (0.1 % of it: with the default ``threshold``, the
    radius at which the points are evened out too).

    Args:
        points: (N, 3) reconstructed world points, or with ``faces`` a mesh's (V, 3) vertices.
        scene_dir: the synthetic scene.
        views: the input view ids (they define the observed part).
        max_dist: distances are clipped at it, and predictions farther than it outside the
            ground truth's bounding box are not scored (default 5% of the GT's bounding-box
            diagonal, the role of DTU's 20 mm cut-off on a ~400 mm object).
        threshold: F-score threshold (default 0.5% of the diagonal).
        rule: how distances beyond ``max_dist`` enter the means: "clip" (default; each counts
            as max_dist, so a hole in the reconstruction costs what a far outlier does) or
            "exclude" (docs/method.md 8.1 / 8.2, the DTU and BlendedMVS evaluations: distances at or
            above max_dist are left out of the means, so holes wider than max_dist cost
            nothing). The F-score is the same under both.
        on_empty: when no prediction lies near the object: "raise" an `InputError`, or "clip":
            every distance is then beyond the cut-off, so accuracy = completeness = overall =
            max_dist, F-score 0 and ``pred_points`` 0 (a method that missed the object still
            gets a number in a comparison table).
        faces: (F, 3) int triangles of a mesh whose vertices ``points`` are, or None.

    Returns:
        dict: accuracy, completeness, overall (by ``rule``), overall_dtu_rule (always the
        "exclude" rule's overall, from the same pass), precision, recall, fscore, threshold,
        max_dist, gt_points (count), pred_points, and ``sampled`` ("points", or "surface" for a
        mesh) with ``density`` (the mesh's sample spacing; None for points).
    """
    if rule not in ("clip", "exclude"):
        raise ValueError(f"rule must be 'clip' or 'exclude', got {rule!r}")
    if on_empty not in ("raise", "clip"):
        raise ValueError(f"on_empty must be 'raise' or 'clip', got {on_empty!r}")
    gt = observed_gt_points(scene_dir, views)
    if len(gt) == 0:
        raise InputError(f"{scene_dir}: no ground-truth point is visible in views {views}")
    diag = float(np.linalg.norm(gt.max(0) - gt.min(0)))
    max_dist = 0.05 * diag if max_dist is None else max_dist
    threshold = 0.005 * diag if threshold is None else threshold
    pred = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    # the ObsMask's bounding box (docs/method.md 8.1): only predictions near the object are scored
    lo, hi = gt.min(0) - max_dist, gt.max(0) + max_dist
    table = _table_height(scene_dir)
    # the table is not part of the object (DTU's plane plays this role): points within the
    # F-score threshold of its plane are left out on both sides
    z_min = -np.inf if table is None else table + threshold
    gt = gt[gt[:, 2] > z_min]
    sampled = {"sampled": "points", "density": None}
    if faces is not None:
        from svolsdf.evaluate.chamfer import mesh_density, mesh_surface_points

        density = mesh_density(diag)
        sampled = {"sampled": "surface", "density": density}
        faces = _faces_reaching_box(pred, faces, np.r_[lo[:2], max(lo[2], z_min)], hi)
        pred = mesh_surface_points(pred, faces, density) if len(faces) else np.zeros((0, 3))
    pred = pred[((pred >= lo) & (pred <= hi)).all(1) & (pred[:, 2] > z_min)]
    if len(pred) == 0:
        if on_empty == "clip":
            return {"accuracy": max_dist, "completeness": max_dist, "overall": max_dist,
                    "overall_dtu_rule": max_dist, "precision": 0.0, "recall": 0.0,
                    "fscore": 0.0, "threshold": threshold, "max_dist": max_dist,
                    "gt_points": int(len(gt)), "pred_points": 0, **sampled}
        raise InputError("no reconstructed point lies near the ground-truth object")
    t = truncated_chamfer(pred, gt, max_dist, threshold)
    sfx = "" if rule == "clip" else "_dtu_rule"
    acc, comp = t["accuracy" + sfx], t["completeness" + sfx]
    return {"accuracy": acc, "completeness": comp, "overall": (acc + comp) / 2,
            "overall_dtu_rule": (t["accuracy_dtu_rule"] + t["completeness_dtu_rule"]) / 2,
            "precision": t["precision"], "recall": t["recall"], "fscore": t["fscore"],
            "threshold": threshold, "max_dist": max_dist, "gt_points": t["gt_points"],
            "pred_points": t["pred_points"], **sampled}


def _faces_reaching_box(vertices: np.ndarray, faces: np.ndarray, lo: np.ndarray,
                        hi: np.ndarray) -> np.ndarray:
    """The (F', 3) rows of (F, 3) ``faces`` that may reach the box [lo, hi]: a triangle whose
    three vertices lie beyond one of its faces has no point in it (sampling the rest only saves
    time; a table's surface far from the object would cost millions of samples)."""
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise InputError(f"faces: expected an (F, 3) int array, got shape {faces.shape}")
    if len(faces) == 0:
        return faces
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InputError(f"faces index vertices 0..{len(vertices) - 1} but hold "
                         f"{faces.min()}..{faces.max()}")
    tri = vertices[faces]  # (F, 3, 3)
    out = ((tri < lo).all(1) | (tri > hi).all(1)).any(1)
    return faces[~out]


def truncated_chamfer(pred: np.ndarray, gt: np.ndarray, max_dist: float, threshold: float,
                      gt_downsampled: bool = False, seed: int = 0) -> dict:
    """The scoring core of `synthetic_chamfer`, by both rules at once (docs/method.md 8.1 / 8.2).

    Both clouds are shuffled (``seed``; ``pred`` first) and greedily downsampled at
    ``threshold / 5`` to even out densities, then: accuracy / completeness clipped at
    ``max_dist`` (rule "clip") and as means over the distances below it (rule "exclude", keys
    ``*_dtu_rule``; ``max_dist`` when none is), precision / recall / F-score at ``threshold``.

    Args:
        pred: (N, 3) float64 predicted points, N > 0 (already cropped to the scored region).
        gt: (M, 3) float64 ground-truth points, M > 0.
        max_dist: cut-off, world units.
        threshold: F-score threshold, world units.
        gt_downsampled: ``gt`` is already downsampled at ``threshold / 5`` (a caller scoring
            many predictions against one reference does it once).
        seed: shuffle seed.

    Returns:
        dict: accuracy, completeness, accuracy_dtu_rule, completeness_dtu_rule, precision,
        recall, fscore, gt_points, pred_points (after downsampling).
    """
    from svolsdf.evaluate.chamfer import _mean_below, greedy_radius_downsample, nn_distances

    rng = np.random.default_rng(seed)
    r = threshold / 5  # even out densities (docs/method.md 8.1's radius downsampling)
    pred = pred[rng.permutation(len(pred))]
    pred = pred[greedy_radius_downsample(pred, r)]
    if not gt_downsampled:
        gt = gt[greedy_radius_downsample(gt[rng.permutation(len(gt))], r)]
    d_pg, d_gp = nn_distances(pred, gt), nn_distances(gt, pred)
    prec, rec = float((d_pg < threshold).mean()), float((d_gp < threshold).mean())

    return {"accuracy": float(np.minimum(d_pg, max_dist).mean()),
            "completeness": float(np.minimum(d_gp, max_dist).mean()),
            "accuracy_dtu_rule": _mean_below(d_pg, max_dist, default=max_dist),
            "completeness_dtu_rule": _mean_below(d_gp, max_dist, default=max_dist),
            "precision": prec, "recall": rec,
            "fscore": 2 * prec * rec / (prec + rec) if prec + rec > 0 else 0.0,
            "gt_points": int(len(gt)), "pred_points": int(len(pred))}
