"""MVSNet / BlendedMVS layout (docs/method.md 1.1).

``cams/{id:08d}_cam.txt``: ``extrinsic`` then the 4x4 world-to-camera matrix, ``intrinsic`` then
K (3x3), then ``depth_min depth_interval [num_depth [depth_max]]``; images in ``images/`` or
``blended_images/`` named ``{id:08d}.*`` (BlendedMVS' ``*_masked.*`` files are skipped);
``cams/pair.txt`` for the source views.

Depth range: max = depth_max when given, otherwise depth_min + interval * (num_depth or 192).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch

from svolsdf.scene.formats import register_scene_format
from svolsdf.scene.formats._common import (
    SceneSource,
    check_camera,
    find_dir,
    list_images,
    match_masks,
    scan_number,
)
from svolsdf.scene.pairs import read_pair_file
from svolsdf.scene.scene import SceneError

__all__ = ["detect", "read", "read_cam_file", "write_cam_file"]

_CAM = re.compile(r"(\d+)_cam\.txt")


def detect(path: Path) -> bool:
    """True when ``cams/*_cam.txt`` and an image folder exist."""
    cams = path / "cams"
    return (cams.is_dir() and any(_CAM.fullmatch(p.name) for p in cams.iterdir())
            and find_dir(path, "images", "blended_images") is not None)


def read_cam_file(path: Path) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    """Parse one ``*_cam.txt``.

    Returns:
        w2c (4, 4), K (3, 3) float64, and (depth_min, depth_max) from the depth line (module
        docstring).

    Raises:
        SceneError: naming the file when a block is missing or malformed.
    """
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise SceneError(f"{path}: cannot read camera file ({e})") from None
    tok = text.split()
    low = [t.lower() for t in tok]
    try:
        e0 = low.index("extrinsic") + 1
        i0 = low.index("intrinsic") + 1
        w2c = np.array(tok[e0:e0 + 16], dtype=np.float64).reshape(4, 4)
        K = np.array(tok[i0:i0 + 9], dtype=np.float64).reshape(3, 3)
        depth = [float(t) for t in tok[i0 + 9:i0 + 13]]
    except ValueError as e:
        raise SceneError(f"{path}: malformed camera file, expected 'extrinsic' + 4x4, "
                         f"'intrinsic' + 3x3, then 'depth_min interval [num max]' ({e})") from None
    if len(depth) < 2:
        raise SceneError(f"{path}: missing the depth line 'depth_min interval [num max]'")
    dmin, interval = depth[0], depth[1]
    if len(depth) >= 4:
        dmax = depth[3]
    else:
        num = depth[2] if len(depth) >= 3 else 192
        dmax = dmin + interval * num
    if not (np.isfinite(dmin) and np.isfinite(dmax) and dmax > dmin):
        raise SceneError(f"{path}: depth line gives an empty range [{dmin}, {dmax}]")
    return w2c, K, (dmin, dmax)


def write_cam_file(path: Path, w2c: np.ndarray, K: np.ndarray, depth_min: float,
                   interval: float, num: int | None = None, depth_max: float | None = None
                   ) -> Path:
    """Write an MVSNet ``*_cam.txt`` (the inverse of `read_cam_file`)."""
    w2c = np.asarray(w2c, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    lines = ["extrinsic"] + [" ".join(f"{v:.10g}" for v in row) for row in w2c] + [""]
    lines += ["intrinsic"] + [" ".join(f"{v:.10g}" for v in row) for row in K] + [""]
    depth = [depth_min, interval] + ([num] if num is not None else [])
    if depth_max is not None:
        depth = [depth_min, interval, num if num is not None else 192, depth_max]
    lines.append(" ".join(f"{v:.10g}" for v in depth))
    Path(path).write_text("\n".join(lines) + "\n")
    return Path(path)


@register_scene_format("mvsnet", detect, order=30,
                       looks_for=("cams/*_cam.txt with images/ or blended_images/ "
                                  "(MVSNet/BlendedMVS)"),
                       title="MVSNet / BlendedMVS (cams/*_cam.txt)")
def read(path: Path, lighting=None) -> SceneSource:
    """Read the layout's cameras, depth ranges and pairs (no pixels)."""
    cams_dir = path / "cams"
    cams = sorted((int(m.group(1)), p) for p in cams_dir.iterdir()
                  if (m := _CAM.fullmatch(p.name)))
    img_dir = find_dir(path, "images", "blended_images")
    files = [p for p in list_images(img_dir) if not p.stem.endswith("_masked")]
    by_id: dict[int, Path] = {}
    for p in files:
        if p.stem.isdigit():
            by_id.setdefault(int(p.stem), p)
    if len(files) != len(cams):
        raise SceneError(f"{cams_dir} has {len(cams)} cameras but {img_dir} has {len(files)} "
                         f"images")
    ids, images, Ks, w2cs, ranges = [], [], [], [], []
    for vid, f in cams:
        if vid not in by_id:
            raise SceneError(f"{f} has no image {vid:08d}.* in {img_dir}")
        w2c, K, rng = read_cam_file(f)
        check_camera(torch.from_numpy(K), torch.from_numpy(w2c), str(f))
        ids.append(vid)
        images.append(by_id[vid])
        Ks.append(torch.from_numpy(K))
        w2cs.append(torch.from_numpy(w2c))
        ranges.append(rng)
    pairs = scores = None
    pair_file = next((p for p in (cams_dir / "pair.txt", path / "pair.txt") if p.is_file()), None)
    extras: dict = {"cameras_file": str(cams_dir)}
    if pair_file is not None:
        pairs, scores = read_pair_file(pair_file)
        extras["pair_file"] = str(pair_file)
    scan = scan_number(path.name)
    if scan is not None:
        extras["scan"] = scan
    # BlendedMVS' evaluation masks cover the input and test views only (docs/method.md 8.2)
    masks = match_masks(find_dir(path, "mask", "masks"), images, ids, partial=True)
    return SceneSource(
        format="mvsnet", path=path, view_ids=ids, image_paths=images, K=torch.stack(Ks),
        w2c=torch.stack(w2cs), camera_source=[str(f) for _, f in cams],
        cameras_file=str(cams_dir), mask_paths=masks, pairs=pairs, pair_scores=scores,
        depth_range=torch.tensor(ranges, dtype=torch.float64), extras=extras,
    )
