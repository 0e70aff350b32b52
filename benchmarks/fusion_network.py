"""A learned network's guided depth as a third fusion hypothesis (`fusion.network`).

For each finished fast-preset run (plane-sweep backbone) given, a copy of its folder is rerun
with ``fusion.network: patchmatchnet`` (`benchmarks/_machine.copy_run`): only the fusion
stage reruns, with the network started from the field's guide depth in every input view
(`svolsdf.mvs.adapters`) and its depth fused as a further hypothesis of each view beside the
guided and unguided plane-sweep sets. Points are scored as benchmarks/fast_preset.py scores
them (synthetic scenes: exact ground truth, clipped / DTU rule), with the ratio to the MVS
backbone alone when its run is given. ``--dtu`` runs on ../shared/data/dtu_scan65 are scored
against the 49-view pseudo ground truth of benchmarks/dtu_pseudo_gt.py, which PatchmatchNet built
(it favours the network's depth: read that row as an upper bound of the gain).

Usage (from the repo root):
    python benchmarks/fusion_network.py --runs D_RUN[:A_RUN] ... [--dtu D_RUN[:A_RUN]]
        [--weights W] [--out /tmp/fusion_network] [--pgt /tmp/dtu_pseudo_gt]
        [--results benchmarks/results/fusion_network.md]
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
from _network import network_args, score_dtu65


def _with_network(d_run: Path, out: Path, weights: Path) -> Path:
    """A copy of ``d_run`` in ``out`` with the fusion network on, its fusion rerun."""
    dst = out / (d_run.name + "_network")

    def edit(cfg) -> None:
        cfg.fusion.network = "patchmatchnet"
        cfg.fusion.network_weights = str(weights)

    if not (dst / "points.ply").is_file() or not (dst / "network").is_dir():
        copy_run(d_run, dst, edit)
    cmd = [sys.executable, "-m", "svolsdf", "reconstruct", "--config", str(dst / "config.yaml"),
           "-o", str(dst), "--no-progress"]
    print("$", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)
    return dst


def _synthetic(run: Path) -> dict:
    from svolsdf.evaluate.synthetic import synthetic_chamfer
    from svolsdf.io.ply import read_ply

    v = json.loads((run / "views.json").read_text())
    return synthetic_chamfer(read_ply(run / "points.ply")["points"], v["scene"], v["inputs"],
                             on_empty="clip")


def _pair(arg: str) -> tuple[Path, Path | None]:
    d, _, a = arg.partition(":")
    return Path(d).resolve(), (Path(a).resolve() if a else None)


def _fmt(r: dict) -> str:
    return f"{r['accuracy']:.3f} / {r['completeness']:.3f} / {r['overall']:.3f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", nargs="*", default=[], metavar="D_RUN[:A_RUN]",
                    help="fast-preset runs of synthetic scenes (and their --mode mvs-only runs)")
    ap.add_argument("--dtu", default=None, metavar="D_RUN[:A_RUN]",
                    help="a fast-preset run of ../shared/data/dtu_scan65 (views 25 22 28)")
    args = network_args(ap, "/tmp/fusion_network", "fusion_network.md")

    rows = []
    for item in args.runs:
        d, a = _pair(item)
        n = _with_network(d, args.out, args.weights)
        rd, rn = _synthetic(d), _synthetic(n)
        ra = _synthetic(a) if a is not None else None
        t = json.loads((n / "timing.json").read_text())["fusion"]
        ratio = (f"{rd['overall'] / ra['overall']:.3f} -> {rn['overall'] / ra['overall']:.3f}"
                 f" / {rd['overall_dtu_rule'] / ra['overall_dtu_rule']:.3f} -> "
                 f"{rn['overall_dtu_rule'] / ra['overall_dtu_rule']:.3f}") if ra else "-"
        rows.append(f"| {Path(json.loads((d / 'views.json').read_text())['scene']).name} | "
                    f"{_fmt(rd)} ({rd['overall_dtu_rule']:.3f}) | {_fmt(rn)} "
                    f"({rn['overall_dtu_rule']:.3f}) | "
                    f"{100 * (rn['overall'] / rd['overall'] - 1):+.1f} % | {ratio} | "
                    f"{t['seconds']:.0f} s, {t.get('points_per_set', {})} |")

    dtu_text = []
    if args.dtu:
        d, a = _pair(args.dtu)
        n = _with_network(d, args.out, args.weights)
        runs = {**({"(a) MVS alone": a} if a else {}), "(d) fast preset": d,
                "(d) + fusion network": n}
        dtu_text = score_dtu65(runs, args.pgt, args.out)

    cmd = ("python benchmarks/fusion_network.py"
           + (f" --runs {' '.join(args.runs)}" if args.runs else "")
           + (f" --dtu {args.dtu} --pgt {args.pgt}" if args.dtu else "") + f" --out {args.out}")
    text = "\n".join([
        "# A learned network's guided depth as a third fusion hypothesis",
        "",
        f"- machine: nproc = {os.cpu_count()}, CPU: {cpu_name()}; shared machine",
        f"- command: `{cmd}`",
        f"- network: {args.weights.name} (PatchmatchNet, DTU-trained TorchScript, "
        "../shared/weights), started from the field's guide depth (`fusion.network`)",
        "- points acc / comp / Chamfer in mm (DTU rule in brackets) against the ground-truth "
        "surface the input views observe, as benchmarks/fast_preset.py; ratio = to the MVS "
        "backbone alone (the plane sweep), clipped / DTU rule, without -> with the network",
        "",
        "| scene | (d) fast preset | (d) + fusion network | change | ratio to (a) | fusion "
        "stage with the network |",
        "|---|---|---|---|---|---|",
        *rows,
        "",
        *dtu_text,
    ])
    write_results(args.results, text)
    print(text)


if __name__ == "__main__":
    main()
