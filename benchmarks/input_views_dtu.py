"""How well a converged field explains its own input views, pixel by pixel (DTU scans).

The field is trained on rays drawn over the whole input images: object, the table it stands on
and the background beyond. This script renders every pixel of each input view of finished run
folders (the run's own field, eval-mode sampler, the view's depth range as the guide stage uses
it) and compares the render with the run's working image (the photo the field was trained on).

Each input view's pixels split into

- ``object``: inside the view's object mask;
- ``table``: outside the mask, where a reference depth exists: PatchmatchNet (the DTU-trained
  module of ../shared/weights) on the view with its four best-paired views, kept where at least
  two of those views' own depths agree (1 px, 1 %) -- a surface several views see, in DTU the
  table and the bricks around the object;
- ``background``: outside the mask without a reference depth (black cloth, far walls).

Per view and class: the share of the image, PSNR, mean opacity, and the share of pixels the
field does not explain: mean absolute colour error over the channels above ``--threshold``
(0.1 of the range by default: about 25 grey levels, far above JPEG and resampling noise).

Pictures per view (``--pictures``): photo | render | error x3 | classes (object green, table
blue, background grey; unexplained pixels red) as JPEG files under RESULTS_DIR/input_views_dtu/.
Results: JSON with the Markdown rendered from it (``--results``), as benchmarks/table1.py.

Usage:
    python benchmarks/input_views_dtu.py --runs scan65:fast=OUT1 scan37:fast=OUT2 ...
        [--work /tmp/input_views_dtu] [--results benchmarks/results/input_views_dtu.json]
        [--pictures]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch
from _machine import cpu_name, git_commit, public_argv, write_results

REPO = Path(__file__).resolve().parents[1]
CLASSES = ("object", "table", "background")


def reference_input_depths(scene_dir: Path, work: Path, ids: list[int], size: tuple[int, int]
                           ) -> dict[int, torch.Tensor]:
    """View id -> (H, W) reference z-depth (0 = none) of ``ids`` at ``size``: PatchmatchNet with
    the four best-paired sources, kept where >= 2 of those sources' own depths agree; the
    PatchmatchNet depths are cached in WORK/<scan>/ (benchmarks/dtu_pseudo_gt.py's step 1)."""
    from dataclasses import replace

    from svolsdf.commands.mvs import mvs_depth_range
    from svolsdf.geometry.reproject import check_geometric_consistency
    from svolsdf.mvs.backbone import get_backbone
    from svolsdf.mvs.cascade import run_cascade
    from svolsdf.scene.loaders import load_scene

    probe = load_scene(scene_dir, image_size=size, load_images=False)
    cache = work / scene_dir.name / f"pmnet_{size[0]}x{size[1]}"
    cache.mkdir(parents=True, exist_ok=True)
    backbone = None

    def depth(v: int) -> torch.Tensor:
        nonlocal backbone
        f = cache / f"{v}.npy"
        if not f.is_file():
            backbone = backbone or get_backbone("patchmatchnet")
            views = [v] + probe.source_views(v)[:4]
            sc = load_scene(scene_dir, views=views, image_size=size)
            sc = replace(sc, depth_range=mvs_depth_range(sc, None))
            torch.manual_seed(v)  # PatchmatchNet's initial depth samples are random
            vol = run_cascade(backbone, sc, ref_ids=[v])
            np.save(cache / f".{v}.tmp.npy", vol[max(vol)][0].depth.float().numpy())
            os.replace(cache / f".{v}.tmp.npy", f)
        return torch.from_numpy(np.load(f))

    all_ids = probe.view_ids
    res = {}
    for v in ids:
        d = depth(v)
        cam = probe.cameras[[all_ids.index(v)]]
        count = torch.zeros(d.shape, dtype=torch.int32)
        for s in probe.source_views(v)[:4]:
            m, _, _ = check_geometric_consistency(d, cam, depth(s),
                                                  probe.cameras[[all_ids.index(s)]])
            count += m.int()
        res[v] = torch.where((d > 0) & (count >= 2), d, torch.zeros_like(d))
    return res


def _psnr(se: torch.Tensor) -> float | None:
    if se.numel() == 0:
        return None
    m = float(se.mean())
    return math.inf if m <= 0 else -10 * math.log10(m)


def measure_run(out: Path, work: Path, threshold: float, pictures: Path | None) -> dict:
    """Render every input view of run folder ``out`` and split its error by class (module
    docstring). Returns {"scan", "views": {id: {class: {...}}}, "mean": {class: {...}},
    "field_psnr_masked": float}."""
    from svolsdf.commands.render import _scene_range, open_run

    p = open_run(out)
    scene = p.load()
    scene_dir = Path(p.cfg.scene.path)
    ids = list(scene.view_ids)
    H, W = scene.images.shape[-2:]
    ref = reference_input_depths(scene_dir, work, ids, (W, H))
    s = float(scene.normalization.scale)
    t0 = time.perf_counter()
    r = p.render_views(scene.cameras_unit, _scene_range(scene, s).to(p.device),
                       keys=("rgb", "opacity"))
    render_s = time.perf_counter() - t0
    res = {"out": str(out), "views": {}, "render_s": render_s}
    acc = {c: {"px": 0, "se": 0.0, "bad": 0, "opacity": 0.0} for c in CLASSES}
    for i, v in enumerate(ids):
        photo = scene.images[i].cpu()
        rgb = r["rgb"][i].permute(2, 0, 1).clamp(0, 1)
        err = (rgb - photo).abs().mean(0)
        se = ((rgb - photo) ** 2).mean(0)
        obj = scene.masks[i, 0] > 0.5 if scene.masks is not None else torch.ones_like(err).bool()
        cls = torch.full(err.shape, 2, dtype=torch.long)
        cls[ref[v] > 0] = 1
        cls[obj] = 0
        bad = err > threshold
        pv = {}
        for c, name in enumerate(CLASSES):
            sel = cls == c
            n = int(sel.sum())
            pv[name] = {"share": n / err.numel(), "psnr": _psnr(se[sel]),
                        "unexplained": float(bad[sel].float().mean()) if n else None,
                        "opacity": float(r["opacity"][i][sel].mean()) if n else None}
            acc[name]["px"] += n
            acc[name]["se"] += float(se[sel].sum())
            acc[name]["bad"] += int(bad[sel].sum())
            acc[name]["opacity"] += float(r["opacity"][i][sel].sum())
        pv["all"] = {"psnr": _psnr(se.reshape(-1)),
                     "unexplained": float(bad.float().mean())}
        res["views"][str(v)] = pv
        if pictures is not None:
            _picture(pictures / f"{v}.jpg", photo, rgb, err, cls, bad)
    mean = {}
    for name, a in acc.items():
        mean[name] = {"psnr": (None if a["px"] == 0 else
                               (math.inf if a["se"] <= 0 else
                                -10 * math.log10(a["se"] / a["px"]))),
                      "unexplained": a["bad"] / a["px"] if a["px"] else None,
                      "opacity": a["opacity"] / a["px"] if a["px"] else None,
                      "share": a["px"] / (len(ids) * H * W)}
    res["mean"] = mean
    # the mean over views of the per-view masked PSNR: the guide stage's field_psnr, full render
    res["object_psnr_mean_of_views"] = float(np.mean(
        [res["views"][str(v)]["object"]["psnr"] for v in ids]))
    return res


def run_facts(out: Path) -> dict:
    """What a run folder says of itself, without rendering: the options that tell the variants
    apart, the guide stage's field PSNR on the inputs (inside the masks, timing.json), the field
    stage's and the whole run's seconds, and the mean whole-image training PSNR of the last 100
    steps (field/losses.csv: every ray of the step, object, table and background)."""
    import csv

    import yaml

    cfg = yaml.safe_load((out / "config.yaml").read_text())
    f, t = cfg.get("field", {}), cfg.get("train", {})
    options = {"field.background": f.get("background"),
               "field.background_model": f.get("background_model", "nerf++")
               if f.get("background") else None,
               "train.object_ray_fraction": t.get("object_ray_fraction"),
               "train.colour_steps": t.get("colour_steps", 0),
               "train.colour_rays": t.get("colour_rays") if t.get("colour_steps") else None}
    timing = json.loads((out / "timing.json").read_text())
    fp = timing.get("guide", {}).get("field_psnr")
    train_psnr = None
    if (out / "field" / "losses.csv").is_file():
        rows = list(csv.DictReader(open(out / "field" / "losses.csv")))
        steps = int(t.get("steps", 1000))
        main = [float(r["psnr"]) for r in rows if int(r["step"]) <= steps
                and int(r["step"]) > steps - 100 and r.get("psnr")]
        train_psnr = float(np.mean(main)) if main else None
    return {"options": options,
            "field_psnr_guide": fp.get("mean_db") if isinstance(fp, dict) else None,
            "field_s": timing.get("field", {}).get("seconds"),
            "total_s": timing.get("total", {}).get("seconds"),
            "training_psnr_last100": train_psnr}


def _picture(path: Path, photo, rgb, err, cls, bad) -> None:
    from PIL import Image

    heat = (err * 3).clamp(0, 1)[None].expand(3, -1, -1)
    col = torch.tensor([[0.2, 0.7, 0.2], [0.2, 0.3, 0.8], [0.5, 0.5, 0.5]])[cls].permute(2, 0, 1)
    col = torch.where(bad[None], torch.tensor([0.9, 0.1, 0.1])[:, None, None], col)
    tiles = torch.cat([photo, rgb, heat, col], dim=2)
    tiles = torch.nn.functional.interpolate(tiles[None], scale_factor=0.5, mode="area")[0]
    a = (tiles.clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(a).save(path, quality=85)


def _fmt(x, nd=2) -> str:
    if x is None:
        return "-"
    if isinstance(x, float) and math.isinf(x):
        return "inf"
    return f"{x:.{nd}f}"


def render_markdown(data: dict) -> str:
    """The Markdown table of a results JSON (`main` writes both; rerendered byte for byte)."""
    lines = [
        "# The field against its own input views (DTU)",
        "",
        f"Commit {data['commit']}, {data['date']}, {data['machine']}; made by "
        + "; ".join(f"`{c}`" for c in data.get("commands", [data.get("command")])) + ".",
        "",
        "Every pixel of each input view rendered by the run's field and compared with the photo "
        "it was trained on (768x576). Classes: object (inside the mask), table (outside the "
        "mask with a reference depth: PatchmatchNet, two of four sources agree), background "
        f"(the rest). Unexplained: mean absolute colour error > {data['threshold']}. "
        "Means over the input views, pixels pooled.",
        "",
        "| scan | variant | chosen on | object PSNR | object unexpl. | object opacity "
        "| table PSNR | table unexpl. | table share | background PSNR | background unexpl. "
        "| field PSNR (mean of views, masked) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in data["rows"]:
        m = row["mean"]
        lines.append(
            f"| {row['scan']} | {row['variant']} | {row.get('chosen_on', '-')} "
            f"| {_fmt(m['object']['psnr'])} | {_fmt(m['object']['unexplained'], 3)} "
            f"| {_fmt(m['object']['opacity'], 3)} "
            f"| {_fmt(m['table']['psnr'])} | {_fmt(m['table']['unexplained'], 3)} "
            f"| {_fmt(m['table']['share'], 3)} "
            f"| {_fmt(m['background']['psnr'])} | {_fmt(m['background']['unexplained'], 3)} "
            f"| {_fmt(row['object_psnr_mean_of_views'])} |")
    lines += ["", "What each run folder says of itself: the options that differ, the guide "
              "stage's field PSNR on its inputs inside the masks (timing.json), the mean "
              "whole-image training PSNR of the schedule's last 100 steps (field/losses.csv), "
              "and seconds (field stage / whole run, two shared cores).", "",
              "| scan | variant | options | field PSNR (guide) | training PSNR | field s "
              "| total s |", "|---|---|---|---|---|---|---|"]
    for row in data["rows"]:
        if "options" not in row:
            continue
        opts = ", ".join(f"`{k}={v}`" for k, v in row["options"].items()
                         if v not in (None, False, 0, 0.0))
        lines.append(f"| {row['scan']} | {row['variant']} | {opts or 'fast preset'} "
                     f"| {_fmt(row['field_psnr_guide'])} | {_fmt(row['training_psnr_last100'])} "
                     f"| {_fmt(row['field_s'], 0)} | {_fmt(row['total_s'], 0)} |")
    lines += ["", "Per view (object / table / background PSNR, unexplained share):", ""]
    for row in data["rows"]:
        for v, pv in row["views"].items():
            lines.append(
                f"- {row['scan']} {row['variant']} view {v}: "
                + ", ".join(f"{c} {_fmt(pv[c]['psnr'])} dB / {_fmt(pv[c]['unexplained'], 3)}"
                            for c in CLASSES))
    if any(row.get("pictures") for row in data["rows"]):
        lines += ["", "Pictures (photo | render | error x3 | classes: object green, table blue, "
                  "background grey, unexplained red): "
                  + ", ".join(f"`{row['pictures']}`" for row in data["rows"]
                              if row.get("pictures")) + "."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", nargs="+", default=[],
                    help="SCAN:VARIANT=RUN_FOLDER (SCAN:VARIANT@CHOSEN_ON=... names the scan a "
                         "choice was made on)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/input_views_dtu"))
    ap.add_argument("--results", type=Path,
                    default=REPO / "benchmarks/results/input_views_dtu.json")
    ap.add_argument("--threshold", type=float, default=0.1)
    ap.add_argument("--pictures", action="store_true")
    ap.add_argument("--append", action="store_true",
                    help="keep the rows of an existing results JSON (others than these runs)")
    ap.add_argument("--facts-only", action="store_true",
                    help="with --append: only (re)read what the run folders say of themselves "
                         "(options, timing, training PSNR) into their existing rows")
    ap.add_argument("--from-json", type=Path,
                    help="only render the Markdown of this results JSON into --results' .md")
    args = ap.parse_args()
    if args.from_json:
        write_results(args.results.with_suffix(".md"),
                      render_markdown(json.loads(args.from_json.read_text())))
        return
    if not args.runs:
        ap.error("give --runs (or --from-json)")
    rows, commands = [], []
    if args.append and args.results.is_file():
        old = json.loads(args.results.read_text())
        rows, commands = old["rows"], old.get("commands", [old.get("command")])
    for spec in args.runs:
        name, _, folder = spec.partition("=")
        scan, _, variant = name.partition(":")
        variant, _, chosen = variant.partition("@")
        pics = None
        if args.pictures:
            pics = args.results.parent / "input_views_dtu" / scan / variant
        if args.facts_only:
            row = next(r for r in rows if (r["scan"], r["variant"]) == (scan, variant))
            row.update(run_facts(Path(folder)))
            continue
        row = measure_run(Path(folder), args.work, args.threshold, pics)
        row.pop("out")
        row.update(run_facts(Path(folder)))
        row.update(scan=scan, variant=variant, chosen_on=chosen or "-",
                   pictures=(str(pics.relative_to(REPO)) if pics and pics.is_relative_to(REPO)
                             else str(pics) if pics else None))
        rows = [r for r in rows if (r["scan"], r["variant"]) != (scan, variant)] + [row]
        print(f"{scan} {variant}: object {row['mean']['object']['psnr']:.2f} dB, "
              f"unexplained {row['mean']['object']['unexplained']:.3f}", flush=True)
    data = {"commit": git_commit(), "date": time.strftime("%Y-%m-%d"),
            "machine": f"{cpu_name()}, {os.cpu_count()} cores, {platform.system()}",
            "commands": [c for c in commands if c] + [
                public_argv(["python", "benchmarks/input_views_dtu.py", *sys.argv[1:]])],
            "threshold": args.threshold, "rows": rows}
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text(json.dumps(data, indent=1) + "\n")
    write_results(args.results.with_suffix(".md"), render_markdown(data))


if __name__ == "__main__":
    main()
