"""``svolsdf evaluate OUT``: metrics of a finished run and its HTML report.

Reads from the run folder OUT:
    points.ply          the fused point cloud (world units)
    mesh.ply            the mesh, if present
    renders/<id>.png    volume-rendered novel views; renders_ibr/<id>.png image-based renders
    depth/*.png, normals/*.png   previews shown in the report
    config.yaml         names the scene and its input views (``scene.path``, ``scene.views``; read
                        by `svolsdf.config.load_config`), else views.json does
    timing.json         stage timings, copied into the metrics

through `svolsdf.io.runfolder.RunFolder`.

Writes OUT/metrics.json with fixed keys (null when not computable)::

    chamfer: {accuracy, completeness, overall, protocol, source}
    chamfer_mesh: {accuracy, completeness, overall, protocol, source, mesh_source, sampled,
                density}: mesh.ply scored by its surface (``sampled``: "surface"), its triangles
                sampled every ``density`` world units (`svolsdf.evaluate.chamfer.mesh_density`:
                DTU 0.2 mm, otherwise 0.1 % of the ground truth's diagonal), never by its
                vertices
    mesh_source: which surface mesh.ply is (field | poisson | tsdf | "field (poisson failed:
                ...)"), from timing.json; mesh_over_points: {accuracy, completeness, overall}
                of the mesh over the points'
    fscore, fscore_threshold, precision, recall
    images:     {psnr: {mean, per_view, missing}, ssim: {...}, lpips: {...}}
                (missing: why the metric is null, e.g. no renders or no LPIPS weights)
    images_ibr: the same for renders_ibr/
                (novel views only: a render of one of the run's input views is never in them)
    images_input_views, images_ibr_input_views: the same for renders of the run's input views
                (training views rendered back, e.g. by `render` on a run with no held-out view)
    views:      {inputs: the run's input views, novel_scored, input_scored: the rendered views
                scored in each role}
    missing:    {metric: why it is null} for every null metric (chamfer, chamfer_mesh, fscore,
                images.psnr, ...: no points.ply, no ground truth, a scene folder that moved,
                ...); the Chamfer blocks keep their own reason under ``missing`` too
    timing: {..timing.json.., evaluate_seconds}
    blendedmvs: null, or with protocol "blendedmvs" {unmasked, masked: Chamfer blocks with
                n_pred and n_gt, volsdf: {run, unmasked, masked} or null, relative_improvement:
                {unmasked, masked} or null, scan, relative_scale, max_dist, plane, masked_views,
                masks_from, units} (`svolsdf.evaluate.blendedmvs_run`; ``chamfer`` holds the
                unmasked score)
    settings: what was evaluated against what; ``image_region`` says where the image errors
                are computed (inside the object mask where the scene has one)

and OUT/report.html (`svolsdf.evaluate.run_report`).

Geometry: with ``dtu_gt`` the DTU protocol (docs/method.md 8.1), with ``gt_points`` the generic
two-way Chamfer, or with ``protocol`` "blendedmvs" the paper's BlendedMVS protocol (docs/method.md
8.2: ground plane removed, masked and unmasked, relative to a ``volsdf`` run), and otherwise,
for a scene written by ``svolsdf synth``, its own ground truth
(`svolsdf.evaluate.synthetic.synthetic_chamfer`, the benchmarks' protocol: F-score at 0.5 % and
distances clipped at 5 % of its diagonal). Otherwise the F-score threshold defaults to 1% of the
ground truth's bounding-box diagonal (DTU: of the STL points above the plane), a scale-free
choice; pass ``threshold`` for a fixed one. In DTU mode precision / recall use the protocol's
point sets (observed prediction points; STL points above the plane) with all distances counted.

Images (docs/method.md 8.3): ground truth is the scene's image at the render's size (bicubic), masks
resized and thresholded at 0.5; PSNR over masked pixels, SSIM and LPIPS (VGG by default) on images
composited onto white.
"""

from __future__ import annotations

import logging
import math
import re
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np

