"""Fast-preset benchmark (issue 5): whole pipeline, three views, wall time, peak memory, Chamfer.

On a synthetic scene with exact ground truth (``svolsdf synth``, 768x576 by default) it runs, one
after another in fresh processes (`svolsdf reconstruct`):

  (a) mvs-only          the MVS backbone alone (stages 1-3 + fusion)
  (b) volsdf            the fast preset's field without the MVS prior (sphere init, no GCE)
  (c) paper             the S-VolSDF paper preset (8x256 MLP, error-bounded sampler), given the
                        wall time that (d) used (stage 1, then optimization until the budget is
                        spent, then its mesh; scored by the mesh)
  (d) fast              the S-VolSDF fast preset (the default)
  (d')                  (d)'s points without the unguided set (`fusion.unguided`
                        off: the guided stages 2-3 alone, as the paper fuses); fusion
                        rerun on a copy of (d)'s folder

and scores points.ply (and mesh.ply, by its surface) against the ground-truth surface the input
views observe (`svolsdf.evaluate.synthetic.synthetic_chamfer`, as `svolsdf evaluate` scores).
Results go to a Markdown file with the machine and the command. Results written before meshes
were scored by their surface scored a mesh by its vertices.

More scenes, (a) and (d) only, one table row each with the ratio:
  --more SEED:OBJECT ...   synthetic scenes generated here (`svolsdf synth`)
  --scenes PATH ...        any scene folder with exact ground truth in the layout `svolsdf synth`
                           writes (cameras.npz, image/, mask/, gt_points.ply, gt_depth/)

Real DTU scans (IDR layout, as ../shared/data/dtu_scan65):
  --dtu                    the fast preset on ../shared/data/dtu_scan65
  --dtu-scenes PATH ...    the fast preset on these scans
  For each: stage times, peak memory, held-out PSNR / SSIM / LPIPS (volume rendering and IBR).
  With --dtu-gt ROOT (DTU's ObsMask/, Points/stl/; the scan number comes from the folder name,
  e.g. dtu_scan24), also (a) the MVS backbone alone, and both scored by the DTU protocol
  (`svolsdf evaluate --dtu-gt`), with the ratio (d)/(a).

Side by side with a baseline commit (issue 39; benchmarks/_side_by_side.py):
  --against REV            the fast preset of this checkout ("new") and of REV ("old", a detached
                           git worktree in OUT/baseline_src), each in fresh `svolsdf reconstruct`
                           processes with its own code and the same arguments, old then new per
                           scene, on --scenes (synthetic), --dtu / --dtu-scenes (DTU); per scene
                           and commit: stage times, wall, peak memory, points and mesh Chamfer
                           (DTU: with --pgt NAME=DIR, the pseudo ground truth of dtu_pseudo_gt.py,
                           as mesh_study.py scores it) and held-out PSNR; then the issue's
                           targets, pass or fail. Only the side-by-side runs (not (a)-(d)).
  --many-views SCENE       also the fast preset on all --many-views-n (9) views of SCENE (new
                           only; --many-views-old: old too)
  --set KEY=VALUE          passed to both sides' `svolsdf reconstruct` (e.g. a tiny smoke test)
  e.g. python benchmarks/fast_preset.py --against REV --out OUT --scenes SYNTH ... \
           --dtu --pgt dtu_scan65=PGT_DIR --many-views SYNTH \
           --results benchmarks/results/fast_preset_side_by_side.md

Usage:
    python benchmarks/fast_preset.py [--size 768x576] [--seed 0] [--out /tmp/fast_bench]
        [--results benchmarks/results/fast_preset.md] [--only a,b,c,d]
        [--more 3:random 7:blobs ...] [--scenes PATH ...]
        [--dtu] [--dtu-scenes PATH ...] [--dtu-gt ROOT]

Everything is cached in OUT: a rerun reuses the finished pipeline stages (`svolsdf reconstruct`
resumes), and the wall time reported is the sum of the stages' recorded times.

Either mode writes its data as JSON beside the Markdown (--results with .json) and renders the
Markdown, its tables, checks and notes, from that JSON alone:
  --from-json FILE.json    render that JSON's Markdown again (to --results, default FILE.md),
                           running nothing; e.g. python benchmarks/fast_preset.py --from-json
                           benchmarks/results/fast_preset_side_by_side.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

# benchmarks/_machine.py (the script's folder is on sys.path)
from _machine import copy_run, cpu_name, peak_rss_gb, public_argv

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def _reconstruct(scene: Path, out: Path, *args: str) -> float:
    cmd = [sys.executable, "-m", "svolsdf", "reconstruct", str(scene), "-o", str(out),
           "--no-progress", *args]
    print("$", " ".join(cmd), flush=True)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    return time.perf_counter() - t0


def _score_ply(scene: Path, f: Path, views: list[int]) -> dict:
    """Chamfer of one PLY: a point cloud by its points, a mesh (a PLY with faces) by its surface
    (`svolsdf.evaluate.chamfer.mesh_surface_points`, as `svolsdf evaluate` scores a mesh);
    nothing near the object scores the clip distance."""
    from svolsdf.io.ply import read_ply

    d = read_ply(f)
    return _score_points(scene, d["points"], views, f.name, faces=d["faces"])


def _score_points(scene: Path, pts, views: list[int], name: str, faces=None) -> dict:
    """Chamfer of (N, 3) world points (N may be 0), or with (F, 3) ``faces`` of the mesh whose
    vertices they are, by its surface; nothing near the object scores the clip distance."""
    from svolsdf.evaluate.synthetic import synthetic_chamfer

    r = synthetic_chamfer(pts, scene, views, on_empty="clip", faces=faces)
    # overall_dtu_rule: the DTU / BlendedMVS rule (docs/method.md 8.1), distances beyond the cut-off
    # left out
    out = {k: r[k] for k in ("accuracy", "completeness", "overall", "overall_dtu_rule", "fscore",
                             "sampled", "density")}
    if r["pred_points"] == 0:
        out["error"] = (f"{name}: no point lies near the ground-truth object; every distance "
                        f"is clipped at {r['max_dist']:.2f} mm")
    return out


def _score_mesh(scene: Path, out: Path, views: list[int]) -> dict:
    f = out / "mesh.ply"
    return {"mesh": _score_ply(scene, f, views)} if f.is_file() else {}


def _score(scene: Path, out: Path) -> dict:
    views = json.loads((out / "views.json").read_text())["inputs"]
    timing = json.loads((out / "timing.json").read_text())
    # sum of the stage times: a rerun that reuses finished stages still reports their real cost
    res = {"wall_s": sum(v["seconds"] for k, v in timing.items() if k != "total"),
           "peak_gb": max(v.get("peak_memory_gb", 0) for v in timing.values()),
           "field_s": timing.get("field", {}).get("seconds"),
           "steps_per_s": timing.get("field", {}).get("steps_per_s"),
           "stages": {k: v["seconds"] for k, v in timing.items()}}
    if (out / "points.ply").is_file():
        res["points"] = _score_ply(scene, out / "points.ply", views)
    res.update(_score_mesh(scene, out, views))
    return res


def _guided_only(scene: Path, d_out: Path) -> dict:
    """(d)'s points without the unguided set (`fusion.unguided` off): the guided stages
    2-3 alone, as the paper fuses. A copy of (d)'s folder in which only fusion reruns."""
    g = copy_run(d_out, d_out.parent / (d_out.name + "_guided_only"),
                 lambda cfg: setattr(cfg.fusion, "unguided", False))
    _reconstruct(scene, g, "--config", str(g / "config.yaml"))
    views = json.loads((g / "views.json").read_text())["inputs"]
    timing = json.loads((g / "timing.json").read_text())
    return {**_score_ply(scene, g / "points.ply", views),
            "wall_s": sum(v["seconds"] for k, v in timing.items()
                          if k not in ("total", "unguided"))}


