"""Why S-VolSDF's fused points are less accurate than the MVS backbone's alone with six and nine
input views (benchmarks/results/views_cpu.md): each depth set a run fuses, scored per pixel
against the scan's pseudo ground truth, and fusion run again on copies of the runs without each
of the fast preset's two fusion extensions (the optimized surface as a consistent source,
``fusion.surface``; the unguided stages 2-3 as a second hypothesis, ``fusion.unguided``).

    python benchmarks/views_accuracy.py --run VIEWS_OUT --data DATA --pgt-cache CACHE \
        --work DIR --results benchmarks/results/views_accuracy.json
    python benchmarks/views_accuracy.py --from-json benchmarks/results/views_accuracy.json \
        --results benchmarks/results/views_accuracy.md       # render only (tests/benchmarks)

VIEWS_OUT is the output folder of ``svolsdf benchmark --experiment experiments/views_cpu.yaml``
(its experiment.json); DIR receives one copy of each S-VolSDF run per fusion variant (about
1 GB each), where ``svolsdf reconstruct -o COPY --from fusion --set ...`` fuses again.
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import shutil
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # dtu_pseudo_gt, experiment_results

# the depth sets of a run folder, each OUT/<dir>/<view>.npy (docs/method.md 6.1-6.3)
DEPTH_SETS = {
    "guide": ("svolsdf", "field/render_depth", "the field's rendered depth (the guide)"),
    "guided": ("svolsdf", "depth", "stages 2-3 centred on the guide (S-VolSDF's final depth)"),
    "unguided": ("svolsdf", "unguided/depth",
                 "stages 2-3 centred on stage 1 (fusion.unguided's second hypothesis)"),
    "mvs-only": ("mvs-only", "depth", "the MVS backbone alone's final depth"),
}
# fusion rerun on a copy of each S-VolSDF run: name -> --set options
FUSION_VARIANTS = {
    "fast preset": [],
    "no surface vote": ["fusion.surface=0"],
    "no unguided set": ["fusion.unguided=false"],
    "neither (the paper's fusion)": ["fusion.surface=0", "fusion.unguided=false"],
}


def depth_set_errors(run: Path, data: Path, cache: Path, record: dict) -> list[dict]:
    """Per view set: each depth set of `DEPTH_SETS` against the depth of the pseudo ground
    truth's points each input view sees (`experiment_results.pgt_depth`), inside the object
    masks: median and 90th percentile of the absolute error (mm), share within 1 and 2 mm, and
    coverage (share of the mask's
    pixels with a reference depth that the set gives a depth)."""
    import numpy as np
    from experiment_results import _at_pixels, pgt_cloud, pgt_depth, row_paths

    from svolsdf.scene.loaders import load_scene

    size = tuple(record["size"])
    rows, clouds = [], {}
    for r in record["rows"]:
        if r["mode"] != "svolsdf" or r.get("status", "ok") != "ok":
            continue
        name, folder, scene_dir = row_paths(r, run, data)
        if name not in clouds:
            clouds[name] = pgt_cloud(cache, name)
        sc = load_scene(scene_dir, views=list(r["views"]), image_size=size)
        row = {"scene": r["scene"], "views": len(r["views"])}
        for key, (variant, sub, _) in DEPTH_SETS.items():
            base = folder.parent / variant / sub
            errs, covered, total = [], 0, 0
            for i, v in enumerate(r["views"]):
                d = np.load(base / f"{v}.npy")
                h, w = d.shape
                gt = pgt_depth(clouds[name], sc.cameras[[i]], h, w)
                m = (_at_pixels(sc.masks[i, 0].numpy(), h, w) > 0.5) & np.isfinite(gt)
                has = m & np.isfinite(d) & (d > 0)
                errs.append(np.abs(d[has] - gt[has]))
                covered, total = covered + int(has.sum()), total + int(m.sum())
            e = np.concatenate(errs)
            row[key] = {"median_mm": round(float(np.median(e)), 3),
                        "p90_mm": round(float(np.percentile(e, 90)), 3),
                        "within_1mm": round(float((e < 1).mean()), 3),
                        "within_2mm": round(float((e < 2).mean()), 3),
                        "coverage": round(covered / max(total, 1), 3)}
        rows.append(row)
    return rows


def _accuracy_tail(points: Path, gt, obj) -> dict:
    """Median distance (mm) from the fused points of ``points`` (inside the scored box of
    `dtu_pseudo_gt.score`) to the (M, 3) reference ``gt``, and the share beyond 2 mm: where the
    accuracy's mean comes from."""
    import numpy as np
    from scipy.spatial import cKDTree

    from svolsdf.io.ply import read_ply

    pred = read_ply(points)["points"].astype(np.float64)
    max_dist = 0.05 * float(np.linalg.norm(obj.max(0) - obj.min(0)))
    lo, hi = obj.min(0) - max_dist, obj.max(0) + max_dist
    d = cKDTree(gt).query(pred[((pred >= lo) & (pred <= hi)).all(1)], workers=1)[0]
    return {"accuracy_median": float(np.median(d)), "beyond_2mm": float((d > 2).mean())}


