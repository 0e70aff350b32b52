"""`Scene.images_at`: a larger MVS size reads the files' own pixels when they are larger."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from scene_testkit import H, W, random_cameras, write_idr, write_nerf

from svolsdf.io.images import read_image, resize_image
from svolsdf.mvs.planesweep import PlaneSweepBackbone
from svolsdf.scene import SceneError, load_scene


def _files(s) -> torch.Tensor:
    return torch.stack([read_image(p) for p in s.image_paths])


def test_larger_size_reads_the_files(tmp_path):
    K, w2c = random_cameras(3)
    root = write_idr(tmp_path / "s", K, w2c)  # 40x30 files of random pixels
    s = load_scene(root, views=[2, 0], image_size=(W // 2, H // 2))
    files = _files(s)
    # the files' own size: their pixels exactly, not the working size upsampled
    torch.testing.assert_close(s.images_at(W, H), files)
    up = s.images_at(W, H, from_files=False)
    ref = F.interpolate(s.images, size=(H, W), mode="bicubic", align_corners=False).clamp(0, 1)
    torch.testing.assert_close(up, ref)
    # random pixels: the halved images lost what the files keep
    assert (up - files).abs().mean() > 5 * (s.images_at(W, H) - files).abs().mean() + 0.05
    # between the two sizes: resized from the files, as the loader resizes them
    torch.testing.assert_close(s.images_at(30, 22), resize_image(files, 30, 22))
    # the working size is the images themselves; smaller sizes come from them
    assert s.images_at(W // 2, H // 2) is s.images
    small = s.images_at(10, 7)
    assert small.shape == (2, 3, 7, 10)


def test_files_no_larger_than_the_working_size_upsample(tmp_path):
    K, w2c = random_cameras(3)
    s = load_scene(write_idr(tmp_path / "s", K, w2c))  # working size = files
    ref = F.interpolate(s.images, size=(2 * H, 2 * W), mode="bicubic",
                        align_corners=False).clamp(0, 1)
    torch.testing.assert_close(s.images_at(2 * W, 2 * H), ref)


def test_rgba_files_keep_their_background(tmp_path):
    K, w2c = random_cameras(3)
    f = 40.0
    K[:] = np.array([[f, 0, W / 2 - 0.5], [0, f, H / 2 - 0.5], [0, 0, 1]])
    s = load_scene(write_nerf(tmp_path / "n", K, w2c, rgba=True), image_size=(W // 2, H // 2))
    full = torch.stack([read_image(p, 1.0) for p in s.image_paths])
    torch.testing.assert_close(s.images_at(W, H), full)


def test_changed_or_missing_files(tmp_path):
    K, w2c = random_cameras(3)
    root = write_idr(tmp_path / "s", K, w2c)
    s = load_scene(root, image_size=(W // 2, H // 2))
    from PIL import Image

    Image.new("RGB", (W + 2, H)).save(s.image_paths[1])
    with pytest.raises(SceneError, match=str(s.image_paths[1].name)):
        s.images_at(W, H)
    s.image_paths[1].unlink()  # gone: upsampled from the working size instead
    ref = F.interpolate(s.images, size=(H, W), mode="bicubic", align_corners=False).clamp(0, 1)
    torch.testing.assert_close(s.images_at(W, H), ref)


@pytest.mark.parametrize("native", [True, False])
def test_plane_sweep_stage3_uses_the_files(tmp_path, native):
    """At scale 2 stage 3 is twice the working size: its grey images come from the files."""
    K, w2c = random_cameras(3)
    s = load_scene(write_idr(tmp_path / "s", K, w2c), image_size=(W // 2, H // 2))
    bb = PlaneSweepBackbone(scale=2.0, native_images=native)
    _, gray, cams = bb._stage_inputs(s, 3)
    assert (cams.width, cams.height) == (W, H)
    src = s.images_at(W, H, from_files=native)
    g = 0.299 * src[:, :1] + 0.587 * src[:, 1:2] + 0.114 * src[:, 2:]
    torch.testing.assert_close(gray, g, atol=1e-5, rtol=0)
