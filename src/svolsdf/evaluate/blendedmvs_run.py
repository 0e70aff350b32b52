"""``svolsdf evaluate RUN --protocol blendedmvs --gt-points GT [--volsdf VOLSDF_RUN]``: a run's
points scored under the paper's BlendedMVS protocol (`svolsdf.evaluate.blendedmvs`, docs/method.md
8.2), and the relative improvement over a VolSDF run of the same scene and views scored the same
way (the same ground truth, plane, masks and cut-off, in the same call).

- Scale: the cut-off is 20 mm at the scan's scale (``max_dist`` = 20 x the scan's
  ``relative_scale``, the protocol file's), the scan given by ``--scan`` or by the scene
  folder's name (``bmvs_scan3``, as the released preset reads it); ``--max-dist`` sets it in
  world units instead. The ground plane's inlier band and its removal margin are 1/20 and 1/10
  of the cut-off (1 mm and 2 mm in DTU-like millimetres). Every number is in the run's world
  units; divide by ``relative_scale`` for DTU-like millimetres.
- Masks: the evaluation masks of ``--eval-masks`` (a folder of masks named by view id, for some
  views only: the released data keeps BlendedMVS' masks of the input and test views apart from
  the scans), else every view of the scene whose mask folder holds a mask (a partial folder
  of the MVSNet/BlendedMVS layout); the cameras are scaled to the masks' size. Without either
  there is no masked score (null, with the reason).
- The plane faces the scene's cameras (their mean centre).

`check_blendedmvs` refuses bad input before any work; `blendedmvs_geometry` fills metrics.json's
``chamfer`` (the unmasked score, protocol ``blendedmvs``) and ``blendedmvs`` blocks.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from svolsdf.errors import InputError
from svolsdf.evaluate.blendedmvs import (
    blendedmvs_chamfer,
    fit_ground_plane,
    protocol,
    protocol_scans,
)
from svolsdf.evaluate.blendedmvs import relative_improvement as _relative
from svolsdf.evaluate.run_outputs import chamfer_block, finite_or_none
from svolsdf.io.runfolder import RunFolder

__all__ = ["BLENDEDMVS_MM", "BlendedMVSJob", "blendedmvs_geometry", "check_blendedmvs"]

log = logging.getLogger(__name__)

BLENDEDMVS_MM = 20.0
"""The protocol's cut-off in DTU-like millimetres (the released eval_bmvs.py's max_dist)."""


@dataclass(frozen=True)
class BlendedMVSJob:
    """What `check_blendedmvs` settled: the scene, the scale and the VolSDF run."""

    scene: Path
    """The scene folder (cameras and evaluation masks)."""
    views: list[int] | None
    """The run's input views (None: not recorded)."""
    scan: int | None
    """The BlendedMVS scan (1-9), None when ``--max-dist`` gives the scale alone."""
    max_dist: float
    """Distances beyond it are left out of the means (world units)."""
    volsdf: Path | None
    """The VolSDF run compared against, or None."""
    eval_masks: dict[int, Path] | None = None
    """{view id: mask file} of ``--eval-masks``; None: the scene's mask folder."""

    @property
    def relative_scale(self) -> float | None:
        """World units per DTU-like millimetre of the scan (the protocol file's)."""
        return None if self.scan is None else float(protocol(self.scan)["relative_scale"])


def _scan_from_name(scene: Path) -> int | None:
    """The BlendedMVS scan a scene folder's name gives (``bmvs_scan3``), else None."""
    from svolsdf.config.presets import scene_scan

    found = scene_scan(str(scene))
    return found[1] if found is not None and found[0] == "blendedmvs" else None


def _run_scene_or_refuse(run: RunFolder, scene: Path | None, option: str
                         ) -> tuple[Path, list[int] | None]:
    from svolsdf.evaluate.run_outputs import run_scene, scene_problem

    path, views = run_scene(run)
    if scene is not None:
        path = Path(scene)
    problem = scene_problem(path, scene is not None)
    if problem is not None:
        raise InputError(f"{option}: the BlendedMVS protocol reads the scene's cameras and "
                         f"evaluation masks, but {problem}")
    return Path(path), views


