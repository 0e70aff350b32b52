"""The BlendedMVS protocol of the paper (docs/method.md 8.2): nine scans, three input views and
12 test views each, Chamfer reported as the relative improvement over VolSDF, with the ground
plane removed, masked and unmasked.

What is known is in ``data/blendedmvs_protocol.json`` with its source (the released code's view
lists, which are the paper supplementary's, its scan hashes and the scale that brings each scan
to DTU's millimetres): `protocol`.

- Ground plane: the largest plane of the ground truth (RANSAC, `fit_ground_plane`), oriented
  towards the cameras; the points at or below it, within ``margin``, are removed from both
  clouds (`above_plane`). The released code compares against a ground truth cropped offline;
  svolsdf removes the plane itself, from the ground truth the user gives.
- Masked: both clouds keep only the points inside the object mask of every view that has one
  and sees the point in its frame (`inside_masks`): the evaluation masks of BlendedMVS cover the
  input and test views only (a partial mask folder: `svolsdf.scene.formats.mvsnet`).
- Chamfer: accuracy and completeness as DTU's rule (distances beyond ``max_dist`` left out), in
  the units of the clouds given (`blendedmvs_chamfer`; divide by the scan's relative scale for
  DTU-like millimetres), and `relative_improvement` over a VolSDF run's.
"""

from __future__ import annotations

import json
from functools import cache
from importlib import resources

import numpy as np

from svolsdf.errors import InputError
from svolsdf.evaluate.points import nn_distances

__all__ = ["above_plane", "blendedmvs_chamfer", "fit_ground_plane", "inside_masks", "protocol",
           "protocol_scans", "relative_improvement"]


@cache
def _data() -> dict:
    return json.loads(resources.files("svolsdf.evaluate").joinpath(
        "data/blendedmvs_protocol.json").read_text())


def protocol_scans() -> list[int]:
    """The scan numbers the protocol lists (1-9)."""
    return [int(k) for k in _data()["scans"]]


def protocol(scan: int) -> dict:
    """``{"hash", "inputs", "test", "relative_scale"}`` of BlendedMVS scan ``scan`` (1-9)."""
    scans = _data()["scans"]
    if str(scan) not in scans:
        raise InputError(f"BlendedMVS scan {scan}: the protocol has scans {', '.join(scans)}")
    return dict(scans[str(scan)])


def fit_ground_plane(points: np.ndarray, up_hint: np.ndarray, threshold: float,
                     iterations: int = 500, seed: int = 0) -> tuple[np.ndarray, float]:
    """The largest plane of ``points`` by RANSAC, refined by least squares on its inliers.

    Args:
        points: (N, 3) the ground truth.
        up_hint: (3,) a point on the side the plane faces (the cameras' mean centre).
        threshold: inlier distance (world units).

    Returns:
        (n, d): unit normal (3,) towards ``up_hint`` and offset, the plane n . x + d = 0.
    """
    p = np.asarray(points, np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 3:
        raise InputError(f"ground plane: points must be (N >= 3, 3), got {p.shape}")
    rng = np.random.default_rng(seed)
    best, best_n = None, -1
    for _ in range(iterations):
        a, b, c = p[rng.choice(len(p), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-12:
            continue
        n /= norm
        count = int((np.abs((p - a) @ n) < threshold).sum())
        if count > best_n:
            best, best_n = (n, -float(n @ a)), count
    if best is None:
        raise InputError("ground plane: the points are collinear")
    n, d = best
    inl = p[np.abs(p @ n + d) < threshold]
    centre = inl.mean(0)
    n = np.linalg.svd(inl - centre, full_matrices=False)[2][-1]  # least squares on the inliers
    d = -float(n @ centre)
    if float(n @ np.asarray(up_hint, np.float64)) + d < 0:
        n, d = -n, -d
    return n, d


def above_plane(points: np.ndarray, plane: tuple[np.ndarray, float], margin: float
                ) -> np.ndarray:
    """(N,) bool: the points more than ``margin`` above ``plane`` (on its normal's side)."""
    n, d = plane
    return np.asarray(points, np.float64) @ n + d > margin


def inside_masks(points: np.ndarray, K: np.ndarray, w2c: np.ndarray, masks: list[np.ndarray]
                 ) -> np.ndarray:
    """(N,) bool: the points inside the object mask of every view that sees them in its frame
    (and in front of it); a point no masked view sees is kept.

    Args:
        K: (V, 3, 3), w2c: (V, 4, 4) the masked views' cameras at the masks' size.
        masks: V (H, W) bool masks.
    """
    p = np.asarray(points, np.float64)
    keep = np.ones(len(p), bool)
    for k, m in enumerate(masks):
        cam = p @ w2c[k][:3, :3].T + w2c[k][:3, 3]
        z = cam[:, 2]
        uv = cam @ K[k].T
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = uv[:, 0] / z, uv[:, 1] / z
        H, W = m.shape
        ui, vi = np.round(u), np.round(v)
        seen = (z > 0) & (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
        inside = np.zeros(len(p), bool)
        inside[seen] = m[vi[seen].astype(int), ui[seen].astype(int)]
        keep &= ~seen | inside
    return keep


def blendedmvs_chamfer(pred: np.ndarray, gt: np.ndarray, plane: tuple[np.ndarray, float],
                       margin: float, max_dist: float, masked: dict | None = None) -> dict:
    """Chamfer of the protocol, unmasked and (with ``masked``) masked.

    Args:
        pred, gt: (N, 3), (M, 3) points in world units.
        plane: the ground plane (`fit_ground_plane`), removed from both with ``margin``.
        max_dist: distances beyond it are left out of the means (DTU's rule).
        masked: ``{"K", "w2c", "masks"}`` of the views with evaluation masks (`inside_masks`).

    Returns:
        ``{"unmasked": {"accuracy", "completeness", "overall", "n_pred", "n_gt"}, "masked": ...
        or None}``.
    """
    pred = np.asarray(pred, np.float64)
    gt = np.asarray(gt, np.float64)
    pred, gt = pred[above_plane(pred, plane, margin)], gt[above_plane(gt, plane, margin)]

    def score(a: np.ndarray, b: np.ndarray, where: str = "above the ground plane") -> dict:
        if not len(a) or not len(b):
            raise InputError(f"BlendedMVS Chamfer: {len(a)} predicted and {len(b)} ground-"
                             f"truth points {where}")
        d_ab, d_ba = nn_distances(a, b), nn_distances(b, a)
        acc = float(d_ab[d_ab < max_dist].mean()) if (d_ab < max_dist).any() else float("nan")
        comp = float(d_ba[d_ba < max_dist].mean()) if (d_ba < max_dist).any() else float("nan")
        return {"accuracy": acc, "completeness": comp, "overall": (acc + comp) / 2,
                "n_pred": int(len(a)), "n_gt": int(len(b))}

    out = {"unmasked": score(pred, gt), "masked": None}
    if masked is not None:
        args = (masked["K"], masked["w2c"], masked["masks"])
        out["masked"] = score(pred[inside_masks(pred, *args)], gt[inside_masks(gt, *args)],
                              "above the ground plane and inside the evaluation masks")
    return out


def relative_improvement(method: float, volsdf: float) -> float:
    """(VolSDF - method) / VolSDF: the paper's BlendedMVS number (positive: better)."""
    if not volsdf > 0:
        raise InputError(f"relative improvement: VolSDF's Chamfer must be > 0, got {volsdf}")
    return (volsdf - method) / volsdf
