"""Normals and the Poisson surface of `svolsdf.fusion.poisson` on a sampled sphere."""

import numpy as np
import pycolmap  # noqa: F401  (a core dependency: without it these tests fail)
import pytest

from svolsdf.fusion.poisson import estimate_normals, orient_normals, poisson_surface


def _sphere(n=20000, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 3))
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def test_normals_are_radial_and_face_the_cameras():
    pts = _sphere()
    n = estimate_normals(pts, k=12)
    assert np.abs(np.abs((n * pts).sum(1)) - 1).max() < 0.02  # radial up to sign
    # cameras on all sides, so that some camera sees each point: its sign comes from the
    # cameras or, where they straddle its tangent plane, from the guide
    cams = 4.0 * np.concatenate([np.eye(3), -np.eye(3)])
    o = orient_normals(pts, n, cams, guide=pts)
    assert ((o * pts).sum(1) > 0).all()
    # one camera: the points it sees (on its side) face it, without any guide
    front = pts[:, 2] > 0.3
    o1 = orient_normals(pts[front], n[front], cams[[2]])
    assert ((o1 * pts[front]).sum(1) > 0).all()
    # and a wrong guide cannot flip them: all of their cameras lie on one side
    o2 = orient_normals(pts[front], n[front], cams[[2]], guide=-pts[front])
    assert ((o2 * pts[front]).sum(1) > 0).all()


def test_orient_normals_checks_shapes():
    with pytest.raises(ValueError, match="normals"):
        orient_normals(np.zeros((5, 3)), np.zeros((4, 3)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="need more than"):
        estimate_normals(np.zeros((5, 3)), k=16)


def test_poisson_surface_of_a_sphere():
    pts = _sphere()
    cols = np.tile(np.array([[200, 40, 10]], np.uint8), (len(pts), 1))
    v, f, c = poisson_surface(pts, pts, cols, depth=7, trim=0)
    r = np.linalg.norm(v, axis=1)
    assert np.abs(r - 1).max() < 0.03, np.abs(r - 1).max()
    assert f.shape[1] == 3 and f.min() >= 0 and f.max() < len(v)
    assert c is not None and np.abs(c.astype(int) - [200, 40, 10]).max() <= 2
    # trimming by density removes the surface where there are no samples: a half sphere
    half = pts[:, 2] > 0
    v2, _, _ = poisson_surface(pts[half], pts[half], None, depth=7, trim=6)
    assert (v2[:, 2] > -0.2).mean() > 0.95
