"""The ablation table's fused points under the paper's fusion: the runs of ablation experiments
(``svolsdf benchmark --experiment experiments/ablation*.yaml``) fused again without the fast
preset's two fusion extensions (``fusion.surface=0``: the optimized surface is no consistent
source; ``fusion.unguided=false``: no second hypothesis from stages 2-3 centred on stage 1,
which every ablation shares), so that the points come from the field-guided depth alone, and
scored beside the fast preset's fusion of the same runs.

    python benchmarks/ablation_fusion.py --run NAME=OUT [NAME=OUT ...] --data NAME=DATA ... \
        --work DIR --results benchmarks/results/ablation_fusion.json [--pgt-cache CACHE]
    python benchmarks/ablation_fusion.py --from-json benchmarks/results/ablation_fusion.json \
        --results benchmarks/results/ablation_fusion.md      # render only (tests/benchmarks)

Synthetic scenes are scored by ``svolsdf evaluate`` against their exact ground truth (each
copy's metrics.json, as the experiment scored the runs); DTU scans against their 49-view pseudo
ground truth (benchmarks/dtu_pseudo_gt.py, ``--pgt-cache``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # dtu_pseudo_gt, experiment_results

#: the paper's fusion: the field-guided depth alone, filtered by the other views
PAPER_FUSION = ["fusion.surface=0", "fusion.unguided=false"]


def _synthetic_score(run: Path) -> dict:
    """``svolsdf evaluate`` on a run folder of a synthetic scene: its points' Chamfer (mm)."""
    subprocess.run(["svolsdf", "evaluate", str(run)], check=True,
                   capture_output=True)
    c = json.loads((run / "metrics.json").read_text())["chamfer"]
    return {k: c[k] for k in ("accuracy", "completeness", "overall")}


def depth_medians(folder: Path, scene_dir: Path, views: list[int], size, cloud=None) -> dict:
    """Median absolute error (mm) inside the object masks over the input views of the run's
    guide (field/render_depth: what stages 2-3 search around) and of its final depth (depth/:
    stages 2-3 around the guide, what fusion filters), against the synthetic scene's exact depth
    (gt_depth/) or, with ``cloud`` (the pseudo ground truth's (N, 3) points), their depth."""
    import numpy as np
    from experiment_results import _at_pixels, pgt_depth

    from svolsdf.scene.loaders import load_scene

    sc = load_scene(scene_dir, views=list(views), image_size=tuple(size))
    out = {}
    for key, sub in (("guide", "field/render_depth"), ("guided", "depth")):
        errs = []
        for i, v in enumerate(views):
            d = np.load(folder / sub / f"{v}.npy")
            h, w = d.shape
            if cloud is None:
                gt = _at_pixels(np.load(scene_dir / "gt_depth" / f"{v:03d}.npy"), h, w)
                gt = np.where(gt > 0, gt, np.inf)
            else:
                gt = pgt_depth(cloud, sc.cameras[[i]], h, w)
            m = (_at_pixels(sc.masks[i, 0].numpy(), h, w) > 0.5) & np.isfinite(gt) \
                & np.isfinite(d) & (d > 0)
            errs.append(np.abs(d[m] - gt[m]))
        out[key] = round(float(np.median(np.concatenate(errs))), 3)
    return out


def experiment_rows(name: str, run: Path, data: Path, work: Path, cache: Path | None) -> list:
    """Each svolsdf-mode row of the experiment in ``run``: Chamfer of its points under the fast
    preset's fusion and under `PAPER_FUSION` (a copy in ``work``/<name>/..., fused again)."""
    from experiment_results import row_paths
    from views_accuracy import fuse_again

    record = json.loads((run / "experiment.json").read_text())
    size = tuple(record["size"]) if record.get("size") else (768, 576)
    rows, refs_of, clouds = [], {}, {}
    for r in record["rows"]:
        if r.get("status", "ok") != "ok" or r.get("run_mode") != "svolsdf":
            continue
        scene, folder, scene_dir = row_paths(r, run, data)
        copy = fuse_again(folder, work / name / folder.relative_to(run), PAPER_FUSION)
        if r.get("protocol") == "synthetic":
            fast = {k: r[k] for k in ("accuracy", "completeness", "overall")}
            paper = _synthetic_score(copy)
            protocol = "exact ground truth"
            depth = depth_medians(folder, scene_dir, list(r["views"]), size)
        else:
            from dtu_pseudo_gt import references, score_run
            from experiment_results import pgt_cloud

            if cache is None:
                raise SystemExit(f"{run}: DTU rows need --pgt-cache")
            if scene not in refs_of:
                refs_of[scene] = references(scene_dir, cache / scene, list(r["views"]), size)
            refs, obj, diag = refs_of[scene]
            ref = {"object": refs["object"]}
            fast, paper = (score_run(f, ref, obj, diag)["object"]["points"]
                           for f in (folder, copy))
            protocol = "pseudo ground truth"
            if scene not in clouds:  # the whole object reference, before the inputs' cut
                clouds[scene] = pgt_cloud(cache, scene)
            depth = depth_medians(folder, scene_dir, list(r["views"]), size, clouds[scene])
        rows.append({"experiment": name, "scene": r["scene"], "variant": r["mode"],
                     "protocol": protocol, "depth_median": depth,
                     "fast": {k: round(float(fast[k]), 4)
                              for k in ("accuracy", "completeness", "overall")},
                     "paper": {k: round(float(paper[k]), 4)
                               for k in ("accuracy", "completeness", "overall")}})
    return rows


