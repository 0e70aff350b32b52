"""Results of ``svolsdf benchmark --experiment`` kept in benchmarks/results/: the run's record
(OUT/experiment.json) copied as NAME.json, with NAME.md (and NAME.png) rendered from it by
`svolsdf.commands.experiment.experiment_markdown` and `experiment_plot`, exactly what the
command writes beside its runs.

    python benchmarks/experiment_results.py --run OUT --results benchmarks/results/NAME.json \
        [--field-alone DATA]      # synthetic scenes: each run's guide depth against gt_depth/
    python benchmarks/experiment_results.py --from-json benchmarks/results/NAME.json \
        --results benchmarks/results/NAME.md      # render only (tests/benchmarks)
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

# render with this checkout's code (the renderer is svolsdf's own), not an installed copy's
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from svolsdf.commands.experiment import (  # noqa: E402
    EXPERIMENT_FILE,
    experiment_markdown,
    experiment_plot,
)


def field_alone(record: dict, run: Path, data: Path) -> dict:
    """Each run's guide depth (OUT/<scene>/<variant>/field/render_depth/<view>.npy: the
    field's rendered depth, or the soft-consistency-only ablation's consistency depth) against
    the synthetic scene's exact depth (gt_depth/<view>.npy) inside its object masks, over the
    input views: the median absolute error (mm) and the share of pixels within 2 mm."""
    import numpy as np

    from svolsdf.io.images import read_mask

    rows = []
    for r in record["rows"]:
        if r.get("status", "ok") != "ok" or r.get("run_mode") != "svolsdf":
            continue
        folder = run / r["scene"] / r["mode"] / "field" / "render_depth"
        scene = data / r["scene"]
        errs = []
        for v in r["views"]:
            guide = np.load(folder / f"{v}.npy")
            gt = np.load(scene / "gt_depth" / f"{v:03d}.npy")
            mask = read_mask(scene / "mask" / f"{v:03d}.png")[0].numpy() > 0.5
            if guide.shape != gt.shape:  # a stage-1 size guide: the exact depth at its pixels
                h, w = guide.shape
                iy = ((np.arange(h) + 0.5) * gt.shape[0] / h).astype(int)
                ix = ((np.arange(w) + 0.5) * gt.shape[1] / w).astype(int)
                gt, mask = gt[np.ix_(iy, ix)], mask[np.ix_(iy, ix)]
            ok = mask & (gt > 0) & np.isfinite(guide)
            errs.append(np.abs(guide[ok] - gt[ok]))
        e = np.concatenate(errs)
        rows.append({"scene": r["scene"], "variant": r["mode"],
                     "median_mm": round(float(np.median(e)), 4),
                     "within_2mm": round(float((e < 2.0).mean()), 4)})
    return {"what": "Guide depth of the input views against the exact depth inside the object "
                    "masks: median absolute error in mm (share of pixels within 2 mm); the "
                    "field alone, before stages 2-3 and fusion.", "rows": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, help="the benchmark's output folder (its experiment.json)")
    ap.add_argument("--results", type=Path, required=True,
                    help="NAME.json to write (with --run) or NAME.md to render (--from-json)")
    ap.add_argument("--from-json", type=Path, help="only render this record's Markdown")
    ap.add_argument("--field-alone", type=Path, metavar="DATA",
                    help="the experiment's data folder: score each run's guide depth (the "
                         "field alone) against its synthetic scene's gt_depth/ in the masks")
    args = ap.parse_args()
    if args.from_json:
        record = json.loads(args.from_json.read_text())
        args.results.with_suffix(".md").write_text(experiment_markdown(record))
        return
    if args.run is None:
        ap.error("give --run OUT (or --from-json)")
    record = json.loads((args.run / EXPERIMENT_FILE).read_text())
    if args.field_alone is not None:
        record["field_alone"] = field_alone(record, args.run, args.field_alone)
    out = args.results.with_suffix(".json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1) + "\n")
    record = json.loads(out.read_text())
    out.with_suffix(".md").write_text(experiment_markdown(record))
    experiment_plot(record, out.with_suffix(".png"))
    print(f"wrote {out}, {out.with_suffix('.md')} and {out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