def _ibr_view(out: Path) -> Path:
    """A sibling folder whose renders/ are OUT's renders_ibr/ (for `svolsdf evaluate`)."""
    import shutil

    d = out.parent / (out.name + "_ibr_eval")
    if d.exists():
        shutil.rmtree(d)
    d.mkdir()
    for f in ("config.yaml", "views.json"):
        shutil.copy(out / f, d / f)
    shutil.copytree(out / "renders_ibr", d / "renders")
    return d


def _try_mesh(p) -> tuple[float, str | None]:
    """Extract ``p``'s mesh; returns (seconds, None), or (seconds, why) when the field has no
    zero level set inside its box (a field early in its optimization may have none)."""
    t0 = time.perf_counter()
    try:
        p.run_stage("mesh")
        err = None
    except ValueError as e:
        err = str(e)
    return time.perf_counter() - t0, err


def _paper_equal_time(scene: Path, out: Path, budget_s: float) -> dict:
    """The paper preset given (d)'s wall time: MVS stage 1, then the field optimization until the
    budget (minus the mesh extraction that follows) is spent, then the mesh of that field.

    The guided finer MVS stages and the fused points need the rendered guide depth of the input
    views, which the 8x256 MLP cannot produce within the budget on a CPU (measured on one small
    view and extrapolated, in the note), so (c) is scored by its mesh.
    """
    import shutil

    import torch

    from svolsdf.config import preset
    from svolsdf.optimize.trainer import Trainer
    from svolsdf.pipeline import Pipeline
    from svolsdf.pipeline.builders import build_sampler
    from svolsdf.prior.consistency import MVSPrior

    if out.exists():
        shutil.rmtree(out)
    cfg = preset("paper")
    cfg.scene.path = str(scene)
    cfg.mesh.resolution = 128  # (d) extracts at 256; the MLP's evaluation is far slower
    t_start = time.perf_counter()
    p = Pipeline(cfg, out, progress=False)
    p.out.mkdir(parents=True, exist_ok=True)
    p.load()
    p.keys = p.stage_keys()
    (p.out / "views.json").write_text(json.dumps({"inputs": list(p.views)}))
    p.run_stage("mvs1")
    model = p.build_model()
    prior = MVSPrior(p.volumes1, p.load().normalization)
    tr = Trainer(model, p.train_data(), cfg.train, prior=prior, sampler=build_sampler(p.cfg, prior))
    # the mesh extraction's cost, measured on the untrained model, is left out of the budget
    p.set_model(model)
    mesh_s, _ = _try_mesh(p)
    (p.out / "mesh.ply").unlink(missing_ok=True)
    field_budget = budget_s - (time.perf_counter() - t_start - mesh_s) - mesh_s
    t0 = time.perf_counter()
    steps = 0
    last = 0.0
    while steps == 0 or time.perf_counter() - t0 + last <= field_budget:
        ts = time.perf_counter()
        tr.train_step()
        last = time.perf_counter() - ts  # stop before a step that would overrun the budget
        steps += 1
    field_s = time.perf_counter() - t0
    rate = steps / max(field_s, 1e-9)
    model.eval()
    p.set_model(model)
    mesh_s, mesh_error = _try_mesh(p)
    wall = time.perf_counter() - t_start - mesh_s  # the first (calibration) extraction not counted
    scene_ = p.load()
    cams = scene_.cameras_unit
    nf = (scene_.depth_range / scene_.normalization.scale).float()
    nf = torch.stack([nf[:, 0] * 0.9, nf[:, 1] * 1.1], -1)
    small = cams[[0]].resize(48, 36)
    t0 = time.perf_counter()
    p.render_views(small, nf[:1])
    per_ray = (time.perf_counter() - t0) / (48 * 36)
    render_s = per_ray * cams.width * cams.height * len(cams)
    if mesh_error is None:
        res = _score_mesh(scene, p.out, views=list(p.views))
    else:  # no surface yet: scored as an empty mesh (every distance at the clip distance)
        import numpy as np

        res = {"mesh": _score_points(scene, np.zeros((0, 3)), list(p.views), "mesh",
                                     faces=np.zeros((0, 3), np.int64))}
        res["mesh"]["error"] = f"no mesh: {mesh_error}"
    note = (f"paper preset (8x256 MLP, error-bounded sampler, 512 rays): {steps} of its 100,000 "
            f"steps in {field_s:.0f} s ({rate:.3f} steps/s), then its mesh (128^3"
            f"{'' if mesh_error is None else '; none: the SDF has no zero level set in the box'}"
            f"); rendering "
            f"the guide depth of the 3 input views for the finer MVS stages would take another "
            f"~{render_s / 60:.0f} min (measured on a 48x36 view, extrapolated), so it has no "
            f"fused points at this budget.")
    return {"wall_s": wall, "peak_gb": peak_rss_gb(), "field_s": field_s, "steps_per_s": rate,
            "stages": {"field": round(field_s, 1), "mesh": round(mesh_s, 1)}, "note": note,
            **res}