def fuse_again(folder: Path, target: Path, sets: list[str]) -> Path:
    """A copy of the run ``folder`` at ``target`` fused again with the ``--set`` options ``sets``
    (``svolsdf reconstruct -o target --from fusion``, the mesh by TSDF: only the points are
    scored); reused when a finished copy is there. Returns ``target``."""
    if not (target / "points.ply").is_file() or not (target / "done").is_file():
        if target.exists():
            shutil.rmtree(target)
        shutil.copytree(folder, target)
        (target / "benchmark_row.json").unlink(missing_ok=True)
        cmd = ["svolsdf", "reconstruct", "-o", str(target), "--from", "fusion",
               "--no-progress", "--set", "mesh.method=tsdf",
               *[a for s in sets for a in ("--set", s)]]
        subprocess.run(cmd, check=True)
        (target / "done").write_text(" ".join(cmd[1:]) + "\n")
    return target


def fusion_variants(run: Path, data: Path, cache: Path, record: dict, work: Path) -> list[dict]:
    """Per view set and `FUSION_VARIANTS` entry: the S-VolSDF run copied into ``work``, fused
    again with the variant's options (``svolsdf reconstruct -o COPY --from fusion``), its points
    scored against the pseudo ground truth (`dtu_pseudo_gt.score_run`); the MVS backbone alone
    beside them."""
    from dtu_pseudo_gt import references, score_run
    from experiment_results import row_paths

    size = tuple(record["size"])
    rows = []
    for r in record["rows"]:
        if r["mode"] != "svolsdf" or r.get("status", "ok") != "ok":
            continue
        name, folder, scene_dir = row_paths(r, run, data)
        refs, obj, diag = references(scene_dir, cache / name, list(r["views"]), size)
        ref = {"object": refs["object"]}
        tag = folder.parent.name
        for variant, sets in [*FUSION_VARIANTS.items(), ("MVS backbone alone", None)]:
            if sets is None:
                target = folder.parent / "mvs-only"
            else:
                target = fuse_again(folder, work / name / tag / variant.split(" (")[0]
                                    .replace(" ", "-"), sets)
            s = score_run(target, ref, obj, diag)["object"]["points"]
            s.update(_accuracy_tail(target / "points.ply", ref["object"][1], obj))
            timing = json.loads((target / "timing.json").read_text())
            rows.append({"scene": r["scene"], "views": len(r["views"]), "fusion": variant,
                         "set": sets, "points": timing["fusion"].get("points"),
                         **{k: round(float(v), 3) for k, v in s.items()}})
    return rows


