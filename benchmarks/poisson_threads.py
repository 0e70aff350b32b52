"""Screened Poisson (pycolmap's PoissonRecon) with one thread and with several: wall time and
whether the same oriented points give the same mesh twice.

    python benchmarks/poisson_threads.py RUN [RUN ...] [--threads 2] [--repeats 2]
        [--out benchmarks/results/poisson_threads.md]

Each RUN is a finished run folder (its points.ply). The normals are computed once per run as the
mesh stage computes them up to the orientation (PCA normals, oriented towards one point on the
-z axis: the field is not loaded; the orientation does not change what is timed), then
`svolsdf.fusion.poisson.poisson_surface` runs ``repeats`` times per thread count, in one process,
alternating the thread counts.
"""

from __future__ import annotations

import argparse
import hashlib
import time
from pathlib import Path

import numpy as np
from _machine import cpu_name, write_results

from svolsdf.fusion.poisson import estimate_normals, orient_normals, poisson_surface
from svolsdf.io.ply import read_ply


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--threads", type=int, default=2, help="the multi-threaded count")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--depth", type=int, default=10)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    rows = []
    for run in args.runs:
        d = read_ply(run / "points.ply")
        pts, cols = d["points"].astype(np.float64), d["colors"]
        normals = orient_normals(pts, estimate_normals(pts, workers=2),
                                 np.array([[0.0, 0.0, -5.0]]))
        res: dict[int, list] = {1: [], args.threads: []}
        for _ in range(args.repeats):
            for th in res:
                t0 = time.perf_counter()
                v, f, _ = poisson_surface(pts, normals, cols, depth=args.depth, threads=th)
                digest = hashlib.sha1(v.tobytes() + f.tobytes()).hexdigest()[:10]
                res[th].append((time.perf_counter() - t0, len(v), digest))
                print(run.name, th, res[th][-1], flush=True)
        for th, r in res.items():
            rows.append(f"| {run.name} | {len(pts):,} | {th} | "
                        + " / ".join(f"{t:.1f}" for t, _, _ in r) + " | "
                        + " / ".join(f"{n:,}" for _, n, _ in r) + " | "
                        + ("yes" if len({h for _, _, h in r}) == 1 else "no") + " |")
    text = "\n".join([
        "| run | points | threads | wall (s), each repeat | vertices, each repeat | "
        "same mesh every repeat |",
        "|---|---|---|---|---|---|", *rows])
    print(text)
    if args.out:
        write_results(args.out, f"machine: {cpu_name()}\n\n{text}\n")


if __name__ == "__main__":
    main()