def _has_masks(scene: Path) -> bool:
    """Whether the scene folder has object masks, as `load_scene` finds them (False when the
    folder is gone, e.g. rescoring saved results)."""
    from svolsdf.scene.loaders import load_scene

    return Path(scene).is_dir() and bool(
        load_scene(scene, load_images=False).extras.get("mask_paths"))


def _ratio(d: dict, a: dict) -> float | None:
    return d["overall"] / a["overall"] if d.get("overall") and a.get("overall") else None


def _dtu_chamfer(out: Path, gt: Path) -> dict:
    """`svolsdf evaluate OUT --dtu-gt GT` (the DTU protocol, docs/method.md 8.1): points and
    mesh."""
    subprocess.run([sys.executable, "-m", "svolsdf", "evaluate", str(out), "--dtu-gt", str(gt),
                    "--no-report"], check=True)
    m = json.loads((out / "metrics.json").read_text())
    return {"points": m.get("chamfer") or {}, "mesh": m.get("chamfer_mesh") or {}}


def _dtu_scan(sc: Path, root: Path, n_test: int, gt: Path | None) -> dict:
    """The fast preset on one real DTU scan: times, peak memory, held-out image metrics; with
    ``gt`` also (a) the MVS backbone alone and both scored by the DTU protocol."""
    out = root / f"{sc.name}_fast"
    _reconstruct(sc, out)
    views = json.loads((out / "views.json").read_text())
    res: dict = {"timing": json.loads((out / "timing.json").read_text()),
                 "inputs": views["inputs"]}
    if gt is not None:
        # before the renders exist, so evaluate scores the geometry only
        d = _dtu_chamfer(out, gt)
        a_out = root / f"{sc.name}_a"
        _reconstruct(sc, a_out, "--mode", "mvs-only")
        a_t = json.loads((a_out / "timing.json").read_text())
        a = _dtu_chamfer(a_out, gt)
        res["chamfer"] = {"gt": str(gt), "d": d["points"], "d_mesh": d["mesh"],
                          "a": a["points"],
                          "a_wall_s": sum(v["seconds"] for k, v in a_t.items() if k != "total")}
    test = views.get("test", [])[:n_test]
    ids = [str(v) for v in test]
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "svolsdf", "render", str(out), "--views", *ids,
                    "--ibr"], check=True)
    res["render_s_per_view"] = (time.perf_counter() - t0) / max(len(ids), 1)
    ev = {}
    for folder in ("renders", "renders_ibr"):
        # evaluate reads OUT/renders; point it at the IBR images through a sibling run dir
        src = out if folder == "renders" else _ibr_view(out)
        subprocess.run([sys.executable, "-m", "svolsdf", "evaluate", str(src), "--views",
                        *ids, "--no-report"], check=True)
        m = json.loads((src / "metrics.json").read_text())["images"]
        ev[folder] = {k: m[k]["mean"] for k in ("psnr", "ssim", "lpips")}
    res["images"] = ev
    res["test_views"] = test
    # evaluate scores inside the object masks when the scene has them (the paper's DTU protocol)
    res["masked"] = _has_masks(sc)
    from PIL import Image

    with Image.open(out / "renders" / f"{test[0]}.png") as im:  # the working size
        res["size"] = f"{im.width}x{im.height}"
    return res


