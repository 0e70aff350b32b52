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
    chamfer_mesh: {accuracy, completeness, overall, protocol, source, mesh_source}
    mesh_source: which surface mesh.ply is (field | poisson | tsdf | "field (poisson failed:
                ...)"), from timing.json; mesh_over_points: {accuracy, completeness, overall}
                of the mesh over the points'
    fscore, fscore_threshold, precision, recall
    images:     {psnr: {mean, per_view, missing}, ssim: {...}, lpips: {...}}
                (missing: why the metric is null, e.g. no renders or no LPIPS weights)
    images_ibr: the same for renders_ibr/
    timing: {..timing.json.., evaluate_seconds}
    settings: what was evaluated against what

and OUT/report.html (`svolsdf.evaluate.report`).

Geometry: with ``dtu_gt`` the DTU protocol (docs/method.md 8.1), with ``gt_points`` the generic
two-way Chamfer, and otherwise, for a scene written by ``svolsdf synth``, its own ground truth
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

import json
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
from svolsdf.evaluate.report import ViewImages
from svolsdf.evaluate.synthetic import is_synthetic_scene
from svolsdf.io.runfolder import RunFolder

__all__ = ["EvaluateConfig", "check_views_rendered", "evaluate_run", "load_gt_points",
           "write_run_report"]

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
    """DTU scan number (default: from the scene)."""
    scene: Path | None = None
    """Scene folder for ground-truth images (default: from OUT/config.yaml)."""
    views: list[int] | None = None
    """View ids to evaluate (default: every renders/<id>.png)."""
    threshold: float | None = None
    """F-score threshold in world units (default: 1% of the ground truth's bbox diagonal)."""
    max_dist: float | None = None
    """Generic Chamfer cut-off (default none; the DTU protocol always uses 20 mm)."""
    lpips_net: Literal["vgg", "alex"] = "vgg"
    """LPIPS backbone, 'vgg' (the paper's) or 'alex'."""
    lpips_weights: Path | None = None
    """LPIPS weights file or folder (default: shared/weights/lpips)."""
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


