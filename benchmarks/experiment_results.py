"""Results of ``svolsdf benchmark --experiment`` kept in benchmarks/results/: the run's record
(OUT/experiment.json) copied as NAME.json, with NAME.md (and NAME.png) rendered from it by
`svolsdf.commands.experiment.experiment_markdown` and `experiment_plot`, exactly what the
command writes beside its runs.

    python benchmarks/experiment_results.py --run OUT --results benchmarks/results/NAME.json \
        [--field-alone DATA]      # synthetic scenes: each run's guide depth against gt_depth/
        [--pseudo-gt DATA --pgt-cache DIR]   # DTU scans: points, mesh and guide depth against
                                             # the 49-view pseudo ground truth (dtu_pseudo_gt.py)
    python benchmarks/experiment_results.py --from-json benchmarks/results/NAME.json \
        --results benchmarks/results/NAME.md      # render only (tests/benchmarks)
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

# render with this checkout's code (the renderer is svolsdf's own), not an installed copy's
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # dtu_pseudo_gt

from svolsdf.commands.experiment import (  # noqa: E402
    EXPERIMENT_FILE,
    experiment_markdown,
    experiment_plot,
)


def row_paths(row: dict, run: Path, data: Path) -> tuple[str, Path, Path]:
    """(scene folder name, the row's run folder, its scene folder) of a benchmark row: with
    several view sets the row's scene label is ``"<scene> [a,b,c]"`` and its runs sit in
    ``OUT/<scene>/views-a-b-c/<variant>/`` (`svolsdf.commands.benchmark`)."""
    name, sep, ids = row["scene"].partition(" [")
    folder = run / name
    if sep:
        folder = folder / ("views-" + "-".join(ids.rstrip("]").split(",")))
    return name, folder / row["mode"], data / name


def _at_pixels(a, h: int, w: int):
    """(h, w) nearest samples of the 2D array ``a`` at the pixel centres of an (h, w) grid."""
    import numpy as np

    iy = ((np.arange(h) + 0.5) * a.shape[0] / h).astype(int)
    ix = ((np.arange(w) + 0.5) * a.shape[1] / w).astype(int)
    return a[np.ix_(iy, ix)]


def _field_row(row: dict, errs: list) -> dict:
    """A field-alone row: the median absolute guide-depth error (mm) over the input views'
    ``errs`` (1D arrays) and the share within 2 mm."""
    import numpy as np

    e = np.concatenate(errs)
    return {"scene": row["scene"], "variant": row["mode"],
            "median_mm": round(float(np.median(e)), 4),
            "within_2mm": round(float((e < 2.0).mean()), 4)}


def field_alone(record: dict, run: Path, data: Path) -> dict:
    """Each run's guide depth (OUT/<scene>/<variant>/field/render_depth/<view>.npy: the
    field's rendered depth, or the soft-consistency-only ablation's consistency depth) against
    the synthetic scene's exact depth (gt_depth/<view>.npy) inside its object masks, over the
    input views: the median absolute error (mm) and the share of pixels within 2 mm."""
    import numpy as np

    from svolsdf.io.images import read_mask

    rows = []
    for r in record["rows"]:
        if r.get("status", "ok") != "ok" or r.get("run_mode") != "svolsdf":
            continue
        _, folder, scene = row_paths(r, run, data)
        folder = folder / "field" / "render_depth"
        errs = []
        for v in r["views"]:
            guide = np.load(folder / f"{v}.npy")
            gt = np.load(scene / "gt_depth" / f"{v:03d}.npy")
            mask = read_mask(scene / "mask" / f"{v:03d}.png")[0].numpy() > 0.5
            if guide.shape != gt.shape:  # a stage-1 size guide: the exact depth at its pixels
                gt, mask = _at_pixels(gt, *guide.shape), _at_pixels(mask, *guide.shape)
            ok = mask & (gt > 0) & np.isfinite(guide)
            errs.append(np.abs(guide[ok] - gt[ok]))
        rows.append(_field_row(r, errs))
    return {"what": "Guide depth of the input views against the exact depth inside the object "
                    "masks: median absolute error in mm (share of pixels within 2 mm); the "
                    "field alone, before stages 2-3 and fusion.", "rows": rows}


def pgt_cloud(cache: Path, scene: str):
    """The whole object reference of ``scene``'s pseudo ground truth in ``cache`` (before the
    inputs' cut; `dtu_pseudo_gt.references` wrote it): (N, 3) float array."""
    import numpy as np

    return np.load(sorted((cache / scene).glob("pseudo_gt_*_dil0.npy"))[0])


def pgt_depth(points, camera, h: int, w: int):
    """The depth of the pseudo ground truth's ``points`` (N, 3) seen by ``camera`` (one view,
    `svolsdf.scene.cameras.Cameras`) at the pixels of an (h, w) grid: their z-buffer, (h, w)
    float64, inf where no point projects."""
    import torch

    cam = camera.resize(w, h).to(dtype=torch.float64)
    uv, z = cam.project(torch.from_numpy(points))
    u, vv = uv[0, :, 0].floor().long(), uv[0, :, 1].floor().long()
    ok = (u >= 0) & (u < w) & (vv >= 0) & (vv < h) & (z[0] > 0)
    zb = torch.full((h * w,), float("inf"), dtype=torch.float64)
    zb.scatter_reduce_(0, (vv * w + u)[ok], z[0][ok], reduce="amin")
    return zb.reshape(h, w).numpy()