def check_blendedmvs(out: Path, gt_points: Path | None, dtu_gt: Path | None, scene: Path | None,
                     scan: int | None, max_dist: float | None, volsdf: Path | None,
                     eval_masks: Path | None = None) -> BlendedMVSJob:
    """The options of ``--protocol blendedmvs``, checked before any work.

    Args:
        out: the run folder; scene: ``--scene`` (default the run's); scan, max_dist: ``--scan``,
            ``--max-dist``; volsdf: ``--volsdf``; eval_masks: ``--eval-masks``.

    Raises:
        InputError: one line naming the option or file: no ``--gt-points`` (or ``--dtu-gt``
            beside it), a run without points.ply, no scene, no scale (neither a scan nor
            ``--max-dist``), a scan the protocol does not have, or a ``--volsdf`` folder that
            is not a finished VolSDF run of the same scene and views, an ``--eval-masks`` folder
            without masks of the scene's views.
    """
    from svolsdf.io.paths import input_dir

    if gt_points is None:
        raise InputError("--protocol blendedmvs needs --gt-points FILE: the scan's ground-truth "
                         "points (its ground included: the protocol removes the plane itself)")
    if dtu_gt is not None:
        raise InputError("--protocol blendedmvs scores against --gt-points; --dtu-gt selects "
                         "the DTU protocol: give one")
    run = RunFolder(out)
    if not run.points.is_file():
        raise InputError(f"{run.points}: no such file; the BlendedMVS protocol scores the run's "
                         "fused points (svolsdf reconstruct makes points.ply)")
    scene_path, views = _run_scene_or_refuse(run, scene, "--protocol blendedmvs")
    if scan is not None:
        try:
            protocol(scan)
        except InputError as e:
            raise InputError(f"--scan {scan}: {e}") from None
    else:
        scan = _scan_from_name(scene_path)  # from the protocol's scans: unknown ones stay None
        if scan is not None and scan not in protocol_scans():
            scan = None
    if max_dist is None:
        if scan is None:
            raise InputError(f"--protocol blendedmvs: scene {scene_path.name} names no "
                             "BlendedMVS scan (a folder like bmvs_scan3) to take the cut-off's "
                             "scale from; pass --scan N (1-9) or --max-dist D in world units")
        max_dist = BLENDEDMVS_MM * float(protocol(scan)["relative_scale"])
    if volsdf is not None:
        volsdf = input_dir(volsdf, "VolSDF run folder", "--volsdf")
        _check_volsdf_run(RunFolder(volsdf), scene_path, views)
    masks = None if eval_masks is None else _eval_mask_files(eval_masks, scene_path)
    return BlendedMVSJob(scene=scene_path, views=views, scan=scan, max_dist=float(max_dist),
                         volsdf=volsdf, eval_masks=masks)


def _eval_mask_files(folder: Path, scene: Path) -> dict[int, Path]:
    """``--eval-masks``: {view id: mask file}, every id a view of ``scene``."""
    from svolsdf.io.images import image_size
    from svolsdf.io.paths import input_dir
    from svolsdf.scene.formats._common import list_images, numbered
    from svolsdf.scene.loaders import load_scene

    folder = input_dir(folder, "evaluation mask folder", "--eval-masks")
    try:
        files = numbered(list_images(folder, "masks"))
    except InputError as e:
        raise InputError(f"--eval-masks: {e}") from None
    have = set(load_scene(scene, load_images=False).view_ids)
    unknown = sorted(set(files) - have)
    if unknown:
        raise InputError(f"--eval-masks {folder}: masks of views {unknown[:5]} that scene "
                         f"{scene} does not have (its views: {min(have)}-{max(have)}); give "
                         "the mask folder of this scan")
    sizes = {image_size(p) for p in files.values()}  # one size: one scaling of the cameras
    if len(sizes) > 1:
        raise InputError(f"--eval-masks {folder}: masks of sizes "
                         f"{', '.join(f'{w}x{h}' for w, h in sorted(sizes))}; give masks of "
                         "one size")
    return dict(sorted(files.items()))


