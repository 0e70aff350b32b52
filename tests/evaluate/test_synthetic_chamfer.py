"""`svolsdf.evaluate.synthetic.synthetic_chamfer`: a synthetic scene scores a point cloud against
the ground truth its views observe."""

from __future__ import annotations

import numpy as np
import pytest

from svolsdf.errors import InputError
from svolsdf.evaluate.synthetic import observed_gt_points, synthetic_chamfer
from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("syn") / "scene"
    make_synthetic_scene(d, SynthConfig(views=3, width=160, height=120, seed=5, object="blobs",
                                        supersample=1, gt_points=40_000))
    return d


def test_chamfer_of_points_far_from_the_object(tiny_scene):
    """Nothing near the object: an InputError by default, the clip distance with on_empty="clip"
    (so a method that missed the object still has a number in a comparison)."""
    views = [0, 1]
    gt = observed_gt_points(tiny_scene, views)
    far = gt.mean(0) + 100.0 * (gt.max(0) - gt.min(0))
    pts = far[None] + np.random.default_rng(0).normal(size=(50, 3))
    with pytest.raises(InputError, match="no reconstructed point"):
        synthetic_chamfer(pts, tiny_scene, views)
    r = synthetic_chamfer(pts, tiny_scene, views, on_empty="clip")
    assert r["pred_points"] == 0 and r["fscore"] == 0.0
    assert r["accuracy"] == r["completeness"] == r["overall"] == r["max_dist"] > 0
    near = synthetic_chamfer(gt[::7], tiny_scene, views, on_empty="clip")
    assert near["overall"] < 0.1 * r["overall"]
    with pytest.raises(ValueError, match="on_empty"):
        synthetic_chamfer(pts, tiny_scene, views, on_empty="ignore")
    # half of the ground truth reconstructed exactly, plus outliers just beyond the cut-off
    half = gt[gt[:, 0] < np.median(gt[:, 0])]
    md = near["max_dist"]
    hi = gt.max(0)
    # outliers off a corner of the GT's box: inside the scored margin, >= 1.4 max_dist from it
    corner = hi + 0.9 * md
    out = corner + np.random.default_rng(1).uniform(-0.05, 0.05, (len(half) // 4, 3)) * md
    mix = np.concatenate([half, out])
    clip = synthetic_chamfer(mix, tiny_scene, views)
    excl = synthetic_chamfer(mix, tiny_scene, views, rule="exclude")
    # clip: the outliers (and the missing half) count as max_dist; exclude: they are left out
    assert excl["accuracy"] < 0.01 * md
    assert clip["accuracy"] > excl["accuracy"] + 0.005 * md
    assert excl["completeness"] < clip["completeness"]
    assert clip["fscore"] == excl["fscore"]
    with pytest.raises(ValueError, match="rule"):
        synthetic_chamfer(pts, tiny_scene, views, rule="truncate")