from svolsdf.errors import InputError
from svolsdf.evaluate import chamfer as ch
from svolsdf.evaluate.images import masked_psnr, ssim
from svolsdf.evaluate.points import checked_ground_truth
from svolsdf.evaluate.report import ViewImages
from svolsdf.evaluate.run_outputs import (
    chamfer_block,
    check_provenance,
    check_run_folder,
    empty_images,
    empty_metrics,
    finite_or_none,
    load_gt_points,
    load_renders,
    mark_roles,
    mesh_chamfer_block,
    run_kind_note,
    run_scene,
    write_json,
)
from svolsdf.evaluate.run_report import write_run_report_unlocked
from svolsdf.evaluate.synthetic import is_synthetic_scene
from svolsdf.io.runfolder import RunFolder

__all__ = ["EvaluateConfig", "evaluate_run"]

log = logging.getLogger(__name__)


@dataclass
class EvaluateConfig:
    """Options of ``svolsdf evaluate``."""

    out: Path
    """The run folder (holds points.ply, renders/, ...)."""
    gt_points: Path | None = None
    """Ground-truth points for the generic Chamfer: a PLY (vertices) or an (N, 3) .npy file."""
    dtu_gt: Path | None = None
    """DTU ground-truth root (ObsMask/, Points/stl/); selects the DTU protocol."""
    scan: int | None = None
    """Scan number: DTU's with dtu_gt, BlendedMVS' (1-9, its scale) with the blendedmvs protocol
    (default: from the scene folder's name)."""
    scene: Path | None = None
    """Scene folder for ground-truth images (default: from OUT/config.yaml)."""
    views: list[int] | None = None
    """View ids to evaluate (default: every renders/<id>.png)."""
    threshold: float | None = None
    """F-score threshold in world units (default: 1% of the ground truth's bbox diagonal)."""
    max_dist: float | None = None
    """Chamfer cut-off in world units (default: none for the generic Chamfer, 20 mm at the scan's
    scale for the BlendedMVS protocol; the DTU protocol always uses 20 mm)."""
    protocol: Literal["auto", "blendedmvs"] = "auto"
    """Chamfer protocol: auto (the one the ground truth implies) or blendedmvs (the paper's
    BlendedMVS protocol against the gt_points cloud: its ground plane removed, masked and
    unmasked). The BlendedMVS protocol is docs/method.md 8.2's."""
    volsdf: Path | None = None
    """A VolSDF run of the same scene and views (mode volsdf), scored the same way: the
    BlendedMVS protocol's relative improvement over it."""
    eval_masks: Path | None = None
    """Evaluation masks for the BlendedMVS protocol's masked score: a folder of masks named by
    view id, for some views only (the released data's eval_mask/scanN/mask; default: the
    scene's mask folder)."""
    lpips_net: Literal["vgg", "alex"] = "vgg"
    """LPIPS backbone, 'vgg' (the paper's) or 'alex'."""
    lpips_weights: Path | None = None
    """LPIPS weights: a whole LPIPS file or folder, or torchvision's backbone file
    (vgg16-397923af.pth) on a machine without internet (default: downloaded once into the torch
    cache)."""
    ssim_data_range: float = 1.0
    """SSIM data range; 2.0 reproduces the released code's numbers (docs/method.md 8.3)."""
    masks: bool = True
    """Use the scene's object masks for image metrics when it has them."""
    seed: int = 0
    """Seed of the DTU protocol's random shuffle."""
    report: bool = True
    """Also write OUT/report.html."""
    extra: dict = field(default_factory=dict)
    """Free-form facts stored under ``settings``."""


