"""Novel-view benchmark on DTU (issue 7): S-VolSDF against the same code's VolSDF-only baseline.

On ../shared/data/dtu_scan65 (inputs 25 22 28 at 768x576, the paper's protocol, docs/method.md 1.3)
it runs, in fresh processes, for each mode (``svolsdf``: the default fast preset; ``volsdf``: the
same field and schedule without the MVS prior, `--mode volsdf`):

    svolsdf reconstruct SCENE -o WORK/<mode> --mode <mode>
    svolsdf render WORK/<mode> --views <the 25 test views> --ibr
    svolsdf evaluate WORK/<mode> --no-report

and writes PSNR / SSIM / LPIPS (masked, docs/method.md 8.3) of volume rendering and of image-based
rendering, averaged over the held-out views and per view, with the render time per view, to a
Markdown file with the machine and the command. A rerun reuses finished pipeline stages.

Usage:
    python benchmarks/novel_views_dtu.py [--work /tmp/novel_views_dtu]
        [--results benchmarks/results/novel_views_dtu.md] [--modes svolsdf,volsdf] [--views N]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

from _machine import cpu_name  # benchmarks/_machine.py (the script's folder is on sys.path)

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
SCENE = SHARED / "data" / "dtu_scan65"


def _run(*args: str) -> float:
    cmd = [sys.executable, "-m", "svolsdf", *args]
    print("$", " ".join(cmd), flush=True)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    return time.perf_counter() - t0


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, check=True,
                              capture_output=True, text=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def run_mode(work: Path, mode: str, n_views: int | None) -> dict:
    out = work / mode
    _run("reconstruct", str(SCENE), "-o", str(out), "--mode", mode, "--no-progress")
    test = json.loads((out / "views.json").read_text())["test"]
    if n_views:
        test = test[:n_views]
    ids = [str(v) for v in test]
    render_s = _run("render", str(out), "--views", *ids, "--ibr")
    _run("evaluate", str(out), "--views", ",".join(ids), "--no-report")
    m = json.loads((out / "metrics.json").read_text())
    timing = json.loads((out / "timing.json").read_text())
    return {"test_views": test, "render_s_per_view": render_s / max(len(ids), 1),
            "images": m["images"], "images_ibr": m["images_ibr"],
            "pipeline_s": sum(v["seconds"] for k, v in timing.items() if k != "total"),
            "field_s": timing.get("field", {}).get("seconds")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/novel_views_dtu"))
    ap.add_argument("--results", type=Path,
                    default=REPO / "benchmarks/results/novel_views_dtu.md")
    ap.add_argument("--modes", default="svolsdf,volsdf")
    ap.add_argument("--keep", action="store_true",
                    help="keep the modes not in --modes from WORK/novel_views_dtu.json (an "
                         "earlier run) instead of dropping them; the table says which")
    ap.add_argument("--views", type=int, default=None,
                    help="only the first N test views (default: all 25)")
    args = ap.parse_args()
    if not SCENE.is_dir():
        sys.exit(f"skipped: {SCENE} is absent (the shared DTU scan)")
    args.work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    old = {}
    js = args.work / "novel_views_dtu.json"
    if args.keep and js.is_file():
        old = json.loads(js.read_text())
    res = {}
    for mode in args.modes.split(","):
        res[mode] = run_mode(args.work, mode, args.views)
        res[mode]["commit"] = _commit()
    kept = [m for m in old if m not in res]
    for m in kept:
        res[m] = old[m]
    js.write_text(json.dumps(res, indent=1))

    lines = ["# Novel views on DTU scan 65: S-VolSDF vs the VolSDF-only baseline (issue 7)", "",
             f"- machine: nproc = {os.cpu_count()}, CPU: {cpu_name()}, shared with other jobs",
             f"- commit {_commit()}, Python {platform.python_version()}",
             "- command: `" + " ".join(["python benchmarks/novel_views_dtu.py", *sys.argv[1:]])
             + "`",
             "- inputs 25 22 28 at 768x576, fast preset; held-out views: the 25 test views of "
             "docs/method.md 1.3; metrics inside the object mask (PSNR) / on a white background "
             "(SSIM, LPIPS-VGG), docs/method.md 8.3",
             f"- whole benchmark: {time.perf_counter() - t0:.0f} s"
             + (f"; kept from an earlier run (--keep): {', '.join(kept)} (commit "
                f"{', '.join(str(res[m].get('commit', 'unknown')) for m in kept)})"
                if kept else ""), "",
             "| mode | renderer | PSNR | SSIM | LPIPS | render s/view | pipeline s |",
             "|---|---|---|---|---|---|---|"]
    for mode, r in res.items():
        for key, name in (("images", "volume rendering"), ("images_ibr", "IBR")):
            m = r[key]
            if m is None:
                lines.append(f"| {mode} | {name} | - | - | - | | |")
                continue
            lines.append(f"| {mode} | {name} | {m['psnr']['mean']:.2f} | {m['ssim']['mean']:.3f} "
                         f"| {m['lpips']['mean']:.3f} | {r['render_s_per_view']:.1f} "
                         f"| {r['pipeline_s']:.0f} |")
    lines += ["", "Render time per view covers volume rendering and IBR together (IBR also "
              "renders the input views' depth once).", "", "## Per view (PSNR, VR / IBR)", "",
              "| view | " + " | ".join(res) + " |", "|---|" + "---|" * len(res)]
    first = next(iter(res.values()))
    for v in first["test_views"]:
        cells = []
        for r in res.values():
            a, b = r["images"]["psnr"], (r["images_ibr"] or {}).get("psnr")
            pv = a.get("per_view", {}).get(str(v))
            pb = b.get("per_view", {}).get(str(v)) if b else None
            cells.append(f"{pv:.2f} / {pb:.2f}" if pv is not None and pb is not None else "-")
        lines.append(f"| {v} | " + " | ".join(cells) + " |")
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
