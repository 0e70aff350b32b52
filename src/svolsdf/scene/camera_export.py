"""Cameras in the formats other tools read: nerfstudio's transforms.json, a COLMAP model
(written with pycolmap) and a plain JSON of K, R, t per view.

Our conventions (`svolsdf.scene.cameras`: OpenCV axes, world-to-camera extrinsics, the centre of
the top-left pixel at (0, 0)) are converted here, once:

- nerfstudio: ``transform_matrix`` is camera-to-world with OpenGL axes (x right, y up, z back),
  c2w_gl = c2w_cv @ diag(1, -1, -1, 1); its pixel centres sit at +0.5 (as COLMAP's), so
  c_ns = c_ours + 0.5. The world frame is the scene's (no ``applied_transform``).
- COLMAP: cam_from_world is our world-to-camera; c_colmap = c_ours + 0.5 (the reader in
  `svolsdf.scene.formats.colmap` subtracts it again).

Skew (a non-zero K[0, 1], as DTU's decomposed projections have) has no place in either format
and is dropped from them; the plain JSON keeps K whole.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from svolsdf.scene.cameras import Cameras

__all__ = ["CONVENTION", "OPENGL_FROM_OPENCV", "camera_json", "colmap_reconstruction",
           "nerfstudio_transforms"]

OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right-multiplying a camera-to-world matrix of OpenCV axes by this gives OpenGL axes."""

CONVENTION = ("OpenCV camera axes (x right, y down, z forward); x_cam = R x_world + t; K in "
              "pixels with the centre of the top-left pixel at (0, 0) (add 0.5 to cx, cy for "
              "COLMAP's and nerfstudio's convention); depth is z in world units")
"""The conventions of `camera_json`, written into the file."""


def _arrays(cameras: Cameras) -> tuple[np.ndarray, np.ndarray]:
    K = cameras.K.detach().double().cpu().numpy()
    w2c = cameras.w2c.detach().double().cpu().numpy()
    return K, w2c


def _check_names(cameras: Cameras, names: Sequence[str], what: str) -> None:
    if len(names) != len(cameras):
        raise ValueError(f"{what}: {len(names)} names for {len(cameras)} cameras")


