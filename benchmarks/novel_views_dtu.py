"""Novel views on real DTU scans, scored as the paper's official evaluation, and where the dB go.

Protocol (docs/method.md 1.4 and 8.3, the released ``eval_vsdf.py``): inputs 25, 22, 28 at 768x576;
the 25 test views (every id of 0..48 but the nine training candidates and the RegNeRF exclusion
list); PSNR over the pixels inside each test view's object mask, against the photo resized to
768x576 by a bicubic resize without antialiasing (OpenCV's INTER_CUBIC), the mask resized
bilinearly and thresholded at 0.5 (`svolsdf.evaluate.protocol`); SSIM and LPIPS-VGG of both images
composited onto white with that mask. Each score is the mean over the test views of one scan.

For every scan and mode it runs, in fresh processes,

    svolsdf reconstruct SCAN -o WORK/<scan>/<mode> --mode ... [--set ...]
    svolsdf render WORK/<scan>/<mode> --views <the 25 test views> --ibr

and scores the volume rendering (renders/) and the image-based rendering (renders_ibr/).

Diagnosis (``--diagnose``, docs/novel-views.md): a reference depth for every view of the scan,
independent of the runs (DTU-trained PatchmatchNet on all 49 views, each pixel kept when three of
its eight best-paired views agree, as benchmarks/dtu_pseudo_gt.py builds its reference), splits
each test view's mask into pixels

- ``object missing``: the run renders nothing there, or something beyond the object's far end
  (the reference's 99th-percentile depth in the mask + 2 %): the table shows where the object is;
- ``unseen, no reference``: the reference has no depth there (textureless or badly lit surface
  that even 49 views do not agree on), and no input view's reference depth explains it;
- ``unseen, placed`` / ``unseen, misplaced``: the reference surface there is consistent with none
  of the three input views' reference depths (no input view sees it); the run's depth within /
  beyond 1 % of the reference;
- ``misplaced``: seen, the run's depth more than 1 % (about 6 mm) from the reference;
- ``placed``: seen, the run's depth within 1 % of the reference;

and gives each class's share of the mask, its share of the squared error and the dB the mean PSNR
would gain if that class were rendered exactly. Swaps isolate the parts: IBR with the reference
geometry (target and input depths) instead of the run's ("geometry"), and IBR with the photo's
own colour where the reference says no input sees ("unseen"): what would be left is what the
input photos cannot explain at the right place (lighting, view dependence, resampling).

Per-view pictures (``--pictures``): photo | volume rendering | IBR | IBR's error inside the mask
| the pixel classes, as JPEG files in RESULTS_DIR/novel_views_dtu/<scan>/<mode>/<view>.jpg.

Which scans are held out: the table names, for every scan, whether a choice of the project was
made while looking at it (``--tuned-on``; the shared scan 65 is the one the diagnosis was done
on, so it is never held out).

Usage:
    python benchmarks/novel_views_dtu.py [--scenes ../shared/data/dtu_scan65 ...]
        [--modes svolsdf,volsdf,volsdf-mlp] [--work /tmp/novel_views_dtu] [--diagnose]
        [--pictures] [--results benchmarks/results/novel_views_dtu.md]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
from _machine import cpu_name, git_commit, write_results

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
INPUTS = [25, 22, 28]
SIZE = (768, 576)

MODES = {  # name -> (reconstruct arguments, what it is)
    "svolsdf": ([], "S-VolSDF, fast preset"),
    "volsdf": (["--mode", "volsdf"], "VolSDF without the prior, fast grid field"),
    "volsdf-mlp": (["--mode", "volsdf", "--set", "field.kind=mlp"],
                   "VolSDF without the prior, VolSDF's MLP field"),
}
PAPER = {"volume rendering": (20.21, 0.820, 0.321), "IBR": (20.58, 0.855, 0.157),
         "VolSDF": (16.99, None, None)}


def _run(*args: str, log: Path | None = None) -> float:
    cmd = [sys.executable, "-m", "svolsdf", *args]
    print("$", " ".join(cmd), flush=True)
    t0 = time.perf_counter()
    if log is None:
        subprocess.run(cmd, check=True)
    else:
        with open(log, "a") as f:
            subprocess.run(cmd, check=True, stdout=f, stderr=subprocess.STDOUT)
    return time.perf_counter() - t0


# --------------------------------------------------------------------------- reference depth
def reference_depths(scene_dir: Path, work: Path, ids: list[int]) -> dict[int, torch.Tensor]:
    """View id -> (H, W) reference z-depth (0 = none) at 768x576 for ``ids``: PatchmatchNet
    depth of every view with its 4 best sources, kept where >= 3 of its 8 best-paired views agree
    (1 px, 1 %), the mean of the agreeing depths (benchmarks/dtu_pseudo_gt.py steps 1-2, per view
    instead of fused into one cloud). Cached in WORK/reference/."""
    import dtu_pseudo_gt

    from svolsdf.geometry.reproject import check_geometric_consistency
    from svolsdf.scene.loaders import load_scene

    cache = work / "reference" / f"{scene_dir.name}_refdepth_{SIZE[0]}x{SIZE[1]}"
    cache.mkdir(parents=True, exist_ok=True)
    todo = [v for v in ids if not (cache / f"{v}.npy").is_file()]
    if todo:
        depths = dtu_pseudo_gt.depth_maps(scene_dir, work / "reference" / scene_dir.name, SIZE, 4)
        sc = load_scene(scene_dir, image_size=SIZE, load_images=False)
        all_ids = sc.view_ids
        for ref in todo:
            d_ref = depths[ref]
            cam = sc.cameras[[all_ids.index(ref)]]
            count = torch.zeros(d_ref.shape, dtype=torch.int32)
            d_sum = d_ref.double().clone()
            for src in sc.source_views(ref)[:8]:
                m, d_rep, _ = check_geometric_consistency(d_ref, cam, depths[src],
                                                          sc.cameras[[all_ids.index(src)]])
                count += m.int()
                d_sum += torch.where(m, d_rep.double(), torch.zeros_like(d_sum))
            keep = (d_ref > 0) & (count >= 3)
            fused = torch.where(keep, d_sum / (1 + count).double(), torch.zeros_like(d_sum))
            np.save(cache / f"{ref}.npy", fused.float().numpy())
    return {v: torch.from_numpy(np.load(cache / f"{v}.npy")) for v in ids}


# --------------------------------------------------------------------------- scoring
def score_views(preds: dict[int, torch.Tensor], gts: torch.Tensor, masks: torch.Tensor,
                ids: list[int], lp) -> dict:
    """Per-view and mean PSNR / SSIM / LPIPS of (3, H, W) predictions (docs/method.md 8.3)."""
    from svolsdf.evaluate.images import masked_psnr, ssim
    from svolsdf.evaluate.lpips import lpips_distance

    per = {}
    for k, v in enumerate(ids):
        if v not in preds:
            continue
        p, g, m = preds[v], gts[k], masks[k]
        per[v] = {"psnr": masked_psnr(p, g, m), "ssim": ssim(p, g, m),
                  "lpips": lpips_distance(p, g, lp, m) if lp is not None else float("nan")}
    mean = {k: float(np.mean([r[k] for r in per.values()])) for k in ("psnr", "ssim", "lpips")}
    return {"mean": mean, "per_view": {str(v): r for v, r in per.items()}}


def _psnr_of_mse(mse: float) -> float:
    return math.inf if mse <= 0 else -10 * math.log10(mse)


CLASSES = ("object missing", "unseen, no reference", "unseen, placed", "unseen, misplaced",
           "misplaced", "placed")


def input_depths(out: Path):
    """The run's scene and the (3, H, W) world z-depth of its input views (0 where the opacity is
    below 0.5), as `svolsdf render --ibr` renders them; cached beside the run folder."""
    from svolsdf.commands.render import OPACITY_SURFACE, _scene_range, open_run

    p = open_run(out)
    scene = p.load()
    cache = out.parent / f"{out.name}_input_depth.pt"  # a minute or more per run on a CPU
    if cache.is_file() and cache.stat().st_mtime > (out / "field" / "model.pt").stat().st_mtime:
        return scene, torch.load(cache)
    s = float(scene.normalization.scale)
    r = p.render_views(scene.cameras_unit, _scene_range(scene, s).to(p.device),
                       keys=("depth", "opacity"))
    d_src = torch.where(r["opacity"] >= OPACITY_SURFACE, r["depth"] * s,
                        torch.zeros_like(r["depth"])).float()
    torch.save(d_src, cache)
    return scene, d_src


def ibr_variant(out: Path, scene_dir: Path, ids: list[int], cfg) -> dict[int, torch.Tensor]:
    """View id -> (3, H, W) IBR of the run's rendered test views with `IBRConfig` ``cfg``."""
    from svolsdf.ibr import ibr_render
    from svolsdf.io.images import read_image
    from svolsdf.scene.loaders import load_scene

    scene, d_src = input_depths(out)
    tsc = load_scene(scene_dir, views=ids, image_size=SIZE, load_images=False)
    mesh = None
    if cfg.hole_depth == "mesh":  # as svolsdf render --ibr-holes mesh
        from svolsdf.commands.render import mesh_depth_fill
        from svolsdf.io.ply import read_ply

        m = read_ply(out / "mesh.ply")
        mesh = (m["points"], m["faces"])
        d_src = mesh_depth_fill(d_src, scene.cameras, *mesh)
    res = {}
    for k, v in enumerate(ids):
        vr = read_image(out / "renders" / f"{v}.png")
        d = torch.from_numpy(np.load(out / "renders" / "depth" / f"{v}.npy")).float()
        if mesh is not None:
            d = mesh_depth_fill(d[None], tsc.cameras[[k]], *mesh)[0]
        res[v] = ibr_render(tsc.cameras[[k]].to(dtype=torch.float64), d, vr, scene.images,
                            scene.cameras.to(dtype=torch.float64), d_src, cfg).rgb
    return res