def pseudo_gt(record: dict, run: Path, data: Path, cache: Path) -> tuple[dict, dict]:
    """Each DTU row's run scored against its scan's many-view pseudo ground truth
    (benchmarks/dtu_pseudo_gt.py: PatchmatchNet on all 49 views, fused, cut to what the input
    views see; cached in ``cache``/<scene>): the points and the mesh's surface against the
    "object" reference, and the field alone (the guide depth of the input views, as
    `field_alone`) against the depth of the pseudo ground truth's points seen by each view
    (their z-buffer at the guide's pixels) inside the object mask.

    Returns:
        ``(pseudo_gt, field_alone)`` sections of the record, rows keyed by scene and variant.
    """
    import numpy as np
    from dtu_pseudo_gt import references, score_run

    from svolsdf.scene.loaders import load_scene

    size = tuple(record["size"]) if record.get("size") else (768, 576)
    rows, field_rows, refs_of, clouds = [], [], {}, {}
    for r in record["rows"]:
        if r.get("status", "ok") != "ok":
            continue
        name, folder, scene_dir = row_paths(r, run, data)
        probe = load_scene(scene_dir, load_images=False)
        if not probe.extras.get("dtu") or not probe.extras.get("mask_paths"):
            continue
        key = (r["scene"], tuple(r["views"]))
        if key not in refs_of:
            refs_of[key] = references(scene_dir, cache / name, list(r["views"]), size)
        refs, obj, diag = refs_of[key]
        s = score_run(folder, {"object": refs["object"]}, obj, diag)["object"]
        rows.append({"scene": r["scene"], "variant": r["mode"],
                     **{f"points_{k}": round(float(v), 4) for k, v in s["points"].items()},
                     **{f"mesh_{k}": round(float(v), 4) for k, v in s.get("mesh", {}).items()}})
        if r.get("run_mode") != "svolsdf":
            continue
        if name not in clouds:  # the whole object reference, before the inputs' cut
            clouds[name] = pgt_cloud(cache, name)
        full = clouds[name]
        sc = load_scene(scene_dir, views=list(r["views"]), image_size=size)
        errs = []
        for i, v in enumerate(r["views"]):
            guide = np.load(folder / "field" / "render_depth" / f"{v}.npy")
            h, w = guide.shape
            gt = pgt_depth(full, sc.cameras[[i]], h, w)
            mask = sc.masks[i, 0].numpy()
            m = (_at_pixels(mask, h, w) > 0.5) & np.isfinite(gt) & np.isfinite(guide) & (guide > 0)
            errs.append(np.abs(guide[m] - gt[m]))
        field_rows.append(_field_row(r, errs))
    return ({"what": "Points and mesh surface against the scan's 49-view pseudo ground truth "
                     "(benchmarks/dtu_pseudo_gt.py: PatchmatchNet on every view, fused where "
                     "three of eight neighbours agree, inside the object masks, cut to what the "
                     "input views see), in mm: accuracy, completeness, their mean clipped at 5 % "
                     "of the reference's diagonal, and the DTU rule (distances beyond it left "
                     "out). The reference carries PatchmatchNet's errors: compare variants, not "
                     "absolute values. Scored by `python benchmarks/experiment_results.py --run "
                     "OUT --results NAME.json --pseudo-gt DATA --pgt-cache CACHE`.",
             "rows": rows},
            {"what": "Guide depth of the input views against the depth of the pseudo ground "
                     "truth's points each view sees, inside the object masks: median absolute "
                     "error in mm (share of pixels within 2 mm); the field alone, before stages "
                     "2-3 and fusion.", "rows": field_rows})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, help="the benchmark's output folder (its experiment.json)")
    ap.add_argument("--results", type=Path, required=True,
                    help="NAME.json to write (with --run) or NAME.md to render (--from-json)")
    ap.add_argument("--from-json", type=Path, help="only render this record's Markdown")
    ap.add_argument("--field-alone", type=Path, metavar="DATA",
                    help="the experiment's data folder: score each run's guide depth (the "
                         "field alone) against its synthetic scene's gt_depth/ in the masks")
    ap.add_argument("--pseudo-gt", type=Path, metavar="DATA",
                    help="the experiment's data folder: score each DTU scan's runs against its "
                         "many-view pseudo ground truth (needs --pgt-cache)")
    ap.add_argument("--pgt-cache", type=Path, metavar="DIR",
                    help="where the pseudo ground truth's depth maps and clouds are cached")
    args = ap.parse_args()
    if args.from_json:
        record = json.loads(args.from_json.read_text())
        args.results.with_suffix(".md").write_text(experiment_markdown(record))
        return
    if args.run is None:
        ap.error("give --run OUT (or --from-json)")
    record = json.loads((args.run / EXPERIMENT_FILE).read_text())
    if args.field_alone is not None:
        record["field_alone"] = field_alone(record, args.run, args.field_alone)
    if args.pseudo_gt is not None:
        if args.pgt_cache is None:
            ap.error("--pseudo-gt needs --pgt-cache DIR")
        record["pseudo_gt"], record["field_alone"] = pseudo_gt(record, args.run, args.pseudo_gt,
                                                               args.pgt_cache)
    out = args.results.with_suffix(".json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1) + "\n")
    record = json.loads(out.read_text())
    out.with_suffix(".md").write_text(experiment_markdown(record))
    experiment_plot(record, out.with_suffix(".png"))
    print(f"wrote {out}, {out.with_suffix('.md')} and {out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