def _geometry(cfg: EvaluateConfig, scan: int | None, points, mesh, metrics: dict,
              notes: list[str], scene_path: Path | None = None,
              input_views: list[int] | None = None, bmvs=None) -> str | None:
    """Chamfer / F-score into ``metrics``; returns why there is no ground-truth geometry (None
    when there is). ``bmvs``: the BlendedMVS protocol's job (`check_blendedmvs`), or None."""
    if bmvs is not None:
        from svolsdf.evaluate.blendedmvs_run import blendedmvs_geometry

        metrics["settings"]["gt_points"] = str(cfg.gt_points)
        blendedmvs_geometry(bmvs, load_gt_points(cfg.gt_points), points[0], metrics, notes)
        metrics["chamfer_mesh"]["missing"] = "the BlendedMVS protocol scores points.ply only"
    elif cfg.dtu_gt is not None:
        if scan is None:
            raise InputError("--dtu-gt needs --scan N (the scene does not name its DTU scan)")
        files = ch.find_dtu_files(cfg.dtu_gt, scan)
        obs = ch.load_obs_mask(files.obs_mask)
        plane = ch.load_plane(files.plane)
        from svolsdf.io.ply import read_ply

        stl = checked_ground_truth(read_ply(files.stl)["points"], files.stl)
        above = stl @ plane[:3] + plane[3] > 0
        if not above.any():
            raise InputError(f"{files.stl}: no ground-truth point lies above the plane of "
                             f"{files.plane}")
        thr = cfg.threshold or _diag(stl[above], files.stl) * 0.01
        metrics["settings"]["dtu"] = {"scan": scan, "obs_mask": str(files.obs_mask),
                                      "plane": str(files.plane), "stl": str(files.stl)}
        if points is not None:
            r = ch.dtu_chamfer_arrays(points[0], stl, obs, plane, seed=cfg.seed,
                                      fscore_threshold=thr)
            metrics["chamfer"] = chamfer_block(r, "dtu", "points.ply")
            _put_fscore(metrics, r, thr)
        if mesh is not None:
            density = ch.mesh_density()
            r = ch.dtu_chamfer_arrays(mesh[0], stl, obs, plane, mode="mesh", faces=mesh[1],
                                      seed=cfg.seed, downsample_density=density)
            metrics["chamfer_mesh"] = mesh_chamfer_block(r, "dtu-mesh", "mesh.ply", density)
    elif cfg.gt_points is not None:
        gt = load_gt_points(cfg.gt_points)
        thr = cfg.threshold or _diag(gt, cfg.gt_points) * 0.01
        metrics["settings"]["gt_points"] = str(cfg.gt_points)
        if points is not None and len(points[0]):
            r = ch.chamfer_fscore(points[0], gt, thr, max_dist=cfg.max_dist)
            metrics["chamfer"] = chamfer_block(r, "generic", "points.ply")
            _put_fscore(metrics, r, thr)
        if mesh is not None:
            density = ch.mesh_density(_diag(gt, cfg.gt_points))
            surf = ch.mesh_surface_points(mesh[0], mesh[1], density, seed=cfg.seed)
            r = ch.chamfer_fscore(surf, gt, thr, max_dist=cfg.max_dist)
            metrics["chamfer_mesh"] = mesh_chamfer_block(r, "generic-mesh", "mesh.ply", density)
    elif scene_path is not None and input_views and is_synthetic_scene(scene_path):
        _synthetic_geometry(cfg, scene_path, input_views, points, mesh, metrics, notes)
    else:
        why = _no_ground_truth(scene_path, cfg.scene is not None, input_views)
        notes.append(f"Chamfer and F-score are null: {why}.")
        return why
    return None


def _no_ground_truth(scene_path: Path | None, given: bool, input_views: list[int] | None
                     ) -> str:
    """Why a run without --gt-points or --dtu-gt has no ground-truth geometry."""
    from svolsdf.evaluate.run_outputs import scene_problem

    way = "pass --gt-points FILE or --dtu-gt ROOT"
    problem = scene_problem(scene_path, given)
    if problem is not None:
        return f"no ground-truth geometry: {problem}, or {way}"
    if not is_synthetic_scene(scene_path):
        return (f"no ground-truth geometry: scene {scene_path} has none of its own (not a "
                f"svolsdf synth scene: no gt_points.ply and gt_depth/); {way}")
    return (f"no ground-truth geometry: the run does not record its input views (views.json), "
            f"which pick the part of scene {scene_path}'s ground truth to score against; {way}")


