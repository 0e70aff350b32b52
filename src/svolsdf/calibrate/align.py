"""Similarity alignment of point sets (Umeyama 1991), to compare estimated cameras with known ones.

Structure from motion recovers cameras up to a similarity (scale, rotation, translation). To
score estimated camera centres against true ones, fit the similarity that maps the estimates onto
the truth in the least-squares sense (S. Umeyama, "Least-squares estimation of transformation
parameters between two point patterns", TPAMI 1991, eqs. 34-43) and measure what remains.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Similarity", "centre_errors", "similarity_fit"]


@dataclass
class Similarity:
    """x -> scale * R @ x + t."""

    scale: float
    """Isotropic scale factor."""
    R: np.ndarray
    """(3, 3) rotation, det +1."""
    t: np.ndarray
    """(3,) translation."""

    def apply(self, x: np.ndarray) -> np.ndarray:
        """(..., 3) points -> (..., 3) transformed points."""
        x = np.asarray(x, dtype=np.float64)
        return self.scale * x @ self.R.T + self.t


def similarity_fit(src: np.ndarray, dst: np.ndarray) -> Similarity:
    """Least-squares similarity mapping ``src`` onto ``dst`` (Umeyama 1991).

    Args:
        src: (N, 3) points, e.g. estimated camera centres.
        dst: (N, 3) corresponding points, e.g. the true centres; N >= 3, not all collinear.

    Returns:
        `Similarity` minimizing sum |dst - (s R src + t)|^2.

    Raises:
        ValueError: shapes differ, fewer than 3 points, or the points are degenerate.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[-1] != 3 or src.shape != dst.shape:
        raise ValueError(f"similarity_fit: src and dst must both be (N, 3), got {src.shape} and "
                         f"{dst.shape}")
    if len(src) < 3:
        raise ValueError(f"similarity_fit: need at least 3 point pairs, got {len(src)}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = (xs**2).sum() / len(src)
    if var_s < 1e-24:
        raise ValueError("similarity_fit: the source points all coincide")
    cov = xd.T @ xs / len(src)  # Umeyama eq. 38
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:  # a reflection otherwise (eq. 39)
        S[2, 2] = -1.0
    R = U @ S @ Vt  # eq. 40
    scale = float((D * np.diag(S)).sum() / var_s)  # eq. 42
    t = mu_d - scale * R @ mu_s  # eq. 41
    return Similarity(scale=scale, R=R, t=t)


def centre_errors(estimated: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, Similarity, float]:
    """Distances between true camera centres and similarity-aligned estimated ones.

    Args:
        estimated: (N, 3) estimated centres (any frame and scale).
        true: (N, 3) true centres.

    Returns:
        errors: (N,) distances in the true frame's units; the fitted `Similarity`; and the
        scene size used to make errors relative: the diagonal of the true centres' bounding box.
    """
    sim = similarity_fit(estimated, true)
    err = np.linalg.norm(sim.apply(estimated) - np.asarray(true, dtype=np.float64), axis=-1)
    true = np.asarray(true, dtype=np.float64)
    size = float(np.linalg.norm(true.max(0) - true.min(0)))
    return err, sim, size
