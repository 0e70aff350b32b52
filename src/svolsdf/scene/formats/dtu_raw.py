"""DTU's own raw layout (DTU MVS dataset, Aanaes et al. 2016).

``Rectified/scanN/rect_XXX_L_r5000.{png,jpg}`` (XXX = 1-based position, L = lighting 0..6) or
``rect_XXX_max.{png,jpg}``, with ``Calibration/cal18/pos_XXX.txt`` (3x4 P = K [R | t] in mm).
View id = XXX - 1. Evaluation files, when present, are recorded in ``extras``:
``ObsMask/ObsMask{N}_10.mat``, ``ObsMask/Plane{N}.mat``, ``Points/stl/stl{N:03d}_total.ply``.
"""

from __future__ import annotations

import re
from pathlib import Path

import torch

from svolsdf.scene.cameras import decompose_projection
from svolsdf.scene.formats import register_scene_format
from svolsdf.scene.formats._common import SceneSource, check_camera, load_txt_matrix, scan_number
from svolsdf.scene.scene import SceneError

__all__ = ["detect", "read", "resolve"]

_NAME = re.compile(r"rect_(\d{3})_(\d+|max)(?:_r5000)?\.(png|jpg|jpeg)", re.IGNORECASE)


def resolve(path: Path) -> tuple[Path, Path] | None:
    """(dataset root, Rectified/scanN folder) for a root or a scan folder, else None.

    Raises:
        SceneError: the root holds several scans (the user must pick one).
    """
    if path.parent.name == "Rectified" and (path.parent.parent / "Calibration").is_dir():
        return path.parent.parent, path
    rect = path / "Rectified"
    if rect.is_dir() and (path / "Calibration" / "cal18").is_dir():
        scans = sorted(p for p in rect.iterdir() if p.is_dir() and scan_number(p.name) is not None)
        if len(scans) == 1:
            return path, scans[0]
        if len(scans) > 1:
            names = ", ".join(p.name for p in scans[:8])
            raise SceneError(f"{rect} holds several scans ({names}); pass one of them, e.g. "
                             f"{scans[0]}")
    return None


def detect(path: Path) -> bool:
    """True for a DTU root with one scan, or a ``Rectified/scanN`` folder."""
    return resolve(path) is not None


@register_scene_format("dtu_raw", detect, order=20,
                       looks_for="Rectified/scanN/ with Calibration/cal18/ (DTU raw)",
                       title="DTU raw (Rectified + Calibration/cal18)")
def read(path: Path, lighting: int | str = 3) -> SceneSource:
    """Read a DTU raw scan at ``lighting`` (0..6 or "max"; default 3, the MVSNet choice)."""
    root, scan_dir = resolve(path)
    scan = scan_number(scan_dir.name)
    calib = root / "Calibration" / "cal18"
    found: dict[str, dict[int, Path]] = {}
    for p in scan_dir.iterdir():
        m = _NAME.fullmatch(p.name)
        if m:
            found.setdefault(m.group(2).lower(), {})[int(m.group(1))] = p
    light = str(lighting).lower()
    if light not in found:
        have = ", ".join(sorted(found)) or "none"
        raise SceneError(f"{scan_dir}: no images rect_XXX_{light}_r5000.(png|jpg) for lighting "
                         f"{light} (lightings found: {have})")
    images = dict(sorted(found[light].items()))
    Ks, w2cs = [], []
    for pos in images:
        f = calib / f"pos_{pos:03d}.txt"
        if not f.is_file():
            raise SceneError(f"{scan_dir} has {len(images)} images but {calib} has no "
                             f"pos_{pos:03d}.txt for rect_{pos:03d}")
        P = torch.from_numpy(load_txt_matrix(f, (3, 4)))
        try:
            K, w2c = decompose_projection(P)
        except ValueError as e:
            raise SceneError(f"{f}: {e}") from None
        check_camera(K, w2c, str(f))
        Ks.append(K)
        w2cs.append(w2c)
    extras: dict = {"scan": scan, "lighting": light, "calibration": str(calib)}
    candidates = {
        "obs_mask": root / "ObsMask" / f"ObsMask{scan}_10.mat",
        "plane": root / "ObsMask" / f"Plane{scan}.mat",
        "stl": root / "Points" / "stl" / f"stl{scan:03d}_total.ply",
    }
    for k, p in candidates.items():
        if p.is_file():
            extras[k] = str(p)
    return SceneSource(
        format="dtu_raw", path=scan_dir, view_ids=[p - 1 for p in images],
        image_paths=list(images.values()), K=torch.stack(Ks), w2c=torch.stack(w2cs),
        camera_source=[str(calib / f"pos_{p:03d}.txt") for p in images],
        cameras_file=str(calib), units="mm", extras=extras,
    )