def _missing(metrics: dict, points, mesh, no_gt: str | None, kind: str | None = None) -> None:
    """``missing`` of the Chamfer blocks and the top-level ``missing`` map: for every null
    metric, why it could not be computed (``kind``: what kind of folder lacks an output,
    `run_kind_note`)."""
    for key, have, name in (("chamfer", points, "points.ply"), ("chamfer_mesh", mesh, "mesh.ply")):
        blk = metrics[key]
        if blk["overall"] is not None or blk.get("missing"):  # scored, or null with its reason
            continue
        if have is None:
            blk["missing"] = (f"no {name} in the run folder" if key == "chamfer" else
                              "no mesh.ply with faces in the run folder") + (
                                  f": {kind}" if kind else "")
        elif no_gt is not None:
            blk["missing"] = no_gt
        elif blk["protocol"] is None:
            blk["missing"] = f"{name} has no points"
        else:
            blk["missing"] = "its distances are not finite numbers"
    out = {}
    if metrics["chamfer"]["missing"] is not None:
        out["chamfer"] = out["fscore"] = metrics["chamfer"]["missing"]
    elif metrics["fscore"] is None:
        out["fscore"] = ("the BlendedMVS protocol has no F-score"
                         if metrics["chamfer"]["protocol"] == "blendedmvs" else
                         "the F-score is not a finite number")
    if metrics["chamfer_mesh"]["missing"] is not None:
        out["chamfer_mesh"] = metrics["chamfer_mesh"]["missing"]
    for key in ("images", "images_ibr"):
        for m, blk in metrics[key].items():
            if blk["mean"] is None:
                out[f"{key}.{m}"] = blk.get("missing") or "no view gave a finite value"
    metrics["missing"] = out


def _synthetic_geometry(cfg: EvaluateConfig, scene_path: Path, views: list[int], points, mesh,
                        metrics: dict, notes: list[str]) -> None:
    """A `svolsdf synth` scene scores itself: `synthetic_chamfer` against the ground truth the
    input views observe, distances clipped at 5 % of its diagonal (``max_dist``), F-score at
    0.5 % (``threshold``); ``overall_dtu_rule`` leaves distances beyond the cut-off out of the
    means (docs/method.md 8.1). The mesh is scored by its surface (``synthetic_chamfer`` with
    its faces)."""
    from svolsdf.evaluate.synthetic import synthetic_chamfer

    def score(pts: np.ndarray, source: str, faces: np.ndarray | None = None
              ) -> tuple[dict, dict]:
        r = synthetic_chamfer(pts, scene_path, views, max_dist=cfg.max_dist,
                              threshold=cfg.threshold, on_empty="clip", faces=faces)
        block = (chamfer_block(r, "synthetic", source) if faces is None else
                 mesh_chamfer_block(r, "synthetic", source, r["density"]))
        block["overall_dtu_rule"] = finite_or_none(r["overall_dtu_rule"])
        if r["pred_points"] == 0:
            notes.append(f"{source}: no point lies near the ground-truth object; every distance "
                         f"is clipped at {r['max_dist']:.4g}.")
        return r, block

    r = None
    if points is not None:
        r, metrics["chamfer"] = score(points[0], "points.ply")
        _put_fscore(metrics, r, r["threshold"])
    if mesh is not None:
        rm, metrics["chamfer_mesh"] = score(mesh[0], "mesh.ply", mesh[1])
        r = r or rm
    if r is not None:
        metrics["settings"]["synthetic"] = {
            "scene": str(scene_path), "input_views": list(views), "max_dist": r["max_dist"],
            "gt_points_observed": int(r["gt_points"])}
        notes.append(f"Geometry against the synthetic scene's ground truth seen by input views "
                     f"{list(views)}: distances clipped at {r['max_dist']:.4g} (5 % of its "
                     f"diagonal); 'overall_dtu_rule' leaves them out instead.")


def _put_fscore(metrics: dict, r: dict, thr: float) -> None:
    metrics["fscore"] = finite_or_none(r.get("fscore"))
    metrics["fscore_threshold"] = float(thr)
    metrics["precision"] = finite_or_none(r.get("precision"))
    metrics["recall"] = finite_or_none(r.get("recall"))