def _check_volsdf_run(vrun: RunFolder, scene: Path, views: list[int] | None) -> None:
    """``--volsdf``: a finished run of ``svolsdf reconstruct --mode volsdf`` with points.ply,
    made by its config.yaml, of the same scene and input views as the run scored."""
    from svolsdf.config import load_config
    from svolsdf.evaluate.run_outputs import check_provenance, run_scene
    from svolsdf.io.runfolder import refuse_in_progress

    label = f"--volsdf {vrun.root}"
    if not vrun.config_file.is_file():
        raise InputError(f"{label}: not a VolSDF run (no config.yaml); give the output folder "
                         "of svolsdf reconstruct --mode volsdf")
    mode = load_config(vrun.config_file).train.mode
    if mode != "volsdf":
        raise InputError(f"{label}: not a VolSDF run (its config.yaml has train.mode {mode}); "
                         "give the output folder of svolsdf reconstruct --mode volsdf")
    refuse_in_progress(vrun.root)
    if not vrun.points.is_file():
        raise InputError(f"{label}: no points.ply (an unfinished run?); the relative "
                         "improvement compares the fused points of both runs")
    check_provenance(vrun, ["points.ply"])
    v_scene, v_views = run_scene(vrun)
    if v_scene is None or Path(v_scene).resolve() != scene.resolve():
        raise InputError(f"{label}: a run of scene {v_scene}, not of {scene}; the relative "
                         "improvement compares runs of one scene")
    if views is not None and v_views is not None and sorted(v_views) != sorted(views):
        raise InputError(f"{label}: input views {sorted(v_views)}, the run's are "
                         f"{sorted(views)}; the relative improvement compares runs of the same "
                         "views")


def _evaluation_masks(scene_path: Path, files: dict[int, Path] | None = None
                      ) -> tuple[dict | None, list[int]]:
    """``{"K", "w2c", "masks"}`` of the views with an evaluation mask (`inside_masks`' inputs:
    the cameras at the masks' size), and those view ids; (None, []) without masks.

    Args:
        files: {view id: mask file} (``--eval-masks``); None: the scene's mask folder.
    """
    from svolsdf.scene.loaders import load_scene

    if files is not None:
        from svolsdf.io.images import read_mask

        ids = sorted(files)
        cams = load_scene(scene_path, views=ids, load_images=False).cameras
        masks = [read_mask(files[v])[0].numpy() > 0.5 for v in ids]  # one size (checked)
        h, w = masks[0].shape
        cams = cams.resize(w, h)
        return {"K": cams.K.numpy().astype(np.float64),
                "w2c": cams.w2c.numpy().astype(np.float64), "masks": masks}, ids
    every = load_scene(scene_path, load_images=False)
    if "eval_mask_paths" in every.extras:  # a partial folder: the inputs' and tests' masks
        ids = sorted(int(v) for v in every.extras["eval_mask_paths"])
    elif every.extras.get("mask_paths"):
        ids = list(every.view_ids)
    else:
        return None, []
    sc = load_scene(scene_path, views=ids)
    if sc.masks is None:
        return None, []
    return {"K": sc.cameras.K.numpy().astype(np.float64),
            "w2c": sc.cameras.w2c.numpy().astype(np.float64),
            "masks": [m[0].numpy() > 0.5 for m in sc.masks]}, ids


def _block(res: dict | None, name: str, max_dist: float, why: str | None = None) -> dict:
    """A Chamfer block of metrics.json (`chamfer_block`) with the point counts scored and, when
    null, why (``why``, else every distance beyond the cut-off)."""
    block = chamfer_block(res, name, "points.ply" if res is not None else None)
    block["n_pred"] = None if res is None else int(res["n_pred"])
    block["n_gt"] = None if res is None else int(res["n_gt"])
    if block["overall"] is None and why is None:
        why = (f"no distance within the cut-off max_dist {max_dist:.4g} (world units; set by "
               "--max-dist or the scan's scale)")
    block["missing"] = why
    return block


