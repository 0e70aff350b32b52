"""COLMAP sparse models (``sparse/0`` or ``sparse/``; text ``.txt`` or binary ``.bin``) with
``images/``, read with pycolmap (``pycolmap.Reconstruction``: cameras, images and their poses,
points3D with their tracks; models of COLMAP 3.12 and later, with rigs and frames, and older).

Conventions converted here: COLMAP puts the centre of the top-left pixel at (0.5, 0.5), ours at
(0, 0), so c_ours = c_colmap - 0.5. Distortion parameters are not applied (MVS needs undistorted
images: run ``colmap image_undistorter``); non-zero ones are reported with a warning and
recorded in ``extras["distortion_ignored"]``. Only pinhole models, exact or up to that distortion,
are read (`SUPPORTED_MODELS`); a fisheye, FOV or unknown model, or a camera with the wrong number
of parameters for its model, is refused, naming cameras.txt (or .bin) and the camera.

View ids are positions in name order (0-based); COLMAP's image ids are in
``extras["colmap_image_ids"]``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from svolsdf.scene.formats import register_scene_format
from svolsdf.scene.formats._common import SceneSource, check_camera, find_dir
from svolsdf.scene.scene import SceneError

__all__ = ["SUPPORTED_MODELS", "detect", "find_model", "read", "read_model"]

log = logging.getLogger(__name__)

#: the models read here: a pinhole, exactly or up to lens distortion (ignored with a warning);
#: the fisheye and FOV models project otherwise, and reading them as a pinhole shifts every ray
SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV",
                    "FULL_OPENCV")
_FILES = ("cameras", "images", "points3D")


def _model_problem(cid, model: str, n_params: int | None = None) -> str | None:
    """Why camera ``cid`` of ``model`` (with ``n_params`` parameters, when known) is not read
    here, or None."""
    import pycolmap

    known = model in pycolmap.CameraModelId.__members__ and model != "INVALID"
    if model not in SUPPORTED_MODELS:
        return (f"camera {cid} has model {model} ({'' if known else 'an unknown model, '}not "
                f"read here; supported: {', '.join(SUPPORTED_MODELS)}); undistort the images "
                "to PINHOLE cameras with `colmap image_undistorter`")
    need = len(pycolmap.Camera.create_from_model_name(0, model, 1.0, 1, 1).params)
    if n_params is not None and n_params != need:
        return f"camera {cid} ({model}) has {n_params} parameters, but {model} takes {need}"
    return None


def _text_camera_problem(path: Path) -> str | None:
    """The first camera line of a cameras.txt that pycolmap cannot read or that is not read
    here, in words (for the message naming the file), or None."""
    for ln in path.read_text(errors="replace").splitlines():
        t = ln.split()
        if not t or t[0].startswith("#"):
            continue
        if len(t) < 4:
            return f"camera line {ln.strip()!r} is not CAMERA_ID MODEL WIDTH HEIGHT PARAMS"
        why = _model_problem(t[0], t[1], len(t) - 4)
        if why is not None:
            return why
    return None


def read_model(folder: Path, ext: str):
    """Read a COLMAP model with pycolmap.

    Returns:
        a ``pycolmap.Reconstruction``.

    Raises:
        SceneError: naming the file when a camera is not read here (`SUPPORTED_MODELS`, the
            number of parameters) and the folder when pycolmap cannot read the model.
    """
    import pycolmap

    cams = folder / f"cameras.{ext}"
    rec = pycolmap.Reconstruction()
    try:
        (rec.read_binary if ext == "bin" else rec.read_text)(str(folder))
    except (ValueError, IndexError, RuntimeError, OSError) as e:
        why = _text_camera_problem(cams) if ext == "txt" and cams.is_file() else None
        if why is not None:
            raise SceneError(f"{cams}: {why}") from None
        msg = " ".join(str(e).split())
        raise SceneError(f"{folder}: cannot read COLMAP {ext} model (pycolmap: "
                         f"{type(e).__name__}: {msg})") from None
    for cid, cam in rec.cameras.items():
        why = _model_problem(cid, cam.model.name)
        if why is not None:
            raise SceneError(f"{cams}: {why}")
    return rec


def find_model(path: Path) -> tuple[Path, str] | None:
    """(folder, "bin" or "txt") of the sparse model under ``path``, or None.

    Looks in ``sparse/0``, then ``sparse``; prefers binary files when both exist. A folder with
    some of the model's files is a model too (`read` names the missing ones), so that a missing
    file is not reported as an unknown layout.
    """
    partial = None
    for folder in (path / "sparse" / "0", path / "sparse"):
        for ext in ("bin", "txt"):
            have = [(folder / f"{n}.{ext}").is_file() for n in _FILES]
            if all(have):
                return folder, ext
            if any(have) and partial is None:
                partial = folder, ext
    return partial


def _missing_files(folder: Path, ext: str) -> list[str]:
    return [f"{n}.{ext}" for n in _FILES if not (folder / f"{n}.{ext}").is_file()]


def detect(path: Path) -> bool:
    """True when a sparse model and ``images/`` exist."""
    return find_model(path) is not None and (path / "images").is_dir()


@register_scene_format("colmap", detect, order=40,
                       looks_for=("sparse/0/ or sparse/ with cameras, images, points3D (.txt "
                                  "or .bin) and images/ (COLMAP)"),
                       title="COLMAP sparse model")
def read(path: Path, lighting=None) -> SceneSource:
    """Read cameras, poses and sparse points (no pixels)."""
    folder, ext = find_model(path)
    missing = _missing_files(folder, ext)
    if missing:
        have = [f"{n}.{ext}" for n in _FILES if f"{n}.{ext}" not in missing]
        need = ", ".join(f"{n}.{ext}" for n in _FILES)
        raise SceneError(f"{folder}/{missing[0]} is missing (the COLMAP model there has "
                         f"{' and '.join(have)}; a model needs {need})")
    rec = read_model(folder, ext)
    img_dir = find_dir(path, "images")
    order = sorted((im for im in rec.images.values() if im.has_pose),
                   key=lambda im: im.name)
    if not order:
        raise SceneError(f"{folder}/images.{ext} has no registered images")
    cams = rec.cameras
    sizes = {(cams[im.camera_id].width, cams[im.camera_id].height) for im in order
             if im.camera_id in cams}
    Ks, w2cs, paths, sources = [], [], [], []
    ignored = {}
    for im in order:
        where = f"{folder}/images.{ext}: image {im.image_id} ({im.name})"
        cam = cams[im.camera_id] if im.camera_id in cams else None
        if cam is None:
            raise SceneError(f"{where} uses camera {im.camera_id}, which is not in "
                             f"{folder}/cameras.{ext}")
        K = np.array([[cam.focal_length_x, 0, cam.principal_point_x - 0.5],
                      [0, cam.focal_length_y, cam.principal_point_y - 0.5], [0, 0, 1]])
        dist = np.asarray(cam.params)[list(cam.extra_params_idxs())]
        if dist.size and np.abs(dist).max() > 0:
            ignored[im.camera_id] = (cam.model.name, dist.tolist())
        w2c = np.eye(4)
        w2c[:3, :4] = im.cam_from_world().matrix()
        check_camera(torch.from_numpy(K), torch.from_numpy(w2c), where)
        p = img_dir / im.name
        if not p.is_file():
            raise SceneError(f"{where}: image file {p} does not exist")
        Ks.append(torch.from_numpy(K))
        w2cs.append(torch.from_numpy(w2c))
        paths.append(p)
        sources.append(where)
    for cid, (model, d) in ignored.items():
        log.warning("%s/cameras.%s: camera %d (%s) has distortion %s, which is ignored; "
                    "undistort with `colmap image_undistorter` for accurate results",
                    folder, ext, cid, model, [round(x, 6) for x in d])
    if len(sizes) > 1:
        raise SceneError(f"{folder}/cameras.{ext}: cameras have different image sizes "
                         f"({', '.join(f'{w}x{h}' for w, h in sorted(sizes))}); all views "
                         f"must share one size")
    col = {im.image_id: k for k, im in enumerate(order)}
    points = [p for _, p in sorted(rec.points3D.items())]  # in id order, as the file
    pts = np.array([p.xyz for p in points], np.float64).reshape(-1, 3)
    vis = torch.zeros(len(pts), len(order), dtype=torch.bool)
    for k, p in enumerate(points):
        js = [col[el.image_id] for el in p.track.elements if el.image_id in col]
        vis[k, js] = True
    extras: dict = {"cameras_file": f"{folder}/cameras.{ext}", "colmap_model": str(folder),
                    "colmap_image_ids": [im.image_id for im in order], "num_points": len(pts)}
    if ignored:
        extras["distortion_ignored"] = {cid: m for cid, (m, _) in ignored.items()}
    return SceneSource(
        format="colmap", path=path, view_ids=list(range(len(order))), image_paths=paths,
        K=torch.stack(Ks), w2c=torch.stack(w2cs), camera_source=sources,
        cameras_file=f"{folder}/images.{ext}", camera_size=sizes.pop(),
        points=torch.from_numpy(pts) if len(pts) else None,
        visibility=vis if len(pts) else None, extras=extras,
    )
