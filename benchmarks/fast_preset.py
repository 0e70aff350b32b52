"""Fast-preset benchmark (issue 5): whole pipeline, three views, wall time, peak memory, Chamfer.

On a synthetic scene with exact ground truth (``svolsdf synth``, 768x576 by default) it runs, one
after another in fresh processes (`svolsdf reconstruct`):

  (a) mvs-only          the MVS backbone alone (stages 1-3 + fusion)
  (b) volsdf            the fast preset's field without the MVS prior (sphere init, no GCE)
  (c) paper             the S-VolSDF paper preset (8x256 MLP, error-bounded sampler), given the
                        optimization wall time that (d) used
  (d) fast              the S-VolSDF fast preset (the default)

and scores points.ply (and mesh.ply) against the ground-truth surface the input views observe
(`svolsdf.evaluate.synthetic.synthetic_chamfer`). Optionally (``--dtu``) it runs the fast preset
on ../shared/data/dtu_scan65 and reports its times. Results go to a Markdown file with the
machine and the command.

Usage:
    python benchmarks/fast_preset.py [--size 768x576] [--seed 0] [--out /tmp/fast_bench]
        [--results benchmarks/results/fast_preset.md] [--only a,b,c,d] [--dtu]
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

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def _cpu() -> str:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _reconstruct(scene: Path, out: Path, *args: str) -> float:
    cmd = [sys.executable, "-m", "svolsdf", "reconstruct", str(scene), "-o", str(out),
           "--no-progress", *args]
    print("$", " ".join(cmd), flush=True)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    return time.perf_counter() - t0


def _score(scene: Path, out: Path) -> dict:
    from svolsdf.evaluate.synthetic import synthetic_chamfer
    from svolsdf.io.ply import read_ply

    views = json.loads((out / "views.json").read_text())["inputs"]
    timing = json.loads((out / "timing.json").read_text())
    res = {"wall_s": timing["total"]["seconds"],
           "peak_gb": max(v.get("peak_memory_gb", 0) for v in timing.values()),
           "field_s": timing.get("field", {}).get("seconds"),
           "steps_per_s": timing.get("field", {}).get("steps_per_s"),
           "stages": {k: v["seconds"] for k, v in timing.items()}}
    for name in ("points", "mesh"):
        f = out / f"{name}.ply"
        if f.is_file():
            try:
                r = synthetic_chamfer(read_ply(f)["points"], scene, views)
                res[name] = {k: r[k] for k in ("accuracy", "completeness", "overall", "fscore")}
            except Exception as e:  # e.g. nothing near the object: report, don't hide
                res[name] = {"error": str(e)}
    return res


def _fmt(x, nd=2):
    return "-" if x is None else (f"{x:.{nd}f}" if isinstance(x, float) else str(x))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="768x576")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--object", default="random")
    ap.add_argument("--out", type=Path, default=Path("/tmp/fast_bench"))
    ap.add_argument("--results", type=Path, default=REPO / "benchmarks/results/fast_preset.md")
    ap.add_argument("--only", default="a,b,c,d")
    ap.add_argument("--dtu", action="store_true", help="also the fast preset on dtu_scan65")
    args = ap.parse_args()

    import svolsdf  # noqa: F401
    from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

    w, h = (int(x) for x in args.size.split("x"))
    scene = args.out / f"scene_{args.object}_{args.seed}_{w}x{h}"
    if not (scene / "gt_points.ply").is_file():
        make_synthetic_scene(scene, SynthConfig(views=5, width=w, height=h, seed=args.seed,
                                                object=args.object))
    runs = {}
    only = set(args.only.split(","))
    if "d" in only:
        _reconstruct(scene, args.out / "d_fast")
        runs["(d) S-VolSDF fast preset"] = _score(scene, args.out / "d_fast")
    if "a" in only:
        _reconstruct(scene, args.out / "a_mvs", "--mode", "mvs-only")
        runs["(a) MVS backbone alone (plane sweep)"] = _score(scene, args.out / "a_mvs")
    if "b" in only:
        _reconstruct(scene, args.out / "b_volsdf", "--mode", "volsdf")
        runs["(b) VolSDF alone (fast field, no prior)"] = _score(scene, args.out / "b_volsdf")
    if "c" in only:
        # the paper preset's steps/s on this machine, then as many steps as (d)'s field time
        field_s = runs.get("(d) S-VolSDF fast preset", {}).get("field_s") or 300.0
        probe = args.out / "c_probe"
        _reconstruct(scene, probe, "--preset", "paper", "--steps", "10", "--mesh-resolution",
                     "64")
        rate = json.loads((probe / "timing.json").read_text())["field"]["steps_per_s"]
        steps = max(10, int(field_s * rate))
        _reconstruct(scene, args.out / "c_paper", "--preset", "paper", "--steps", str(steps),
                     "--mesh-resolution", "256")
        r = _score(scene, args.out / "c_paper")
        r["note"] = f"{steps} steps at {rate:.3f} steps/s (equal optimization time to (d))"
        runs["(c) S-VolSDF paper preset, equal time"] = r
    dtu = None
    if args.dtu and (SHARED / "data/dtu_scan65").is_dir():
        out = args.out / "dtu65_fast"
        _reconstruct(SHARED / "data/dtu_scan65", out)
        dtu = json.loads((out / "timing.json").read_text())

    lines = ["# Fast preset benchmark (issue 5)", "",
             f"- machine: nproc = {os.cpu_count()}, CPU: {_cpu()}, torch threads = default "
             f"(OMP_WAIT_POLICY=PASSIVE); shared machine, other jobs may have been running",
             f"- command: `python benchmarks/fast_preset.py {' '.join(sys.argv[1:])}`",
             f"- scene: `svolsdf synth --seed {args.seed} --views 5 --size {args.size}` "
             f"(object {args.object}); 3 input views (default choice); Chamfer in mm against "
             "the ground-truth surface the input views observe (evaluate/synthetic.py), "
             "distances clipped at 5% of the object's diagonal", "",
             "| run | wall (s) | peak mem (GB) | points acc | points comp | points Chamfer | "
             "points F | mesh Chamfer | field steps/s |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, r in runs.items():
        p, m = r.get("points", {}), r.get("mesh", {})
        lines.append(f"| {name} | {_fmt(r['wall_s'], 0)} | {_fmt(r['peak_gb'])} | "
                     f"{_fmt(p.get('accuracy'))} | {_fmt(p.get('completeness'))} | "
                     f"{_fmt(p.get('overall'))} | {_fmt(p.get('fscore'), 3)} | "
                     f"{_fmt(m.get('overall'))} | {_fmt(r.get('steps_per_s'))} |")
    lines.append("")
    for name, r in runs.items():
        lines.append(f"- {name}: stages {json.dumps(r['stages'])}"
                     + (f"; {r['note']}" if r.get("note") else "")
                     + (f"; points error: {r['points']['error']}" if "error" in r.get("points", {})
                        else ""))
    a = runs.get("(a) MVS backbone alone (plane sweep)", {}).get("points", {}).get("overall")
    b = runs.get("(b) VolSDF alone (fast field, no prior)", {}).get("points", {}).get("overall")
    d = runs.get("(d) S-VolSDF fast preset", {}).get("points", {}).get("overall")
    if d is not None:
        lines.append("")
        if a:
            lines.append(f"- ratio (d)/(a) points Chamfer: {d / a:.2f} (target <= 0.75)")
        if b:
            lines.append(f"- ratio (d)/(b) points Chamfer: {d / b:.2f} (target <= 0.5)")
    if dtu is not None:
        lines += ["", "## dtu_scan65, fast preset (views 25 22 28, 768x576)", "",
                  f"- stages: {json.dumps({k: v['seconds'] for k, v in dtu.items()})}",
                  f"- peak memory: {max(v.get('peak_memory_gb', 0) for v in dtu.values()):.2f} GB"]
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text("\n".join(lines) + "\n")
    (args.results.with_suffix(".json")).write_text(json.dumps(runs, indent=1))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
