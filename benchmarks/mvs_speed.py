"""Plane-sweep speed: the box filter and the SGM aggregation against their previous versions.

The plane-sweep backbone (svolsdf.mvs.planesweep) spent most of its CPU time in two places:
``F.avg_pool2d`` inside the box filter (ZNCC windows and the guided filter; a third of stages 2-3)
and the Python loop of the SGM scanline passes (another third). Both were rewritten:

- box filter: shifted in-place adds along each axis divided by the window's pixel count, instead
  of ``F.avg_pool2d(..., count_include_pad=False)`` (the same mean, to float rounding);
- SGM: the passes over the same slices run as one batch (a reverse pass is a forward pass over
  the flipped slices with the opposite shift; predecessors are gathered from a buffer padded by a
  constant column, which keeps C where a pass has no predecessor), so 8 directions take W + H
  Python steps instead of 2 W + 6 H, and the edge-aware P2 is computed once per volume.

This script times the current functions against the previous ones, interleaved (round-robin,
median of ``--repeats``) at the sizes the backbone uses at 768x576 (stage 1: 192 hypotheses at
1/4 size, stage 2: 32 at 1/2, stage 3: 8 at full size; the box filter on a 24-hypothesis chunk),
and checks that they agree. With ``--scene`` it also times a whole MVS-only run of the current
code, ``svolsdf reconstruct SCENE --mode mvs-only`` (a fresh output folder), per stage.

Run (from the repo root):

    python benchmarks/mvs_speed.py [--scene SCENE] [--out benchmarks/results/mvs_speed.md]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from _machine import cpu_name, write_results

from svolsdf.mvs.planesweep import box_filter, sgm_aggregate

REPO = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------- previous versions
def box_filter_pool(x: torch.Tensor, radius: int) -> torch.Tensor:
    """The previous box filter: separable ``avg_pool2d`` without the padded pixels."""
    k = 2 * radius + 1
    x = F.avg_pool2d(x, (1, k), stride=1, padding=(0, radius), count_include_pad=False)
    return F.avg_pool2d(x, (k, 1), stride=1, padding=(radius, 0), count_include_pad=False)


def _sgm_pass_loop(c, g, p1, p2, sigma, reverse, shift):
    """The previous SGM pass: one direction at a time, P2 recomputed at every step."""
    n, _, m = c.shape
    out = torch.empty_like(c)
    if shift == 0:
        tgt, src = slice(0, m), slice(0, m)
    elif shift > 0:
        tgt, src = slice(1, m), slice(0, m - 1)
    else:
        tgt, src = slice(0, m - 1), slice(1, m)
    order = range(n - 1, -1, -1) if reverse else range(n)
    prev = None
    for i in order:
        if prev is None:
            cur = c[i].clone()
        else:
            j = i + 1 if reverse else i - 1
            P = prev[:, src]
            mval = P.min(dim=0, keepdim=True).values
            pen2 = p1 + (p2 - p1) * torch.exp(-(g[i, tgt] - g[j, src]).abs() / sigma)
            best = torch.minimum(P, mval + pen2[None])
            best[1:] = torch.minimum(best[1:], P[:-1] + p1)
            best[:-1] = torch.minimum(best[:-1], P[1:] + p1)
            cur = c[i].clone()
            cur[:, tgt] += best - mval
        out[i] = cur
        prev = cur
    return out


def sgm_loop(cost, guide, p1, p2, sigma, directions=8):
    """The previous `sgm_aggregate`: 2 passes per path, one after the other."""
    total = torch.zeros_like(cost)
    paths = [(2, 0), (1, 0)] + ([(1, 1), (1, -1)] if directions == 8 else [])
    for dim, shift in paths:
        c = cost.movedim(dim, 0)
        g = guide.movedim(dim - 1, 0)
        for reverse in (False, True):
            total += _sgm_pass_loop(c, g, p1, p2, sigma, reverse,
                                    -shift if reverse else shift).movedim(0, dim)
    return total / len(paths) / 2


# ---------------------------------------------------------------------- timing
def _interleaved(fns: dict, repeats: int) -> dict[str, float]:
    """Median wall seconds of each callable, timed round-robin."""
    times = {k: [] for k in fns}
    for f in fns.values():  # warm-up
        f()
    for _ in range(repeats):
        for k, f in fns.items():
            t0 = time.perf_counter()
            f()
            times[k].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in times.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", type=Path, default=None,
                    help="also time `svolsdf reconstruct SCENE --mode mvs-only` per stage")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks/results/mvs_speed.md")
    args = ap.parse_args()
    g = torch.Generator().manual_seed(0)
    lines = [
        "# Plane-sweep speed: box filter and SGM, current against previous",
        "",
        f"- machine: {cpu_name()}, nproc = {os.cpu_count()}, torch threads = "
        f"{torch.get_num_threads()}, torch {torch.__version__}, Python "
        f"{platform.python_version()}; shared machine, timings interleaved, median of "
        f"{args.repeats}",
        f"- command: `python benchmarks/mvs_speed.py {' '.join(sys.argv[1:])}`".replace("  ", " "),
        "",
        "## Box filter (radius 2, the ZNCC window and guided-filter radius of every stage)",
        "",
        "| input (N, C, H, W) | previous (ms) | current (ms) | speed-up | max abs diff |",
        "|---|---|---|---|---|",
    ]
    for shape in [(1, 24, 144, 192), (1, 24, 288, 384), (1, 8, 576, 768), (1, 1, 576, 768)]:
        x = torch.rand(*shape, generator=g)
        diff = float((box_filter(x, 2) - box_filter_pool(x, 2)).abs().max())
        t = _interleaved({"old": lambda x=x: box_filter_pool(x, 2),
                          "new": lambda x=x: box_filter(x, 2)}, args.repeats)
        lines.append(f"| {shape} | {1e3 * t['old']:.1f} | {1e3 * t['new']:.1f} | "
                     f"{t['old'] / t['new']:.1f}x | {diff:.1e} |")
        print(lines[-1], flush=True)
    lines += ["", "## SGM, 8 directions (P1 0.03, P2 2.0, sigma 0.04: the backbone's defaults)", "",
              "| cost volume (D, H, W) | previous (s) | current (s) | speed-up | max abs diff "
              "| argmin differs |", "|---|---|---|---|---|---|"]
    for shape in [(192, 144, 192), (32, 288, 384), (8, 576, 768)]:
        c = 2 * torch.rand(*shape, generator=g)
        gd = torch.rand(*shape[1:], generator=g)
        a, b = sgm_aggregate(c, gd, 0.03, 2.0, 0.04, 8), sgm_loop(c, gd, 0.03, 2.0, 0.04, 8)
        diff = float((a - b).abs().max())
        flips = int((a.argmin(0) != b.argmin(0)).sum())
        t = _interleaved({"old": lambda c=c, gd=gd: sgm_loop(c, gd, 0.03, 2.0, 0.04, 8),
                          "new": lambda c=c, gd=gd: sgm_aggregate(c, gd, 0.03, 2.0, 0.04, 8)},
                         max(1, args.repeats // 2))
        lines.append(f"| {shape} | {t['old']:.2f} | {t['new']:.2f} | {t['old'] / t['new']:.1f}x "
                     f"| {diff:.1e} | {flips} of {shape[1] * shape[2]} |")
        print(lines[-1], flush=True)
    if args.scene is not None:
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "run"
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "svolsdf", "reconstruct", str(args.scene),
                            "-o", str(out), "--mode", "mvs-only", "--no-progress"], check=True,
                           stdout=subprocess.DEVNULL)
            wall = time.perf_counter() - t0
            stages = json.loads((out / "timing.json").read_text())
        st = {k: round(v["seconds"], 1) for k, v in stages.items() if isinstance(v, dict)}
        lines += ["", f"## Whole MVS-only run of the current code on `{args.scene}`", "",
                  f"- `svolsdf reconstruct {args.scene} --mode mvs-only`: {wall:.0f} s wall "
                  f"(process start included); stages (s): {st}"]
        print(lines[-1], flush=True)
    write_results(args.out, "\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
