"""What every format reader returns (`SceneSource`) and the checks they share."""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from svolsdf.scene.scene import Normalization, SceneError

__all__ = [
    "IMAGE_SUFFIXES",
    "SceneSource",
    "check_camera",
    "find_dir",
    "list_images",
    "load_txt_matrix",
    "match_masks",
    "match_numbered",
    "numbered",
    "scan_number",
]

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp"}


@dataclass
class SceneSource:
    """A scene as a format reader finds it on disk, before images are loaded.

    Attributes:
        format: "idr", "dtu_raw", "mvsnet", "colmap" or "nerf".
        path: the scene folder.
        view_ids: V view ids, in file order.
        image_paths: V image files.
        K: (V, 3, 3) float64 intrinsics (integer pixel centres, see `svolsdf.scene.cameras`).
        w2c: (V, 4, 4) float64 world-to-camera (OpenCV axes).
        camera_size: (width, height) the intrinsics refer to, when the format says so
            (COLMAP, transforms.json); None = the size of the image files.
        camera_source: V strings naming where each camera came from (for error messages).
        cameras_file: the file (or folder) the cameras came from, for count messages.
        mask_paths: V mask files (None for a view without one, in formats whose mask folder
            may cover only some views: `match_masks` with ``partial``), or None.
        masks_from_alpha: masks are the images' alpha channels (transforms.json RGBA).
        background: grey level to composite RGBA images onto, or None to drop alpha.
        pairs, pair_scores: from pair.txt, or None (computed later).
        depth_range: (V, 2) float64 from the files, or None.
        normalization: from the files (scale_mat), or None (computed later).
        points: (N, 3) float64 sparse points, or None.
        visibility: (N, V) bool, which views see each point (tracks), or None.
        units: world units when the format says ("mm" for DTU).
        extras: format-specific facts, copied into `Scene.extras`.
    """

    format: str
    path: Path
    view_ids: list[int]
    image_paths: list[Path]
    K: Tensor
    w2c: Tensor
    camera_source: list[str]
    cameras_file: str
    camera_size: tuple[int, int] | None = None
    mask_paths: list[Path | None] | None = None
    masks_from_alpha: bool = False
    background: float | None = None
    pairs: dict[int, list[int]] | None = None
    pair_scores: dict[int, list[float]] | None = None
    depth_range: Tensor | None = None
    normalization: Normalization | None = None
    points: Tensor | None = None
    visibility: Tensor | None = None
    units: str = "unknown"
    extras: dict = field(default_factory=dict)


def _unreadable_entry(p: Path) -> str | None:
    """Why the folder entry ``p`` (named like an image) is not an image file, or None."""
    if p.is_file():
        return None
    if p.is_symlink() and not p.exists():
        return f"{p} is a symbolic link to {os.readlink(p)}, which does not exist"
    if p.is_dir():
        return f"{p} is a folder, not an image file"
    return f"{p} is not a regular file"


def list_images(folder: Path, what: str = "images") -> list[Path]:
    """Image files (`IMAGE_SUFFIXES`) in ``folder`` (not recursive), sorted by name; hidden
    files skipped.

    Raises:
        SceneError: an entry named like an image is a folder, a dangling link or no regular
            file (it would silently drop a view); or the folder holds no image (the message
            lists the accepted types and the ones found).
    """
    entries = sorted(p for p in folder.iterdir() if not p.name.startswith("."))
    files = []
    for p in entries:
        if p.suffix.lower() in IMAGE_SUFFIXES:
            cause = _unreadable_entry(p)
            if cause is not None:
                raise SceneError(f"{cause}; put the image file there or remove the entry")
            files.append(p)
    if not files:
        accepted = ", ".join(sorted(IMAGE_SUFFIXES))
        other = sorted({p.suffix.lower() or p.name for p in entries})
        if not other:
            raise SceneError(f"{folder}: no {what} found (the folder is empty); add the {what} "
                             f"({accepted}) or remove {folder.name}/")
        found = ", ".join(other[:5]) + (" ..." if len(other) > 5 else "")
        raise SceneError(f"{folder}: no {what} found (it holds only {found}; accepted types: "
                         f"{accepted}); convert the {what} to one of these types")
    return files


def find_dir(root: Path, *names: str) -> Path | None:
    """The first of ``root/name`` that is a folder, or None."""
    for n in names:
        if (root / n).is_dir():
            return root / n
    return None


def numbered(files: list[Path]) -> dict[int, Path]:
    """{view number: file}: the number is the last run of digits in the file's stem
    (``000007.png`` and ``7.jpg`` -> 7).

    Raises:
        SceneError: a file's name holds no number, or two files hold the same number.
    """
    out: dict[int, Path] = {}
    for p in files:
        digits = re.findall(r"\d+", p.stem)
        if not digits:
            raise SceneError(f"{p}: the file name holds no view number (name the files by the "
                             f"number of their camera, e.g. 000007{p.suffix})")
        v = int(digits[-1])
        if v in out:
            raise SceneError(f"{out[v]} and {p} both hold view {v}; keep one of them")
        out[v] = p
    return out


