"""NeRF-style ``transforms.json`` (Blender synthetic, instant-ngp, nerfstudio).

Intrinsics: ``fl_x``/``fl_y``/``cx``/``cy``/``w``/``h`` (top level or per frame), or
``camera_angle_x`` (and optionally ``camera_angle_y``) with the image size, fx = W / (2 tan(a/2)).
These tools place pixel centres at +0.5, so c_ours = c - 0.5 (default c = W/2, H/2).
``transform_matrix`` is camera-to-world in OpenGL axes (x right, y up, z backwards); OpenCV axes
follow by flipping the camera's y and z axes: c2w_cv = c2w_gl @ diag(1, -1, -1, 1).
``file_path`` is relative to the json file; a missing extension is tried as .png then .jpg.
RGBA images are composited onto white (NeRF's convention) and their alpha becomes the mask.
View ids are the frames' positions in the file.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import torch

from svolsdf.io.images import ImageReadError, image_size
from svolsdf.scene.formats import register_scene_format
from svolsdf.scene.formats._common import SceneSource, check_camera
from svolsdf.scene.scene import SceneError

__all__ = ["FILES", "detect", "read"]

log = logging.getLogger(__name__)

FILES = ("transforms.json", "transforms_train.json")
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def detect(path: Path) -> bool:
    """True when ``transforms.json`` (or ``transforms_train.json``) exists."""
    return any((path / f).is_file() for f in FILES)


def _image_file(base: Path, file_path: str) -> Path:
    p = base / file_path
    if p.suffix == "" or not p.exists():
        for suf in (".png", ".jpg", ".jpeg"):
            q = p.with_name(p.name + suf)
            if q.is_file():
                return q
    return p


def _focal(g: dict, key: str, side: int, where: str) -> float:
    """The focal length in pixels of the field of view ``g[key]`` (radians) across ``side``
    pixels, f = side / (2 tan(a/2)); `SceneError` unless 0 < a < pi."""
    a = float(g[key])
    if not 0.0 < a < math.pi:
        raise SceneError(f"{where}: {key} is {g[key]!r}; a field of view in radians must be "
                         f"between 0 and pi (e.g. 0.69 for 40 degrees)")
    return 0.5 * side / math.tan(0.5 * a)


@register_scene_format("nerf", detect, order=50,
                       looks_for="transforms.json (NeRF)",
                       title="NeRF transforms.json")
def read(path: Path, lighting=None) -> SceneSource:
    """Read the frames' cameras (no pixels)."""
    f = next(path / n for n in FILES if (path / n).is_file())
    try:
        meta = json.loads(f.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise SceneError(f"{f}: cannot parse JSON ({e})") from None
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not frames or not isinstance(frames, list):
        raise SceneError(f"{f}: no 'frames' list")
    Ks, w2cs, paths, sources, masks, sizes = [], [], [], [], [], set()
    for k, fr in enumerate(frames):
        where = f"{f}: frames[{k}]"
        if not isinstance(fr, dict):
            raise SceneError(f"{where} is {json.dumps(fr)[:40]}, not an object with "
                             "'file_path' and 'transform_matrix'")
        g = {**meta, **fr}
        if "file_path" not in fr or "transform_matrix" not in fr:
            raise SceneError(f"{where} lacks 'file_path' or 'transform_matrix'")
        img = _image_file(f.parent, str(fr["file_path"]))
        if not img.is_file():
            raise SceneError(f"{where}: image file {img} does not exist")
        w, h = g.get("w"), g.get("h")
        if w is None or h is None:
            try:
                w, h = image_size(img)
            except ImageReadError as e:
                raise SceneError(str(e)) from None
        try:
            w, h = int(w), int(h)
        except (TypeError, ValueError):
            raise SceneError(f"{where}: image size w={w!r}, h={h!r} is not two integers") from None
        sizes.add((w, h))
        try:
            if "fl_x" in g:
                fx = float(g["fl_x"])
                fy = float(g.get("fl_y", fx))
            elif "camera_angle_x" in g:
                fx = _focal(g, "camera_angle_x", w, where)
                fy = _focal(g, "camera_angle_y", h, where) if "camera_angle_y" in g else fx
            else:
                raise SceneError(f"{where}: no intrinsics (need fl_x or camera_angle_x)")
            cx = float(g.get("cx", w / 2.0)) - 0.5
            cy = float(g.get("cy", h / 2.0)) - 0.5
            c2w = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise SceneError(f"{where}: malformed camera ({e})") from None
        if c2w.shape == (3, 4):
            c2w = np.vstack([c2w, [0, 0, 0, 1]])
        if c2w.shape != (4, 4):
            raise SceneError(f"{where}: transform_matrix has shape {c2w.shape}, expected 4x4")
        if not np.isfinite(c2w).all():
            raise SceneError(f"{where}: transform_matrix has non-finite entries")
        if abs(np.linalg.det(c2w[:3, :3])) < 1e-9:
            raise SceneError(f"{where}: transform_matrix is singular")
        dist = [float(g.get(n, 0.0)) for n in ("k1", "k2", "k3", "k4", "p1", "p2")]
        if any(dist):
            log.warning("%s: distortion %s is ignored", where, dist)
        w2c = np.linalg.inv(c2w @ _GL_TO_CV)
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
        check_camera(torch.from_numpy(K), torch.from_numpy(w2c), where)
        Ks.append(torch.from_numpy(K))
        w2cs.append(torch.from_numpy(w2c))
        paths.append(img)
        sources.append(where)
        if "mask_path" in fr:
            masks.append(_image_file(f.parent, str(fr["mask_path"])))
    if len(sizes) > 1:
        raise SceneError(f"{f}: frames have different image sizes "
                         f"({', '.join(f'{a}x{b}' for a, b in sorted(sizes))})")
    if masks and len(masks) != len(frames):
        raise SceneError(f"{f}: {len(masks)} frames have a mask_path but {len(frames)} frames "
                         "exist; give every frame a mask or none")
    return SceneSource(
        format="nerf", path=path, view_ids=list(range(len(frames))), image_paths=paths,
        K=torch.stack(Ks), w2c=torch.stack(w2cs), camera_source=sources, cameras_file=str(f),
        camera_size=sizes.pop(), mask_paths=masks or None, masks_from_alpha=not masks,
        background=1.0,
        extras={"cameras_file": str(f)},
    )