def load_gt_points(path: str | Path) -> np.ndarray:
    """(N, 3) float64 ground-truth points from a .ply or .npy file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: ground-truth points file does not exist")
    if path.suffix.lower() == ".npy":
        try:
            a = np.load(path)
        except Exception as e:
            raise InputError(f"{path}: cannot read as .npy ({e})") from None
        if a.ndim != 2 or a.shape[1] < 3:
            raise InputError(f"{path}: expected an (N, 3) array, got shape {a.shape}")
        return a[:, :3].astype(np.float64)
    from svolsdf.io.ply import read_ply

    return read_ply(path)["points"]


def run_scene(run: RunFolder) -> tuple[Path | None, list[int] | None]:
    """The scene folder and the input view ids of a run: those of its config.yaml (read by
    `svolsdf.config.load_config`), else those views.json records; None for what neither names.

    Raises:
        InputError: config.yaml is not a config (`load_config` names the key or value).
    """
    path = views = None
    if run.config_file.is_file():
        from svolsdf.config import load_config

        cfg = load_config(run.config_file)
        path = cfg.scene.path or None
        views = [int(v) for v in cfg.scene.views] if cfg.scene.views else None
    if path is None or views is None:
        rv = run.views()
        if rv is not None:
            path = path or rv.scene
            views = views or rv.inputs or None
    return (Path(path) if path else None), views


def _empty_images(missing: str | None = None) -> dict:
    return {k: {"mean": None, "per_view": {}, "missing": missing}
            for k in ("psnr", "ssim", "lpips")}


def _finite_or_none(x):
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _chamfer_block(res: dict | None, protocol: str | None, source: str | None) -> dict:
    res = res or {}
    return {"accuracy": _finite_or_none(res.get("accuracy")),
            "completeness": _finite_or_none(res.get("completeness")),
            "overall": _finite_or_none(res.get("overall")),
            "protocol": protocol, "source": source}


def _geometry(cfg: EvaluateConfig, scan: int | None, points, mesh, metrics: dict,
              notes: list[str], scene_path: Path | None = None,
              input_views: list[int] | None = None) -> None:
    if cfg.dtu_gt is not None:
        if scan is None:
            raise InputError("--dtu-gt needs --scan N (the scene does not name its DTU scan)")
        files = ch.find_dtu_files(cfg.dtu_gt, scan)
        obs = ch.load_obs_mask(files.obs_mask)
        plane = ch.load_plane(files.plane)
        from svolsdf.io.ply import read_ply

        stl = read_ply(files.stl)["points"]
        above = stl @ plane[:3] + plane[3] > 0
        thr = cfg.threshold or _diag(stl[above]) * 0.01
        metrics["settings"]["dtu"] = {"scan": scan, "obs_mask": str(files.obs_mask),
                                      "plane": str(files.plane), "stl": str(files.stl)}
        if points is not None:
            r = ch.dtu_chamfer_arrays(points[0], stl, obs, plane, seed=cfg.seed,
                                      fscore_threshold=thr)
            metrics["chamfer"] = _chamfer_block(r, "dtu", "points.ply")
            _put_fscore(metrics, r, thr)
        if mesh is not None:
            r = ch.dtu_chamfer_arrays(mesh[0], stl, obs, plane, mode="mesh", faces=mesh[1],
                                      seed=cfg.seed)
            metrics["chamfer_mesh"] = _chamfer_block(r, "dtu-mesh", "mesh.ply")
    elif cfg.gt_points is not None:
        gt = load_gt_points(cfg.gt_points)
        thr = cfg.threshold or _diag(gt) * 0.01
        metrics["settings"]["gt_points"] = str(cfg.gt_points)
        if points is not None and len(points[0]):
            r = ch.chamfer_fscore(points[0], gt, thr, max_dist=cfg.max_dist)
            metrics["chamfer"] = _chamfer_block(r, "generic", "points.ply")
            _put_fscore(metrics, r, thr)
        if mesh is not None:
            surf = ch.sample_mesh_surface(mesh[0], mesh[1], density=_diag(gt) / 1000)
            r = ch.chamfer_fscore(surf, gt, thr, max_dist=cfg.max_dist)
            metrics["chamfer_mesh"] = _chamfer_block(r, "generic-mesh", "mesh.ply")
    elif scene_path is not None and input_views and is_synthetic_scene(scene_path):
        _synthetic_geometry(cfg, scene_path, input_views, points, mesh, metrics, notes)
    else:
        notes.append("No ground-truth geometry given (--gt-points or --dtu-gt): Chamfer and "
                     "F-score are null.")


def _synthetic_geometry(cfg: EvaluateConfig, scene_path: Path, views: list[int], points, mesh,
                        metrics: dict, notes: list[str]) -> None:
    """A `svolsdf synth` scene scores itself: `synthetic_chamfer` against the ground truth the
    input views observe, distances clipped at 5 % of its diagonal (``max_dist``), F-score at
    0.5 % (``threshold``); ``overall_dtu_rule`` leaves distances beyond the cut-off out of the
    means (docs/method.md 8.1). The mesh is scored by its vertices, as benchmarks/fast_preset.py."""
    from svolsdf.evaluate.synthetic import synthetic_chamfer

    def score(pts: np.ndarray, source: str) -> tuple[dict, dict]:
        r = synthetic_chamfer(pts, scene_path, views, max_dist=cfg.max_dist,
                              threshold=cfg.threshold, on_empty="clip")
        block = _chamfer_block(r, "synthetic", source)
        block["overall_dtu_rule"] = _finite_or_none(r["overall_dtu_rule"])
        if r["pred_points"] == 0:
            notes.append(f"{source}: no point lies near the ground-truth object; every distance "
                         f"is clipped at {r['max_dist']:.4g}.")
        return r, block

    r = None
    if points is not None:
        r, metrics["chamfer"] = score(points[0], "points.ply")
        _put_fscore(metrics, r, r["threshold"])
    if mesh is not None:
        rm, metrics["chamfer_mesh"] = score(mesh[0], "mesh.ply")
        r = r or rm
    if r is not None:
        metrics["settings"]["synthetic"] = {
            "scene": str(scene_path), "input_views": list(views), "max_dist": r["max_dist"],
            "gt_points_observed": int(r["gt_points"])}
        notes.append(f"Geometry against the synthetic scene's ground truth seen by input views "
                     f"{list(views)}: distances clipped at {r['max_dist']:.4g} (5 % of its "
                     f"diagonal); 'overall_dtu_rule' leaves them out instead.")


def _put_fscore(metrics: dict, r: dict, thr: float) -> None:
    metrics["fscore"] = _finite_or_none(r.get("fscore"))
    metrics["fscore_threshold"] = float(thr)
    metrics["precision"] = _finite_or_none(r.get("precision"))
    metrics["recall"] = _finite_or_none(r.get("recall"))


def _diag(p: np.ndarray) -> float:
    if len(p) == 0:
        raise InputError("ground truth has no points")
    return float(np.linalg.norm(p.max(0) - p.min(0)))


def _render_views(run: RunFolder, scene_path: Path | None, views: list[int] | None,
                  masks: bool, notes: list[str], missing: dict[str, str] | None = None
                  ) -> tuple[dict[str, list[ViewImages]], object]:
    """Renders of renders/ ("images") and renders_ibr/ ("images_ibr") with their ground truth,
    without metrics; returns them by set and the scene loaded at the renders' size.
    ``missing`` (if given) receives, per set, why it has no images."""
    from svolsdf.io.images import read_image

    missing = {} if missing is None else missing
    sets = {"images": run.render_files(views=views),
            "images_ibr": run.render_files(ibr=True, views=views)}
    for key, files in sets.items():
        if not files:
            folder = "renders" if key == "images" else "renders_ibr"
            missing[key] = f"no {folder}/<view id>.png" + (
                f" of views {views}" if views is not None else "")
    if not any(sets.values()):
        notes.append("No renders (renders/<view id>.png): image metrics are null.")
        return {}, None
    if scene_path is None:
        notes.append("No scene (config.yaml or --scene): image metrics are null.")
        for key, files in sets.items():
            if files:
                missing[key] = "no scene (config.yaml or --scene)"
        return {}, None
    from svolsdf.scene.loaders import load_scene

    ids = sorted({v for s in sets.values() for v in s})
    first = read_image(next(iter(next(s for s in sets.values() if s).values())))
    h, w = first.shape[-2:]
    scene = load_scene(scene_path, views=ids, image_size=(w, h), masks=masks)
    loaded: dict[str, list[ViewImages]] = {}
    for key, files in sets.items():
        if not files:
            continue
        loaded[key] = []
        for vid, path in files.items():
            pred = read_image(path)
            if pred.shape[-2:] != (h, w):
                raise InputError(f"{path} is {pred.shape[-1]}x{pred.shape[-2]} but "
                                 f"{next(iter(files.values()))} is {w}x{h}; renders must share "
                                 "one size")
            k = scene.index(vid)
            mask = scene.masks[k] if scene.masks is not None else None
            loaded[key].append(ViewImages(vid, pred, scene.images[k], mask, {},
                                          "volume" if key == "images" else "ibr"))
    return loaded, scene


def _images(cfg: EvaluateConfig, scene_path: Path | None, metrics: dict, notes: list[str]
            ) -> tuple[list[ViewImages], object]:
    """Image metrics for renders/ and renders_ibr/; returns the views and the loaded scene.
    A set without images, or a metric that cannot be computed (LPIPS without its weights),
    keeps null values and says why in ``missing``."""
    missing: dict[str, str] = {}
    loaded, scene = _render_views(RunFolder(cfg.out), scene_path, cfg.views, cfg.masks, notes,
                                  missing)
    for key, why in missing.items():
        metrics[key] = _empty_images(why)
    if scene is None:
        return [], None
    metrics["settings"]["scene"] = str(scene_path)
    metrics["settings"]["image_size"] = [int(scene.width), int(scene.height)]
    metrics["settings"]["masks"] = scene.masks is not None
    from svolsdf.evaluate.lpips import LPIPS, lpips_distance

    lp = lp_missing = None
    try:
        lp = LPIPS(cfg.lpips_net, cfg.lpips_weights)
    except InputError as e:  # PSNR, SSIM and the geometry do not need it
        lp_missing = f"LPIPS not computed: {e}"
        log.warning("%s (pass --lpips-weights)", lp_missing)
        notes.append(lp_missing + ".")
    metrics["settings"]["lpips_net"] = cfg.lpips_net
    metrics["settings"]["ssim_data_range"] = cfg.ssim_data_range
    views: list[ViewImages] = []
    for key, group in loaded.items():
        block = _empty_images()
        for v in group:
            v.metrics = {"psnr": masked_psnr(v.pred, v.gt, v.mask),
                         "ssim": ssim(v.pred, v.gt, v.mask, data_range=cfg.ssim_data_range),
                         "lpips": lpips_distance(v.pred, v.gt, lp, v.mask)
                         if lp is not None else None}
            for m, x in v.metrics.items():
                block[m]["per_view"][str(v.view_id)] = _finite_or_none(x)
            views.append(v)
        for m in block:
            vs = [x for x in block[m]["per_view"].values() if x is not None]
            block[m]["mean"] = float(np.mean(vs)) if vs else None
        if lp is None:
            block["lpips"]["missing"] = lp_missing
        metrics[key] = block
    return views, scene


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
    from svolsdf.io.folders import ensure_writable_folder
    from svolsdf.io.runfolder import folder_lock

    out = Path(cfg.out)
    if not out.is_dir():
        raise InputError(f"{out}: run folder does not exist")
    run = RunFolder(out)
    found = _check_run_folder(run, cfg.scene)
    _check_evaluate_options(cfg, out)
    prov = _check_provenance(run, found)
    ensure_writable_folder(out, "run folder")  # metrics.json goes there: fail before the work
    with folder_lock(out, "svolsdf evaluate"):
        return _evaluate_run(replace(cfg, extra={**cfg.extra, "provenance": prov}))


def _check_run_folder(run: RunFolder, scene: Path | None) -> list[str]:
    """The outputs evaluate and report read in OUT (`RunFolder.outputs`); refuses a folder
    without any (a scene, an empty or half-finished run: nothing is written into it) and a
    ``scene`` that is none."""
    found = run.outputs()
    if not found:
        raise InputError(f"{run.root}: not a run folder (no points.ply, mesh.ply or "
                         "renders/<view id>.png); give the output folder of svolsdf "
                         "reconstruct, mvs or render, once it has finished")
    if scene is not None:
        from svolsdf.scene.loaders import detect_format

        detect_format(scene)  # --scene WRONG: refused, not scored against nothing
    return found


def check_views_rendered(out: str | Path, views: list[int] | None) -> None:
    """``svolsdf evaluate --views``: every view asked for has a render to score (a benchmark
    passes its held-out views whether or not the run rendered them, and gets nulls).

    Raises:
        InputError: naming the views without renders/<id>.png and the command that makes them.
    """
    if views is None:
        return
    run = RunFolder(out)
    have = set(run.render_files()) | set(run.render_files(ibr=True))
    missing = [v for v in views if v not in have]
    if missing:
        raise InputError(f"--views: no renders/<id>.png of view(s) {missing} in {out} "
                         f"(rendered: {sorted(have) or 'none'}); run svolsdf render {out} "
                         f"--views {' '.join(map(str, views))} first")


def _check_evaluate_options(cfg: EvaluateConfig, out: Path) -> None:
    """Options that evaluate could not honour are errors, not silently ignored."""
    if cfg.scan is not None and cfg.dtu_gt is None:
        raise InputError(f"--scan {cfg.scan}: only the DTU protocol uses it; add --dtu-gt ROOT")
    if cfg.dtu_gt is not None and cfg.gt_points is not None:
        raise InputError("--dtu-gt and --gt-points: give one ground truth")


def _check_provenance(run: RunFolder, found: list[str]) -> dict[str, str]:
    """{output: whether OUT/config.yaml made it} (`svolsdf.io.runfolder.output_provenance`);
    refuses outputs that an earlier config made, which would be scored under the wrong one."""
    names = [n for n in found if n in ("points.ply", "mesh.ply")]
    if any(n.startswith("renders") for n in found):
        names.append("renders")
    prov = run.output_provenance(names)
    stale = [n for n, v in prov.items() if v == "another config"]
    if stale:
        out = run.root
        again = f"svolsdf reconstruct -o {out} --config {run.config_file}"
        if "renders" in stale:
            again = (f"{again}, then " if stale != ["renders"] else "") + f"svolsdf render {out}"
        raise InputError(f"{out}: {', '.join(stale)} came from an earlier config than "
                         f"{run.config_file} (a rerun with other options stopped before "
                         f"it made them again); run {again} first")
    return prov


def _evaluate_run(cfg: EvaluateConfig) -> dict:
    """`evaluate_run` once its checks passed and the lock is held."""
    t0 = time.perf_counter()
    out = Path(cfg.out)
    if cfg.lpips_net not in ("vgg", "alex"):
        raise InputError(f"--lpips-net {cfg.lpips_net!r}: expected 'vgg' or 'alex'")
    for name, v in (("--threshold", cfg.threshold), ("--ssim-data-range", cfg.ssim_data_range),
                    ("max_dist", cfg.max_dist)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise InputError(f"{name} {v}: expected a number > 0")
    from svolsdf.io.ply import read_ply

    run = RunFolder(out)
    # the inputs the run used (config.yaml may leave them default: views.json has them)
    scene_path, input_views = run_scene(run)
    if cfg.scene is not None:
        scene_path = Path(cfg.scene)
    notes: list[str] = []
    metrics = _empty_metrics()
    metrics["settings"] = dict(cfg.extra)
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

    views, scene = _images(cfg, scene_path, metrics, notes)
    scan = cfg.scan
    if scan is None and scene is not None and scene.extras.get("scan") is not None:
        scan = int(scene.extras["scan"])
    if scan is None and scene_path is not None:
        m = re.search(r"scan(\d+)", str(scene_path))
        scan = int(m.group(1)) if m else None
    t_geo = time.perf_counter()
    _geometry(cfg, scan, points, mesh, metrics, notes, scene_path, input_views)
    log.info("geometry metrics in %.1fs", time.perf_counter() - t_geo)

    timing = run.timing()
    if timing is None:  # the stage timings only: the scores do not need them
        log.warning("%s is unreadable; timing left out", run.timing_file)
        notes.append(f"{run.timing_file.name} unreadable: stage timings left out.")
    else:
        metrics["timing"] = timing
    metrics["timing"]["evaluate_seconds"] = round(time.perf_counter() - t0, 3)
    _mesh_provenance(metrics, mesh is not None)
    _write_json(run.metrics_file, metrics)

    if cfg.report:
        _write_run_report(out, metrics, views, notes, scene_path=scene_path,
                         input_views=input_views)
        metrics["timing"]["evaluate_seconds"] = round(time.perf_counter() - t0, 3)
        _write_json(run.metrics_file, metrics)
    return metrics


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


def _empty_metrics() -> dict:
    return {"chamfer": _chamfer_block(None, None, None),
            "chamfer_mesh": _chamfer_block(None, None, None),
            "fscore": None, "fscore_threshold": None, "precision": None, "recall": None,
            "images": _empty_images(), "images_ibr": _empty_images(),
            "mesh_source": None,
            "mesh_over_points": {"accuracy": None, "completeness": None, "overall": None},
            "timing": {}, "settings": {}}


def _report_gt_points(metrics: dict, scene_path: Path | None) -> np.ndarray | None:
    """The ground truth the metrics were computed against (or a synthetic scene's own)."""
    st = metrics.get("settings") or {}
    try:
        if st.get("dtu") and st["dtu"].get("stl"):
            from svolsdf.io.ply import read_ply

            return read_ply(st["dtu"]["stl"])["points"]
        if st.get("gt_points"):
            return load_gt_points(st["gt_points"])
        syn = (st.get("synthetic") or {}).get("scene") or scene_path
        if syn is not None and is_synthetic_scene(syn):
            return load_gt_points(Path(syn) / "gt_points.ply")
    except InputError as e:
        log.warning("report: ground truth not shown (%s)", e)
    return None


def write_run_report(out: str | Path, metrics: dict | None = None,
                     views: list[ViewImages] | None = None, notes: list[str] | None = None,
                     scene_path: Path | None = None, input_views: list[int] | None = None,
                     ) -> Path:
    """Write OUT/report.html from a run folder (`svolsdf.evaluate.report.write_report`).

    Reads points.ply, mesh.ply (with its vertex colours), depth/, normals/, config.yaml,
    timing.json, the scene's input photos and cameras and, for a synthetic scene, its
    ground-truth points and depth. Without ``metrics`` it takes OUT/metrics.json (nulls when
    there is none); without ``views`` it loads renders/ and renders_ibr/ beside their ground
    truth and takes their per-view metrics from the metrics.

    Args:
        out: the run folder.
        metrics: the evaluation's metrics (default: OUT/metrics.json).
        views: evaluated novel views (default: loaded from the renders).
        notes: lines shown under the title.
        scene_path: the scene folder (default: from OUT/config.yaml or OUT/views.json).
        input_views: the input view ids (default: from config.yaml or views.json).

    Returns:
        the path of report.html.

    Raises:
        InputError: OUT is not a folder or not a run (no outputs yet), ``scene_path`` is not a
            scene, outputs came from an earlier config, a file in it is unreadable, or another
            command writes the folder.
    """
    from svolsdf.io.folders import ensure_writable_folder
    from svolsdf.io.runfolder import folder_lock

    out = Path(out)
    if not out.is_dir():
        raise InputError(f"{out}: run folder does not exist")
    run = RunFolder(out)
    _check_provenance(run, _check_run_folder(run, scene_path))
    ensure_writable_folder(out, "run folder")
    with folder_lock(out, "svolsdf report"):
        return _write_run_report(out, metrics, views, notes, scene_path, input_views)


def _write_run_report(out: Path, metrics: dict | None = None,
                      views: list[ViewImages] | None = None, notes: list[str] | None = None,
                      scene_path: Path | None = None, input_views: list[int] | None = None,
                      ) -> Path:
    """`write_run_report` once its checks passed and the lock is held."""
    from svolsdf.io.ply import read_ply

    out = Path(out)
    run = RunFolder(out)
    notes = list(notes or [])
    if scene_path is None or not input_views:
        run_path, run_views = run_scene(run)
        scene_path = scene_path or run_path
        input_views = input_views or run_views
    if metrics is None:
        metrics = run.metrics()
        if metrics is None:
            metrics = _empty_metrics()
            notes.append(f"No metrics.json: run svolsdf evaluate {out} for the metrics.")
            metrics["timing"] = run.timing() or {}
    points = mesh = None
    if run.points.is_file():
        d = read_ply(run.points)
        points = (d["points"], d["colors"])
    if run.mesh().is_file():
        d = read_ply(run.mesh())
        if d["faces"] is not None and len(d["faces"]):
            mesh = (d["points"], d["faces"], d["colors"])
    if views is None and scene_path is not None:
        try:
            loaded, _ = _render_views(run, scene_path, None, True, [])
        except InputError as e:
            notes.append(f"Novel views not shown: {e}")
            loaded = {}
        views = []
        for key, group in loaded.items():
            for v in group:
                blk = metrics.get(key) or {}
                v.metrics = {m: (blk.get(m) or {}).get("per_view", {}).get(str(v.view_id))
                             for m in ("psnr", "ssim", "lpips")}
                v.metrics = {m: x for m, x in v.metrics.items() if x is not None}
                views.append(v)
    inputs, cameras, units, gt_depth = [], None, None, None
    if scene_path is not None:
        ids = input_views or sorted(int(p.stem) for p in run.depth_dir.glob("*.npy")
                                    if re.fullmatch(r"\d+", p.stem))
        if ids:
            try:
                from svolsdf.scene.loaders import load_scene

                s = load_scene(scene_path, views=ids, masks=False)
                inputs = list(zip(s.view_ids, s.images, strict=True))
                cameras, units = s.cameras, s.units
            except InputError as e:
                notes.append(f"Inputs not shown: {e}")
            if is_synthetic_scene(scene_path):
                units = units if units not in (None, "unknown") else _synthetic_units(scene_path)
                gt_depth = {v: np.load(f) for v in ids
                            if (f := Path(scene_path) / "gt_depth" / f"{v:03d}.npy").is_file()}
    config_text = run.config_file.read_text() if run.config_file.is_file() else None
    from svolsdf.evaluate.report import write_report

    return write_report(out, metrics, views, inputs, points, mesh,
                        title=f"svolsdf run {out.resolve().name}", notes=notes, cameras=cameras,
                        gt_points=_report_gt_points(metrics, scene_path), gt_depth=gt_depth,
                        units=units, config_text=config_text)


def _synthetic_units(scene_path: Path) -> str | None:
    """The "units" that `svolsdf synth` records in scene.json (millimetres), or None."""
    try:
        return json.loads((Path(scene_path) / "scene.json").read_text()).get("units")
    except (OSError, ValueError, AttributeError):
        return None


def _write_json(path: Path, obj: dict) -> None:
    from svolsdf.io.runfolder import atomic_write

    text = json.dumps(obj, indent=2, allow_nan=False)
    atomic_write(path, lambda tmp: tmp.write_text(text))

