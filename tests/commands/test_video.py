"""The orbit video: frames of any size are padded to H.264's 16-pixel blocks with their edge
pixels, not stretched by imageio-ffmpeg (which warned on the terminal about it)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from svolsdf.commands.render import write_video


def test_video_frames_padded_not_stretched_and_no_warning(tmp_path, caplog):
    pytest.importorskip("imageio_ffmpeg")
    import imageio.v3 as iio

    frames = []
    for _ in range(4):
        f = np.full((50, 66, 3), 40, np.uint8)
        f[:, 30:34] = 230  # a bright band at x = 30..33
        frames.append(f)
    with caplog.at_level(logging.WARNING):
        path = write_video(frames, tmp_path / "orbit")
    assert path.suffix == ".mp4"
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.text
    back = iio.imread(path, index=0, extension=".mp4")
    assert back.shape[:2] == (64, 80)  # padded up to 16-pixel blocks
    band = back[:50, :66, 0].astype(float).mean(0)
    assert 30 <= int(np.argmax(band)) <= 33  # where it was: no stretch