def markdown(rec: dict) -> str:
    """The record rendered as Markdown: per experiment and scene, each variant's Chamfer under
    both fusions, the best of each column in bold."""
    lines = ["# The ablation table's points under the paper's fusion", "", rec["what"], "",
             "| experiment | scene | variant | guide depth | final depth | fast preset's fusion: "
             "acc. / comp. / Chamfer | paper's fusion: acc. / comp. / Chamfer |",
             "|---|---|---|---:|---:|---|---|"]
    groups: dict = {}
    for r in rec["rows"]:
        groups.setdefault((r["experiment"], r["scene"]), []).append(r)
    for (exp, scene), rows in groups.items():
        best = {k: min(r[k]["overall"] for r in rows) for k in ("fast", "paper")}
        for r in rows:
            cells = []
            for k in ("fast", "paper"):
                c = r[k]
                ch = f"{c['overall']:.2f}"
                cells.append(f"{c['accuracy']:.2f} / {c['completeness']:.2f} / "
                             + (f"**{ch}**" if c["overall"] == best[k] else ch))
            dm = r["depth_median"]
            lines.append(f"| {exp} | {scene} ({r['protocol']}) | {r['variant']} | "
                         f"{dm['guide']:.2f} | {dm['guided']:.2f} | " + " | ".join(cells) + " |")
    lines += ["", "## What ran", "", f"Commit {rec['commit']}, {rec['date']}; {rec['machine']}.",
              "", f"Command: `{rec['command']}`; the experiments' runs: "
              + "; ".join(f"{k}: `{v}`" for k, v in rec["runs_commands"].items()) + ".", ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", nargs="+", default=[], metavar="NAME=OUT",
                    help="experiment output folders (their experiment.json), each named")
    ap.add_argument("--data", nargs="+", default=[], metavar="NAME=DATA",
                    help="each experiment's data folder")
    ap.add_argument("--work", type=Path, help="where the copies fused again go")
    ap.add_argument("--pgt-cache", type=Path, help="pseudo ground truth cache (DTU rows)")
    ap.add_argument("--results", type=Path, required=True)
    ap.add_argument("--from-json", type=Path, help="only render this record's Markdown")
    args = ap.parse_args()
    from views_accuracy import provenance, write_record

    if args.from_json:
        rec = json.loads(args.from_json.read_text())
        args.results.with_suffix(".md").write_text(markdown(rec))
        return
    runs = dict(a.split("=", 1) for a in args.run)
    datas = dict(a.split("=", 1) for a in args.data)
    if not runs or set(runs) != set(datas) or args.work is None:
        ap.error("give --run NAME=OUT ..., the same names in --data NAME=DATA ..., and --work")
    rows, commands, machine = [], {}, {}
    for name, out in runs.items():
        rows += experiment_rows(name, Path(out), Path(datas[name]), args.work, args.pgt_cache)
        record = json.loads((Path(out) / "experiment.json").read_text())
        commands[name] = record.get("command", "")
        machine = record.get("machine") or machine
    rec = {
        "what": "Points Chamfer (mm) of each svolsdf-mode run of the ablation experiments, as "
                "the experiment fused them (the fast preset: the optimized surface counts as a "
                "consistent source and the unguided stages 2-3 give each view a second "
                "hypothesis) and fused again from the field-guided depth alone "
                "(`svolsdf reconstruct -o COPY --from fusion --set fusion.surface=0 --set "
                "fusion.unguided=false`, the paper's fusion). Synthetic scenes against their "
                "exact ground truth (`svolsdf evaluate`), DTU scans against their 49-view "
                "pseudo ground truth (benchmarks/dtu_pseudo_gt.py: compare rows, not absolute "
                "values). Guide depth and final depth: median absolute error (mm) inside the "
                "object masks over the input views of the field's rendered depth (what stages "
                "2-3 search around) and of the final depth (stages 2-3 around it, what fusion "
                "filters), against the exact depth or the pseudo ground truth's. Best Chamfer of "
                "each scene and fusion in bold.",
        "rows": rows,
        **provenance(machine),
        "command": "python benchmarks/ablation_fusion.py --run NAME=OUT ... --data NAME=DATA ... "
                   "--work DIR --pgt-cache CACHE --results benchmarks/results/ablation_fusion.json",
        "runs_commands": commands,
    }
    write_record(rec, args.results, markdown)


if __name__ == "__main__":
    main()
