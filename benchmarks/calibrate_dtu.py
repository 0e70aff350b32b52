"""`svolsdf calibrate` on DTU scan 65: time and camera accuracy against DTU's known cameras.

For 20 views (ids spread evenly over 0..48) and for all 49 views of ../shared/data/dtu_scan65,
the photos are given without their cameras to `svolsdf.calibrate.calibrate` (shrunk to
``--max-size`` pixels on the longer side); the estimated camera centres are aligned to the true
ones (cameras_sphere.npz, millimetres) by a similarity (Umeyama) fit, and the remaining distances
are reported in mm and as % of the scene size (the diagonal of the true centres' bounding box).
The views that ``--views auto`` picks on each calibrated scene are listed too.

Run from the repository root:

    python benchmarks/calibrate_dtu.py [--max-size 800] [--threads 2] [--views 20 49]

Writes benchmarks/results/calibrate_dtu.md.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _machine import cpu_name, peak_rss_gb  # benchmarks/_machine.py, on sys.path

from svolsdf.calibrate import CalibrateConfig, calibrate, centre_errors
from svolsdf.pipeline import auto_views
from svolsdf.scene.loaders import load_scene

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def run_case(scene_dir: Path, n: int, work: Path, cfg: CalibrateConfig) -> dict:
    truth = load_scene(scene_dir, load_images=False)
    ids = sorted({int(round(x)) for x in np.linspace(0, len(truth) - 1, n)})
    photos = work / f"photos{n}"
    photos.mkdir(parents=True)
    for v in ids:
        p = truth.image_paths[truth.index(v)]
        shutil.copyfile(p, photos / p.name)
    out = work / f"scene{n}"
    t0 = time.perf_counter()
    s = calibrate(photos, out, cfg)
    seconds = time.perf_counter() - t0
    est = load_scene(out, load_images=False)
    by_name = {p.name: k for k, p in enumerate(truth.image_paths)}
    idx = [by_name[p.name] for p in est.image_paths]
    err, sim, size = centre_errors(est.cameras.centers.numpy(),
                                   truth.cameras.centers[idx].numpy())
    K = est.cameras.K[0]
    scale = s["size"][0] / truth.width
    auto = auto_views(est, 3)
    auto_names = [est.image_paths[est.index(v)].name for v in auto]
    return {
        "views": n, "ids": ids, "registered": len(s["registered"]), "size": s["size"],
        "seconds": round(seconds, 1), "stages": s["seconds"],
        "centre_error_mm": {"mean": float(err.mean()), "median": float(np.median(err)),
                            "max": float(err.max())},
        "centre_error_pct": {"mean": float(100 * err.mean() / size),
                             "max": float(100 * err.max() / size)},
        "scene_size_mm": size,
        "focal_px": float(K[0, 0]), "true_focal_px": float(truth.cameras.K[0, 0, 0] * scale),
        "reprojection_px": s["mean_reprojection_error_px"],
        "auto_views": [by_name[nm] for nm in auto_names],
        "peak_memory_gb": round(peak_rss_gb(), 2),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-size", type=int, default=800)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--views", type=int, nargs="+", default=[20, 49])
    ap.add_argument("--work", type=Path, default=None, help="keep the scenes here")
    args = ap.parse_args()
    scene_dir = SHARED / "data" / "dtu_scan65"
    if not scene_dir.is_dir():
        sys.exit(f"{scene_dir} is absent (the team's shared data lives in ../shared)")
    cfg = CalibrateConfig(max_size=args.max_size, threads=args.threads, progress=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        for n in args.views:
            r = run_case(scene_dir, n, work, cfg)
            print(json.dumps(r), flush=True)
            rows.append(r)
    lines = [
        "# svolsdf calibrate on DTU scan 65",
        "",
        f"Machine: {cpu_name()}, 2 CPU cores (shared with other jobs), pycolmap "
        f"{__import__('pycolmap').__version__}, {args.threads} thread(s).",
        "",
        "Command (from the repository root): `python benchmarks/calibrate_dtu.py "
        f"--max-size {args.max_size} --threads {args.threads} --views "
        f"{' '.join(map(str, args.views))}`",
        "",
        "The photos of ../shared/data/dtu_scan65 (1600x1200) are given without cameras, shrunk to "
        f"{args.max_size} px on the longer side; exhaustive matching, one shared camera. "
        "Centre error: distance between each true camera centre and the estimated one after a "
        "similarity (Umeyama) fit, in mm and in % of the scene size (diagonal of the true "
        "centres' bounding box). Focal length at the calibrated size.",
        "",
        "| views | registered | size | time (s) | features / matching / mapping (s) | "
        "centre error mean / max (mm) | mean / max (% of scene) | focal est. / true (px) | "
        "scene size (mm) | reprojection (px) | `--views auto` | peak memory (GB) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        st = r["stages"]
        lines.append(
            f"| {r['views']} | {r['registered']} | {r['size'][0]}x{r['size'][1]} | "
            f"{r['seconds']:.0f} | {st['features']:.0f} / {st['matching']:.0f} / "
            f"{st['mapping']:.0f} | {r['centre_error_mm']['mean']:.2f} / "
            f"{r['centre_error_mm']['max']:.2f} | {r['centre_error_pct']['mean']:.3f} / "
            f"{r['centre_error_pct']['max']:.3f} | {r['focal_px']:.1f} / "
            f"{r['true_focal_px']:.1f} | {r['scene_size_mm']:.0f} | {r['reprojection_px']} | "
            f"{' '.join(map(str, r['auto_views']))} | {r['peak_memory_gb']} |")
    lines += ["", "DTU's protocol views are 25 22 28; `--views auto` (3 views) lists view ids of "
              "the original 49. The 20 views are ids "
              f"{' '.join(map(str, rows[0]['ids']))}." if rows[0]['views'] == 20 else "", ""]
    out = REPO / "benchmarks" / "results" / "calibrate_dtu.md"
    out.write_text("\n".join(lines))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
