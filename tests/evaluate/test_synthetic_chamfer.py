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


def test_a_mesh_is_scored_by_its_surface(tiny_scene, tmp_path, monkeypatch):
    """With faces, `synthetic_chamfer` scores the mesh's surface (`mesh_surface_points` at
    `mesh_density` of the observed ground truth's diagonal) and says so; a mesh without faces
    has no surface and scores the clip distance; the benchmarks' scorer of a PLY
    (benchmarks/fast_preset.py, which mesh_study.py, _side_by_side.py and
    volsdf_mlp_equal_time.py follow) scores a mesh PLY the same way."""
    import importlib.util
    from pathlib import Path

    from svolsdf.evaluate.chamfer import mesh_density, mesh_surface_points
    from svolsdf.io.ply import read_ply, write_mesh_ply

    views = [0, 1]
    gt = observed_gt_points(tiny_scene, views)
    diag = float(np.linalg.norm(gt.max(0) - gt.min(0)))
    m = read_ply(tiny_scene / "gt_mesh.ply")
    v, f = m["points"].astype(np.float64), m["faces"]
    f = f[v[f].mean(1)[:, 2] > v[:, 2].max() - 3]  # the object's top: a small surface
    r = synthetic_chamfer(v, tiny_scene, views, faces=f)
    assert r["sampled"] == "surface" and r["density"] == pytest.approx(diag / 1000)
    want = synthetic_chamfer(mesh_surface_points(v, f, mesh_density(diag)), tiny_scene, views)
    assert want["sampled"] == "points" and want["density"] is None
    for k in ("accuracy", "completeness", "overall", "fscore"):
        assert r[k] == pytest.approx(want[k], rel=1e-9)
    empty = synthetic_chamfer(v, tiny_scene, views, faces=np.zeros((0, 3), np.int64),
                              on_empty="clip")
    assert empty["overall"] == empty["max_dist"] and empty["sampled"] == "surface"
    bench = Path(__file__).resolve().parents[2] / "benchmarks"
    monkeypatch.syspath_prepend(str(bench))
    spec = importlib.util.spec_from_file_location("fast_preset", bench / "fast_preset.py")
    fast_preset = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fast_preset)
    write_mesh_ply(tmp_path / "mesh.ply", v, f)
    s = fast_preset._score_ply(tiny_scene, tmp_path / "mesh.ply", views)
    v32 = v.astype(np.float32).astype(np.float64)
    assert s["sampled"] == "surface"
    assert s["overall"] == pytest.approx(
        synthetic_chamfer(v32, tiny_scene, views, faces=f)["overall"], rel=1e-9)
