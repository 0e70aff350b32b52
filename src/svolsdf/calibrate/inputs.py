"""The photos to calibrate: a folder of photos or frames sampled from a video, made ready for SfM.

`gather_inputs` lists the photos of a folder (or samples frames of a video with imageio-ffmpeg),
applies their EXIF orientation, shrinks them to ``max_size`` pixels on the longer side and writes
them to a work folder; `shared_camera` says whether they share one camera (same size and the same
EXIF camera: make, model and focal length; frames of one video always do).
"""

from __future__ import annotations

import logging
import shutil
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from svolsdf.errors import InputError

__all__ = ["IMAGE_SUFFIXES", "VIDEO_SUFFIXES", "Photo", "gather_inputs", "list_photos",
           "sample_video", "shared_camera"]

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")
VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm", ".mpg", ".mpeg")

# EXIF tags that identify a camera and its lens setting (PIL.ExifTags.Base)
_EXIF_MAKE, _EXIF_MODEL, _EXIF_IFD = 0x010F, 0x0110, 0x8769
_EXIF_FOCAL, _EXIF_FOCAL35 = 0x920A, 0xA405


@dataclass
class Photo:
    """One photo made ready for SfM."""

    name: str
    """File name in the work folder (unique; the name SCENE/images/ will use)."""
    source: str
    """Where it came from: the photo's path, or ``video.mp4#frame 120``."""
    size: tuple[int, int]
    """(width, height) after orientation and shrinking."""
    exif_camera: tuple = field(default_factory=tuple)
    """(make, model, focal length, 35 mm focal length) from EXIF; empty without EXIF."""


def _natural_key(name: str):
    import re

    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def list_photos(folder: Path) -> list[Path]:
    """Image files of ``folder`` (not recursive) in natural name order (img2 before img10)."""
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    return sorted(files, key=lambda p: _natural_key(p.name))


def _exif_camera(im: Image.Image) -> tuple:
    exif = im.getexif()
    if not exif:
        return ()
    sub = exif.get_ifd(_EXIF_IFD)
    vals = (exif.get(_EXIF_MAKE), exif.get(_EXIF_MODEL), sub.get(_EXIF_FOCAL),
            sub.get(_EXIF_FOCAL35))
    if all(v is None for v in vals):
        return ()
    return tuple(None if v is None else (str(v).strip("\x00 ") if isinstance(v, str | bytes)
                                         else float(v)) for v in vals)


def _shrunk(size: tuple[int, int], max_size: int | None) -> tuple[int, int]:
    w, h = size
    if not max_size or max(w, h) <= max_size:
        return w, h
    s = max_size / max(w, h)
    return max(1, round(w * s)), max(1, round(h * s))


def _prepare_photo(path: Path, out: Path, max_size: int | None) -> Photo:
    """Orient, shrink and write one photo; the EXIF block is kept (SfM reads the focal length)."""
    with Image.open(path) as im:
        im.load()
        cam = _exif_camera(im)
        oriented = ImageOps.exif_transpose(im)
        size = _shrunk(oriented.size, max_size)
        dst = out / path.name
        if oriented is im and size == im.size and im.mode in ("RGB", "L"):
            shutil.copyfile(path, dst)
        else:
            img = oriented.convert("RGB") if oriented.mode not in ("RGB", "L") else oriented
            if size != img.size:
                img = img.resize(size, Image.Resampling.LANCZOS)
            exif = oriented.getexif()
            kw = {"exif": exif.tobytes()} if exif else {}
            if path.suffix.lower() in (".jpg", ".jpeg"):
                kw["quality"] = 95
            img.save(dst, **kw)
    return Photo(name=path.name, source=str(path), size=size, exif_camera=cam)


