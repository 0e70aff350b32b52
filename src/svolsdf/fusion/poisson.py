"""A mesh from the fused points: oriented normals and screened Poisson surface reconstruction.

``mesh.method`` = "poisson". The fused points (docs/method.md 6.3) are placed by the
finer MVS stages and are more accurate than the optimized field's zero level; the screened
Poisson surface (Kazhdan and Hoppe 2013) interpolates them, and trimming by the octree's sample
density removes what the points do not support. The surface reconstruction itself is COLMAP's
PoissonRecon through pycolmap (a well-kept implementation, no code of ours); what is written here
is what it needs and does not do: normals with a consistent outward sign.

Points are (N, 3) float64 numpy arrays in world units; meshes are (vertices (V, 3), faces (F, 3)
int64, colours (V, 3) uint8) numpy arrays.
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from svolsdf.io.ply import read_ply, write_points_ply

__all__ = ["estimate_normals", "orient_normals", "poisson_surface"]

log = logging.getLogger(__name__)


def estimate_normals(points: np.ndarray, k: int = 16, workers: int = 1) -> np.ndarray:
    """Unoriented normals by principal component analysis of each point's neighbourhood.

    Args:
        points: (N, 3) float, N > k.
        k: neighbours (the point itself included).
        workers: threads of the neighbour query.

    Returns:
        (N, 3) float64 unit normals: the eigenvector of the smallest eigenvalue of the k-nearest
        neighbours' covariance; the sign is arbitrary (see `orient_normals`).
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points: expected (N, 3), got {pts.shape}")
    if len(pts) <= k:
        raise ValueError(f"points: {len(pts)} points, need more than k = {k} for normals")
    _, nn = cKDTree(pts).query(pts, k=k, workers=workers)
    out = np.empty_like(pts)
    for s in range(0, len(pts), 262144):  # bounded memory: (chunk, k, 3) neighbourhoods
        nb = pts[nn[s:s + 262144]]
        nb = nb - nb.mean(1, keepdims=True)
        _, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
        out[s:s + 262144] = vec[:, :, 0]
    return out


def orient_normals(points: np.ndarray, normals: np.ndarray, centres: np.ndarray,
                   guide: np.ndarray | None = None) -> np.ndarray:
    """Give each normal the sign that faces the cameras that saw its point.

    Every fused point is seen by input views, and a surface seen from a camera faces it, so
    when all camera centres lie on one side of a point's tangent plane the normal points to
    that side. Where the centres straddle the plane (grazing views: about 5 % of the points on
    synthetic scenes), ``guide`` decides (the field's SDF gradient, which points outwards), and
    without one the sum of the unit directions to the cameras.

    Args:
        points: (N, 3) world points.
        normals: (N, 3) unit normals, any sign.
        centres: (V, 3) camera centres of the input views.
        guide: (N, 3) or None, a direction that points outwards (need not be unit).

    Returns:
        (N, 3) float64 normals, each ``normals[i]`` or its negation.
    """
    pts = np.asarray(points, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    if n.shape != pts.shape:
        raise ValueError(f"normals: expected {pts.shape}, got {n.shape}")
    out = np.empty_like(n)
    for s in range(0, len(pts), 262144):
        p, m = pts[s:s + 262144], n[s:s + 262144]
        to_cam = c[None] - p[:, None]  # (n, V, 3)
        dots = np.einsum("nvk,nk->nv", to_cam, m)
        if guide is not None:
            fallback = np.einsum("nk,nk->n", np.asarray(guide[s:s + 262144], np.float64), m)
        else:
            unit = to_cam / np.linalg.norm(to_cam, axis=-1, keepdims=True).clip(min=1e-12)
            fallback = np.einsum("nk,nk->n", unit.sum(1), m)
        sign = np.where((dots > 0).all(1), 1.0,
                        np.where((dots < 0).all(1), -1.0, np.where(fallback < 0, -1.0, 1.0)))
        out[s:s + 262144] = m * sign[:, None]
    return out


def poisson_surface(points: np.ndarray, normals: np.ndarray, colors: np.ndarray | None = None,
                    depth: int = 10, trim: float = 5.0, threads: int = 1
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Screened Poisson surface of oriented points, trimmed by sample density.

    Args:
        points: (N, 3) float.
        normals: (N, 3) outward normals (`orient_normals`).
        colors: (N, 3) uint8 or None; the mesh's vertex colours are interpolated from them.
        depth: octree depth (the finest cell is the points' box / 2^depth).
        trim: remove the surface where the sample density (in octree levels) is below this;
            0 keeps the closed surface.
        threads: PoissonRecon's threads.

    Returns:
        vertices (V, 3) float64, faces (F, 3) int64, colours (V, 3) uint8 or None.

    Raises:
        ImportError: pycolmap is not installed.
    """
    import pycolmap  # the mesher; a dependency of svolsdf

    opts = pycolmap.PoissonMeshingOptions()
    opts.depth, opts.trim = int(depth), float(trim)
    opts.num_threads, opts.color = int(threads), colors is not None
    with tempfile.TemporaryDirectory(prefix="svolsdf-poisson-") as tmp:
        src, dst = Path(tmp) / "oriented.ply", Path(tmp) / "mesh.ply"
        write_points_ply(src, np.asarray(points, np.float32), colors,
                         normals=np.asarray(normals, np.float32))
        pycolmap.poisson_meshing(str(src), str(dst), opts)
        if not dst.is_file():
            raise RuntimeError("Poisson meshing wrote no mesh")
        m = read_ply(dst)
    faces = m.get("faces")
    if faces is None or len(faces) == 0:
        raise RuntimeError(f"Poisson meshing of {len(points)} points gave no faces "
                           f"(depth {depth}, trim {trim})")
    cols = m.get("colors") if colors is not None else None
    return (np.asarray(m["points"], np.float64), np.asarray(faces, np.int64),
            None if cols is None else np.asarray(cols, np.uint8))
