"""PatchmatchNet inside S-VolSDF: the network started from the field's guide depth, or not.

With ``--backbone patchmatchnet`` the pipeline's guided stages 2-3 get the field's rendered
depth (docs/method.md 6.1). By default the network then reruns from that depth (`mvs.guide_network`,
`svolsdf.mvs.adapters`: its coarsest PatchMatch stage samples around the guide instead of at
random); with ``mvs.guide_network: false`` it runs once per view, unguided, and the guide only
centres the hypotheses its Laplacian is discretized on. For each scene this runs, in fresh
processes (`svolsdf reconstruct --backbone patchmatchnet --weights W`):

  (a)   --mode mvs-only            the network alone (its own cascade, fused)
  (d)   the fast preset            the network started from the guide (the default)
  (d0)  mvs.guide_network: false   a copy of (d)'s folder in which only the guided stages 2-3
                                   and fusion rerun (same field, same guide)

Synthetic scenes (``--scenes``, the layout `svolsdf synth` writes, or ``--seeds``, generated
here at 768x576) are scored against their exact ground truth
(`svolsdf.evaluate.synthetic.synthetic_chamfer`, as benchmarks/fast_preset.py). ``--dtu``
also runs ../shared/data/dtu_scan65 (views 25 22 28) and scores it against the 49-view pseudo
ground truth of benchmarks/dtu_pseudo_gt.py (which PatchmatchNet built, so it favours the
network's own depth: compare (d) with (d0), and read (d)/(a) there as a lower bound).

Usage (from the repo root):
    python benchmarks/patchmatchnet_guided.py [--seeds 0 3] [--scenes PATH ...] [--dtu]
        [--weights W] [--out /tmp/pm_bench] [--pgt /tmp/pgt]
        [--results benchmarks/results/patchmatchnet_guided.md]

Runs are cached in OUT (`svolsdf reconstruct` reuses finished stages).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

# benchmarks/_machine.py (the script's folder is on sys.path)
from _machine import copy_run, cpu_name, write_results
from _network import SHARED, network_args, score_dtu65


def _run(*args: str) -> None:
    cmd = [sys.executable, "-m", "svolsdf", *args]
    print("$", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)


def _three_runs(scene: Path, out: Path, weights: Path, *extra: str) -> dict[str, Path]:
    """(a), (d) and (d0) folders of ``scene`` under ``out`` (made or reused)."""
    common = ("--backbone", "patchmatchnet", "--weights", str(weights), "--no-progress", *extra)
    a, d, d0 = out.with_name(out.name + "_a"), out.with_name(out.name + "_d"), \
        out.with_name(out.name + "_d0")
    _run("reconstruct", str(scene), "-o", str(a), "--mode", "mvs-only", *common)
    _run("reconstruct", str(scene), "-o", str(d), *common)
    if not (d0 / "points.ply").is_file():
        copy_run(d, d0, lambda cfg: setattr(cfg.mvs, "guide_network", False))
    _run("reconstruct", "--config", str(d0 / "config.yaml"), "-o", str(d0), "--no-progress")
    return {"(a) network alone": a, "(d) network started from the guide": d,
            "(d0) network unguided, guide centres the hypotheses": d0}


def _timing(run: Path) -> dict:
    t = json.loads((run / "timing.json").read_text())
    return {k: round(v["seconds"], 1) for k, v in t.items() if k != "total"}


def _synthetic_rows(name: str, runs: dict[str, Path], scene: Path) -> list[str]:
    from svolsdf.evaluate.synthetic import synthetic_chamfer
    from svolsdf.io.ply import read_ply

    rows, base = [], None
    for label, run in runs.items():
        views = json.loads((run / "views.json").read_text())["inputs"]
        r = synthetic_chamfer(read_ply(run / "points.ply")["points"], scene, views,
                              on_empty="clip")
        base = base or r
        rows.append(f"| {name} | {label} | {r['accuracy']:.3f} / {r['completeness']:.3f} / "
                    f"{r['overall']:.3f} | {r['overall_dtu_rule']:.3f} | "
                    f"{r['overall'] / base['overall']:.3f} / "
                    f"{r['overall_dtu_rule'] / base['overall_dtu_rule']:.3f} | "
                    f"{_timing(run).get('mvs23', '-')} |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", nargs="*", type=int, default=[0],
                    help="synthetic scenes generated here (svolsdf synth --seed N, 768x576)")
    ap.add_argument("--scenes", nargs="*", type=Path, default=[],
                    help="synthetic scene folders with exact ground truth")
    ap.add_argument("--dtu", action="store_true", help="also ../shared/data/dtu_scan65")
    args = network_args(ap, "/tmp/pm_bench", "patchmatchnet_guided.md")

    scenes = []
    for s in args.seeds:
        sc = args.out / f"scene_random_{s}_768x576"
        if not (sc / "gt_points.ply").is_file():
            _run("synth", str(sc), "--seed", str(s), "--views", "5", "--size", "768x576")
        scenes.append((f"seed {s}", sc))
    scenes += [(p.name, p.resolve()) for p in args.scenes]

    rows = []
    for name, sc in scenes:
        runs = _three_runs(sc, args.out / sc.name, args.weights)
        rows += _synthetic_rows(name, runs, sc)

    dtu_text = []
    if args.dtu:
        sc = SHARED / "data/dtu_scan65"
        runs = _three_runs(sc, args.out / "dtu_scan65", args.weights, "--views", "25", "22", "28")
        dtu_text = score_dtu65(runs, args.pgt, args.out)
        dtu_text += [f"- {k}: stages (s) {_timing(v)}" for k, v in runs.items()] + [""]

    cmd = "python benchmarks/patchmatchnet_guided.py " + " ".join(
        ([f"--seeds {' '.join(map(str, args.seeds))}"] if args.seeds else ["--seeds"])
        + ([f"--scenes {' '.join(map(str, args.scenes))}"] if args.scenes else [])
        + ([f"--dtu --pgt {args.pgt}"] if args.dtu else []) + [f"--out {args.out}"])
    text = "\n".join([
        "# PatchmatchNet in S-VolSDF: started from the guide depth, or not",
        "",
        f"- machine: nproc = {os.cpu_count()}, CPU: {cpu_name()}; shared machine",
        f"- command: `{cmd}`",
        f"- weights: {args.weights.name} (DTU-trained TorchScript, ../shared/weights)",
        "- points Chamfer in mm against the ground-truth surface the input views observe "
        "(clipped at 5 % of the object's diagonal; \"DTU rule\": distances beyond it left out), "
        "as benchmarks/fast_preset.py; ratios to (a); mvs23 = the guided stages 2-3 (s), where "
        "(d) runs the network a second time",
        "",
        "| scene | run | acc / comp / Chamfer | DTU rule | ratio to (a), clipped / DTU rule "
        "| mvs23 (s) |",
        "|---|---|---|---|---|---|",
        *rows,
        "",
        *dtu_text,
    ])
    write_results(args.results, text)
    print(text)


if __name__ == "__main__":
    main()
