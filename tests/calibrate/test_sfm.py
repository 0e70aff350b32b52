"""`calibrate` end to end on a synthetic scene given without its cameras: camera accuracy after a
similarity fit, the scene it writes, ``--views auto`` on it, and a reconstruction on the estimated
cameras against one on the true cameras. Also the errors: pycolmap missing, too few registered."""

from __future__ import annotations

import json
import sys

import numpy as np
import pycolmap  # noqa: F401  (a core dependency: without it these tests fail)
import pytest
from PIL import Image

from svolsdf.calibrate import CalibrateConfig, CalibrationError, calibrate, centre_errors
from svolsdf.calibrate.sfm import _undistort_points, undistort_simple_radial
from svolsdf.errors import InputError
from svolsdf.scene.loaders import load_scene
from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

# 20 views of one camera (no per-view intrinsics jitter) on a DTU-like cap, small and fast
SYNTH = SynthConfig(views=20, width=384, height=288, seed=0, intrinsics_jitter=0.0,
                    supersample=1, gt_points=50_000, mesh_resolution=3.0)
FAST = {"threads": 2, "max_features": 1024, "progress": False}


@pytest.fixture(scope="module")
def truth(tmp_path_factory):
    d = tmp_path_factory.mktemp("syn") / "scene"
    make_synthetic_scene(d, SYNTH)
    return d


@pytest.fixture(scope="module")
def calibrated(truth, tmp_path_factory):
    out = tmp_path_factory.mktemp("cal") / "scene"
    summary = calibrate(truth / "image", out, CalibrateConfig(**FAST))
    return out, summary


def _matched(truth_dir, est_dir):
    t = load_scene(truth_dir, load_images=False)
    e = load_scene(est_dir, load_images=False)
    by_name = {p.name: k for k, p in enumerate(t.image_paths)}
    idx = [by_name[p.name] for p in e.image_paths]
    return t, e, idx


@pytest.mark.slow  # structure from motion on 20 views: ~20 s
def test_camera_centres_within_half_a_percent(truth, calibrated):
    out, summary = calibrated
    assert len(summary["registered"]) == 20 and summary["unregistered"] == []
    assert summary["shared_camera"] and summary["matcher"] == "exhaustive"
    t, e, idx = _matched(truth, out)
    assert e.format == "colmap" and len(e) == 20
    err, sim, size = centre_errors(e.cameras.centers.numpy(), t.cameras.centers[idx].numpy())
    assert err.max() < 0.005 * size, (err.max(), size)
    # one shared pinhole camera, focal length close to the truth's
    assert abs(e.cameras.K[0, 0, 0] / t.cameras.K[0, 0, 0] - 1) < 0.01
    assert json.loads((out / "calibration.json").read_text())["registered"] == summary["registered"]
    assert sorted(p.name for p in (out / "images").iterdir()) == summary["registered"]
    # the depth ranges come from the sparse points and hold the surface
    assert e.extras["depth_range_source"] == "sparse points"


def test_too_few_registered_says_how_many_and_what_helps(tmp_path):
    rng = np.random.default_rng(0)
    photos = tmp_path / "photos"
    photos.mkdir()
    for k in range(4):  # unrelated noise: nothing can be matched
        Image.fromarray(rng.integers(0, 255, (96, 128, 3), dtype=np.uint8)).save(
            photos / f"{k}.png")
    with pytest.raises(CalibrationError, match=r"only \d of 4 photos .*more overlap.*more photos"):
        calibrate(photos, tmp_path / "out", CalibrateConfig(**FAST))


def test_missing_pycolmap_prints_the_install_command(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # import fails
    with pytest.raises(InputError, match=r"pip install 'svolsdf\[colmap\]'"):
        calibrate(tmp_path, tmp_path / "out")


def test_undistortion_maps_points_and_pixels_alike():
    """A dot drawn where the distorted camera sees a ray lands, after `undistort_simple_radial`,
    where `_undistort_points` puts that ray in the pinhole image."""
    f, cx, cy, k = 100.0, 64.0, 48.0, -0.08
    xy_pin = np.array([[110.0, 80.0]])  # pinhole pixel (COLMAP convention)
    x = (xy_pin - [cx, cy]) / f
    xy_dist = x * (1 + k * (x**2).sum()) * f + [cx, cy]
    img = np.zeros((96, 128, 3), np.uint8)
    u, v = (xy_dist[0] - 0.5).round().astype(int)
    img[v - 1:v + 2, u - 1:u + 2] = 255
    out = np.asarray(undistort_simple_radial(Image.fromarray(img), f, cx, cy, k))[..., 0]
    vv, uu = np.nonzero(out > 128)
    assert abs(uu.mean() + 0.5 - xy_pin[0, 0]) < 1.0 and abs(vv.mean() + 0.5 - xy_pin[0, 1]) < 1.0
    assert np.allclose(_undistort_points(xy_dist, f, cx, cy, k), xy_pin, atol=1e-6)


def _tiny_cfg(scene, views=None, steps=100):
    from svolsdf.config import preset

    cfg = preset("fast")
    cfg.scene.path = str(scene)
    if views is None:
        cfg.scene.view_selection = "auto"
    else:
        cfg.scene.views = views
    cfg.scene.image_size = [160, 120]
    cfg.train.steps = steps
    cfg.train.rays = 256
    cfg.train.checkpoint_every = 100
    cfg.field.grid_start_resolution = 32
    cfg.field.grid_resolution = 64
    cfg.mesh.resolution = 96
    return cfg


@pytest.mark.slow  # two reconstructions: ~90 s
def test_reconstruction_on_auto_views_scores_like_the_true_cameras(truth, calibrated, tmp_path):
    """3 views picked by --views auto, reconstructed on the estimated cameras and on the true
    ones (both without object masks, which photos do not come with): the Chamfer of the points
    and of the mesh (the estimate mapped into the true frame by the cameras' similarity fit) is
    within 20 % of the true cameras'."""
    import shutil

    from svolsdf.calibrate import similarity_fit
    from svolsdf.evaluate.synthetic import synthetic_chamfer
    from svolsdf.io.ply import read_ply
    from svolsdf.pipeline import Pipeline

    out, _ = calibrated
    t, e, idx = _matched(truth, out)
    est = Pipeline(_tiny_cfg(out), tmp_path / "est", progress=False)
    s_est = est.run()
    assert len(est.views) == 3 and len(set(est.views)) == 3
    by_name = {p.name: v for p, v in zip(t.image_paths, t.view_ids, strict=True)}
    ids = [by_name[e.image_paths[e.index(v)].name] for v in est.views]
    plain = tmp_path / "true_scene"  # the true cameras and photos, no masks
    shutil.copytree(truth / "image", plain / "image")
    shutil.copyfile(truth / "cameras.npz", plain / "cameras.npz")
    s_true = Pipeline(_tiny_cfg(plain, ids), tmp_path / "true", progress=False).run()
    sim = similarity_fit(e.cameras.centers.numpy(), t.cameras.centers[idx].numpy())
    for name in ("points", "mesh"):
        ref = synthetic_chamfer(read_ply(s_true[name])["points"], truth, ids)["overall"]
        got = synthetic_chamfer(sim.apply(read_ply(s_est[name])["points"]), truth,
                                ids)["overall"]
        assert got <= 1.2 * ref, (name, got, ref)
