"""What every format reader returns (`SceneSource`) and the checks they share."""

from __future__ import annotations

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
        mask_paths: V mask files, or None.
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
    mask_paths: list[Path] | None = None
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


def list_images(folder: Path) -> list[Path]:
    """Image files in ``folder`` (not recursive), sorted by name; hidden files skipped."""
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
                  and not p.name.startswith("."))


def find_dir(root: Path, *names: str) -> Path | None:
    """The first of ``root/name`` that is a folder, or None."""
    for n in names:
        if (root / n).is_dir():
            return root / n
    return None


def match_masks(mask_dir: Path | None, image_paths: list[Path], view_ids: list[int]
                ) -> list[Path] | None:
    """Mask files for the views, or None when there is no mask folder.

    Masks are matched by sorted order (IDR: ``mask/000.png`` goes with the first image), which
    requires one mask per image.

    Raises:
        SceneError: the counts differ (names both folders).
    """
    if mask_dir is None:
        return None
    masks = list_images(mask_dir)
    if len(masks) != len(image_paths):
        img_dir = image_paths[0].parent if image_paths else mask_dir.parent
        raise SceneError(f"{mask_dir} has {len(masks)} masks but {img_dir} has "
                         f"{len(image_paths)} images; give one mask per image or remove "
                         f"{mask_dir.name}/")
    return masks


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
