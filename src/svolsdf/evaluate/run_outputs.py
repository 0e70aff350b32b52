"""What ``svolsdf evaluate`` and ``svolsdf report`` read from a run folder, and what they check
before they write into it: the run's scene and input views (its config.yaml through
`svolsdf.config.load_config`, else views.json), the renders beside their ground-truth images, the
outputs present and the config that made them (`svolsdf.io.runfolder.RunFolder`), ground-truth
point files, and metrics.json's layout with every value null.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from svolsdf.errors import InputError
from svolsdf.evaluate.report_parts import ViewImages
from svolsdf.io.paths import input_file
from svolsdf.io.runfolder import OUTPUT_STAGES, RunFolder

__all__ = ["PROTOCOLS", "chamfer_block", "check_provenance", "check_run_folder",
           "check_views_rendered", "empty_images", "empty_metrics", "finite_or_none",
           "load_gt_points", "load_renders", "mark_roles", "metric_lines", "protocol_label",
           "run_kind_note", "run_scene", "scene_problem", "write_json"]


def run_scene(run: RunFolder) -> tuple[Path | None, list[int] | None]:
    """The scene folder and the input view ids of a run: those of its config.yaml (read by
    `svolsdf.config.load_config`), else those views.json records, else those of mvs.json (an
    output folder of ``svolsdf mvs``); None for what none of them names.

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
    if path is None or views is None:
        mvs_path, mvs_views = _mvs_summary_scene(run.root / "mvs.json")
        path = path or mvs_path
        views = views or mvs_views
    return (Path(path) if path else None), views


def _mvs_summary_scene(path: Path) -> tuple[str | None, list[int] | None]:
    """The ``scene`` and ``views`` that ``svolsdf mvs`` wrote to its mvs.json (Nones when the
    file is missing, unreadable or lacks them: the run then names no scene)."""
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError):
        return None, None
    if not isinstance(d, dict):
        return None, None
    scene = d.get("scene") if isinstance(d.get("scene"), str) and d.get("scene") else None
    views = d.get("views")
    ok = isinstance(views, list) and views and all(isinstance(v, int) for v in views)
    return scene, (list(views) if ok else None)


def scene_problem(scene_path: Path | None, given: bool) -> str | None:
    """Why the scene a run names cannot give ground truth (None when it is a folder): none
    named, or a folder that is not there any more.

    Args:
        scene_path: the run's scene folder (`run_scene`) or ``--scene``'s.
        given: whether ``--scene`` gave it (else the run's files named it).
    """
    if scene_path is None:
        return ("the run names no scene folder (no config.yaml, views.json or mvs.json with "
                "one); pass --scene FOLDER")
    if not Path(scene_path).is_dir():
        named = "--scene" if given else "the run folder's config.yaml / views.json / mvs.json"
        rel = "" if Path(scene_path).is_absolute() else ", read from the current folder"
        return (f"scene folder {scene_path} (named by {named}{rel}) does not exist (moved? "
                "pass --scene FOLDER)")
    return None


def load_gt_points(path: str | Path) -> np.ndarray:
    """(N, 3) float64 ground-truth points from a .ply or .npy file.

    Raises:
        InputError: naming the file: unreadable, not (N, 3), empty, or with NaN or infinite
            coordinates (`svolsdf.evaluate.points.checked_ground_truth`).
    """
    from svolsdf.evaluate.points import checked_ground_truth

    path = input_file(path, "ground-truth points file")
    if path.suffix.lower() == ".npy":
        try:
            a = np.load(path)
        except Exception as e:
            raise InputError(f"{path}: cannot read as .npy ({e})") from None
        if a.ndim != 2 or a.shape[1] < 3:
            raise InputError(f"{path}: expected an (N, 3) array, got shape {a.shape}")
        return checked_ground_truth(a[:, :3], path)
    from svolsdf.io.ply import read_ply

    return checked_ground_truth(read_ply(path)["points"], path)


def check_run_folder(run: RunFolder, scene: Path | None) -> list[str]:
    """The outputs evaluate and report read in OUT (`RunFolder.outputs`); refuses a folder
    without any (a scene, an empty or half-finished run: nothing is written into it) and a
    ``scene`` that is none. A folder another command is writing (a reconstruction in progress)
    is refused first, naming it: its files are not yet the run's."""
    from svolsdf.io.runfolder import refuse_in_progress

    refuse_in_progress(run.root)
    found = run.outputs()
    if not found:
        raise InputError(f"{run.root}: not a run folder (no points.ply, mesh.ply or "
                         "renders/<view id>.png); give the output folder of svolsdf "
                         "reconstruct, mvs or render, once it has finished")
    if scene is not None:
        from svolsdf.scene.loaders import scene_folder

        scene_folder(scene, "--scene")  # --scene WRONG: refused, not scored against nothing
    return found