def _ids_text(ids: list[int]) -> str:
    shown = ", ".join(str(v) for v in ids[:5])
    return shown + (f" and {len(ids) - 5} more" if len(ids) > 5 else "")


def match_numbered(files: dict[int, Path], view_ids: list[int], folder: Path, what: str,
                   owner: str) -> list[Path]:
    """The files of ``view_ids`` in that order, matched by the number in their names
    (`numbered`), never by position.

    Args:
        files: {view number: file} of ``folder``.
        view_ids: the views the cameras define, in order.
        what: "image" or "mask", for the message.
        owner: what defines the views ("camera in cameras.npz (world_mat_0..world_mat_2)"),
            for the message.

    Raises:
        SceneError: a view has no file (a gap) or a file has no view (an extra): both named.
    """
    missing = [v for v in view_ids if v not in files]
    known = set(view_ids)
    extra = sorted(v for v in files if v not in known)
    if not missing and not extra:
        return [files[v] for v in view_ids]
    parts = []
    if extra:
        names = ", ".join(files[v].name for v in extra[:3]) + (" ..." if len(extra) > 3 else "")
        parts.append(f"{folder}/{names} {'is' if len(extra) == 1 else 'are'} view "
                     f"{_ids_text(extra)}, which has no {owner}")
    if missing:
        parts.append(f"{folder} has no {what} of view {_ids_text(missing)}")
    raise SceneError("; ".join(parts) + f"; name each {what} by its camera's number (e.g. "
                     f"{view_ids[0]:06d}.png), one per camera")


def match_masks(mask_dir: Path | None, image_paths: list[Path], view_ids: list[int],
                partial: bool = False) -> list[Path | None] | None:
    """Mask files for the views, or None when there is no mask folder.

    Masks are matched by the number in their names (`numbered`: IDR's ``mask/007.png`` goes
    with view 7, the image ``image/000007.png``), one per image. With ``partial`` a folder
    that holds the masks of some views only (BlendedMVS' evaluation masks: the input and test
    views) gives None for the others; `svolsdf.scene.loaders.load_scene` then uses masks only
    when every loaded view has one.

    Raises:
        SceneError: a mask's name holds no number, a view has no mask (unless ``partial``) or
            a mask no view.
    """
    if mask_dir is None:
        return None
    masks = numbered(list_images(mask_dir, "masks"))
    if partial and masks and set(masks) <= set(view_ids):
        return [masks.get(v) for v in view_ids]
    img_dir = image_paths[0].parent if image_paths else mask_dir.parent
    return match_numbered(masks, view_ids, mask_dir, "mask", f"image in {img_dir}")


def check_camera(K: Tensor, w2c: Tensor, where: str) -> None:
    """Raise `SceneError` naming ``where`` when a camera is non-finite or degenerate.

    Args:
        K: (3, 3) intrinsics; must be finite with non-zero focal lengths.
        w2c: (4, 4) world-to-camera; must be finite with a rotation block (R R^T = I,
            det R = +1, to 1e-3).
    """
    K = torch.as_tensor(K, dtype=torch.float64)
    w2c = torch.as_tensor(w2c, dtype=torch.float64)
    if not torch.isfinite(K).all():
        raise SceneError(f"{where}: intrinsics have non-finite entries")
    if not torch.isfinite(w2c).all():
        raise SceneError(f"{where}: extrinsics have non-finite entries")
    if abs(float(torch.linalg.det(K))) < 1e-12 or float(K[0, 0]) == 0 or float(K[1, 1]) == 0:
        raise SceneError(f"{where}: intrinsics are singular (focal length 0)")
    R = w2c[:3, :3]
    err = float((R @ R.T - torch.eye(3, dtype=torch.float64)).abs().max())
    if err > 1e-3 or float(torch.linalg.det(R)) < 0:
        raise SceneError(f"{where}: extrinsic rotation is not a rotation (|R R^T - I| = {err:.3g}, "
                         f"det = {float(torch.linalg.det(R)):.3g})")


def scan_number(*names: str) -> int | None:
    """The N of the first ``scanN`` found in ``names`` (folder names), or None."""
    for n in names:
        m = re.fullmatch(r"scan(\d+)", n)
        if m:
            return int(m.group(1))
    return None


def load_txt_matrix(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """Read whitespace-separated numbers into ``shape``; SceneError naming the file otherwise."""
    try:
        a = np.array(path.read_text().split(), dtype=np.float64)
    except (OSError, ValueError) as e:
        raise SceneError(f"{path}: cannot read a {shape[0]}x{shape[1]} matrix ({e})") from None
    if a.size < shape[0] * shape[1]:
        raise SceneError(f"{path}: expected a {shape[0]}x{shape[1]} matrix, found {a.size} numbers")
    return a[: shape[0] * shape[1]].reshape(shape)
