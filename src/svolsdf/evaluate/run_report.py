"""``svolsdf report OUT``, and the last step of ``svolsdf evaluate``: OUT/report.html of a run
folder, from its outputs, metrics.json, config and scene (`svolsdf.evaluate.report.write_report`
builds the page).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from svolsdf.errors import InputError
from svolsdf.evaluate.report import ViewImages
from svolsdf.evaluate.run_outputs import (
    check_provenance,
    check_run_folder,
    empty_metrics,
    load_gt_points,
    load_renders,
    mark_roles,
    run_scene,
    scene_problem,
)
from svolsdf.evaluate.synthetic import is_synthetic_scene
from svolsdf.io.runfolder import RunFolder

__all__ = ["write_run_report", "write_run_report_unlocked"]

log = logging.getLogger(__name__)


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
    from svolsdf.io.paths import input_dir, output_dir
    from svolsdf.io.runfolder import folder_lock

    out = input_dir(out, "run folder")
    run = RunFolder(out)
    check_provenance(run, check_run_folder(run, scene_path))
    output_dir(out, "run folder")
    with folder_lock(out, "svolsdf report"):
        return write_run_report_unlocked(out, metrics, views, notes, scene_path, input_views)


def write_run_report_unlocked(out: Path, metrics: dict | None = None,
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
            metrics = empty_metrics()
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
            missing: dict[str, str] = {}
            loaded, _ = load_renders(run, scene_path, None, True, [], missing)
            problem = scene_problem(scene_path, given=False)
            if problem is not None and missing:  # renders, but no scene to compare with
                notes.append(f"Novel views not shown: {problem}")
        except InputError as e:
            notes.append(f"Novel views not shown: {e}")
            loaded = {}
        mark_roles(loaded, input_views)
        views = []
        for key, group in loaded.items():
            for v in group:  # an input view's values are those of its own label
                blk = metrics.get(key if v.role == "novel" else f"{key}_input_views") or {}
                v.metrics = {m: (blk.get(m) or {}).get("per_view", {}).get(str(v.view_id))
                             for m in ("psnr", "ssim", "lpips")}
                v.metrics = {m: x for m, x in v.metrics.items() if x is not None}
                views.append(v)
    inputs, cameras, units, gt_depth, masks = [], None, None, None, None
    if scene_path is not None:
        ids = input_views or sorted(int(p.stem) for p in run.depth_dir.glob("*.npy")
                                    if re.fullmatch(r"\d+", p.stem))
        if ids:
            try:
                from svolsdf.scene.loaders import load_scene

                s = load_scene(scene_path, views=ids)
                inputs = list(zip(s.view_ids, s.images, strict=True))
                cameras, units = s.cameras, s.units
                if s.masks is not None:  # depth errors count inside the object
                    masks = {v: s.masks[k, 0].numpy() for k, v in enumerate(s.view_ids)}
            except InputError as e:
                notes.append(f"Inputs not shown: {e}")
            if is_synthetic_scene(scene_path):
                gt_depth = {v: np.load(f) for v in ids
                            if (f := Path(scene_path) / "gt_depth" / f"{v:03d}.npy").is_file()}
    config_text = run.config_file.read_text() if run.config_file.is_file() else None
    from svolsdf.evaluate.report import write_report

    return write_report(out, metrics, views, inputs, points, mesh,
                        title=f"svolsdf run {out.resolve().name}", notes=notes, cameras=cameras,
                        gt_points=_report_gt_points(metrics, scene_path), gt_depth=gt_depth,
                        units=units, config_text=config_text, masks=masks,
                        run_info=run.run_info(), losses=_losses(run))


def _losses(run: RunFolder) -> dict[str, list[dict]]:
    """The loss logs of the run's optimizations: the field's, and the finer stage's when it
    ran (`svolsdf.evaluate.report_run.read_losses`)."""
    from svolsdf.evaluate.report_run import read_losses

    logs = {"field": run.field_dir / "losses.csv",
            "finer-stage field": run.refined_model.parent / "losses.csv"}
    return {name: rows for name, f in logs.items() if (rows := read_losses(f))}


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