def _fmt(x, nd=2):
    return "-" if x is None else (f"{x:.{nd}f}" if isinstance(x, float) else str(x))


def _triple(p: dict) -> str:
    return " / ".join(_fmt(p.get(k)) for k in ("accuracy", "completeness", "overall"))


def render_issue5(data: dict) -> str:
    """The issue-5 results file (tables (a)-(d), more scenes, DTU scans), from the JSON the run
    wrote beside it (``{"meta", "runs", "more", "dtu"}``)."""
    meta, runs, more, dtu = data["meta"], data["runs"], data["more"], data["dtu"]
    lines = ["# Fast preset benchmark (issue 5)", "",
             f"- machine: nproc = {meta['nproc']}, CPU: {meta['cpu']}, torch threads = default "
             f"(OMP_WAIT_POLICY=PASSIVE); shared machine, other jobs may have been running",
             f"- command: `python benchmarks/fast_preset.py {meta['command']}`",
             f"- scene: `svolsdf synth --seed {meta['seed']} --views 5 --size {meta['size']}` "
             f"(object {meta['object']}); 3 input views (default choice); Chamfer in mm against "
             "the ground-truth surface the input views observe (evaluate/synthetic.py), "
             "distances clipped at 5% of the object's diagonal (holes cost the cut-off); "
             "\"DTU rule\": the same with distances beyond the cut-off left out of the means "
             "(docs/method.md 8.1, holes wider than the cut-off cost nothing); a mesh by its "
             "surface, sampled at 0.1 % of that diagonal (svolsdf.evaluate.chamfer."
             "mesh_density), not by its vertices", "",
             "| run | wall (s) | peak mem (GB) | points acc | points comp | points Chamfer | "
             "points Chamfer, DTU rule | points F | mesh Chamfer | mesh Chamfer, DTU rule | "
             "field steps/s |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in runs.items():
        p, m = r.get("points", {}), r.get("mesh", {})
        lines.append(f"| {name} | {_fmt(r['wall_s'], 0)} | {_fmt(r['peak_gb'])} | "
                     f"{_fmt(p.get('accuracy'))} | {_fmt(p.get('completeness'))} | "
                     f"{_fmt(p.get('overall'))} | {_fmt(p.get('overall_dtu_rule'))} | "
                     f"{_fmt(p.get('fscore'), 3)} | {_fmt(m.get('overall'))} | "
                     f"{_fmt(m.get('overall_dtu_rule'))} | {_fmt(r.get('steps_per_s'))} |")
        if "guided_only" in r:
            g = r["guided_only"]
            lines.append(f"| {name.split()[0][:-1]}') the same, guided depth only "
                         "(no unguided set) | "
                         f"{_fmt(g['wall_s'], 0)} | - | {_fmt(g.get('accuracy'))} | "
                         f"{_fmt(g.get('completeness'))} | {_fmt(g.get('overall'))} | "
                         f"{_fmt(g.get('overall_dtu_rule'))} | {_fmt(g.get('fscore'), 3)} | "
                         "- | - | - |")
    lines.append("")
    for name, r in runs.items():
        lines.append(f"- {name}: stages (s) {json.dumps(r['stages'])}"
                     + (f"; {r['note']}" if r.get("note") else "")
                     + "".join(f"; {r[k]['error']}" for k in ("points", "mesh")
                               if "error" in r.get(k, {})))
    def get(run: str, what: str, key: str):
        return next((r for n, r in runs.items() if n.startswith(run)), {}).get(what, {}).get(key)

    lines.append("")
    for key, label in (("overall", "points Chamfer"), ("overall_dtu_rule", "points Chamfer, "
                                                                          "DTU rule")):
        d = get("(d)", "points", key)
        for other, target in (("(a)", "<= 0.75"), ("(b)", "<= 0.5")):
            o = get(other, "points", key)
            if d is not None and o:
                lines.append(f"- ratio (d)/{other} {label}: {d / o:.2f} (target {target})")
        g = next((r for n, r in runs.items() if n.startswith("(d)")), {}).get("guided_only")
        o = get("(a)", "points", key)
        if g and g.get(key) is not None and o:
            lines.append(f"- ratio (d')/(a) {label}, guided depth only: {g[key] / o:.2f}")
    for key in ("overall", "overall_dtu_rule"):
        dm, cm = get("(d)", "mesh", key), get("(c)", "mesh", key)
        if dm is not None and cm:
            lines.append(f"- ratio (d)/(c) mesh Chamfer{', DTU rule' if 'dtu' in key else ''} "
                         f"at equal wall time: {dm / cm:.2f} (target < 1)")
    if more:
        lines += ["", "## More synthetic scenes: (d) against (a)", "",
                  "| scene | masks | (d) wall (s) | (d) peak (GB) | (d) acc / comp / Chamfer | "
                  "(a) acc / comp / Chamfer | ratio (d)/(a) | ratio, DTU rule | "
                  "(d') guided depth only: acc / comp / Chamfer | ratio (d')/(a) |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        # (ratio, ratio by the DTU rule, ratio of (d')) per scene, grouped by whether the scene
        # has object masks (fusion and the field's initial surface use them); the first table's
        # scene counts too
        groups: dict[bool, list] = {True: [], False: []}

        def ratios_of(pd: dict, pa: dict, pg: dict) -> tuple:
            return tuple(x[k] / pa[k] if x.get(k) and pa.get(k) else None
                         for x, k in ((pd, "overall"), (pd, "overall_dtu_rule"),
                                      (pg, "overall")))

        d0 = next((r for n, r in runs.items() if n.startswith("(d)")), None)
        a0 = next((r for n, r in runs.items() if n.startswith("(a)")), None)
        if d0 and a0 and d0.get("points") and a0.get("points"):
            groups[bool(d0.get("masks"))].append(ratios_of(d0["points"], a0["points"],
                                                    d0.get("guided_only", {})))
        for name, r in more.items():
            pd, pa = r["d"].get("points", {}), r["a"].get("points", {})
            pg = r["d"].get("guided_only", {})
            x = ratios_of(pd, pa, pg)
            masks = bool(r["d"].get("masks"))
            groups[masks].append(x)
            lines.append(f"| {name} | {'yes' if masks else 'no'} | {_fmt(r['d']['wall_s'], 0)} | "
                         f"{_fmt(r['d']['peak_gb'])} | {_triple(pd)} | {_triple(pa)} | "
                         f"{_fmt(x[0])} | {_fmt(x[1])} | {_triple(pg) if pg else '-'} | "
                         f"{_fmt(x[2])} |")
        lines.append("")
        for masks, xs in groups.items():
            if not xs:
                continue
            what = "with object masks" if masks else "without masks"
            means = [[x[k] for x in xs if x[k] is not None] for k in range(3)]
            means = [sum(m) / len(m) if m else None for m in means]
            lines.append(f"- mean over the {len(xs)} synthetic scene(s) {what} (both tables): "
                         f"ratio (d)/(a) {_fmt(means[0])}, DTU rule {_fmt(means[1])} (target "
                         f"<= 0.75); (d')/(a) guided depth only {_fmt(means[2])}")
    c = runs.get("(c) S-VolSDF paper preset, equal time")
    if c is not None:
        lines += ["", "## (c) the paper preset at (d)'s wall time", "",
                  f"- {c['note']}"]
    for name, r in dtu.items():
        t = r["timing"]
        # "total" is the last invocation's wall time (a rerun that reuses every stage writes
        # ~2 s); the sum of the stages is the pipeline's cost
        st = {k: v["seconds"] for k, v in t.items() if k != "total"}
        lines += ["", f"## {name}, fast preset (views {' '.join(map(str, r['inputs']))}, "
                  f"{r['size']})", "",
                  f"- stages (s): {json.dumps(st)}; sum {sum(st.values()):.0f} s",
                  f"- peak memory: {max(v.get('peak_memory_gb', 0) for v in t.values()):.2f} GB",
                  f"- held-out views {r['test_views']} (the first {len(r['test_views'])} of "
                  "the scene's test views), "
                  + ("masked as the paper evaluates (evaluate/images.py):"
                     if r.get("masked", True) else
                     "over the whole image (the scene has no object masks; the paper's DTU "
                     "numbers are masked):"),
                  f"  - volume rendering: {json.dumps(r['images']['renders'])}",
                  f"  - image-based rendering: {json.dumps(r['images']['renders_ibr'])}",
                  f"  - render time per view (VR + IBR, incl. loading): "
                  f"{r['render_s_per_view']:.1f} s"]
        if r.get("chamfer"):
            c = r["chamfer"]
            lines += [f"- DTU protocol ({c['gt']}), points acc / comp / Chamfer (mm): "
                      f"(d) {_triple(c['d'])}, (a) MVS backbone alone {_triple(c['a'])} "
                      f"({c['a_wall_s']:.0f} s); ratio (d)/(a) "
                      f"{_fmt(_ratio(c['d'], c['a']))} (target <= 0.75)"]
            if c.get("d_mesh"):
                lines[-1] += f"; (d) mesh {_triple(c['d_mesh'])}"
        else:
            lines += ["- Chamfer: no DTU ground truth given (`--dtu-gt ROOT`)"]
    if not dtu:
        lines += ["", "## dtu_scan65", "",
                  "The fast preset's times, peak memory and held-out PSNR / SSIM / LPIPS on "
                  "dtu_scan65 (views 25 22 28, all 25 DTU test views) are measured by "
                  "`python benchmarks/novel_views_dtu.py` (benchmarks/results/novel_views_dtu.md);"
                  " `--dtu` here runs a shorter version."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="768x576")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--object", default="random")
    ap.add_argument("--out", type=Path, default=Path("/tmp/fast_bench"))
    ap.add_argument("--results", type=Path, default=REPO / "benchmarks/results/fast_preset.md")
    ap.add_argument("--only", default="a,b,c,d")
    ap.add_argument("--more", nargs="*", default=[], metavar="SEED:OBJECT",
                    help="more synthetic scenes on which only (a) and (d) run, e.g. 3:random "
                         "7:blobs (a second table with the ratio per scene)")
    ap.add_argument("--rescore", action="store_true",
                    help="score the runs saved in OUT/fast_preset.json again and rewrite the "
                         "results, without reconstructing")
    ap.add_argument("--scenes", nargs="*", type=Path, default=[], metavar="PATH",
                    help="more scene folders with exact ground truth (the layout of `svolsdf "
                         "synth`: gt_points.ply, gt_depth/); (a) and (d) run on each")
    ap.add_argument("--dtu", action="store_true", help="also the fast preset on dtu_scan65")
    ap.add_argument("--dtu-scenes", nargs="*", type=Path, default=[], metavar="PATH",
                    help="more real DTU scans in the IDR layout (as dtu_scan65)")
    ap.add_argument("--dtu-gt", type=Path, default=None, metavar="ROOT",
                    help="DTU ground-truth root (ObsMask/, Points/stl/): also run (a) on the "
                         "DTU scans and score (a) and (d) by the DTU protocol")
    ap.add_argument("--dtu-test-views", type=int, default=5,
                    help="held-out DTU views rendered and scored")
    sbs = ap.add_argument_group("side by side with a baseline commit (issue 39)")
    sbs.add_argument("--against", default=None, metavar="REV",
                     help="baseline commit: run the fast preset of REV and of this checkout side "
                          "by side on --scenes / --dtu / --dtu-scenes (nothing else runs)")
    sbs.add_argument("--pgt", nargs="*", default=[], metavar="NAME=DIR",
                     help="pseudo ground truth folder (dtu_pseudo_gt.py --out) per DTU scene "
                          "folder name, e.g. dtu_scan65=DIR")
    sbs.add_argument("--many-views", type=Path, default=None, metavar="SCENE",
                     help="also a run on --many-views-n views of this scene (new only)")
    sbs.add_argument("--many-views-n", type=int, default=9)
    sbs.add_argument("--many-views-old", action="store_true",
                     help="the many-view run for the baseline too")
    sbs.add_argument("--held-out-views", type=int, default=3,
                     help="held-out test views rendered and scored per scene")
    sbs.add_argument("--held-out-scale", type=float, default=0.5,
                     help="held-out renders at this fraction of the working size")
    sbs.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                     help="passed as --set to both sides' svolsdf reconstruct (against a "
                          "commit before the config sections, give the old output.* names: "
                          "the new code still reads them)")
    sbs.add_argument("--new-preset", default=None, metavar="NAME",
                     help="the new side runs this preset (e.g. draft), in OUT/new-NAME; the old "
                          "side keeps the fast preset and its cached runs in OUT/old")
    ap.add_argument("--from-json", type=Path, default=None, metavar="FILE.json",
                    help="render the Markdown of a run from the JSON it wrote (to --results, "
                         "default FILE.md) and run nothing")
    args = ap.parse_args()
    if args.from_json is not None:
        from _side_by_side import render

        data = json.loads(args.from_json.read_text())
        if "scenes" in data and "targets" in data:
            text = render(data)
        elif "runs" in data and "meta" in data:
            text = render_issue5(data)
        else:
            sys.exit(f"{args.from_json}: not a JSON this script renders (a side-by-side run's, "
                     "or an issue-5 run's with its meta; JSON written before issue 50 has no "
                     "meta: benchmarks/results/history/README.md)")
        results = (args.from_json.with_suffix(".md")
                   if args.results == ap.get_default("results") else args.results)
        results.write_text(text)
        print(f"wrote {results}")
        return
    if args.against is not None:
        from _side_by_side import side_by_side

        if args.results == ap.get_default("results"):
            args.results = REPO / "benchmarks/results/fast_preset_side_by_side.md"
        side_by_side(args, sys.argv[1:])
        return

    import svolsdf  # noqa: F401
    from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

    w, h = (int(x) for x in args.size.split("x"))

    def make(seed: int, obj: str) -> Path:
        d = args.out / f"scene_{obj}_{seed}_{w}x{h}"
        if not (d / "gt_points.ply").is_file():
            make_synthetic_scene(d, SynthConfig(views=5, width=w, height=h, seed=seed,
                                                object=obj))
        return d

    only = set(args.only.split(",")) if not args.rescore else set()
    # the first table's scene, generated only when a run needs it (e.g. not for --only "" --dtu)
    scene = make(args.seed, args.object) if only & set("abcd") else None
    args.out.mkdir(parents=True, exist_ok=True)
    dump = args.out / "fast_preset.json"
    if args.rescore:
        # score the finished runs again (e.g. after a change of the evaluation), keep the rest
        saved = json.loads(dump.read_text())
        runs, more, dtu = saved["runs"], saved["more"], saved.get("dtu", {})
        for r in [*runs.values(), *(x for m in more.values() for x in m.values())]:
            if r.get("dir"):
                d = Path(r["dir"])
                views = json.loads((d / "views.json").read_text())["inputs"]
                r.pop("points", None)
                if (d / "points.ply").is_file():
                    r["points"] = _score_ply(Path(r["scene"]), d / "points.ply", views)
                g = d.parent / (d.name + "_guided_only")
                if "guided_only" in r and (g / "points.ply").is_file():
                    r["guided_only"].update(_score_ply(Path(r["scene"]), g / "points.ply",
                                                       views))
                r.update(_score_mesh(Path(r["scene"]), d, views))
                if Path(r["scene"]).is_dir():
                    r["masks"] = _has_masks(Path(r["scene"]))
    else:
        runs, more, dtu = {}, {}, {}

    meta = {"nproc": os.cpu_count(), "cpu": cpu_name(), "command": public_argv(sys.argv[1:]),
            "seed": args.seed, "size": args.size, "object": args.object}

    def save() -> None:
        dump.write_text(json.dumps({"meta": meta, "runs": runs, "more": more, "dtu": dtu},
                                   indent=1))

    def run(sc: Path, out: Path, *extra: str) -> dict:
        _reconstruct(sc, out, *extra)
        r = {**_score(sc, out), "dir": str(out), "scene": str(sc), "masks": _has_masks(sc)}
        if (out / "unguided").is_dir():  # (d): also its points without the unguided set
            r["guided_only"] = _guided_only(sc, out)
        return r

    if "d" in only:
        runs["(d) S-VolSDF fast preset"] = run(scene, args.out / "d_fast")
        save()
    if "a" in only:
        runs["(a) MVS backbone alone (plane sweep)"] = run(scene, args.out / "a_mvs",
                                                           "--mode", "mvs-only")
        save()
    if "b" in only:
        runs["(b) VolSDF alone (fast field, no prior)"] = run(scene, args.out / "b_volsdf",
                                                              "--mode", "volsdf")
        save()
    if "c" in only:
        c_out = args.out / "c_paper"
        runs["(c) S-VolSDF paper preset, equal time"] = {
            **_paper_equal_time(scene, c_out,
                                runs.get("(d) S-VolSDF fast preset", {}).get("wall_s") or 300.0),
            "dir": str(c_out), "scene": str(scene)}
        save()
    extra_scenes = []
    for item in args.more:
        seed, _, obj = item.partition(":")
        extra_scenes.append((f"seed {seed}, {obj or 'random'}",
                             lambda seed=seed, obj=obj: make(int(seed), obj or "random")))
    for path in args.scenes:
        path = path.resolve()  # the scene path enters the stage keys: keep it stable
        for f in ("gt_points.ply", "gt_depth"):
            if not (path / f).exists():
                sys.exit(f"--scenes {path}: no {f} (a scene with exact ground truth in the "
                         "layout `svolsdf synth` writes is needed)")
        extra_scenes.append((path.name, lambda path=path: path))
    for name, get_scene in extra_scenes if not args.rescore else []:
        sc = get_scene()
        r = {}
        for tag, extra in (("d", ()), ("a", ("--mode", "mvs-only"))):
            r[tag] = run(sc, args.out / f"{sc.name}_{tag}", *extra)
        more[name] = r
        save()
    dtu_scenes = ([SHARED / "data/dtu_scan65"] if args.dtu else []) + list(args.dtu_scenes)
    for sc in dtu_scenes:
        sc = sc.resolve()
        if not sc.is_dir():
            sys.exit(f"DTU scene {sc} does not exist")
        dtu[sc.name] = _dtu_scan(sc, args.out, args.dtu_test_views, args.dtu_gt)
        save()

    from _side_by_side import _public

    # the results' JSON names no machine path (OUT/..., DATA/<name>); OUT/fast_preset.json keeps
    # them for --rescore
    data = _public({"meta": meta, "runs": runs, "more": more, "dtu": dtu}, args.out)
    args.results.with_suffix(".json").write_text(json.dumps(data, indent=1))
    # rendered from the JSON as written, so --from-json reproduces it
    text = render_issue5(json.loads(args.results.with_suffix(".json").read_text()))
    args.results.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