def sample_video(video: Path, out: Path, frames: int, max_size: int | None,
                 progress: bool = False) -> list[Photo]:
    """Write ``frames`` frames spread evenly over ``video`` to ``out`` as JPEG files.

    Raises:
        InputError: imageio-ffmpeg is missing (with the install command) or the video cannot be
            decoded.
    """
    try:
        import imageio_ffmpeg
    except ImportError:
        raise InputError(f"{video}: reading a video needs imageio-ffmpeg; install it with: "
                         f"pip install 'svolsdf[video]'  (or: pip install imageio-ffmpeg)"
                         ) from None
    from tqdm import tqdm

    try:
        n_total, _ = imageio_ffmpeg.count_frames_and_secs(str(video))
        reader = imageio_ffmpeg.read_frames(str(video))
        meta = next(reader)
    except (RuntimeError, OSError, StopIteration) as e:
        raise InputError(f"{video}: cannot read the video ({e.__class__.__name__}: "
                         f"{str(e).splitlines()[0] if str(e) else ''})") from None
    w, h = meta["size"]
    if n_total < 1:
        raise InputError(f"{video}: the video has no frames")
    keep = set(np.unique(np.linspace(0, n_total - 1, min(frames, n_total)).round().astype(int))
               .tolist())
    size = _shrunk((w, h), max_size)
    photos: list[Photo] = []
    bar = tqdm(total=len(keep), desc="calibrate: video frames", unit="frame",
               disable=not progress)
    try:
        for i, buf in enumerate(reader):
            if i not in keep:
                continue
            img = Image.frombuffer("RGB", (w, h), buf, "raw", "RGB", 0, 1)
            if size != (w, h):
                img = img.resize(size, Image.Resampling.LANCZOS)
            name = f"frame_{i:06d}.jpg"
            img.save(out / name, quality=95)
            photos.append(Photo(name=name, source=f"{video}#frame {i}", size=size))
            bar.update()
    except (RuntimeError, OSError) as e:
        raise InputError(f"{video}: decoding failed after {len(photos)} frames "
                         f"({e.__class__.__name__}: {e})") from None
    finally:
        bar.close()
        reader.close()
    if not photos:
        raise InputError(f"{video}: no frame could be decoded")
    return photos


def gather_inputs(path: Path, out: Path, max_size: int | None = 1600, frames: int = 40,
                  progress: bool = False) -> tuple[list[Photo], bool]:
    """Photos of a folder, or frames of a video, oriented and shrunk into ``out``.

    Args:
        path: a folder of photos or a video file.
        out: the work folder to write the prepared photos to.
        max_size: longest side in pixels (None: keep the size).
        frames: frames to sample from a video.

    Returns:
        the photos in order, and whether they come from a video.

    Raises:
        InputError: the path does not exist, the folder has no photos, some photos cannot be read
            (all are named), or the photos have different aspect ratios.
    """
    from svolsdf.io.paths import input_path

    path = input_path(path, "folder of photos or video file")
    out.mkdir(parents=True, exist_ok=True)
    if path.is_file():
        if path.suffix.lower() not in VIDEO_SUFFIXES:
            raise InputError(f"{path}: not a video ({', '.join(VIDEO_SUFFIXES)}); pass a folder "
                             f"of photos or a video file")
        return sample_video(path, out, frames, max_size, progress), True
    files = list_photos(path)
    if not files:
        raise InputError(f"{path}: no photos found (looked for {', '.join(IMAGE_SUFFIXES)})")
    photos, bad = [], []
    from tqdm import tqdm

    for p in tqdm(files, desc="calibrate: reading photos", unit="photo", disable=not progress):
        try:
            photos.append(_prepare_photo(p, out, max_size))
        except (UnidentifiedImageError, OSError, SyntaxError, ValueError,
                Image.DecompressionBombError) as e:  # a header declaring gigapixels
            bad.append(f"{p.name} ({e.__class__.__name__}: {e})")
    if bad:
        raise InputError(f"{path}: {len(bad)} of {len(files)} photos cannot be read: "
                         f"{'; '.join(bad[:5])}{' ...' if len(bad) > 5 else ''}; fix or remove "
                         f"them")
    _same_size(photos, out)
    return photos, False


def _same_size(photos: list[Photo], out: Path) -> None:
    """Bring all photos to one size (the reconstruction needs it): photos of the most common
    aspect ratio at another resolution are resized to the smallest; another aspect is an error."""
    sizes = Counter(p.size for p in photos)
    if len(sizes) == 1:
        return
    main = sizes.most_common(1)[0][0]
    aspect = main[0] / main[1]
    odd = [p for p in photos if abs(p.size[0] / p.size[1] - aspect) > 0.01 * aspect]
    if odd:
        listing = ", ".join(f"{p.name} ({p.size[0]}x{p.size[1]})" for p in odd[:5])
        raise InputError(f"{len(odd)} of {len(photos)} photos have another shape than "
                         f"{main[0]}x{main[1]}: {listing}{' ...' if len(odd) > 5 else ''}; all "
                         f"photos must have one orientation and aspect ratio (rotate or remove "
                         f"these)")
    target = min(sizes, key=lambda s: s[0] * s[1])
    for p in photos:
        if p.size != target:
            with Image.open(out / p.name) as im:
                im.load()
                exif = im.getexif()
                img = im.resize(target, Image.Resampling.LANCZOS)
            img.save(out / p.name, **({"exif": exif.tobytes()} if exif else {}))
            p.size = target


def shared_camera(photos: list[Photo], from_video: bool) -> bool:
    """True when the photos say they come from one camera: one size and the same EXIF camera
    (or none at all); frames of one video always do."""
    if from_video:
        return True
    return len({p.size for p in photos}) == 1 and len({p.exif_camera for p in photos}) == 1
