"""Similarity (Umeyama) fit: exact recovery, no reflections, residual errors, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from svolsdf.calibrate.align import centre_errors, similarity_fit


def test_recovers_a_known_similarity():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(20, 3))
    R = Rotation.from_euler("xyz", [30, -50, 110], degrees=True).as_matrix()
    y = 2.5 * x @ R.T + [1.0, -2.0, 3.0]
    sim = similarity_fit(x, y)
    assert np.isclose(sim.scale, 2.5) and np.allclose(sim.R, R) and np.allclose(sim.t, [1, -2, 3])
    assert np.allclose(sim.apply(x), y)


def test_a_mirrored_set_gets_a_rotation_not_a_reflection():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(10, 3))
    sim = similarity_fit(x, x * [1, 1, -1])
    assert np.isclose(np.linalg.det(sim.R), 1.0)


def test_centre_errors_are_the_residuals_in_the_true_frame():
    x = np.random.default_rng(2).uniform(0, 1, size=(50, 3))
    y = 10 * x
    y[3, 2] += 0.4  # one centre off by 0.4 along z; the fit spreads little of it to the others
    err, sim, size = centre_errors(x, y)
    assert np.isclose(size, np.linalg.norm(y.max(0) - y.min(0)))
    assert err.argmax() == 3 and 0.3 < err.max() < 0.4 and np.median(err) < 0.02
    assert np.isclose(sim.scale, 10, rtol=1e-2)


def test_bad_input():
    with pytest.raises(ValueError, match="at least 3"):
        similarity_fit(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        similarity_fit(np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="coincide"):
        similarity_fit(np.ones((4, 3)), np.zeros((4, 3)))
