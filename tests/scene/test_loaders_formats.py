"""Round trips: scenes written in each format from known cameras read back to the same cameras."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scene_testkit import (
    H,
    W,
    random_cameras,
    random_points,
    write_colmap,
    write_idr,
    write_mvsnet,
    write_nerf,
)
from scipy.spatial.transform import Rotation

from svolsdf.scene import load_scene
from svolsdf.scene.loaders import detect_format


def _check_cameras(scene, K, w2c, tol=1e-6):
    torch.testing.assert_close(scene.cameras.K, torch.from_numpy(K), atol=tol, rtol=0)
    torch.testing.assert_close(scene.cameras.w2c, torch.from_numpy(w2c), atol=tol, rtol=0)
    # projection agrees with P = K [R|t] applied directly
    pts = torch.from_numpy(random_points(50))
    uv, z = scene.cameras.project(pts)
    for v in range(len(K)):
        ph = (K[v] @ w2c[v][:3]) @ np.c_[pts.numpy(), np.ones(50)].T
        ref = (ph[:2] / ph[2]).T
        assert np.abs(uv[v].numpy() - ref).max() < 1e-6


def test_idr_roundtrip_with_scale_mat(tmp_path):
    K, w2c = random_cameras(4)
    S = np.diag([2.0, 2.0, 2.0, 1.0])
    S[:3, 3] = [0.3, -0.2, 0.1]
    write_idr(tmp_path / "s", K, w2c, scale_mat=S)
    s = load_scene(tmp_path / "s")
    assert s.format == "idr" and s.units == "unknown" and s.view_ids == [0, 1, 2, 3]
    assert s.images.shape == (4, 3, H, W) and s.masks.shape == (4, 1, H, W)
    assert s.masks[:, 0, 5:20, 10:30].min() == 1 and s.masks.sum() == 4 * 15 * 20
    _check_cameras(s, K, w2c)
    assert s.normalization.scale == 2.0 and s.normalization.radius == 3.0
    torch.testing.assert_close(s.normalization.center, torch.tensor([0.3, -0.2, 0.1],
                                                                     dtype=torch.float64))
    # no pair.txt: computed; no depth in files: the object sphere (unit-frame radius 1, so
    # r = 1 * 2 = 2 world units about the centre)
    assert s.extras["pairs_source"].startswith("view selection")
    assert set(s.pairs) == {0, 1, 2, 3} and all(len(v) == 3 for v in s.pairs.values())
    zc = s.cameras.world_to_camera(s.normalization.center[None])[:, 0, 2]
    torch.testing.assert_close(s.depth_range[:, 1], zc + 2.0)


def test_idr_views_and_resize(tmp_path):
    K, w2c = random_cameras(4)
    write_idr(tmp_path / "s", K, w2c, name="cameras_sphere.npz",
              scale_mat=np.diag([1.5, 1.5, 1.5, 1.0]))
    s = load_scene(tmp_path / "s", views=[2, 0], image_size=(20, 15))
    assert s.view_ids == [2, 0] and s.images.shape == (2, 3, 15, 20)
    assert s.normalization.radius == 1.0  # NeuS convention
    full = load_scene(tmp_path / "s", load_images=False)
    assert full.images is None and full.masks is None and (full.width, full.height) == (W, H)
    ref = full.cameras[[2, 0]].resize(20, 15)
    torch.testing.assert_close(s.cameras.K, ref.K)
    # c' = s (c + 0.5) - 0.5 with s = 0.5
    assert abs(float(s.cameras.K[0, 0, 2]) - (0.5 * (K[2][0, 2] + 0.5) - 0.5)) < 1e-9


@pytest.mark.parametrize("bad", ["zero", "rank2", "nan"])
def test_idr_degenerate_world_mat_names_the_file_and_key(tmp_path, bad):
    from svolsdf.scene.scene import SceneError

    K, w2c = random_cameras(3)
    root = write_idr(tmp_path / "s", K, w2c)
    d = dict(np.load(root / "cameras.npz"))
    if bad == "zero":  # an all-zero matrix once passed the relative singularity test
        d["world_mat_1"] = np.zeros((4, 4))
    elif bad == "rank2":
        d["world_mat_1"][:3, 2] = d["world_mat_1"][:3, 0]
    else:
        d["world_mat_1"][0, 0] = np.nan
    np.savez(root / "cameras.npz", **d)
    with pytest.raises(SceneError, match=r"cameras\.npz: world_mat_1: "):
        load_scene(root, load_images=False)


@pytest.mark.parametrize("image_dir", ["images", "blended_images"])
def test_mvsnet_roundtrip(tmp_path, image_dir):
    K, w2c = random_cameras(4)
    lines = ["2.0 0.01", "2.0 0.01 100", "2.0 0.01 100 7.5", "1.5 0.02"]
    pairs = {0: [1, 3, 2], 1: [0, 2], 2: [3], 3: [2, 0]}
    root = write_mvsnet(tmp_path / "m", K, w2c, lines, pairs, image_dir=image_dir)
    if image_dir == "blended_images":  # BlendedMVS' masked copies are not views
        (root / image_dir / "00000000_masked.jpg").write_bytes(
            (root / image_dir / "00000000.jpg").read_bytes())
    s = load_scene(root, load_images=False)
    assert s.format == "mvsnet" and s.view_ids == [0, 1, 2, 3]
    _check_cameras(s, K, w2c, tol=1e-9)
    expect = torch.tensor([[2.0, 2 + 0.01 * 192], [2.0, 3.0], [2.0, 7.5], [1.5, 1.5 + 0.02 * 192]],
                          dtype=torch.float64)
    torch.testing.assert_close(s.depth_range, expect)
    assert s.pairs == pairs and s.extras["pairs_source"] == "pair.txt"
    assert s.source_views(0) == [1, 3, 2]


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_roundtrip(tmp_path, binary):
    K, w2c = random_cameras(5)
    pts = random_points(400)
    root = write_colmap(tmp_path / "c", K, w2c, pts, binary=binary)
    assert detect_format(root) == "colmap"
    s = load_scene(root)
    assert s.format == "colmap" and s.view_ids == [0, 1, 2, 3, 4]
    assert [p.name for p in s.image_paths] == [f"img_{i:02d}.png" for i in range(5)]
    assert s.extras["colmap_image_ids"] == [10, 13, 16, 19, 22]
    _check_cameras(s, K, w2c, tol=1e-9)
    # depth ranges from the visible points' depths; they bracket the points
    z = s.cameras.world_to_camera(torch.from_numpy(pts))[..., 2]
    assert s.extras["depth_range_source"] == "sparse points"
    q = torch.quantile(z, torch.tensor([0.05, 0.95], dtype=torch.float64), dim=1).T
    assert (s.depth_range[:, 0] < q[:, 0]).all() and (s.depth_range[:, 1] > q[:, 1]).all()
    assert (s.depth_range[:, 0] > 0).all()
    # normalization centred on the points' median, cameras within 3 / 1.1
    torch.testing.assert_close(s.normalization.center,
                               torch.from_numpy(pts).median(0).values)
    d = s.normalization.to_unit(s.cameras.centers).norm(dim=-1)
    assert float(d.max()) == pytest.approx(3 / 1.1, rel=1e-9)
    assert s.extras["pairs_source"] == "view selection on sparse points"


def test_colmap_text_and_binary_agree(tmp_path):
    K, w2c = random_cameras(3)
    pts = random_points(200)
    a = load_scene(write_colmap(tmp_path / "t", K, w2c, pts, False), load_images=False)
    b = load_scene(write_colmap(tmp_path / "b", K, w2c, pts, True), load_images=False)
    torch.testing.assert_close(a.cameras.w2c, b.cameras.w2c)
    torch.testing.assert_close(a.depth_range, b.depth_range)
    assert a.pairs == b.pairs


def test_quaternion_roundtrip():
    # COLMAP's files hold (w, x, y, z); pycolmap, which reads them, takes (x, y, z, w): the
    # reader's rotations are scipy's of the same quaternion
    import pycolmap

    rng = np.random.default_rng(3)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[0] >= 0 else -q
        R = pycolmap.Rotation3d(np.r_[q[1:], q[0]]).matrix()
        np.testing.assert_allclose(R, Rotation.from_quat(np.r_[q[1:], q[0]]).as_matrix(),
                                   atol=1e-10)


def test_nerf_roundtrip_explicit_intrinsics(tmp_path):
    K, w2c = random_cameras(3)
    s = load_scene(write_nerf(tmp_path / "n", K, w2c))
    assert s.format == "nerf" and s.masks is None
    _check_cameras(s, K, w2c, tol=1e-9)


def test_nerf_camera_angle_and_alpha(tmp_path):
    K, w2c = random_cameras(3)
    f = 40.0
    K[:] = np.array([[f, 0, W / 2 - 0.5], [0, f, H / 2 - 0.5], [0, 0, 1]])
    s = load_scene(write_nerf(tmp_path / "n", K, w2c, use_angle=True, rgba=True))
    _check_cameras(s, K, w2c, tol=1e-9)
    assert s.masks is not None and s.masks.shape == (3, 1, H, W)  # from alpha
    # RGBA composited on white: where alpha = 0 the pixel is white
    a = np.asarray(__import__("PIL.Image").Image.open(s.image_paths[0]))
    zero = a[..., 3] == 0
    if zero.any():
        assert torch.all(s.images[0][:, torch.from_numpy(zero)] == 1.0)
    torch.testing.assert_close(s.masks[0, 0], torch.from_numpy((a[..., 3] > 127).astype(
        np.float32)))
