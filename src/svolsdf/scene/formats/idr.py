"""IDR / VolSDF / NeuS layout (docs/method.md 1.1-1.2).

``cameras.npz`` (IDR, VolSDF) or ``cameras_sphere.npz`` (NeuS) with ``world_mat_i`` (the top
3x4 is P = K [R | t] in world units) and ``scale_mat_i`` (unit frame -> world); images in
``image/`` or ``images/``, numbered by their camera (``000007.png`` is view 7, whose camera is
``world_mat_7``); optional masks in ``mask/``, numbered alike (``007.png``). One image (and mask)
per camera: a gap or an extra file is refused, never matched by position.
"""

from __future__ import annotations

import logging
import zipfile
from pathlib import Path

import numpy as np
import torch

from svolsdf.scene.cameras import decompose_projection
from svolsdf.scene.formats import register_scene_format
from svolsdf.scene.formats._common import (
    SceneSource,
    check_camera,
    find_dir,
    list_images,
    match_masks,
    match_numbered,
    numbered,
    scan_number,
)
from svolsdf.scene.pairs import read_pair_file
from svolsdf.scene.scene import Normalization, SceneError

__all__ = ["CAMERA_FILES", "detect", "read"]

log = logging.getLogger(__name__)

CAMERA_FILES = ("cameras.npz", "cameras_sphere.npz")


def _matrix(value: np.ndarray, cam_file: Path, key: str) -> np.ndarray:
    """``cam_file``'s entry ``key`` as a float64 array; `SceneError` naming both when it is not
    numbers (a string, an object)."""
    if value.dtype.kind not in "biuf":
        raise SceneError(f"{cam_file}: {key} is stored as {value.dtype} ({value.dtype.kind!r} "
                         f"data), not as numbers; save it as a 4x4 float array")
    return np.asarray(value, dtype=np.float64)


def detect(path: Path) -> bool:
    """True when ``path`` holds a camera file and an image folder of this layout."""
    return any((path / f).is_file() for f in CAMERA_FILES) and find_dir(
        path, "image", "images") is not None


@register_scene_format("idr", detect, order=10,
                       looks_for=("cameras.npz or cameras_sphere.npz with image/ or images/ "
                                  "(IDR/VolSDF/NeuS)"),
                       title="IDR / VolSDF / NeuS (world_mat + scale_mat)")
def read(path: Path, lighting=None) -> SceneSource:
    """Read the layout's cameras and file lists (no pixels). See the module docstring.

    The normalization comes from ``scale_mat_0``; its sphere radius is 3 for ``cameras.npz``
    (IDR / VolSDF convention: region of interest inside radius 3) and 1 for
    ``cameras_sphere.npz`` (NeuS convention: the object inside the unit sphere).
    """
    cam_file = next(path / f for f in CAMERA_FILES if (path / f).is_file())
    try:
        data = dict(np.load(cam_file))
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise SceneError(f"{cam_file}: cannot read camera file ({e})") from None
    idx = sorted(int(k[len("world_mat_"):]) for k in data
                 if k.startswith("world_mat_") and k[len("world_mat_"):].isdigit())
    if not idx:
        found = ", ".join(sorted(data)[:6])
        raise SceneError(f"{cam_file}: no world_mat_<i> keys (found: {found})")
    if idx != list(range(len(idx))):
        missing = sorted(set(range(idx[-1] + 1)) - set(idx))
        raise SceneError(f"{cam_file}: world_mat keys are not 0..{len(idx) - 1} "
                         f"(missing world_mat_{missing[0]})")
    n = len(idx)
    img_dir = find_dir(path, "image", "images")
    images = match_numbered(numbered(list_images(img_dir)), list(range(n)), img_dir, "image",
                            f"camera in {cam_file} (world_mat_0..world_mat_{n - 1})")
    masks = match_masks(find_dir(path, "mask", "masks"), images, list(range(n)))

    Ks, w2cs = [], []
    for i in range(n):
        key = f"world_mat_{i}"
        P = _matrix(data[key], cam_file, key)
        if P.shape not in ((3, 4), (4, 4)):
            raise SceneError(f"{cam_file}: {key} has shape {P.shape}, expected 4x4 or 3x4")
        try:
            K, w2c = decompose_projection(torch.from_numpy(P))
        except ValueError as e:
            raise SceneError(f"{cam_file}: {key}: {e}") from None
        check_camera(K, w2c, f"{cam_file}: {key}")
        Ks.append(K)
        w2cs.append(w2c)

    normalization = None
    radius = 1.0 if cam_file.name == "cameras_sphere.npz" else 3.0
    if "scale_mat_0" in data:
        S = _matrix(data["scale_mat_0"], cam_file, "scale_mat_0")
        if S.shape != (4, 4) or not np.isfinite(S).all() or not S[0, 0] > 0:
            raise SceneError(f"{cam_file}: scale_mat_0 is not a finite 4x4 similarity with "
                             f"positive scale")
        others = [k for k in data if k.startswith("scale_mat_") and k[10:].isdigit()]
        if any(not np.allclose(data[k], S) for k in others):
            log.warning("%s: scale_mat_i differ between views; using scale_mat_0 (as S-VolSDF "
                        "does)", cam_file)
        normalization = Normalization(center=torch.from_numpy(S[:3, 3].copy()),
                                      scale=float(S[0, 0]), radius=radius)

    pairs = scores = None
    pair_file = next((p for p in (path / "pair.txt", path / "cams" / "pair.txt") if p.is_file()),
                     None)
    if pair_file is not None:
        pairs, scores = read_pair_file(pair_file)

    extras = {"cameras_file": str(cam_file)}
    scan = scan_number(path.name)
    if scan is not None:
        extras["scan"] = scan
    if pair_file is not None:
        extras["pair_file"] = str(pair_file)
    return SceneSource(
        format="idr", path=path, view_ids=list(range(n)), image_paths=images,
        K=torch.stack(Ks), w2c=torch.stack(w2cs),
        camera_source=[f"{cam_file}: world_mat_{i}" for i in range(n)],
        cameras_file=str(cam_file), mask_paths=masks, pairs=pairs, pair_scores=scores,
        normalization=normalization, extras=extras,
    )
