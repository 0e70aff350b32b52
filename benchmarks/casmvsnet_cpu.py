"""CasMVSNet on the CPU at the paper's MVS resolution (issue 3 target): time and peak memory.

Three views at the working size 768x576 are upsampled to the paper's network input 1536x1152
(docs/method.md 1.3, ``x2_mvsres``) and run through all three stages (192 / 32 / 8 hypotheses). No
CasMVSNet weights ship with svolsdf, so the network is randomly initialised (seed 0), saved in the
official checkpoint format (``{'model': state_dict}``, docs/method.md 2.1) and loaded back through
``svolsdf.mvs.casmvsnet_net.load_casmvsnet``, exactly as a user's checkpoint would be. Random
weights do the same arithmetic as trained ones, so the time and memory are those of the real
network; the depth they give is meaningless and is not scored.

Scene: ../shared/data/dtu_scan65 (views 25 22 28) when present, else a synthetic scene with DTU-like
cameras from ``svolsdf synth``.

Run (from the repo root):

    python benchmarks/casmvsnet_cpu.py [--chunk-mb 512] [--work /tmp/casmvsnet_bench]

Writes benchmarks/results/casmvsnet_cpu.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import torch
from _machine import cpu_name, peak_rss_gb

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
RESULTS = REPO / "benchmarks/results"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--chunk-mb", type=float, default=512.0)
    ap.add_argument("--work", type=Path, default=Path("/tmp/casmvsnet_bench"))
    ap.add_argument("--size", default="768x576", help="working size; the network runs at 2x")
    args = ap.parse_args()

    from svolsdf.mvs.casmvsnet import CasMVSNetBackbone, mvs_input_size
    from svolsdf.mvs.casmvsnet_net import CasMVSNet
    from svolsdf.scene.loaders import load_scene

    w, h = (int(x) for x in args.size.split("x"))
    args.work.mkdir(parents=True, exist_ok=True)
    dtu = SHARED / "data/dtu_scan65"
    if dtu.is_dir():
        scene = load_scene(dtu, views=[25, 22, 28], image_size=(w, h))
        scene_desc = "../shared/data/dtu_scan65, views 25 22 28"
    else:
        from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

        path = args.work / "synth"
        if not (path / "gt_points.ply").is_file():
            make_synthetic_scene(path, SynthConfig(views=3, width=w, height=h, seed=0))
        scene = load_scene(path, image_size=(w, h))
        scene_desc = "svolsdf synth --seed 0 --views 3 (dtu_scan65 absent)"

    torch.manual_seed(0)
    ckpt = args.work / "casmvsnet_random.ckpt"
    torch.save({"model": CasMVSNet().state_dict()}, ckpt)
    base_gb = peak_rss_gb()
    t0 = time.perf_counter()
    backbone = CasMVSNetBackbone.create(weights=ckpt, chunk_mb=args.chunk_mb)
    stage_s, shapes = {}, {}
    prev = None
    for k in (1, 2, 3):
        t = time.perf_counter()
        vols = backbone.stage(k, scene, prev=prev)
        stage_s[k] = time.perf_counter() - t
        shapes[k] = list(vols[0].prob.shape)
        prev = {v.view_id: v for v in vols}
        finite = all(bool(torch.isfinite(v.depth).all()) for v in vols)
        print(f"stage {k}: {stage_s[k]:.1f} s, volume {shapes[k]}, finite depth {finite}, "
              f"peak {peak_rss_gb():.2f} GB", flush=True)
    total = time.perf_counter() - t0
    Wn, Hn = mvs_input_size(w, h)
    res = {
        "network_input": [Wn, Hn], "stage_seconds": stage_s, "total_seconds": total,
        "volume_shapes": shapes, "peak_rss_gb": peak_rss_gb(), "rss_before_gb": base_gb,
        "chunk_mb": args.chunk_mb, "threads": torch.get_num_threads(),
    }
    lines = [
        "# CasMVSNet on the CPU at the paper's MVS resolution (issue 3)", "",
        f"- machine: nproc = {os.cpu_count()}, {torch.get_num_threads()} torch threads, "
        f"CPU: {cpu_name()}; "
        "shared machine",
        f"- torch {torch.__version__}, Python {platform.python_version()}",
        f"- command: `python benchmarks/casmvsnet_cpu.py {' '.join(sys.argv[1:])}`",
        f"- scene: {scene_desc}; working size {w}x{h}, network input {Wn}x{Hn} "
        "(docs/method.md 1.3, x2_mvsres); random weights loaded from the official checkpoint "
        "format",
        f"- row-chunk budget of the cost volume / 3D U-Net: {args.chunk_mb:g} MB", "",
        "| stage | hypotheses x H x W | seconds (3 views) |",
        "|---|---|---|",
    ]
    for k in (1, 2, 3):
        lines.append(f"| {k} | {' x '.join(str(x) for x in shapes[k])} | {stage_s[k]:.1f} |")
    lines += ["", f"- all stages: **{total:.0f} s**; peak memory (max RSS of the process): "
              f"**{res['peak_rss_gb']:.2f} GB** (before the network: {base_gb:.2f} GB)",
              "- unchunked, the stage-1 variance volume alone would be 32 x 192 x 288 x 384 floats "
              "= 2.7 GB per view (src/svolsdf/mvs/casmvsnet.py, module docstring)"]
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "casmvsnet_cpu.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(json.dumps(res))


if __name__ == "__main__":
    main()
