"""Checks that a scene can be reconstructed, and that an output folder may be written, made before
any stage runs: degenerate input ends in one line (exit 2), not in a traceback or an empty result
after minutes of work.

- `check_scene`: images of at least `MIN_SIDE` pixels a side, object masks that are not empty,
  right-handed camera rotations, cameras that do not all sit at one point, and input views that
  see the scene's bounding region (the unit sphere of its normalization), at least two of them
  the same part of it.
- `check_outside_scenes`: the output is no scene folder, and neither is, lies inside nor holds
  a scene the command reads (every command that writes runs: reconstruct, mvs, benchmark, demo).
- `check_output_folder`: the output is neither the scene folder, inside it, nor around it, nor a
  folder that another command wrote (a scene, a run of ``reconstruct`` for ``mvs`` and back), nor
  a folder holding files that are not the command's (the user's notes, photos, ...): new, empty,
  or the command's own earlier output (a rerun resumes it).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch

from svolsdf.scene.scene import Scene, SceneError

__all__ = ["MIN_SIDE", "check_output_folder", "check_outside_scenes", "check_scene",
           "region_visibility"]

MIN_SIDE = 16
"""The smallest working width and height, in pixels. The field's warm-up target blurs the images
with a 31-pixel kernel (reflect padding needs 16 pixels), and MVS stage 1 runs at a quarter of the
MVS size; below 16 pixels the first crashes and the second has 2-4 pixels to match."""


def region_visibility(scene: Scene, samples: int = 9) -> torch.Tensor:
    """(V, N) bool: which of N points spread through the unit sphere of ``scene.normalization``
    (its bounding region) each input view sees, in front of it and inside its image."""
    t = torch.linspace(-1.0, 1.0, samples, dtype=torch.float64)
    grid = torch.cartesian_prod(t, t, t)
    grid = grid[grid.norm(dim=-1) <= 1.0]
    pts = scene.normalization.to_world(grid)
    cams = scene.cameras.to(device="cpu", dtype=torch.float64)
    uv, z = cams.project(pts)
    return ((z > 0) & (uv[..., 0] >= -0.5) & (uv[..., 0] <= cams.width - 0.5)
            & (uv[..., 1] >= -0.5) & (uv[..., 1] <= cams.height - 0.5))


def check_scene(scene: Scene, use_masks: bool = True) -> None:
    """Refuse a scene that no stage can reconstruct (module docstring).

    Args:
        scene: the input views at the working size, images loaded.
        use_masks: the run applies the object masks (their emptiness matters only then).

    Raises:
        SceneError: one line naming the file or view and what to do.
    """
    path, ids = scene.path, list(scene.view_ids)
    if min(scene.width, scene.height) < MIN_SIDE:
        native = scene.extras.get("native_size")
        was = f" (the images are {native[0]}x{native[1]})" if native else ""
        raise SceneError(f"{scene.image_paths[0]}: the working size is {scene.width}x"
                         f"{scene.height}{was}; reconstruction needs at least {MIN_SIDE} pixels "
                         f"a side: use larger images or a larger --size")
    R = scene.cameras.w2c[:, :3, :3].double().cpu()
    det = torch.linalg.det(R)
    for v, d in zip(ids, det.tolist(), strict=True):
        if d < 0:
            raise SceneError(f"{path}: the rotation of view {v}'s camera is left-handed (det R = "
                             f"{d:.3g}); cameras must be right-handed world-to-camera rotations "
                             "(OpenCV axes): flip the sign of one axis consistently")
    centers = scene.cameras.centers.double().cpu()
    spread = float((centers - centers.mean(0)).norm(dim=-1).max())
    dist = float((centers - scene.normalization.center.double().cpu()).norm(dim=-1).max())
    if spread <= 1e-4 * max(dist, 1e-12):
        raise SceneError(f"{path}: the input views {ids} all have their camera at one point "
                         f"(spread {spread:.3g}, {dist:.3g} from the scene's centre): depth needs "
                         "views from different positions; check the cameras or the --views")
    seen = region_visibility(scene)
    for v, row in zip(ids, seen, strict=True):
        if not bool(row.any()):
            raise SceneError(f"{path}: view {v}'s camera does not see the scene's bounding "
                             f"region (it looks away from it, or the region is behind it); "
                             f"check its camera (rotation, sign) or leave the view out")
    if int(seen.sum(0).max()) < 2:
        raise SceneError(f"{path}: the input views {ids} share no view of the scene's bounding "
                         "region (no part of it is seen by two of them); choose overlapping "
                         "views (--views auto) or check the cameras")
    if use_masks and scene.masks is not None:
        files = scene.extras.get("mask_paths") or [None] * len(ids)
        for k, v in enumerate(ids):
            if not bool((scene.masks[k] > 0.5).any()):
                name = files[k] or f"{path}: the mask of view {v}"
                raise SceneError(f"{name}: the object mask of view {v} is empty (all black): "
                                 "the object is not in the view, or the mask is inverted; fix "
                                 "the mask, leave the view out, or pass --set "
                                 "scene.use_masks=false")


def _scene_format(folder: Path) -> str | None:
    from svolsdf.scene.formats import scene_formats

    try:
        return next((f.name for f in scene_formats() if f.detect(folder)), None)
    except (OSError, ValueError):
        return None


def check_outside_scenes(out: str | Path, scenes: Sequence[str | Path] = (), what: str = "the run",
                         enclosing: bool = False) -> None:
    """Refuse an output folder that is a scene folder (any format), or is, lies inside or holds
    one of ``scenes``: a command writes its runs to a folder of its own, never among a scene's
    files (reconstruct, mvs, benchmark and demo share this check).

    Args:
        out: the output folder (need not exist).
        scenes: the scene folders the command reads.
        what: what the command writes, for the message ("the benchmark").
        enclosing: also refuse an ``out`` inside any scene folder, not only those of
            ``scenes`` (the demo, which reads none and makes a scene of its own).

    Raises:
        SceneError: one line naming the folder and why.
    """
    out = Path(out)
    o = out.resolve()
    for scene in scenes:
        s = Path(scene).resolve()
        if o == s or s in o.parents:
            raise SceneError(f"-o {out}: the output is the scene folder {scene} or inside it; "
                             f"write {what} to a folder of its own")
        if o in s.parents:
            raise SceneError(f"-o {out}: the output folder holds the scene {scene}; write "
                             f"{what} to a folder of its own")
    if out.is_dir():
        fmt = _scene_format(out)
        if fmt is not None:
            raise SceneError(f"-o {out}: that folder is a scene ({fmt}); write {what} to a "
                             "folder of its own")
    if enclosing:
        for a in o.parents:
            fmt = _scene_format(a)
            if fmt is not None:
                raise SceneError(f"-o {out}: that folder is inside the scene {a} ({fmt}); "
                                 f"write {what} to a folder of its own")


def check_output_folder(out: str | Path, scene: str | Path | None, command: str) -> None:
    """Refuse an output folder that a run must not write (module docstring).

    Args:
        out: the output folder (need not exist).
        scene: the scene folder the command reads, or None.
        command: "svolsdf reconstruct" or "svolsdf mvs".

    Raises:
        SceneError: one line naming the folder and why.
    """
    from svolsdf.io.runfolder import MVS_NAMES, MVS_STATE, RUN_NAMES, RunFolder, foreign_names

    out = Path(out)
    check_outside_scenes(out, [] if scene is None else [scene])
    if not out.is_dir():
        return
    run_files = [n for n in ("config.yaml", "views.json", "stages.json") if (out / n).is_file()]
    if command == "svolsdf mvs" and run_files:
        raise SceneError(f"-o {out}: that folder is a run of svolsdf reconstruct "
                         f"({run_files[0]}); svolsdf mvs would replace its points.ply and depth/: "
                         "choose another output folder")
    mvs_output = (out / "mvs.json").is_file() or (out / MVS_STATE).is_file()
    if command == "svolsdf reconstruct" and mvs_output and not run_files:
        raise SceneError(f"-o {out}: that folder holds the output of svolsdf mvs (mvs.json); "
                         "choose another output folder")
    # a run of this command (resumed or replaced) is recognised by its bookkeeping file; a folder
    # without one must hold nothing but what the command writes (a run stopped before writing
    # it, or a new folder), never files of the user's that the run would mix with its own
    if command == "svolsdf mvs":
        own, mine, again = MVS_NAMES, mvs_output, "resume or replace that earlier output"
    else:
        own, mine, again = RUN_NAMES, RunFolder(out).is_run(), "resume that earlier run"
    try:
        foreign = [] if mine else foreign_names(out, own)
    except OSError as e:
        raise SceneError(f"-o {out}: cannot list that folder ({e.strerror or e}); choose a "
                         "folder you can read") from None
    if foreign:
        shown = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3
                                          else "")
        raise SceneError(f"-o {out}: that folder holds files that are not a svolsdf run "
                         f"({shown}); write to a new or empty folder, or to the folder of an "
                         f"earlier {command} to {again}")