def _diag(p: np.ndarray, source: Path) -> float:
    """The bounding-box diagonal of ground-truth points (checked by `checked_ground_truth`),
    the scale of the default F-score threshold and mesh sampling density."""
    d = float(np.linalg.norm(p.max(0) - p.min(0)))
    if not d > 0:
        raise InputError(f"{source}: the ground truth's {len(p)} point(s) all lie at one "
                         "position; it has no size to scale the F-score threshold by")
    return d


def _images(cfg: EvaluateConfig, scene_path: Path | None, metrics: dict, notes: list[str],
            lp=None, input_views: list[int] | None = None) -> tuple[list[ViewImages], object]:
    """Image metrics for renders/ and renders_ibr/; returns the views and the loaded scene.
    ``lp``: the LPIPS model of ``--lpips-weights`` (loaded before the work); None: the default
    weights, whose absence leaves LPIPS null. A set without images, or a metric that cannot be
    computed, keeps null values and says why in ``missing``. A render of one of the run's
    ``input_views`` is scored under ``images_input_views`` (``images_ibr_input_views``), never in
    ``images``, whose means are those of novel views only (`mark_roles`)."""
    missing: dict[str, str] = {}
    loaded, scene = load_renders(RunFolder(cfg.out), scene_path, cfg.views, cfg.masks, notes,
                                  missing)
    for key, why in missing.items():
        metrics[key] = empty_images(why)
    if scene is None:
        return [], None
    metrics["settings"]["scene"] = str(scene_path)
    metrics["settings"]["image_size"] = [int(scene.width), int(scene.height)]
    metrics["settings"]["masks"] = scene.masks is not None
    metrics["settings"]["ground_truth_resize"] = "bicubic without antialiasing (official)"
    ibr_json = Path(cfg.out) / "renders_ibr" / "ibr.json"
    if ibr_json.is_file() and "images_ibr" in loaded:  # which IBR made renders_ibr/
        import json

        ibr_cfg = json.loads(ibr_json.read_text())
        metrics["settings"]["ibr"] = ibr_cfg
        if ibr_cfg.get("unseen", "render") != "render":
            notes.append(f"IBR: where no input view sees the surface the colour is "
                         f"'{ibr_cfg['unseen']}' (svolsdf render --ibr-unseen), not the paper's "
                         "volume-rendered colour.")
    from svolsdf.evaluate.lpips import LPIPS, lpips_distance

    lp_missing = None
    if lp is None:
        try:
            lp = LPIPS(cfg.lpips_net)
        except InputError as e:  # the default weights: PSNR, SSIM and the geometry go on
            lp_missing = f"LPIPS not computed: {e}"
            log.warning("%s (pass --lpips-weights)", lp_missing)
            notes.append(lp_missing + ".")
    metrics["settings"]["lpips_net"] = cfg.lpips_net
    metrics["settings"]["ssim_data_range"] = cfg.ssim_data_range
    masked = any(v.mask is not None for g in loaded.values() for v in g)
    metrics["settings"]["image_region"] = (
        "inside the object mask (PSNR over its pixels; SSIM and LPIPS of both images "
        "composited onto white outside it)" if masked else
        "all pixels: " + ("object masks turned off" if not cfg.masks else
                          "the scene has no object masks"))
    roles = mark_roles(loaded, input_views, metrics, notes)
    views: list[ViewImages] = []
    for key, group in loaded.items():
        for v in group:
            v.metrics = {"psnr": masked_psnr(v.pred, v.gt, v.mask),
                         "ssim": ssim(v.pred, v.gt, v.mask, data_range=cfg.ssim_data_range),
                         "lpips": lpips_distance(v.pred, v.gt, lp, v.mask)
                         if lp is not None else None}
            views.append(v)
        for role, dest in (("novel", key), ("input", f"{key}_input_views")):
            members = [v for v in group if v.role == role]
            metrics[dest] = _image_block(members, roles[role] if not members else None,
                                         lp_missing if lp is None else None)
    return views, scene