def check_provenance(run: RunFolder, found: list[str]) -> dict[str, str]:
    """{output: whether OUT/config.yaml made it} (`svolsdf.io.runfolder.output_provenance`);
    refuses outputs that an earlier config made, which would be scored under the wrong one."""
    names = [n for n in found if n in ("points.ply", "mesh.ply")]
    if any(n.startswith("renders") for n in found):
        names.append("renders")
    for name in names:  # cut short or replaced since its stage finished: no score for it
        why = run.changed_output(OUTPUT_STAGES.get(name, name))
        if why is not None:
            raise InputError(f"{run.root}: {why}; run svolsdf reconstruct -o {run.root} "
                             f"--config {run.config_file} to make it again")
    prov = run.output_provenance(names)
    if prov.get("renders") == "another config" and _renders_of_the_current_field(run):
        prov["renders"] = "the current field (config.yaml changed elsewhere)"
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


def _renders_of_the_current_field(run: RunFolder) -> bool:
    """Whether renders/ came from the field the run has now: the model file `svolsdf render`
    recorded is unchanged and no finer-stage field has replaced it since. A config change that
    left the field alone (the mesh's options) then keeps the renders, with no new render."""
    from svolsdf.io.runfolder import file_record

    prov = run.stage_state().get("provenance")
    rec = prov.get("render") if isinstance(prov, dict) else None
    if not isinstance(rec, dict) or not isinstance(rec.get("model"), str):
        return False
    model = run.root / rec["model"]
    if not model.is_file() or file_record(model) != rec.get("model_record"):
        return False
    if run.output_provenance(["field"])["field"] == "another config":
        return False  # a rerun changed the field's options and stopped before training it
    return model == run.refined_model or not run.refined_model.is_file()


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


def load_renders(run: RunFolder, scene_path: Path | None, views: list[int] | None,
                  masks: bool, notes: list[str], missing: dict[str, str] | None = None
                  ) -> tuple[dict[str, list[ViewImages]], object]:
    """Renders of renders/ ("images") and renders_ibr/ ("images_ibr") with their ground truth,
    without metrics; returns them by set and the scene loaded at the renders' size.
    ``missing`` (if given) receives, per set, why it has no images."""
    from svolsdf.io.images import read_image

    missing = {} if missing is None else missing
    sets = {"images": run.render_files(views=views),
            "images_ibr": run.render_files(ibr=True, views=views)}
    kind = run_kind_note(run)
    for key, files in sets.items():
        if not files:
            folder = "renders" if key == "images" else "renders_ibr"
            missing[key] = f"no {folder}/<view id>.png" + (
                f" of views {views}" if views is not None else "") + (
                f": {kind}" if kind else "")
    if not any(sets.values()):
        notes.append("No renders (renders/<view id>.png): image metrics are null.")
        return {}, None
    no_scene = scene_problem(scene_path, given=False)
    if no_scene is not None:
        notes.append(f"Image metrics are null: {no_scene}.")
        for key, files in sets.items():
            if files:
                missing[key] = no_scene
        return {}, None
    from svolsdf.scene.loaders import load_scene

    ids = sorted({v for s in sets.values() for v in s})
    first = read_image(next(iter(next(s for s in sets.values() if s).values())))
    h, w = first.shape[-2:]
    scene = load_scene(scene_path, views=ids, image_size=(w, h), masks=masks)
    # the ground truth as the official evaluation prepares it (docs/method.md 8.3): the photo
    # resized without antialiasing, the mask bilinear > 0.5 (svolsdf.evaluate.protocol)
    from svolsdf.evaluate.protocol import official_test_images

    gt_images, gt_masks = official_test_images(scene_path, ids, (w, h))
    if not masks:
        gt_masks = None
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
            mask = gt_masks[k][None].float() if gt_masks is not None else None
            loaded[key].append(ViewImages(vid, pred, gt_images[k], mask, {},
                                          "volume" if key == "images" else "ibr"))
    return loaded, scene


