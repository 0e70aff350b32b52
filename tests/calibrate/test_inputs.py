"""Inputs of `calibrate`: photo listing, orientation and shrinking, one shared camera or not,
unreadable photos and odd shapes, and frames sampled from a video."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from svolsdf.calibrate.inputs import gather_inputs, list_photos, sample_video, shared_camera
from svolsdf.errors import InputError


def _photo(path, w=120, h=90, exif=None, seed=0):
    a = np.random.default_rng(seed).integers(0, 255, (h, w, 3), dtype=np.uint8)
    im = Image.fromarray(a)
    kw = {}
    if exif is not None:
        e = Image.Exif()
        for k, v in exif.items():
            e[k] = v
        kw["exif"] = e.tobytes()
    im.save(path, **kw)


def test_natural_order_and_non_images_skipped(tmp_path):
    for n in ("img10.png", "img2.png", "img1.jpg"):
        _photo(tmp_path / n)
    (tmp_path / "notes.txt").write_text("x")
    assert [p.name for p in list_photos(tmp_path)] == ["img1.jpg", "img2.png", "img10.png"]


def test_shrink_orientation_and_shared_camera(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    _photo(src / "a.jpg", 400, 300, exif={0x010F: "Acme", 0x0110: "X1"})
    # EXIF orientation 6 (rotate 90 degrees clockwise to display): a 400x300 landscape file of
    # a photo taken upright displays as 300x400
    _photo(src / "b.jpg", 400, 300, exif={0x010F: "Acme", 0x0110: "X1", 0x0112: 6})
    with pytest.raises(InputError, match=r"1 of 2 photos have another shape"):
        gather_inputs(src, tmp_path / "w1", max_size=200)
    (src / "b.jpg").unlink()
    _photo(src / "b.jpg", 800, 600, exif={0x010F: "Acme", 0x0110: "X1"})  # same shape, larger
    photos, video = gather_inputs(src, tmp_path / "w2", max_size=200)
    assert not video and [p.size for p in photos] == [(200, 150), (200, 150)]
    with Image.open(tmp_path / "w2" / "b.jpg") as im:
        assert im.size == (200, 150) and im.getexif().get(0x0110) == "X1"  # EXIF kept
    assert shared_camera(photos, False)
    photos[1].exif_camera = ("Other", "Y2", None, None)
    assert not shared_camera(photos, False) and shared_camera(photos, True)


def test_unreadable_photos_are_named(tmp_path):
    _photo(tmp_path / "good.png")
    (tmp_path / "broken.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(InputError, match=r"1 of 2 photos cannot be read: broken.jpg"):
        gather_inputs(tmp_path, tmp_path / "w")


def test_missing_and_empty_inputs(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        gather_inputs(tmp_path / "nope", tmp_path / "w")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no photos found"):
        gather_inputs(tmp_path / "empty", tmp_path / "w")
    (tmp_path / "x.txt").write_text("x")
    with pytest.raises(InputError, match="not a video"):
        gather_inputs(tmp_path / "x.txt", tmp_path / "w")


def test_video_frames_are_sampled_evenly(tmp_path):
    ffmpeg = pytest.importorskip("imageio_ffmpeg", reason="video input needs imageio-ffmpeg")
    video = tmp_path / "clip.mp4"
    w = ffmpeg.write_frames(str(video), (128, 96), fps=10, macro_block_size=16)
    w.send(None)
    for k in range(30):
        a = np.full((96, 128, 3), 8 * k, np.uint8)
        w.send(a.tobytes())
    w.close()
    out = tmp_path / "frames"
    out.mkdir()
    photos = sample_video(video, out, frames=5, max_size=64)
    assert [p.name for p in photos] == [f"frame_{i:06d}.jpg" for i in (0, 7, 14, 22, 29)]
    assert all(p.size == (64, 48) for p in photos) and shared_camera(photos, True)
    with Image.open(out / photos[-1].name) as im:  # the last frame, not the first
        assert abs(np.asarray(im).mean() - 8 * 29) < 4
    (tmp_path / "bad.mp4").write_bytes(b"garbage")
    with pytest.raises(InputError, match="bad.mp4: cannot read the video"):
        gather_inputs(tmp_path / "bad.mp4", tmp_path / "w")


def test_missing_imageio_ffmpeg_prints_the_install_command(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # import fails
    (tmp_path / "clip.mp4").write_bytes(b"x")
    with pytest.raises(InputError, match=r"pip install 'svolsdf\[video\]'"):
        gather_inputs(tmp_path / "clip.mp4", tmp_path / "w")