def blendedmvs_geometry(job: BlendedMVSJob, gt: np.ndarray, points: np.ndarray,
                        metrics: dict, notes: list[str]) -> None:
    """Score ``points`` (and the VolSDF run's) under the protocol into ``metrics``.

    Args:
        job: `check_blendedmvs`'s result.
        gt: (M, 3) the ground truth, ground included (world units).
        points: (N, 3) the run's points.ply.
        metrics: metrics.json being built: ``chamfer`` gets the unmasked score (protocol
            ``blendedmvs``) and ``blendedmvs`` everything: ``unmasked``, ``masked`` (protocol
            ``blendedmvs-masked``), ``volsdf`` (its run and both scores), ``relative_improvement``
            (of the overall Chamfer, unmasked and masked), the plane, scale and masked views.
    """
    from svolsdf.io.ply import read_ply
    from svolsdf.scene.loaders import load_scene

    cams = load_scene(job.scene, load_images=False).cameras
    unit = job.max_dist / BLENDEDMVS_MM  # one DTU-like millimetre
    plane = fit_ground_plane(gt, cams.centers.numpy().mean(0), threshold=unit)
    margin = 2.0 * unit
    masked, masked_views = _evaluation_masks(job.scene, job.eval_masks)
    no_masks = None if masked is not None else (f"scene {job.scene} has no object masks (pass "
                                                "--eval-masks FOLDER)")

    def score(pts: np.ndarray) -> tuple[dict, dict]:
        try:
            r = blendedmvs_chamfer(pts, gt, plane, margin, job.max_dist, masked=masked)
        except InputError as e:  # no point above the plane or inside the masks: null, and why
            null_masked = _block(None, "blendedmvs-masked", job.max_dist, str(e))
            try:  # the masks left nothing: the unmasked score stands
                r = blendedmvs_chamfer(pts, gt, plane, margin, job.max_dist)
            except InputError:
                return _block(None, "blendedmvs", job.max_dist, str(e)), null_masked
            return _block(r["unmasked"], "blendedmvs", job.max_dist), null_masked
        return (_block(r["unmasked"], "blendedmvs", job.max_dist),
                _block(r["masked"], "blendedmvs-masked", job.max_dist, no_masks))

    unmasked, masked_block = score(points)
    block = {"unmasked": unmasked, "masked": masked_block, "volsdf": None,
             "relative_improvement": None, "scan": job.scan,
             "relative_scale": job.relative_scale, "max_dist": job.max_dist,
             "plane": {"normal": [float(x) for x in plane[0]], "offset": float(plane[1]),
                       "inlier_band": unit, "margin": margin},
             "masked_views": masked_views,
             "masks_from": None if masked is None else (
                 "--eval-masks" if job.eval_masks is not None else "the scene's mask folder"),
             "units": "world units of the run (divide by "
             "relative_scale for DTU-like millimetres)"}
    if job.volsdf is not None:
        vpts = read_ply(RunFolder(job.volsdf).points)["points"]
        v_unmasked, v_masked = score(vpts)
        block["volsdf"] = {"run": str(job.volsdf), "unmasked": v_unmasked, "masked": v_masked}
        block["relative_improvement"] = {
            key: (finite_or_none(_relative(ours["overall"], theirs["overall"]))
                  if ours["overall"] is not None and (theirs["overall"] or 0) > 0 else None)
            for key, ours, theirs in (("unmasked", unmasked, v_unmasked),
                                      ("masked", masked_block, v_masked))}
    metrics["chamfer"] = {k: unmasked[k] for k in chamfer_block(None, None, None)}
    metrics["blendedmvs"] = block
    notes.append(
        f"BlendedMVS protocol: the ground plane fitted to the ground truth and removed from "
        f"both clouds (margin {margin:.4g}), distances beyond {job.max_dist:.4g} left out; "
        + (f"masked inside the masks of views {masked_views}" if masked is not None else
           f"no masked score ({no_masks})") + ".")
    log.info("BlendedMVS protocol: unmasked %s, masked %s", unmasked["overall"],
             masked_block["overall"])