def mark_roles(loaded: dict[str, list[ViewImages]], input_views: list[int] | None,
               metrics: dict | None = None, notes: list[str] | None = None) -> dict[str, str]:
    """Sets each loaded view's ``role``: "input" when the run used it as an input view (its
    render is a training view copied back, not a novel view), else "novel". Records in
    ``metrics["views"]`` the run's input views and which rendered views were scored in each
    role, and adds a note when input views were rendered or the run names none.

    Returns:
        {role: why that role has no views}, the reason its metrics are null when it is empty.
    """
    inputs = set(input_views or [])
    for group in loaded.values():
        for v in group:
            v.role = "input" if v.view_id in inputs else "novel"
    ids = {role: sorted({v.view_id for g in loaded.values() for v in g if v.role == role})
           for role in ("novel", "input")}
    if metrics is not None:
        metrics["views"] = {"inputs": None if input_views is None else sorted(inputs),
                            "novel_scored": ids["novel"], "input_scored": ids["input"]}
    if notes is not None and ids["input"]:
        notes.append(f"Views {ids['input']} are input views of the run (it trained on them): "
                     "their renders are scored under their own label, input views, and left "
                     "out of every novel-view mean.")
    if notes is not None and input_views is None and ids["novel"]:
        notes.append("The run records no input views (config.yaml, views.json): the renders "
                     "are scored as novel views without that check.")
    return {"novel": (f"every rendered view ({ids['input']}) is an input view of the run, "
                      "scored under images_input_views, not as a novel view; render held-out "
                      "views with svolsdf render OUT --views ID ..."),
            "input": "no input view of the run was rendered"}


PROTOCOLS = {
    "dtu": "DTU protocol: the official ObsMask, plane and STL points, distances cut at 20 mm "
           "(docs/method.md 8.1)",
    "dtu-mesh": "DTU protocol on the mesh's surface (docs/method.md 8.1)",
    "generic": "generic two-way Chamfer against the whole --gt-points cloud, no cut-off unless "
               "max_dist",
    "generic-mesh": "generic two-way Chamfer of the mesh's surface against the whole "
                    "--gt-points cloud",
    "synthetic": "the synthetic scene's own ground truth, only the part the input views see, "
                 "distances clipped at 5 % of its diagonal (the benchmarks' protocol)",
    "blendedmvs": "BlendedMVS protocol, unmasked: the ground plane fitted to --gt-points and "
                  "removed from both clouds, distances beyond max_dist left out (docs/method.md "
                  "8.2)",
    "blendedmvs-masked": "BlendedMVS protocol, masked: as unmasked, both clouds kept inside the "
                         "evaluation masks of the views that see them (docs/method.md 8.2)",
}
"""What each Chamfer ``protocol`` of metrics.json measures. Numbers of two protocols differ on
the same reconstruction (the whole ground truth against the part the inputs see; a cut-off or
none) and are never compared: benchmark tables refuse to mix them in a column."""


def protocol_label(protocol: str | None) -> str:
    """One line saying which protocol a Chamfer number follows (`PROTOCOLS`)."""
    if protocol is None:
        return "not recorded (metrics of an older version)"
    return PROTOCOLS.get(protocol, f"protocol {protocol!r}")


def metric_lines(m: dict) -> list[str]:
    """What ``svolsdf evaluate`` prints of metrics.json: each number with the protocol it
    follows (Chamfer) or the views and region it covers (images), then one line per reason a
    metric is null; never a bare None."""

    def num(x) -> str:
        return f"{x:.4g}"

    lines = []
    for key, what in (("chamfer", "points.ply"), ("chamfer_mesh", "mesh.ply")):
        c = m.get(key) or {}
        if c.get("overall") is None:
            continue
        line = (f"{what} Chamfer [{protocol_label(c.get('protocol'))}]: accuracy "
                f"{num(c['accuracy'])}, completeness {num(c['completeness'])}, overall "
                f"{num(c['overall'])}")
        if key == "chamfer" and m.get("fscore") is not None:
            line += f"; F-score {num(m['fscore'])} at {num(m['fscore_threshold'])}"
        if key == "chamfer_mesh" and c.get("density"):
            line += f" (its surface, sampled every {c['density']:.3g})"
        lines.append(line)
    lines += _blendedmvs_lines(m.get("blendedmvs"), num)
    region = (m.get("settings") or {}).get("image_region")
    views = m.get("views") or {}
    for key, what, ids in (
            ("images", "novel views, volume rendering", views.get("novel_scored")),
            ("images_ibr", "novel views, IBR", views.get("novel_scored")),
            ("images_input_views", "input views (trained on, not novel), volume rendering",
             views.get("input_scored")),
            ("images_ibr_input_views", "input views (trained on, not novel), IBR",
             views.get("input_scored"))):
        blk = m.get(key) or {}
        vals = [f"{k} {num(blk[k]['mean'])}" for k in ("psnr", "ssim", "lpips")
                if (blk.get(k) or {}).get("mean") is not None]
        if vals:
            lines.append(f"{what} {ids or ''} [{region}]: {', '.join(vals)}".replace(" []", ""))
    by_reason: dict[str, list[str]] = {}  # each null metric and why, one line per reason
    for name, why in (m.get("missing") or {}).items():
        by_reason.setdefault(why, []).append(name)
    lines += [f"not computed: {', '.join(names)}: {why}" for why, names in by_reason.items()]
    return lines


