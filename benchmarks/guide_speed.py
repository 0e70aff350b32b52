"""Guide-depth rendering (pipeline stage ``guide``): every pixel against the dilated masks only.

The guide (docs/method.md 6.1) is the field's rendered depth of each input view. With object masks,
fusion keeps the field-guided depth only within a few pixels of the masks
(``fusion.guided_dilation``; the unguided set, which does not use the guide, within
``fusion.unguided_dilation``), so the fast preset
renders only the masks dilated by ``guide.mask_dilation`` pixels. This times
`Pipeline.render_views` on a finished run's input views for each dilation, round-robin (the
machine is shared; ratios in one run are what counts), and reports the share of pixels rendered.

Run (from the repo root), on a finished `svolsdf reconstruct` folder of a scene with masks:

    python benchmarks/guide_speed.py --run OUT [--dilations none 32 16] [--repeats 3]
        [--out benchmarks/results/guide_speed.md]
"""

from __future__ import annotations

import argparse
import logging
import os
import platform
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import cpu_name, write_results

from svolsdf.commands.render import open_run

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", type=Path, required=True,
                    help="a finished fast-preset run folder of a scene with masks")
    ap.add_argument("--dilations", nargs="+", default=["none", "32", "16"],
                    help="guide_mask_dilation values to time (none = every pixel)")
    ap.add_argument("--repeats", type=int, default=3, help="timed renders per variant")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks/results/guide_speed.md")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

    p = open_run(args.run)
    scene = p.load()
    if scene.masks is None:
        raise SystemExit(f"{args.run}: its scene has no masks; every pixel is rendered there")
    nf = p.unit_near_far().to(p.device)
    base = p.cfg
    variants = {}
    for d in args.dilations:
        r = None if d == "none" else int(d)
        p.cfg = replace(base, guide=replace(base.guide, mask_dilation=r))
        variants[d] = p.guide_pixels()
    p.cfg = base
    times = {d: [] for d in variants}
    with torch.no_grad():
        p.render_views(scene.cameras_unit[[0]], nf[[0]])  # warm-up
        for _ in range(args.repeats):
            for d, pix in variants.items():
                t0 = time.perf_counter()
                p.render_views(scene.cameras_unit, nf, pixels=pix)
                times[d].append(time.perf_counter() - t0)
    V, H, W = len(scene), scene.height, scene.width
    ref = statistics.median(times[args.dilations[0]])
    rows = []
    for d, pix in variants.items():
        share = 1.0 if pix is None else float(pix.float().mean())
        med = statistics.median(times[d])
        rows.append(f"| {d} | {100 * share:.1f} % | {med:.1f} s ({med / V:.1f} s per view) | "
                    f"{ref / med:.2f}x |")
    cmd = "python benchmarks/guide_speed.py " + " ".join(
        f"--{k} {' '.join(v) if isinstance(v, list) else v}" for k, v in vars(args).items()
        if k != "out")
    text = "\n".join([
        "# Guide-depth rendering: every pixel against the dilated masks",
        "",
        f"- machine: nproc = {os.cpu_count()}, CPU: {cpu_name()}, torch {torch.__version__}, "
        f"threads {torch.get_num_threads()}, Python {platform.python_version()}; shared machine",
        f"- command: `{cmd}`",
        f"- run: {args.run.name}, {V} input views at {W}x{H}; the median of {args.repeats} "
        "renders of all input views per variant, round-robin",
        "",
        "| guide_mask_dilation (px) | pixels rendered | render time | speed-up vs the first |",
        "|---|---|---|---|",
        *rows,
        "",
    ])
    write_results(args.out, text)
    print(text)


if __name__ == "__main__":
    main()