def nerfstudio_transforms(cameras: Cameras, files: Sequence[str],
                          points_file: str | None = None) -> dict:
    """nerfstudio's transforms.json of ``cameras``.

    Args:
        cameras: V world cameras at the size of the image files.
        files: V image paths relative to the transforms.json (``images/0001.png``).
        points_file: a PLY of points with colours beside it (nerfstudio's ``ply_file_path``,
            which splatfacto starts from), or None.

    Returns:
        {"camera_model": "OPENCV", "w", "h", and "fl_x", "fl_y", "cx", "cy" when every view
        shares them, "frames": [{"file_path", "transform_matrix" (4x4 camera-to-world, OpenGL
        axes), "fl_x", "fl_y", "cx", "cy", "w", "h"}]} (zero distortion).
    """
    _check_names(cameras, files, "files")
    K, w2c = _arrays(cameras)
    frames = []
    for k, f in zip(K, w2c, strict=True):
        c2w = np.linalg.inv(f) @ OPENGL_FROM_OPENCV
        frames.append({"file_path": str(files[len(frames)]),
                       "transform_matrix": c2w.tolist(),
                       **_intrinsics(k, cameras.width, cameras.height)})
    out = {"camera_model": "OPENCV", "w": cameras.width, "h": cameras.height,
           "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0}
    shared = {key: frames[0][key] for key in ("fl_x", "fl_y", "cx", "cy")}
    if all(all(fr[key] == v for key, v in shared.items()) for fr in frames):
        out.update(shared)
    if points_file is not None:
        out["ply_file_path"] = points_file
    out["frames"] = frames
    return out


def _intrinsics(K: np.ndarray, width: int, height: int) -> dict:
    """fl_x, fl_y, cx, cy (pixel centres at +0.5), w, h of one (3, 3) K."""
    return {"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]) + 0.5,
            "cy": float(K[1, 2]) + 0.5, "w": int(width), "h": int(height)}


def colmap_reconstruction(cameras: Cameras, names: Sequence[str],
                          points: np.ndarray | None = None, colours: np.ndarray | None = None,
                          seen: np.ndarray | None = None):
    """A COLMAP model of ``cameras`` (one PINHOLE camera per image, image id = camera id =
    position + 1) and, when given, ``points`` with their tracks.

    Args:
        cameras: V world cameras at the size of the image files.
        names: V image file names relative to COLMAP's image folder.
        points: (N, 3) world points, or None.
        colours: (N, 3) uint8 colours of the points, or None (grey).
        seen: (N, V) bool, which views observe each point (its track: the point's projection
            in each such view becomes a 2D point of that image); None: empty tracks.

    Returns:
        a ``pycolmap.Reconstruction`` (write it with ``.write(folder)``).
    """
    import pycolmap

    _check_names(cameras, names, "names")
    K, w2c = _arrays(cameras)
    V = len(cameras)
    pts = np.zeros((0, 3)) if points is None else np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {pts.shape}")
    if seen is None:
        seen = np.zeros((len(pts), V), bool)
    if seen.shape != (len(pts), V):
        raise ValueError(f"seen must be ({len(pts)}, {V}), got {seen.shape}")
    cols = (np.full((len(pts), 3), 128, np.uint8) if colours is None
            else np.asarray(colours, np.uint8))
    rec = pycolmap.Reconstruction()
    index = np.full((len(pts), V), -1, np.int64)  # point -> its 2D point index in each image
    for v in range(V):
        fx, fy, cx, cy = K[v, 0, 0], K[v, 1, 1], K[v, 0, 2] + 0.5, K[v, 1, 2] + 0.5
        rec.add_camera_with_trivial_rig(pycolmap.Camera(
            model="PINHOLE", width=cameras.width, height=cameras.height,
            params=[fx, fy, cx, cy], camera_id=v + 1))
        ids = np.flatnonzero(seen[:, v])
        cam = pts[ids] @ w2c[v, :3, :3].T + w2c[v, :3, 3]
        uv = cam[:, :2] / cam[:, 2:] * [fx, fy] + [cx, cy]
        index[ids, v] = np.arange(len(ids))
        image = pycolmap.Image(name=str(names[v]), keypoints=uv.reshape(-1, 2),
                               camera_id=v + 1, image_id=v + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(w2c[v, :3, :4]))
    for p in range(len(pts)):
        track = pycolmap.Track()
        for v in np.flatnonzero(seen[p]):
            track.add_element(int(v) + 1, int(index[p, v]))
        rec.add_point3D(pts[p], track, cols[p])
    return rec


def camera_json(cameras: Cameras, view_ids: Sequence[int], files: Sequence[str], units: str,
                scene: str | Path, scene_format: str, normalization=None) -> dict:
    """The cameras as plain JSON, in the scene's world frame and units (`CONVENTION`).

    Args:
        cameras: V world cameras at the size of the image files.
        view_ids: V view ids as the scene numbers them.
        files: V image paths (relative to the JSON file).
        units: the world units ("mm", or "unknown").
        scene, scene_format: the scene folder and its format, naming the world frame.
        normalization: the scene's `Normalization` (world <-> the unit frame the field used),
            or None.

    Returns:
        {"units", "world_frame", "convention", "width", "height", "normalization", "views":
        [{"id", "file", "K" 3x3, "R" 3x3, "t" 3, "center" 3}]}.
    """
    _check_names(cameras, files, "files")
    K, w2c = _arrays(cameras)
    centres = cameras.centers.detach().double().cpu().numpy()
    views = [{"id": int(i), "file": str(f), "K": k.tolist(), "R": e[:3, :3].tolist(),
              "t": e[:3, 3].tolist(), "center": c.tolist()}
             for i, f, k, e, c in zip(view_ids, files, K, w2c, centres, strict=True)]
    out = {"units": units,
           "world_frame": f"the world frame of the scene {scene} ({scene_format} format)",
           "convention": CONVENTION, "width": cameras.width, "height": cameras.height}
    if normalization is not None:
        out["normalization"] = {
            "center": [float(x) for x in normalization.center.tolist()],
            "scale": float(normalization.scale),
            "note": "x_unit = (x_world - center) / scale: the frame the field was fitted in"}
    out["views"] = views
    return out
