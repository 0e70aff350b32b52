"""Report generation time on a run with 2 million points (issue 30: under 30 s).

Takes a finished run folder (or makes a small one: a 128x96 synthetic scene, 50 field steps),
copies it, and scales it up: points.ply becomes N points (the run's points repeated with a
jitter of a tenth of their spacing, colours kept) and mesh.ply is subdivided (each face into 4)
until it has at least M faces. Then times ``svolsdf report OUT`` as a user runs it (a fresh
process, imports included), once in-process with the report's own breakdown in the log, and
``svolsdf evaluate OUT`` (the metrics, then the same report) for scale.

Usage:
    python benchmarks/report_speed.py [--run RUN] [--points 2000000] [--faces 1000000]
        [--results benchmarks/results/report_speed.md]
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import cpu_name, write_results  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def _svolsdf(*args: str) -> float:
    env = dict(os.environ, PYTHONPATH=str(REPO / "src") + os.pathsep
               + os.environ.get("PYTHONPATH", ""))
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "svolsdf", *args], check=True, env=env,
                   stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def _small_run(tmp: Path) -> Path:
    scene, run = tmp / "scene", tmp / "run"
    _svolsdf("synth", str(scene), "--size", "128x96", "--views", "5")
    _svolsdf("reconstruct", str(scene), "-o", str(run), "--steps", "50", "--no-progress")
    _svolsdf("render", str(run), "--ibr")
    return run


def _scale_up(run: Path, n_points: int, n_faces: int) -> tuple[int, int]:
    import trimesh

    from svolsdf.io.ply import read_ply, write_mesh_ply, write_points_ply

    d = read_ply(run / "points.ply")
    p, c = d["points"], d["colors"]
    rng = np.random.default_rng(0)
    idx = rng.integers(0, len(p), n_points)
    spacing = float(np.linalg.norm(p.max(0) - p.min(0))) / np.sqrt(len(p))
    big = p[idx] + rng.normal(0, 0.1 * spacing, (n_points, 3))
    write_points_ply(run / "points.ply", big, rgb=None if c is None else c[idx])
    m = read_ply(run / "mesh.ply")
    v, f, vc = m["points"], m["faces"], m["colors"]
    while len(f) < n_faces:
        attrs = {"vertex_colors": vc} if vc is not None else {}
        v, f, attrs = trimesh.remesh.subdivide(v, f, vertex_attributes=attrs)
        vc = attrs.get("vertex_colors") if vc is not None else None
    write_mesh_ply(run / "mesh.ply", v, f,
                   vertex_colors=None if vc is None else np.asarray(vc, np.uint8))
    return len(big), len(f)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", type=Path, help="a finished run folder (default: make a small one)")
    ap.add_argument("--points", type=int, default=2_000_000)
    ap.add_argument("--faces", type=int, default=1_000_000)
    ap.add_argument("--results", type=Path, default=REPO / "benchmarks/results/report_speed.md")
    args = ap.parse_args()

    from svolsdf.runtime import set_cpu_env

    set_cpu_env()  # before torch loads

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        src = args.run or _small_run(tmp)
        run = tmp / "big"
        shutil.copytree(src, run)
        n_pts, n_faces = _scale_up(run, args.points, args.faces)
        (run / "report.html").unlink(missing_ok=True)
        cli = _svolsdf("report", str(run))
        size_mb = (run / "report.html").stat().st_size / 1e6
        try:  # metrics and report; needs the LPIPS weights when the run has renders
            ev = _svolsdf("evaluate", str(run))
        except subprocess.CalledProcessError:
            ev = None
        logging.basicConfig(level=logging.INFO, format="%(message)s")
        from svolsdf.evaluate.run_report import write_run_report

        t0 = time.perf_counter()
        write_run_report(run)
        inproc = time.perf_counter() - t0
    what = ("a small synthetic run (128x96, 50 field steps, renders with IBR)"
            if args.run is None else "the given run")
    cmd = f"python benchmarks/report_speed.py {' '.join(sys.argv[1:])}".strip()
    lines = ["# Report generation time (issue 30: under 30 s for a 2-million-point run)", "",
             f"- machine: nproc = {os.cpu_count()}, CPU: {cpu_name()}; no GPU; shared machine",
             f"- command: `{cmd}`",
             f"- run: {what}, scaled to {n_pts:,} points and a {n_faces:,}-face mesh",
             "- the page shows 200,000 of the points, 100,000 coloured by their distance to the "
             "ground truth, and the mesh decimated to at most 300,000 faces", "",
             "| what | seconds |", "|---|---|",
             f"| `svolsdf report OUT` (fresh process, imports included) | {cli:.1f} |",
             f"| `write_run_report(OUT)` in-process | {inproc:.1f} |",
             "| `svolsdf evaluate OUT` (Chamfer on all points, image metrics, then the report) | "
             + ("failed (LPIPS weights?)" if ev is None else f"{ev:.1f}") + " |", "",
             f"report.html: {size_mb:.1f} MB", ""]
    write_results(args.results, "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