def diagnose(out: Path, scene_dir: Path, ids: list[int], gts: torch.Tensor, masks: torch.Tensor,
             ref: dict[int, torch.Tensor], pictures: Path | None) -> dict:
    """The split of module docstring "Diagnosis" for one run folder; returns per-class shares,
    per-view class PSNRs and the swaps' mean PSNRs."""
    from svolsdf.evaluate.images import masked_psnr
    from svolsdf.ibr import IBRConfig, ibr_render
    from svolsdf.io.images import read_image
    from svolsdf.scene.loaders import load_scene

    scene, d_src = input_depths(out)
    src_imgs = scene.images
    src_cams = scene.cameras.to(dtype=torch.float64)
    in_ids = scene.view_ids
    g_src = torch.stack([ref[v] for v in in_ids]).float()
    tsc = load_scene(scene_dir, views=ids, image_size=SIZE, load_images=False)
    cfg = IBRConfig()
    res = {"per_view": {}, "swaps": {}}
    sums = {c: {"px": 0.0, "se_vr": 0.0, "se_ibr": 0.0} for c in CLASSES}
    swap_psnr = {k: [] for k in ("vr", "ibr", "ibr_released", "ibr_ref_geometry",
                                 "ibr_ref_geometry_unseen_exact", "ibr_unseen_exact",
                                 "vr_unseen_exact")}
    gain = {c: {"vr": [], "ibr": []} for c in CLASSES}
    for k, v in enumerate(ids):
        vr = read_image(out / "renders" / f"{v}.png")
        ibr = read_image(out / "renders_ibr" / f"{v}.png")
        d = torch.from_numpy(np.load(out / "renders" / "depth" / f"{v}.npy")).float()
        g = ref[v].float()
        cam = tsc.cameras[[k]].to(dtype=torch.float64)
        gt, m = gts[k], masks[k].bool()
        rr = ibr_render(cam, g, vr, src_imgs, src_cams, g_src, cfg)
        seen = rr.n_valid > 0
        # the object's far end in this view: the reference's 99th percentile depth in the mask
        far = torch.quantile(g[m & (g > 0)], 0.99) * 1.02 if bool((m & (g > 0)).any()) else 0
        missing = (d <= 0) | (d > far)  # the render shows the table or nothing: no object there
        off = (g > 0) & ((d - g).abs() > 0.01 * g)  # > 1 % (about 6 mm) from the reference
        cls = torch.full(m.shape, 5, dtype=torch.long)  # placed
        cls[off] = 4  # misplaced
        cls[~seen & ~off] = 2  # unseen, placed
        cls[~seen & off] = 3  # unseen, misplaced
        cls[~seen & (g <= 0)] = 1  # unseen, no reference depth
        cls[missing] = 0  # object missing
        se_vr = ((vr - gt) ** 2).mean(0)
        se_ibr = ((ibr - gt) ** 2).mean(0)
        n = float(m.sum())
        mse_vr, mse_ibr = float(se_vr[m].mean()), float(se_ibr[m].mean())
        pv = {"psnr_vr": _psnr_of_mse(mse_vr), "psnr_ibr": _psnr_of_mse(mse_ibr)}
        for c, name in enumerate(CLASSES):
            sel = m & (cls == c)
            pv[f"share_{name}"] = float(sel.sum()) / n
            sums[name]["px"] += float(sel.sum()) / n
            sums[name]["se_vr"] += float(se_vr[sel].sum()) / float(se_vr[m].sum())
            sums[name]["se_ibr"] += float(se_ibr[sel].sum()) / float(se_ibr[m].sum())
            pv[f"psnr_ibr_{name}"] = (_psnr_of_mse(float(se_ibr[sel].mean()))
                                      if sel.any() else None)
            gain[name]["vr"].append(_psnr_of_mse(float(se_vr[m & (cls != c)].sum()) / n)
                                    - pv["psnr_vr"])
            gain[name]["ibr"].append(_psnr_of_mse(float(se_ibr[m & (cls != c)].sum()) / n)
                                     - pv["psnr_ibr"])
        unseen = m & ~seen
        ref_geo = rr.rgb
        ref_geo_exact = torch.where(unseen[None], gt, ref_geo)
        swap_psnr["vr"].append(pv["psnr_vr"])
        swap_psnr["ibr"].append(pv["psnr_ibr"])
        swap_psnr["ibr_ref_geometry"].append(masked_psnr(ref_geo, gt, m))
        rel = ibr_render(cam, d, vr, src_imgs, src_cams, d_src, IBRConfig.released()).rgb
        swap_psnr["ibr_released"].append(masked_psnr(rel, gt, m))
        swap_psnr["ibr_ref_geometry_unseen_exact"].append(masked_psnr(ref_geo_exact, gt, m))
        swap_psnr["ibr_unseen_exact"].append(masked_psnr(torch.where(unseen[None], gt, ibr), gt, m))
        swap_psnr["vr_unseen_exact"].append(masked_psnr(torch.where(unseen[None], gt, vr), gt, m))
        pv["psnr_ibr_ref_geometry"] = swap_psnr["ibr_ref_geometry"][-1]
        res["per_view"][str(v)] = pv
        if pictures is not None:
            _picture(pictures / f"{v}.jpg", gt, vr, ibr, m, cls, se_ibr)
    nv = len(ids)
    res["classes"] = {c: {"share_px": sums[c]["px"] / nv, "share_se_vr": sums[c]["se_vr"] / nv,
                          "share_se_ibr": sums[c]["se_ibr"] / nv,
                          "gain_db_vr": float(np.mean(gain[c]["vr"])),
                          "gain_db_ibr": float(np.mean(gain[c]["ibr"]))} for c in CLASSES}
    res["swaps"] = {k: float(np.mean(x)) for k, x in swap_psnr.items()}
    return res