def _blendedmvs_lines(b: dict | None, num) -> list[str]:
    """The BlendedMVS protocol's masked score, the VolSDF run's scores and the relative
    improvement over it (`svolsdf.evaluate.blendedmvs_run`); the unmasked score is the
    ``chamfer`` line."""
    if not b:
        return []

    def chamfer(blk: dict) -> str:
        if blk["overall"] is None:
            return f"null ({blk['missing']})"
        return (f"accuracy {num(blk['accuracy'])}, completeness {num(blk['completeness'])}, "
                f"overall {num(blk['overall'])}")

    lines = [f"points.ply Chamfer [{protocol_label('blendedmvs-masked')}]: "
             f"{chamfer(b['masked'])}"]
    v = b.get("volsdf")
    if v:
        for key in ("unmasked", "masked"):
            lines.append(f"VolSDF run {v['run']} Chamfer [{protocol_label(v[key]['protocol'])}]"
                         f": {chamfer(v[key])}")
        rel = b["relative_improvement"]
        vals = ", ".join(f"{k} " + ("null" if rel[k] is None else f"{100 * rel[k]:.1f} %")
                         for k in ("unmasked", "masked"))
        lines.append(f"relative improvement over VolSDF, (VolSDF - run) / VolSDF of the overall "
                     f"Chamfer [BlendedMVS protocol]: {vals}")
    return lines


def run_kind_note(run: RunFolder) -> str | None:
    """Why an output folder of ``svolsdf mvs`` (mvs.json, no config.yaml) lacks renders and a
    mesh: the MVS job makes neither. None for other folders."""
    if (run.root / "mvs.json").is_file() and not run.config_file.is_file():
        return ("an svolsdf mvs folder: the MVS job makes depth maps and points, no field, "
                "renders or mesh (svolsdf reconstruct, then svolsdf render, make them)")
    return None


def empty_metrics() -> dict:
    return {"chamfer": chamfer_block(None, None, None),
            "chamfer_mesh": mesh_chamfer_block(None, None, None, None),
            "fscore": None, "fscore_threshold": None, "precision": None, "recall": None,
            "images": empty_images(), "images_ibr": empty_images(),
            "images_input_views": empty_images(), "images_ibr_input_views": empty_images(),
            "views": {"inputs": None, "novel_scored": [], "input_scored": []},
            "mesh_source": None,
            "mesh_over_points": {"accuracy": None, "completeness": None, "overall": None},
            "blendedmvs": None, "missing": {}, "timing": {}, "settings": {}}


def empty_images(missing: str | None = None) -> dict:
    return {k: {"mean": None, "per_view": {}, "missing": missing}
            for k in ("psnr", "ssim", "lpips")}


def chamfer_block(res: dict | None, protocol: str | None, source: str | None) -> dict:
    res = res or {}
    return {"accuracy": finite_or_none(res.get("accuracy")),
            "completeness": finite_or_none(res.get("completeness")),
            "overall": finite_or_none(res.get("overall")),
            "protocol": protocol, "source": source, "missing": None}


def mesh_chamfer_block(res: dict | None, protocol: str | None, source: str | None,
                       density: float | None) -> dict:
    """`chamfer_block` of a mesh, which is scored by its surface
    (`svolsdf.evaluate.chamfer.mesh_surface_points`): ``sampled`` "surface" and ``density``, the
    spacing of the samples in world units (null when not scored). Metrics written before meshes
    were scored this way have neither key: those scored the vertices."""
    block = chamfer_block(res, protocol, source)
    scored = res is not None
    block["sampled"] = "surface" if scored else None
    block["density"] = finite_or_none(density) if scored else None
    return block


def finite_or_none(x):
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def write_json(path: Path, obj: dict) -> None:
    from svolsdf.io.runfolder import atomic_write

    text = json.dumps(obj, indent=2, allow_nan=False)
    atomic_write(path, lambda tmp: tmp.write_text(text))
