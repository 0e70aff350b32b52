"""How far the grid field's colour can fit its own input views when the surface is frozen.

docs/novel-views.md found the object's error on the input views to be appearance: colour steps
(``train.colour_steps``: the surface frozen, only the feature grids, the colour network and the
background train) raise the field's masked PSNR on its inputs with every ray they add. This
script asks where that stops: it opens a finished run folder, keeps its surface, and runs colour
steps far beyond any preset (``--steps`` of ``--rays`` rays, ``--object-fraction`` of them inside
the dilated object masks), scoring the input views inside their masks every ``--every`` steps
(the guide stage's ``field_psnr``: the full-resolution render of the masked pixels). If the
curve flattens far below the photos, more rays on this colour representation and this surface
will not reach them.

Results: JSON with the Markdown rendered from it (``--results``; ``--from-json`` remakes it).

Usage:
    python benchmarks/colour_ceiling.py --runs scan37=RUN37 scan65=RUN65 [--steps 1000]
        [--every 250] [--rays 4096] [--object-fraction 0.7]
        [--results benchmarks/results/colour_ceiling.json]
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
from _machine import cpu_name, git_commit, public_argv, write_results

REPO = Path(__file__).resolve().parents[1]


def ceiling(out: Path, steps: int, every: int, rays: int, frac: float) -> dict:
    """Colour steps on run folder ``out``'s frozen surface; returns {"curve": [[step, dB,
    seconds], ...], "settings": {...}} with the masked PSNR of the input views after each
    ``every`` steps (step 0: the run's field as it finished)."""
    from svolsdf.optimize.trainer import Trainer
    from svolsdf.pipeline import builders
    from svolsdf.pipeline.loaded_run import Run
    from svolsdf.pipeline.previews import field_psnr

    run = Run.open(out)
    scene = run.load()
    model = run.model()
    cfg = run.cfg
    if scene.masks is None:
        raise SystemExit(f"{out}: the scene has no object masks (the score is inside them)")
    t = cfg.train
    t.colour_steps, t.colour_rays, t.colour_object_fraction = steps, rays, frac
    t.mode = "volsdf"  # no prior term: colour steps use none, and the trainer needs no volumes
    trainer = Trainer(model, builders.build_train_data(cfg, scene, None), t, prior=None,
                      sampler=builders.build_sampler(cfg, None), out_dir=None,
                      device=run.device, grid_schedule=builders.grid_schedule(cfg))
    trainer.step = t.steps  # past the schedule: every step from here is a colour step
    masks = scene.masks[:, 0] > 0.5
    near_far = run.unit_near_far().to(run.device)

    def score() -> float:
        model.eval()
        r = run.render_views(scene.cameras_unit, near_far, keys=("rgb",), pixels=masks)
        return field_psnr(scene, list(scene.view_ids), r["rgb"], masks, True)["mean_db"]

    curve = [[0, score(), 0.0]]
    print(out, curve[-1], flush=True)
    t0 = time.perf_counter()
    done = 0
    while done < steps:
        n = min(every, steps - done)
        trainer.fit(steps=trainer.step + n, progress=False)
        done += n
        curve.append([done, score(), round(time.perf_counter() - t0, 1)])
        print(out, curve[-1], flush=True)
    px = int(masks.sum())
    return {"curve": curve, "object_pixels": px,
            "object_rays_per_pixel": round(steps * rays * frac / px, 2),
            "background_model": cfg.field.background_model if cfg.field.background else "none"}


def render_markdown(data: dict) -> str:
    """The Markdown of a results JSON (``--from-json`` remakes it)."""
    s = data["settings"]
    lines = ["# The colour's ceiling on a frozen surface (input views, inside the masks)", "",
             f"- machine: {data['machine']}",
             f"- commit {data['commit']}, {data['date']}, {data['software']}",
             f"- command: `{data['command']}`",
             *([f"- runs: {data['runs']}"] if data.get("runs") else []),
             f"- colour steps: {s['steps']} of {s['rays']} rays, {s['object_fraction']:.0%} "
             "inside the dilated masks; the surface, beta and the schedule's result kept",
             "- score: the mean over the input views of the PSNR inside each view's object "
             "mask (the guide stage's field_psnr)", "",
             "| scan | background | object rays per object pixel | "
             + " | ".join(f"after {c[0]} steps" for c in next(iter(data["rows"].values()))
                          ["curve"]) + " | seconds |",
             "|---|---|---|" + "---|" * (len(next(iter(data["rows"].values()))["curve"]) + 1)]
    for scan, r in data["rows"].items():
        lines.append(f"| {scan} | {r['background_model']} | {r['object_rays_per_pixel']:.2f} | "
                     + " | ".join(f"{c[1]:.2f}" for c in r["curve"])
                     + f" | {r['curve'][-1][2]:.0f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", nargs="+", default=[], help="NAME=RUN_FOLDER ...")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--every", type=int, default=250)
    ap.add_argument("--rays", type=int, default=4096)
    ap.add_argument("--object-fraction", type=float, default=0.7)
    ap.add_argument("--results", type=Path,
                    default=REPO / "benchmarks/results/colour_ceiling.json",
                    help="the JSON; the Markdown it renders goes beside it")
    ap.add_argument("--from-json", type=Path,
                    help="only render the Markdown of this results JSON into --results")
    args = ap.parse_args()
    if args.from_json:
        write_results(args.results.with_suffix(".md"),
                      render_markdown(json.loads(args.from_json.read_text())))
        return
    torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))
    rows = {}
    for spec in args.runs:
        name, _, folder = spec.partition("=")
        if not folder:
            sys.exit(f"--runs {spec!r}: expected NAME=RUN_FOLDER")
        rows[name] = ceiling(Path(folder), args.steps, args.every, args.rays,
                             args.object_fraction)
    data = {"commit": git_commit(), "date": time.strftime("%Y-%m-%d"),
            "machine": f"nproc = {os.cpu_count()}, CPU: {cpu_name()}",
            "software": f"Python {platform.python_version()}, torch {torch.__version__}",
            "command": public_argv(["python", "benchmarks/colour_ceiling.py", *sys.argv[1:]]),
            "settings": {"steps": args.steps, "every": args.every, "rays": args.rays,
                         "object_fraction": args.object_fraction},
            "rows": rows}
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.with_suffix(".json").write_text(json.dumps(data, indent=1) + "\n")
    text = render_markdown(data)
    write_results(args.results.with_suffix(".md"), text)
    print(text)


if __name__ == "__main__":
    main()
