"""Cameras in other tools' formats (`svolsdf.scene.camera_export`): the conventions converted
once, checked against the definitions of each format."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from svolsdf.scene.camera_export import (
    camera_json,
    colmap_reconstruction,
    nerfstudio_transforms,
)
from svolsdf.scene.cameras import Cameras


def _cameras(n: int = 3, seed: int = 0) -> Cameras:
    """``n`` cameras on a circle of radius 5 looking at the origin, each its own intrinsics."""
    g = torch.Generator().manual_seed(seed)
    K, w2c = [], []
    for k in range(n):
        a = 2 * math.pi * k / n
        c = torch.tensor([5 * math.cos(a), 5 * math.sin(a), 1.0], dtype=torch.float64)
        z = -c / c.norm()
        x = torch.linalg.cross(z, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
        x = x / x.norm()
        y = torch.linalg.cross(z, x)
        R = torch.stack([x, y, z])
        m = torch.eye(4, dtype=torch.float64)
        m[:3, :3], m[:3, 3] = R, -R @ c
        w2c.append(m)
        f = 60 + 10 * torch.rand(1, generator=g, dtype=torch.float64).item()
        K.append(torch.tensor([[f, 0, 31.3 + k], [0, f * 1.01, 23.7], [0, 0, 1]],
                              dtype=torch.float64))
    return Cameras(torch.stack(K), torch.stack(w2c), 64, 48)


def test_nerfstudio_frames_are_opengl_camera_to_world():
    cams = _cameras()
    t = nerfstudio_transforms(cams, ["a.png", "b.png", "c.png"], points_file="p.ply")
    assert "fl_x" not in t  # the views differ: intrinsics per frame only
    assert t["ply_file_path"] == "p.ply"
    for k, fr in enumerate(t["frames"]):
        c2w = np.asarray(fr["transform_matrix"])
        np.testing.assert_allclose(c2w[:3, 3], cams.centers[k].numpy(), atol=1e-12)
        # OpenGL: the camera looks along its -z, its +y is our -y (image up)
        np.testing.assert_allclose(-c2w[:3, 2], cams.view_dirs[k].numpy(), atol=1e-12)
        np.testing.assert_allclose(-c2w[:3, 1], cams.w2c[k, 1, :3].numpy(), atol=1e-12)
        assert fr["cx"] == pytest.approx(float(cams.K[k, 0, 2]) + 0.5)
        assert (fr["w"], fr["h"]) == (64, 48)


def test_nerfstudio_shared_intrinsics_at_the_top():
    cams = _cameras()
    cams = Cameras(cams.K[:1].expand(3, 3, 3).clone(), cams.w2c, 64, 48)
    t = nerfstudio_transforms(cams, ["a", "b", "c"])
    assert t["fl_x"] == pytest.approx(float(cams.K[0, 0, 0]))
    assert t["cy"] == pytest.approx(float(cams.K[0, 1, 2]) + 0.5)


def test_colmap_model_round_trips_through_the_scene_reader(tmp_path):
    from svolsdf.scene.formats.colmap import read

    cams = _cameras()
    pts = np.array([[0.0, 0.0, 0.0], [0.3, -0.2, 0.1]])
    seen = np.array([[True, True, False], [False, True, True]])
    rec = colmap_reconstruction(cams, ["a.png", "b.png", "c.png"], pts,
                                np.array([[255, 0, 0], [0, 255, 0]], np.uint8), seen)
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    rec.write(str(tmp_path / "sparse" / "0"))
    (tmp_path / "images").mkdir()
    for n in ("a.png", "b.png", "c.png"):
        (tmp_path / "images" / n).write_bytes(b"")  # the reader checks only that they exist
    src = read(tmp_path)
    torch.testing.assert_close(src.K, cams.K, rtol=0, atol=1e-9)
    torch.testing.assert_close(src.w2c, cams.w2c, rtol=0, atol=1e-9)
    np.testing.assert_allclose(src.points.numpy(), pts)
    assert src.visibility.numpy().tolist() == seen.tolist()


def test_camera_json_keeps_k_whole_and_names_the_frame():
    cams = _cameras()
    cams.K[:, 0, 1] = 0.25  # skew: kept here, not in nerfstudio's or COLMAP's files
    d = camera_json(cams, [4, 5, 6], ["a", "b", "c"], "mm", "/s", "idr")
    assert d["units"] == "mm" and "idr" in d["world_frame"]
    v = d["views"][1]
    assert v["id"] == 5 and v["K"][0][1] == 0.25
    R, t = np.asarray(v["R"]), np.asarray(v["t"])
    np.testing.assert_allclose(-R.T @ t, v["center"], atol=1e-12)


def test_names_must_match_the_cameras():
    with pytest.raises(ValueError, match="2 names for 3 cameras"):
        nerfstudio_transforms(_cameras(), ["a", "b"])
