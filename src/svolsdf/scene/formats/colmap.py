"""COLMAP sparse models (``sparse/0`` or ``sparse/``; text ``.txt`` or binary ``.bin``) with
``images/``.

A small reader of COLMAP's documented model formats (colmap.github.io/format.html):
``cameras`` (id, model, width, height, params), ``images`` (id, quaternion qw qx qy qz and
translation of world-to-camera, camera id, name, 2D points) and ``points3D`` (id, xyz, rgb,
error, track of (image id, 2D point index)).

Conventions converted here: COLMAP puts the centre of the top-left pixel at (0.5, 0.5), ours at
(0, 0), so c_ours = c_colmap - 0.5. Distortion parameters are not applied (MVS needs undistorted
images: run ``colmap image_undistorter``); non-zero ones are reported with a warning and
recorded in ``extras["distortion_ignored"]``. Only pinhole models, exact or up to that distortion,
are read (`SUPPORTED_MODELS`); a fisheye, FOV or unknown model, or a camera with the wrong number
of parameters for its model, is refused.

View ids are positions in name order (0-based); COLMAP's image ids are in
``extras["colmap_image_ids"]``.
"""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from svolsdf.scene.formats import register_scene_format
from svolsdf.scene.formats._common import SceneSource, check_camera, find_dir
from svolsdf.scene.scene import SceneError

__all__ = [
    "CAMERA_MODELS",
    "SUPPORTED_MODELS",
    "ColmapCamera",
    "ColmapImage",
    "detect",
    "find_model",
    "qvec_to_rotmat",
    "read",
    "read_model",
    "rotmat_to_qvec",
]

log = logging.getLogger(__name__)

# model id -> (name, number of params); COLMAP's src/colmap/sensor/models.h
CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
}
_MODEL_BY_NAME = {name: (mid, n) for mid, (name, n) in CAMERA_MODELS.items()}
#: the models read here: a pinhole, exactly or up to lens distortion (ignored with a warning);
#: the fisheye and FOV models project otherwise, and reading them as a pinhole shifts every ray
SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV",
                    "FULL_OPENCV")
_FILES = ("cameras", "images", "points3D")


@dataclass
class ColmapCamera:
    """One COLMAP camera: ``params`` in COLMAP's order for ``model``."""

    id: int
    model: str
    width: int
    height: int
    params: np.ndarray

    def intrinsics(self) -> tuple[np.ndarray, np.ndarray]:
        """(K (3, 3) in our integer-pixel-centre convention, distortion parameters)."""
        p = self.params
        if self.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE",
                          "RADIAL_FISHEYE"):
            fx = fy = p[0]
            cx, cy = p[1], p[2]
            dist = p[3:]
        elif self.model in SUPPORTED_MODELS:  # PINHOLE, OPENCV, FULL_OPENCV
            fx, fy, cx, cy = p[:4]
            dist = p[4:]
        else:
            raise ValueError(f"camera {self.id} has model {self.model}, which is not read here "
                             f"(supported: {', '.join(SUPPORTED_MODELS)}); undistort the "
                             "images to PINHOLE cameras with `colmap image_undistorter`")
        K = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1]], dtype=np.float64)
        return K, np.asarray(dist, dtype=np.float64)


@dataclass
class ColmapImage:
    """One registered image: world-to-camera rotation as quaternion (w, x, y, z) and t."""

    id: int
    qvec: np.ndarray
    tvec: np.ndarray
    camera_id: int
    name: str


def qvec_to_rotmat(q: np.ndarray) -> np.ndarray:
    """(4,) quaternion (w, x, y, z), normalised inside -> (3, 3) rotation."""
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError(f"quaternion {q.tolist()} has zero or non-finite norm")
    w, x, y, z = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (4,) unit quaternion (w, x, y, z) with w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    K = np.array([
        [R[0, 0] - R[1, 1] - R[2, 2], 0, 0, 0],
        [R[1, 0] + R[0, 1], R[1, 1] - R[0, 0] - R[2, 2], 0, 0],
        [R[2, 0] + R[0, 2], R[2, 1] + R[1, 2], R[2, 2] - R[0, 0] - R[1, 1], 0],
        [R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], R[0, 0] + R[1, 1] + R[2, 2]],
    ]) / 3.0
    w, v = np.linalg.eigh(K)
    q = v[[3, 0, 1, 2], np.argmax(w)]
    return -q if q[0] < 0 else q