_CLASS_RGB = torch.tensor([[0.2, 0.4, 1.0], [0.6, 0.6, 0.6], [0.95, 0.8, 0.1],
                           [0.95, 0.45, 0.1], [0.9, 0.15, 0.15], [0.2, 0.75, 0.3]])
# object missing blue; unseen: no reference grey, placed yellow, misplaced orange; seen: misplaced
# red, placed green


def _picture(path: Path, gt, vr, ibr, m, cls, se) -> None:
    """photo | VR | IBR | IBR's RMS error inside the mask (0..0.5) | classes; half size, JPEG."""
    import matplotlib
    from PIL import Image

    err = se.sqrt().clamp(0, 0.5) / 0.5
    heat = torch.from_numpy(matplotlib.colormaps["inferno"](err.numpy())[..., :3]).permute(
        2, 0, 1).float() * m[None]
    cmap = _CLASS_RGB[cls].permute(2, 0, 1) * m[None]
    tiles = torch.cat([gt, vr, ibr, heat, cmap], dim=2)
    tiles = torch.nn.functional.interpolate(tiles[None], scale_factor=0.5, mode="area")[0]
    a = (tiles.clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(a).save(path, quality=85)


# --------------------------------------------------------------------------- main
def run_mode(scene_dir: Path, work: Path, mode: str, test: list[int], log: Path,
             variant: str = "", sets: tuple[str, ...] = ()) -> dict:
    out = work / scene_dir.name / (f"{mode}-{variant}" if variant else mode)
    args, _ = MODES[mode]
    extra = [a for s in sets for a in ("--set", s)]
    t_rec = _run("reconstruct", str(scene_dir), "-o", str(out),
                 *args, *extra, "--no-progress", log=log)
    t_ren = _run("render", str(out), "--views", *map(str, test), "--ibr",
                 log=log)
    timing = json.loads((out / "timing.json").read_text())
    fp = timing.get("guide", {}).get("field_psnr")
    return {"out": str(out), "reconstruct_s": t_rec, "render_s": t_ren,
            "pipeline_s": sum(v["seconds"] for k, v in timing.items() if k != "total"),
            "field_psnr": fp.get("mean_db") if isinstance(fp, dict) else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", type=Path, default=[SHARED / "data" / "dtu_scan65"])
    ap.add_argument("--modes", default="svolsdf,volsdf")
    ap.add_argument("--work", type=Path, default=Path("/tmp/novel_views_dtu"))
    ap.add_argument("--results", type=Path, default=REPO / "benchmarks/results/novel_views_dtu.md",
                    help="the Markdown; the JSON it is rendered from goes beside it")
    ap.add_argument("--from-json", type=Path,
                    help="only render the Markdown of this results JSON into --results")
    ap.add_argument("--tuned-on", nargs="*", default=["dtu_scan65"],
                    help="scan folder names a choice of the project was made on (not held out)")
    ap.add_argument("--diagnose", action="store_true")
    ap.add_argument("--pictures", action="store_true")
    ap.add_argument("--inpaint", action="store_true",
                    help="also score IBR with --ibr-unseen inpaint (docs/novel-views.md)")
    ap.add_argument("--ibr-holes-mesh", action="store_true",
                    help="also score IBR with --ibr-holes mesh (the mesh's depth where the "
                         "field renders none)")
    ap.add_argument("--variant", default="",
                    help="a name for the --set options below (run folders MODE-VARIANT)")
    ap.add_argument("--set", dest="sets", action="append", default=[],
                    help="section.option=value passed to every reconstruct (repeatable)")
    ap.add_argument("--skip-runs", action="store_true",
                    help="score existing run folders in WORK without rerunning anything")
    args = ap.parse_args()
    if args.from_json:
        write_results(args.results, render_markdown(json.loads(args.from_json.read_text())))
        return
    modes = args.modes.split(",")
    for m in modes:
        if m not in MODES:
            sys.exit(f"--modes: unknown {m!r}; expected some of {', '.join(MODES)}")
    from svolsdf.evaluate.lpips import LPIPS
    from svolsdf.evaluate.protocol import official_test_images
    from svolsdf.scene.loaders import load_scene

    lp = LPIPS("vgg")
    args.work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    js = args.work / "novel_views_dtu.json"
    earlier = json.loads(js.read_text()) if js.is_file() else {}
    results = {}
    for scene_dir in args.scenes:
        scene_dir = scene_dir.resolve()
        probe = load_scene(scene_dir, load_images=False)
        if not probe.extras.get("mask_paths"):
            print(f"skipped {scene_dir}: no object masks (the protocol scores inside them)")
            continue
        test = [v for v in range(49) if v not in {3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 36, 37,
                                                   38, 39, 25, 22, 28, 40, 44, 48, 0, 8, 13}]
        gts, masks = official_test_images(scene_dir, test, SIZE)
        ref = (reference_depths(scene_dir, args.work, test + INPUTS) if args.diagnose else None)
        for mode in modes:
            name = f"{mode}-{args.variant}" if args.variant else mode
            log = args.work / f"{scene_dir.name}_{name}.log"
            key = f"{scene_dir.name}/{name}"
            out = args.work / scene_dir.name / name
            r = ({"out": str(out)} if args.skip_runs
                 else run_mode(scene_dir, args.work, mode, test, log, args.variant,
                               tuple(args.sets)))
            from svolsdf.io.images import read_image

            for kind, folder in (("volume rendering", "renders"), ("IBR", "renders_ibr")):
                if args.skip_runs and kind in earlier.get(key, {}):  # scored by an earlier run
                    r[kind] = earlier[key][kind]
                    continue
                preds = {v: read_image(out / folder / f"{v}.png") for v in test
                         if (out / folder / f"{v}.png").is_file()}
                r[kind] = score_views(preds, gts, masks, test, lp)
            if args.inpaint:  # IBR with the unseen surface inpainted (svolsdf render
                from svolsdf.ibr import IBRConfig  # --ibr-unseen inpaint), scored the same way

                kind = "IBR, unseen inpainted"
                if args.skip_runs and kind in earlier.get(key, {}):
                    r[kind] = earlier[key][kind]
                else:
                    preds = ibr_variant(out, scene_dir, test, IBRConfig(unseen="inpaint"))
                    r[kind] = score_views(preds, gts, masks, test, lp)
            if args.ibr_holes_mesh:  # IBR with the mesh's depth in the field's holes
                from svolsdf.ibr import IBRConfig  # (svolsdf render --ibr-holes mesh)

                kind = "IBR, holes from the mesh"
                if args.skip_runs and kind in earlier.get(key, {}):
                    r[kind] = earlier[key][kind]
                else:
                    preds = ibr_variant(out, scene_dir, test, IBRConfig(hole_depth="mesh"))
                    r[kind] = score_views(preds, gts, masks, test, lp)
            if ref is not None:
                pic = (args.results.parent / "novel_views_dtu" / scene_dir.name / mode
                       if args.pictures else None)
                r["diagnosis"] = diagnose(out, scene_dir, test, gts, masks, ref, pic)
            r["held_out"] = scene_dir.name not in args.tuned_on
            for k in ("reconstruct_s", "render_s", "pipeline_s"):
                if args.skip_runs and k in earlier.get(key, {}):
                    r[k] = earlier[key][k]
            results[key] = r
            js.write_text(json.dumps({**earlier, **results}, indent=1))
    _write(args, results, time.perf_counter() - t0)


def _write(args, results: dict, seconds: float) -> None:
    """Write RESULTS (.json, the data) and its Markdown (rendered from the JSON alone)."""
    from _machine import public_argv

    rows = {}
    for key, r in results.items():
        r = dict(r)
        r.pop("out", None)  # a machine's folder
        r["chosen_on"] = sorted(args.tuned_on)
        rows[key] = r
    data = {"commit": git_commit(), "date": time.strftime("%Y-%m-%d"),
            "machine": f"nproc = {os.cpu_count()}, CPU: {cpu_name()}",
            "software": f"Python {platform.python_version()}, torch {torch.__version__}",
            "command": public_argv(["python", "benchmarks/novel_views_dtu.py", *sys.argv[1:]]),
            "seconds": round(seconds), "tuned_on": sorted(args.tuned_on), "paper": PAPER,
            "rows": rows}
    js = args.results.with_suffix(".json")
    js.parent.mkdir(parents=True, exist_ok=True)
    js.write_text(json.dumps(data, indent=1, default=float) + "\n")
    text = render_markdown(data)
    write_results(args.results.with_suffix(".md"), text)
    print(text)


def render_markdown(data: dict) -> str:
    """The Markdown of a results JSON written by `_write` (``--from-json`` remakes it)."""
    results = data["rows"]
    paper_of = data["paper"]
    lines = ["# Novel views on real DTU scans, official protocol, and where the dB go", "",
             f"- machine: {data['machine']}",
             f"- commit {data['commit']}, {data['date']}, {data['software']}",
             f"- command: `{data['command']}`",
             "- protocol: inputs 25 22 28 at 768x576; the 25 test views; PSNR inside the test "
             "view's mask against the photo resized by bicubic without antialiasing (OpenCV "
             "INTER_CUBIC), mask bilinear > 0.5; SSIM and LPIPS-VGG on white "
             "(docs/method.md 8.3, svolsdf.evaluate.protocol)",
             "- scans the project's choices were made on (not held out): "
             + (", ".join(data["tuned_on"]) or "none"),
             f"- whole benchmark: {data['seconds']:.0f} s", "",
             "| scan | held out | run | renderer | PSNR | SSIM | LPIPS | field PSNR on its inputs "
             "| pipeline s | paper (PSNR / SSIM / LPIPS) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for key, r in results.items():
        scan, mode = key.split("/")
        for kind in ("volume rendering", "IBR", "IBR, unseen inpainted",
                     "IBR, holes from the mesh"):
            if kind not in r:
                continue
            m = r[kind]["mean"]
            pp = paper_of["VolSDF"] if mode.startswith("volsdf") else \
                paper_of[kind.split(",")[0]]
            paper = " / ".join("-" if x is None else f"{x:g}" for x in pp)
            fp = r.get("field_psnr")
            lines.append(f"| {scan} | {'yes' if r['held_out'] else 'no'} | {mode} | {kind} "
                         f"| {m['psnr']:.2f} | {m['ssim']:.3f} | {m['lpips']:.3f} "
                         f"| {'-' if fp is None else f'{fp:.2f}'} "
                         f"| {r.get('pipeline_s', float('nan')):.0f} | {paper} |")
    diag = {k: r["diagnosis"] for k, r in results.items() if "diagnosis" in r}
    if diag:
        lines += ["", "## Where the dB go (means over the test views)", "",
                  "Classes of mask pixels (module docstring): share of the mask, share of the "
                  "squared error, and the dB the mean PSNR gains when that class alone is exact.",
                  "", "| run | class | share of mask | share of error VR / IBR "
                  "| gain if exact VR / IBR (dB) |", "|---|---|---|---|---|"]
        for key, dg in diag.items():
            for c, x in dg["classes"].items():
                lines.append(f"| {key} | {c} | {x['share_px']:.1%} | {x['share_se_vr']:.1%} / "
                             f"{x['share_se_ibr']:.1%} | {x['gain_db_vr']:+.2f} / "
                             f"{x['gain_db_ibr']:+.2f} |")
        lines += ["", "Swaps (mean PSNR over the test views, dB):", "",
                  "| run | VR | IBR | IBR, released blending | IBR, reference geometry "
                  "| IBR, reference geometry, unseen exact | IBR, unseen exact | VR, unseen exact "
                  "|", "|---|---|---|---|---|---|---|---|"]
        for key, dg in diag.items():
            s = dg["swaps"]
            lines.append(f"| {key} | {s['vr']:.2f} | {s['ibr']:.2f} | {s['ibr_released']:.2f} "
                         f"| {s['ibr_ref_geometry']:.2f}"
                         f" | {s['ibr_ref_geometry_unseen_exact']:.2f} | "
                         f"{s['ibr_unseen_exact']:.2f} | {s['vr_unseen_exact']:.2f} |")
    lines += ["", "## Per view (PSNR, volume rendering / IBR)", "",
              "| view | " + " | ".join(results) + " |", "|---|" + "---|" * len(results)]
    first = next(iter(results.values()), None)
    if first:
        for v in first["IBR"]["per_view"]:
            cells = []
            for r in results.values():
                a = r["volume rendering"]["per_view"].get(v, {}).get("psnr")
                b = r["IBR"]["per_view"].get(v, {}).get("psnr")
                cells.append("-" if a is None or b is None else f"{a:.2f} / {b:.2f}")
            lines.append(f"| {v} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"




if __name__ == "__main__":
    main()