def _image_block(views: list[ViewImages], why_empty: str | None, lp_missing: str | None
                 ) -> dict:
    """The per-view values and means of PSNR, SSIM and LPIPS over ``views`` (one role of one
    renderer); ``why_empty``: the reason its values are null when ``views`` is empty."""
    block = empty_images(why_empty)
    for v in views:
        for m, x in v.metrics.items():
            block[m]["per_view"][str(v.view_id)] = finite_or_none(x)
    for m in block:
        vs = [x for x in block[m]["per_view"].values() if x is not None]
        block[m]["mean"] = float(np.mean(vs)) if vs else None
    if lp_missing is not None and views:
        block["lpips"]["missing"] = lp_missing
    return block


def evaluate_run(cfg: EvaluateConfig) -> dict:
    """Compute OUT/metrics.json (and OUT/report.html) for a run folder, holding its lock.

    Args:
        cfg: `EvaluateConfig`.

    Returns:
        the metrics dict that was written.

    Raises:
        InputError: a missing folder or ground-truth file, unreadable inputs, not a run, an
            option that cannot be honoured (a scene that is not one, views without renders),
            outputs that an earlier config made (``settings.provenance`` of the metrics), or
            another command writing the folder.
    """
    from svolsdf.io.paths import input_dir, output_dir
    from svolsdf.io.runfolder import folder_lock

    out = input_dir(cfg.out, "run folder")
    cfg = replace(cfg, out=out)
    run = RunFolder(out)
    found = check_run_folder(run, cfg.scene)
    _check_evaluate_options(cfg, out)
    bmvs = None
    if cfg.protocol == "blendedmvs":
        from svolsdf.evaluate.blendedmvs_run import check_blendedmvs

        bmvs = check_blendedmvs(out, cfg.gt_points, cfg.dtu_gt, cfg.scene, cfg.scan,
                                cfg.max_dist, cfg.volsdf, cfg.eval_masks)
    prov = check_provenance(run, found)
    lp = None
    if cfg.lpips_weights is not None:  # weights asked for and unreadable: an error, not a null
        from svolsdf.evaluate.lpips import LPIPS

        lp = LPIPS(cfg.lpips_net, cfg.lpips_weights)
    output_dir(out, "run folder")  # metrics.json goes there: fail before the work
    with folder_lock(out, "svolsdf evaluate"):
        return _evaluate_run(replace(cfg, extra={**cfg.extra, "provenance": prov}), lp, bmvs)