# --------------------------------------------------------------------------- text
def _check_model(where: Path, cid, model: str, n_params: int) -> None:
    """Refuse (`SceneError` naming the file ``where``) a camera whose model is not read here or
    whose number of parameters is not its model's."""
    if model not in SUPPORTED_MODELS:
        known = "" if model in _MODEL_BY_NAME else "an unknown model, "
        raise SceneError(f"{where}: camera {cid} has model {model} ({known}not read here; "
                         f"supported: {', '.join(SUPPORTED_MODELS)}); undistort the images to "
                         "PINHOLE cameras with `colmap image_undistorter`")
    need = _MODEL_BY_NAME[model][1]
    if n_params != need:
        raise SceneError(f"{where}: camera {cid} ({model}) has {n_params} parameters, but "
                         f"{model} takes {need}")


def _data_lines(path: Path) -> list[str]:
    return [ln.strip() for ln in path.read_text().splitlines()
            if ln.strip() and not ln.lstrip().startswith("#")]


def _read_text(folder: Path):
    cams: dict[int, ColmapCamera] = {}
    f = folder / "cameras.txt"
    for ln in _data_lines(f):
        t = ln.split()
        if len(t) < 4:
            raise ValueError(f"camera line {ln!r} is not CAMERA_ID MODEL WIDTH HEIGHT PARAMS")
        _check_model(f, t[0], t[1], len(t) - 4)
        cams[int(t[0])] = ColmapCamera(int(t[0]), t[1], int(t[2]), int(t[3]),
                                       np.array(t[4:], dtype=np.float64))
    imgs: dict[int, ColmapImage] = {}
    f = folder / "images.txt"
    # An image takes two lines; the second (2D points) may be empty, so parse raw lines.
    raw = [ln for ln in f.read_text().splitlines() if not ln.lstrip().startswith("#")]
    i = 0
    while i < len(raw):
        t = raw[i].split()
        if not t:
            i += 1
            continue
        imgs[int(t[0])] = ColmapImage(int(t[0]), np.array(t[1:5], dtype=np.float64),
                                      np.array(t[5:8], dtype=np.float64), int(t[8]),
                                      " ".join(t[9:]))
        i += 2
    pts, tracks = [], []
    f = folder / "points3D.txt"
    for ln in _data_lines(f):
        t = ln.split()
        pts.append([float(t[1]), float(t[2]), float(t[3])])
        tracks.append(np.array(t[8::2], dtype=np.int64))
    return cams, imgs, np.array(pts, dtype=np.float64).reshape(-1, 3), tracks


# --------------------------------------------------------------------------- binary
class _Reader:
    def __init__(self, data: bytes):
        self.b = data
        self.o = 0

    def take(self, fmt: str):
        v = struct.unpack_from("<" + fmt, self.b, self.o)
        self.o += struct.calcsize("<" + fmt)
        return v

    def array(self, dtype, count: int) -> np.ndarray:
        a = np.frombuffer(self.b, dtype=dtype, count=count, offset=self.o)
        self.o += a.nbytes
        return a

    def cstring(self) -> str:
        end = self.b.index(b"\x00", self.o)
        s = self.b[self.o:end].decode("utf-8")
        self.o = end + 1
        return s