def markdown(rec: dict) -> str:
    """The record rendered as Markdown."""
    lines = ["# Why S-VolSDF's points lose accuracy with six and nine views", "",
             rec["what"], "", "## Each depth set against the pseudo ground truth", "",
             rec["depth_sets_what"], ""]
    keys = list(DEPTH_SETS)
    lines += ["| scene | " + " | ".join(keys) + " |", "|---|" + "---:|" * len(keys)]
    for r in rec["depth_sets"]:
        cells = [f"{r[k]['median_mm']:.2f} / {r[k]['p90_mm']:.1f} mm "
                 f"({100 * r[k]['within_2mm']:.0f} %)" for k in keys]
        lines.append(f"| {r['scene']} | " + " | ".join(cells) + " |")
    lines += ["", "Sets: " + "; ".join(f"{k} = {v[2]}" for k, v in DEPTH_SETS.items()) + ".",
              "", "## Fusion without each extension", "", rec["fusion_what"], "",
              "| scene | fusion | set | points | acc. | acc. median | beyond 2 mm | comp. | "
              "Chamfer | DTU rule | F |",
              "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rec["fusion"]:
        sets = ", ".join(f"`{s}`" for s in r["set"]) if r["set"] else "-"
        pts = f"{int(r['points']):,}" if r.get("points") else "-"
        lines.append(f"| {r['scene']} | {r['fusion']} | {sets} | {pts} | "
                     f"{r['accuracy']:.2f} | {r['accuracy_median']:.2f} | "
                     f"{100 * r['beyond_2mm']:.0f} % | {r['completeness']:.2f} | "
                     f"{r['overall']:.2f} | {r['overall_dtu_rule']:.2f} | {r['fscore']:.2f} |")
    lines += ["", "## What ran", "", f"Commit {rec['commit']}, {rec['date']}; {rec['machine']}.",
              "", f"Command: `{rec['command']}` (runs: `{rec['runs_command']}`).", ""]
    return "\n".join(lines)


def provenance(machine: dict | None) -> dict:
    """The record's ``commit`` (this checkout's, with the package version), ``date`` and
    ``machine`` (an experiment record's machine entry, else this machine's processor)."""
    import torch

    from svolsdf import __version__

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True, cwd=Path(__file__).parent).stdout.strip()
    m = machine or {}
    return {"commit": f"{commit} (svolsdf {__version__})",
            "date": datetime.date.today().isoformat(),
            "machine": (f"{m.get('cpu') or platform.processor()}, {m.get('cores', '?')} cores, "
                        f"torch {m.get('torch') or torch.__version__}")}


def write_record(rec: dict, results: Path, render) -> None:
    """``rec`` written as ``results``' .json and rendered from that file by ``render`` into
    its .md."""
    out = results.with_suffix(".json")
    out.write_text(json.dumps(rec, indent=1) + "\n")
    out.with_suffix(".md").write_text(render(json.loads(out.read_text())))
    print(f"wrote {out} and {out.with_suffix('.md')}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, help="output folder of the views_cpu experiment")
    ap.add_argument("--data", type=Path, help="the experiment's data folder")
    ap.add_argument("--pgt-cache", type=Path, help="pseudo ground truth cache (dtu_pseudo_gt)")
    ap.add_argument("--work", type=Path, help="where the fusion variants' run copies go")
    ap.add_argument("--results", type=Path, required=True)
    ap.add_argument("--from-json", type=Path, help="only render this record's Markdown")
    args = ap.parse_args()
    if args.from_json:
        rec = json.loads(args.from_json.read_text())
        args.results.with_suffix(".md").write_text(markdown(rec))
        return
    if None in (args.run, args.data, args.pgt_cache, args.work):
        ap.error("give --run, --data, --pgt-cache and --work (or --from-json)")
    record = json.loads((args.run / "experiment.json").read_text())
    rec = {
        "what": "S-VolSDF (fast preset) and the MVS backbone alone on DTU scan 65 from 3, 6 and 9 "
                "input views (benchmarks/results/views_cpu), in mm against the scan's 49-view "
                "pseudo ground truth (benchmarks/dtu_pseudo_gt.py). The reference carries "
                "PatchmatchNet's errors (the runs use the plane sweep): compare rows, not "
                "absolute values.",
        "depth_sets_what": "Per pixel inside the object masks, over the input views: median "
                           "and 90th-percentile absolute depth error against the depth of the "
                           "pseudo ground truth's points each view sees (share within 2 mm); "
                           "every set covers every masked pixel that has a reference depth.",
        "fusion_what": "Fusion run again on copies of each S-VolSDF run (`svolsdf reconstruct "
                       "-o COPY --from fusion --set ...`), points scored as in views_cpu: "
                       "accuracy (mean distance to the reference, and its median and share of "
                       "points beyond 2 mm), completeness, their mean clipped at 5 % of the "
                       "reference's diagonal, the DTU rule and F-score.",
        "depth_sets": depth_set_errors(args.run, args.data, args.pgt_cache, record),
        "fusion": fusion_variants(args.run, args.data, args.pgt_cache, record, args.work),
        **provenance(record.get("machine")),
        "command": "python benchmarks/views_accuracy.py --run OUT --data DATA --pgt-cache CACHE "
                   "--work DIR --results benchmarks/results/views_accuracy.json",
        "runs_command": record.get("command", ""),
    }
    write_record(rec, args.results, markdown)


if __name__ == "__main__":
    main()
