"""Point-cloud building blocks of the Chamfer protocols (docs/method.md 8.1): nearest-neighbour
distances, the protocol's seeded row shuffle and the exact greedy radius downsampling.

Nearest neighbours come from `scipy.spatial.cKDTree` with ``workers=-1``; the greedy downsampling is
exact (the same kept set as the sequential loop of the DTUeval-python script) but runs as a
vectorized fixed-point iteration over all close pairs instead of a Python loop over points.
Trees are built on, and queries issued in, Morton (Z-curve) order, so that nearby points sit
nearby in memory (benchmarks/evaluate_dtu.py); distances and the kept set do not depend on the
order. The row shuffle is ``x[permutation]``, exactly ``Generator.shuffle(x, axis=0)``'s result
without its per-row Python-level swaps.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from svolsdf.errors import InputError

__all__ = ["checked_ground_truth", "greedy_radius_downsample", "nn_distances", "shuffle_rows"]

log = logging.getLogger(__name__)


def _check_points(name: str, points: np.ndarray) -> np.ndarray:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"{name}: expected an (N, 3) array of points, got shape {points.shape}")
    return points.astype(np.float64, copy=False)


def checked_ground_truth(points: np.ndarray, source: str | Path) -> np.ndarray:
    """Ground-truth points as read from ``source``, refused when no score could be computed
    from them: an empty set, or coordinates that are NaN or infinite (a threshold or a
    distance from them would be NaN, and the error would name neither the file nor why).

    Args:
        points: (N, 3) positions read from ``source``.
        source: the file (or its description) the message names.

    Returns:
        (N, 3) float64 points.

    Raises:
        InputError: naming ``source`` and the problem.
    """
    points = _check_points(str(source), points)
    if len(points) == 0:
        raise InputError(f"{source}: the ground truth has no points")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise InputError(f"{source}: {int(bad.sum())} of {len(points)} ground-truth points have "
                         f"NaN or infinite coordinates (first: row {int(np.argmax(bad))})")
    return points


def _kdtree(points: np.ndarray) -> cKDTree:
    # Unbalanced trees without compact nodes build several times faster on millions of points and
    # answer nearest-neighbour queries about as fast.
    return cKDTree(points, balanced_tree=False, compact_nodes=False)


#: Below this many points the Morton sort costs more than it saves.
_SORT_MIN = 20_000


def _spread_bits(v: np.ndarray) -> np.ndarray:
    """Insert two zero bits between the low 21 bits of each value (3D Morton code helper)."""
    v = v.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                        (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


def _morton_order(points: np.ndarray, bits: int = 10) -> np.ndarray:
    """(N,) permutation putting (N, 3) points in Z-curve order on a 2^bits grid over their
    0.1-99.9 percentile box (outliers are clamped to its border cells)."""
    lo = np.percentile(points, 0.1, axis=0)
    hi = np.percentile(points, 99.9, axis=0)
    cell = max(float((hi - lo).max()), 1e-12) / (2**bits - 1)
    g = np.clip(np.floor((points - lo) / cell), 0, 2**bits - 1).astype(np.int64)
    code = (_spread_bits(g[:, 0]) << np.uint64(2)) | (_spread_bits(g[:, 1]) << np.uint64(1)) \
        | _spread_bits(g[:, 2])
    return np.argsort(code, kind="stable")


def nn_distances(query: np.ndarray, ref: np.ndarray | cKDTree,
                 upper_bound: float | None = None) -> np.ndarray:
    """Distance from each query point to its nearest reference point.

    Args:
        query: (N, 3) float points.
        ref: (M, 3) float points, or a `cKDTree` built on them.
        upper_bound: if given, distances above it are returned as ``inf`` (faster search); use it
            when values above a cut-off are discarded anyway.

    Returns:
        (N,) float64 distances (``inf`` when M == 0 or above ``upper_bound``).
    """
    query = _check_points("query", query)
    if isinstance(ref, cKDTree):
        tree = ref
    else:
        ref = _check_points("ref", ref)
        if len(ref) >= _SORT_MIN:
            ref = ref[_morton_order(ref)]
        tree = _kdtree(ref)
    if len(query) == 0:
        return np.zeros(0)
    if tree.n == 0:
        return np.full(len(query), np.inf)
    ub = np.inf if upper_bound is None else float(upper_bound) * (1 + 1e-9) + 1e-12
    if len(query) < _SORT_MIN:
        d, _ = tree.query(query, k=1, distance_upper_bound=ub, workers=-1)
        return np.asarray(d, dtype=np.float64)
    order = _morton_order(query)
    d, _ = tree.query(query[order], k=1, distance_upper_bound=ub, workers=-1)
    out = np.empty(len(query), dtype=np.float64)
    out[order] = d
    return out


def shuffle_rows(points: np.ndarray, seed: int | None) -> np.ndarray:
    """The protocol's random shuffle (docs/method.md 8.1, step 1), as a new array.

    Equal to ``np.random.default_rng(seed).shuffle(x, axis=0)`` on a copy (the same Fisher-Yates
    swaps, applied to the row indices), but tens of times faster on millions of rows.

    Args:
        points: (N, ...) array.
        seed: generator seed (None: unseeded, as the reference script).

    Returns:
        (N, ...) the rows in shuffled order.
    """
    return points[np.random.default_rng(seed).permutation(len(points))]


def greedy_radius_downsample(points: np.ndarray, radius: float,
                             tree: cKDTree | None = None, chunk: int = 2_000_000) -> np.ndarray:
    """Greedy radius downsampling in the given point order (docs/method.md 8.1, step 2).

    Visits the points in order; a point that is still kept removes every other point within
    ``radius`` (distance <= radius). The kept set is exactly that of the sequential loop of the
    DTUeval-python script: the lexicographically first maximal independent set of the radius
    graph. It is computed from all close pairs at once (``cKDTree.query_pairs``) by a vectorized
    fixed-point iteration: a point is decided "kept" once all its earlier neighbours are removed
    and "removed" once one earlier neighbour is kept. Each round decides at least the earliest
    undecided point; for randomly ordered points the number of rounds grows like log N.

    Memory: the close pairs of a dense cloud are many (a 49-view fusion of ~10M points has
    hundreds of millions at the protocol's radius). Clouds longer than ``chunk`` are therefore
    visited ``chunk`` points at a time, in order: a point of a later chunk that lies within
    ``radius`` of a point kept in an earlier chunk is removed (a KD-tree query), and the rest of
    the chunk is decided among itself as above. A point's fate depends only on the earlier
    points that are kept, so the kept set is the same as in one pass; for a shuffled cloud each
    chunk holds (chunk / N)^2 of the pairs.

    Args:
        points: (N, 3) float points, already in visiting order (shuffle first for the protocol).
        radius: suppression radius (DTU: 0.2 mm).
        tree: optional `cKDTree` already built on ``points`` (then one pass, whatever N).
        chunk: points per pass (> 0).

    Returns:
        (N,) bool mask of the kept points.
    """
    points = _check_points("points", points)
    n = len(points)
    if chunk <= 0:
        raise ValueError(f"chunk must be > 0, got {chunk}")
    if tree is not None or n <= chunk:
        return _greedy_one_pass(points, radius, tree)
    keep = np.zeros(n, dtype=bool)
    for s in range(0, n, chunk):
        part = points[s:s + chunk]
        open_ = np.ones(len(part), dtype=bool)
        if keep[:s].any():  # suppressed by a point kept in an earlier chunk
            d = nn_distances(part, points[:s][keep[:s]], upper_bound=radius)
            open_ = d > radius
        idx = np.flatnonzero(open_)
        keep[s + idx] = _greedy_one_pass(part[idx], radius, None)
    return keep


def _greedy_one_pass(points: np.ndarray, radius: float, tree: cKDTree | None) -> np.ndarray:
    """`greedy_radius_downsample` over all close pairs of (N, 3) ``points`` at once."""
    n = len(points)
    if n == 0:
        return np.zeros(0, dtype=bool)
    if tree is not None:
        pairs = tree.query_pairs(r=radius, output_type="ndarray")  # (K, 2), i < j
    elif n >= _SORT_MIN:
        perm = _morton_order(points)
        pairs = perm[_kdtree(points[perm]).query_pairs(r=radius, output_type="ndarray")]
    else:
        pairs = _kdtree(points).query_pairs(r=radius, output_type="ndarray")
    # Only an earlier point can suppress a later one: edge later (row) <- earlier (col).
    row = pairs.max(axis=1)
    col = pairs.min(axis=1)
    del pairs
    state = np.zeros(n, dtype=np.int8)  # 0 undecided, 1 kept, 2 removed
    rounds = 0
    while True:
        und = state == 0
        if not und.any():
            break
        sc = state[col]
        has_kept = np.zeros(n, dtype=bool)
        has_kept[row[sc == 1]] = True
        has_open = np.zeros(n, dtype=bool)
        has_open[row[sc == 0]] = True
        state[und & has_kept] = 2
        state[und & ~has_kept & ~has_open] = 1
        live = state[row] == 0  # edges into decided points no longer matter
        row, col = row[live], col[live]
        rounds += 1
    log.debug("greedy downsampling: %d -> %d points in %d rounds", n, int((state == 1).sum()),
              rounds)
    return state == 1