def _read_binary(folder: Path):
    cams: dict[int, ColmapCamera] = {}
    r = _Reader((folder / "cameras.bin").read_bytes())
    for _ in range(r.take("Q")[0]):
        cid, mid, w, h = r.take("iiQQ")
        name, n = CAMERA_MODELS.get(mid, (f"id {mid}", 0))
        _check_model(folder / "cameras.bin", cid, name, n)
        cams[cid] = ColmapCamera(cid, name, w, h, np.array(r.take("d" * n)))
    imgs: dict[int, ColmapImage] = {}
    r = _Reader((folder / "images.bin").read_bytes())
    for _ in range(r.take("Q")[0]):
        vals = r.take("i7di")
        name = r.cstring()
        n2d = r.take("Q")[0]
        r.o += n2d * 24  # (x, y double; point3D_id int64): not needed here
        imgs[vals[0]] = ColmapImage(vals[0], np.array(vals[1:5]), np.array(vals[5:8]), vals[8],
                                    name)
    r = _Reader((folder / "points3D.bin").read_bytes())
    n = r.take("Q")[0]
    pts = np.zeros((n, 3))
    tracks = []
    for k in range(n):
        vals = r.take("Q3d3BdQ")
        pts[k] = vals[1:4]
        tl = vals[-1]
        tracks.append(r.array(np.int32, 2 * tl)[0::2].astype(np.int64))
    return cams, imgs, pts, tracks


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


def read_model(folder: Path, ext: str):
    """Read a COLMAP model.

    Returns:
        cameras: id -> `ColmapCamera`; images: id -> `ColmapImage`; points (N, 3) float64;
        tracks: N int64 arrays of the image ids observing each point.

    Raises:
        SceneError: naming the folder when a file is truncated or malformed.
    """
    try:
        return _read_binary(folder) if ext == "bin" else _read_text(folder)
    except SceneError:
        raise
    except (OSError, ValueError, IndexError, struct.error, UnicodeDecodeError) as e:
        raise SceneError(f"{folder}: cannot read COLMAP {ext} model "
                         f"({e.__class__.__name__}: {e})") from None


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
    cams, imgs, pts, tracks = read_model(folder, ext)
    img_dir = find_dir(path, "images")
    order = sorted(imgs.values(), key=lambda im: im.name)
    if not order:
        raise SceneError(f"{folder}/images.{ext} has no registered images")
    sizes = {(c.width, c.height) for c in (cams.get(im.camera_id) for im in order) if c}
    Ks, w2cs, paths, sources = [], [], [], []
    ignored = {}
    for im in order:
        where = f"{folder}/images.{ext}: image {im.id} ({im.name})"
        cam = cams.get(im.camera_id)
        if cam is None:
            raise SceneError(f"{where} uses camera {im.camera_id}, which is not in "
                             f"{folder}/cameras.{ext}")
        K, dist = cam.intrinsics()
        if dist.size and np.abs(dist).max() > 0:
            ignored[cam.id] = (cam.model, dist.tolist())
        try:
            R = qvec_to_rotmat(im.qvec)
        except ValueError as e:
            raise SceneError(f"{where}: {e}") from None
        w2c = np.eye(4)
        w2c[:3, :3] = R
        w2c[:3, 3] = im.tvec
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
    col = {im.id: k for k, im in enumerate(order)}
    vis = torch.zeros(len(pts), len(order), dtype=torch.bool)
    for k, tr in enumerate(tracks):
        js = [col[i] for i in tr.tolist() if i in col]
        vis[k, js] = True
    extras: dict = {"cameras_file": f"{folder}/cameras.{ext}", "colmap_model": str(folder),
                    "colmap_image_ids": [im.id for im in order], "num_points": len(pts)}
    if ignored:
        extras["distortion_ignored"] = {cid: m for cid, (m, _) in ignored.items()}
    return SceneSource(
        format="colmap", path=path, view_ids=list(range(len(order))), image_paths=paths,
        K=torch.stack(Ks), w2c=torch.stack(w2cs), camera_source=sources,
        cameras_file=f"{folder}/images.{ext}", camera_size=sizes.pop(),
        points=torch.from_numpy(pts) if len(pts) else None,
        visibility=vis if len(pts) else None, extras=extras,
    )
