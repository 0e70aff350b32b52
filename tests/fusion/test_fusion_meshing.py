"""Tests of svolsdf.fusion.meshing: filling a mesh's small holes from a second surface."""

from __future__ import annotations

import numpy as np
import torch

from svolsdf.fusion.meshing import fill_small_holes


def _grid(x0, x1, y0, y1, z, step=0.1):
    """A flat triangulated grid at height ``z``: (V, 3) float32 vertices, (F, 3) faces."""
    xs = np.arange(x0, x1 + step / 2, step)
    ys = np.arange(y0, y1 + step / 2, step)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    v = np.stack([gx, gy, np.full_like(gx, z)], -1).reshape(-1, 3)
    ny = len(ys)
    i, j = np.meshgrid(np.arange(len(xs) - 1), np.arange(ny - 1), indexing="ij")
    a = (i * ny + j).ravel()
    f = np.concatenate([np.stack([a, a + ny, a + 1], 1), np.stack([a + 1, a + ny, a + ny + 1], 1)])
    return torch.from_numpy(v).float(), torch.from_numpy(f).long()


def _centroids(v, f):
    return v[f].mean(1).numpy()


def _small_hole(c):
    return np.hypot(c[:, 0] - 1.0, c[:, 1] - 1.0) < 0.3


def _big_hole(c):
    return (c[:, 0] > 2.5) & (c[:, 0] < 3.8) & (c[:, 1] > 0.3) & (c[:, 1] < 1.7)


def _plane_with_holes():
    """A 4 x 2 plane with a small hole (0.6 across) and a large one (1.3 x 1.4)."""
    v, f = _grid(0, 4, 0, 2, 0.0)
    c = _centroids(v, f)
    keep = ~(_small_hole(c) | _big_hole(c))
    return v, f[torch.from_numpy(keep)]


def test_fill_small_holes_fills_the_small_hole_only():
    v, f = _plane_with_holes()
    pv, pf = _grid(0, 4, 0, 2, 0.0)  # the whole plane: a surface over both holes
    iv, if_ = _grid(1.0, 1.3, 0.2, 0.5, 2.0)  # and an island away from the mesh
    pv, pf = torch.cat([pv, iv]), torch.cat([pf, if_ + len(pv)])
    cols = torch.full((len(v), 3), 7, dtype=torch.uint8)
    pcols = torch.full((len(pv), 3), 200, dtype=torch.uint8)
    v2, f2, c2, added = fill_small_holes(v, f, cols, pv, pf, pcols, gap=0.15, max_size=1.0)
    assert added > 0 and len(f2) == len(f) + added and len(c2) == len(v2)
    new = _centroids(v2, f2[len(f):])
    assert _small_hole(new).all()  # every added face lies in the small hole
    assert not _big_hole(new).any() and (np.abs(new[:, 2]) < 1e-6).all()  # no island
    assert (c2[len(v):] == 200).all() and (c2[:len(v)] == 7).all()
    assert torch.equal(f2[:len(f)], f) and torch.equal(v2[:len(v)], v)  # the mesh unchanged


def test_fill_small_holes_with_a_larger_size_also_fills_the_large_hole():
    v, f = _plane_with_holes()
    pv, pf = _grid(0, 4, 0, 2, 0.0)
    v2, f2, c2, added = fill_small_holes(v, f, None, pv, pf, None, gap=0.15, max_size=3.0)
    new = _centroids(v2, f2[len(f):])
    assert added > 0 and c2 is None
    assert _big_hole(new).any() and _small_hole(new).any()


def test_fill_small_holes_without_size_or_holes_returns_the_mesh():
    v, f = _plane_with_holes()
    pv, pf = _grid(0, 4, 0, 2, 0.0)
    v2, f2, c2, added = fill_small_holes(v, f, None, pv, pf, None, gap=0.15, max_size=0.0)
    assert added == 0 and v2 is v and f2 is f and c2 is None
    full_v, full_f = _grid(0, 4, 0, 2, 0.0)
    _, f3, _, added = fill_small_holes(full_v, full_f, None, pv, pf, None, gap=0.15,
                                       max_size=1.0)
    assert added == 0 and len(f3) == len(full_f)