def _check_evaluate_options(cfg: EvaluateConfig, out: Path) -> None:
    """Options that evaluate could not honour are errors, not silently ignored."""
    if cfg.protocol not in ("auto", "blendedmvs"):
        raise InputError(f"--protocol {cfg.protocol!r}: expected 'auto' or 'blendedmvs'")
    if cfg.scan is not None and cfg.dtu_gt is None and cfg.protocol != "blendedmvs":
        raise InputError(f"--scan {cfg.scan}: only the DTU and BlendedMVS protocols use it; add "
                         "--dtu-gt ROOT or --protocol blendedmvs")
    if cfg.eval_masks is not None and cfg.protocol != "blendedmvs":
        raise InputError(f"--eval-masks {cfg.eval_masks}: only the BlendedMVS protocol's masked "
                         "score reads them; add --protocol blendedmvs")
    if cfg.volsdf is not None and cfg.protocol != "blendedmvs":
        raise InputError(f"--volsdf {cfg.volsdf}: only the BlendedMVS protocol compares against "
                         "a VolSDF run; add --protocol blendedmvs")
    if cfg.dtu_gt is not None and cfg.gt_points is not None:
        raise InputError("--dtu-gt and --gt-points: give one ground truth")
    if cfg.lpips_net not in ("vgg", "alex"):
        raise InputError(f"--lpips-net {cfg.lpips_net!r}: expected 'vgg' or 'alex'")
    for name, v in (("--threshold", cfg.threshold), ("--ssim-data-range", cfg.ssim_data_range),
                    ("max_dist", cfg.max_dist)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise InputError(f"{name} {v}: expected a number > 0")


def _evaluate_run(cfg: EvaluateConfig, lp=None, bmvs=None) -> dict:
    """`evaluate_run` once its checks passed and the lock is held (``lp``: `_images`; ``bmvs``:
    the BlendedMVS protocol's job, `_geometry`)."""
    t0 = time.perf_counter()
    out = Path(cfg.out)
    from svolsdf.io.ply import read_ply

    run = RunFolder(out)
    # the inputs the run used (config.yaml may leave them default: views.json has them)
    scene_path, input_views = run_scene(run)
    if cfg.scene is not None:
        scene_path = Path(cfg.scene)
    notes: list[str] = []
    metrics = empty_metrics()
    metrics["settings"] = dict(cfg.extra)
    _backbone_provenance(run, metrics, notes)
    points = mesh = None
    if run.points.is_file():
        d = read_ply(run.points)
        points = (d["points"], d["colors"])
    else:
        notes.append("No points.ply in the run folder.")
    if run.mesh().is_file():
        d = read_ply(run.mesh())
        if d["faces"] is not None and len(d["faces"]):
            mesh = (d["points"], d["faces"])

    views, scene = _images(cfg, scene_path, metrics, notes, lp, input_views)
    scan = cfg.scan
    if scan is None and scene is not None and scene.extras.get("scan") is not None:
        scan = int(scene.extras["scan"])
    if scan is None and scene_path is not None:
        m = re.search(r"scan(\d+)", str(scene_path))
        scan = int(m.group(1)) if m else None
    t_geo = time.perf_counter()
    no_gt = _geometry(cfg, scan, points, mesh, metrics, notes, scene_path, input_views, bmvs)
    log.info("geometry metrics in %.1fs", time.perf_counter() - t_geo)
    _missing(metrics, points, mesh, no_gt, run_kind_note(run))

    timing = run.timing()
    if timing is None:  # the stage timings only: the scores do not need them
        log.warning("%s is unreadable; timing left out", run.timing_file)
        notes.append(f"{run.timing_file.name} unreadable: stage timings left out.")
    else:
        metrics["timing"] = timing
    metrics["timing"]["evaluate_seconds"] = round(time.perf_counter() - t0, 3)
    _mesh_provenance(metrics, mesh is not None)
    write_json(run.metrics_file, metrics)

    if cfg.report:
        write_run_report_unlocked(out, metrics, views, notes, scene_path=scene_path,
                         input_views=input_views)
        metrics["timing"]["evaluate_seconds"] = round(time.perf_counter() - t0, 3)
        write_json(run.metrics_file, metrics)
    return metrics


def _backbone_provenance(run: RunFolder, metrics: dict, notes: list[str]) -> None:
    """``settings.mvs_backbone``: which MVS backbone made the run and whether it is the paper's
    (`svolsdf.config.presets.backbone_provenance`), from its config.yaml; with the paper or
    released preset and another backbone, a note says so (the report shows it)."""
    from svolsdf.config import load_config
    from svolsdf.config.presets import backbone_provenance

    if not run.config_file.is_file():
        return
    try:
        rc = load_config(run.config_file)
    except InputError as e:
        log.warning("%s: backbone not recorded (%s)", run.config_file, e)
        return
    metrics["settings"]["mvs_backbone"] = {**backbone_provenance(rc), "preset": rc.preset}
    if rc.preset in ("paper", "released") and not metrics["settings"]["mvs_backbone"]["papers"]:
        notes.append(f"{rc.preset} preset: {metrics['settings']['mvs_backbone']['note']}.")


def _mesh_provenance(metrics: dict, has_mesh: bool) -> None:
    """``mesh_source`` (which surface mesh.ply is, `svolsdf.io.runfolder.mesh_source`) and
    ``mesh_over_points`` (the mesh's accuracy, completeness and Chamfer over the points'), so
    that a mesh worse than the points shows as a number."""
    from svolsdf.io.runfolder import mesh_source

    src = mesh_source(metrics.get("timing")) if has_mesh else None
    if has_mesh and src is None:
        src = "unknown (no mesh entry in timing.json)"
    metrics["mesh_source"] = src
    metrics["chamfer_mesh"]["mesh_source"] = src
    p, m = metrics["chamfer"], metrics["chamfer_mesh"]
    metrics["mesh_over_points"] = {
        k: (round(m[k] / p[k], 4) if m.get(k) is not None and p.get(k) else None)
        for k in ("accuracy", "completeness", "overall")}
