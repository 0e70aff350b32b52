"""Which views of a scene a run uses: the input views (DTU's protocol, a central view and its
best sources, or ``--views auto``) and the held-out test views. The working size has one rule,
`svolsdf.scene.size.working_size`."""

from __future__ import annotations

import torch

from svolsdf.config import DTU_EXCLUDED_IDS, DTU_TRAIN_IDS
from svolsdf.scene.scene import Scene, SceneError

__all__ = ["auto_views", "default_views", "test_views"]


def _is_dtu49(scene: Scene) -> bool:
    return bool(scene.extras.get("dtu")) and set(range(49)) <= set(scene.view_ids)


def default_views(scene: Scene, n: int = 3) -> list[int]:
    """Input views: DTU's protocol (docs/method.md 1.4) on DTU scans, else a central view and its
    n - 1 best source views (by the scene's pairs)."""
    if _is_dtu49(scene):
        return DTU_TRAIN_IDS[:n]
    cams = scene.cameras
    dirs = cams.view_dirs
    mean = dirs.mean(0)
    centre = int(torch.argmax(dirs @ mean))
    ref = scene.view_ids[centre]
    return [ref] + scene.source_views(ref)[: n - 1]


def auto_views(scene: Scene, n: int = 3) -> list[int]:
    """``--views auto``: n views with good overlap and baselines on any calibrated scene
    (`svolsdf.scene.pairs.select_views`), from the views' shared sparse points (COLMAP scenes)
    or points sampled in the object sphere, seen from the object centre."""
    from svolsdf.scene.loaders import read_source
    from svolsdf.scene.pairs import (
        covisibility,
        sample_sphere_points,
        select_views,
        visible_in_views,
    )

    V = len(scene.view_ids)
    if V < 2:
        raise SceneError(f"{scene.path}: --views auto: the scene has only {V} view "
                         f"({scene.view_ids}); reconstruction needs at least 2 views")
    if n > V:
        raise SceneError(f"{scene.path}: --views auto {n}: the scene has only {V} views; ask "
                         f"for at most {V} (--views auto {V})")
    src = read_source(scene.path, lighting=scene.extras.get("lighting", 3))
    cams = scene.cameras
    if src.points is not None and src.visibility is not None and len(src.points) > 0 and \
            list(src.view_ids) == list(scene.view_ids):
        vis = src.visibility
    else:
        vis = visible_in_views(cams, sample_sphere_points(scene.normalization, 4096))
    pos = select_views(covisibility(vis), cams.centers, scene.normalization.center.reshape(3), n)
    return [scene.view_ids[i] for i in pos]


def test_views(scene: Scene, inputs: list[int]) -> list[int]:
    """Held-out views: DTU's 15-view exclusion protocol on DTU scans, the protocol's test views
    on a BlendedMVS scan run from its input views (`_blendedmvs_test_views`), else every other
    view."""
    if _is_dtu49(scene):
        return [v for v in range(49) if v not in DTU_TRAIN_IDS and v not in DTU_EXCLUDED_IDS]
    bmvs = _blendedmvs_test_views(scene, inputs)
    if bmvs is not None:
        return bmvs
    return [v for v in scene.view_ids if v not in inputs]


def _blendedmvs_test_views(scene: Scene, inputs: list[int]) -> list[int] | None:
    """The BlendedMVS protocol's test views (docs/method.md 8.2) of a scan whose folder names
    it (``bmvs_scan3``, as the released preset reads it) when the run's inputs are the
    protocol's and the scene has every test view; else None."""
    from svolsdf.config.presets import scene_scan
    from svolsdf.evaluate.blendedmvs import protocol, protocol_scans

    found = scene_scan(str(scene.path))
    if found is None or found[0] != "blendedmvs" or found[1] not in protocol_scans():
        return None
    p = protocol(found[1])
    if sorted(inputs) != sorted(p["inputs"]) or not set(p["test"]) <= set(scene.view_ids):
        return None
    return list(p["test"])
