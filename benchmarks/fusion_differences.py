"""What each difference between the modes' fusion does to their points (issue 50): a copy of
each finished run of a `svolsdf benchmark` folder, fused again with one difference changed, and
scored as `svolsdf evaluate` scores it.

Every mode's depth is fused under the same multi-view check and, since issue 50, within the
same object masks (`svolsdf.pipeline.options.mask_dilation`). What still differs, and what this
script measures on the runs of the table (benchmarks/table1.py folds its output into
benchmarks/results/table1.json; why each is kept: docs/table1.md):

- ``volsdf-depth-scaled``: VolSDF fuses its rendered depth at the working size, S-VolSDF its MVS
  stage 3 at ``mvs.scale`` x it; here VolSDF's field is rendered at S-VolSDF's depth size (read
  from the svolsdf run of the same scene) and fused at that size;
- ``volsdf-surface-vote``: S-VolSDF's depth may pass on the rendered surface alone
  (``fusion.surface``, ``min_views`` 1); VolSDF's depth is that surface, so the vote would
  pass every pixel it renders: ``--set fusion.min_views=0`` is the same rule;
- ``svolsdf-no-surface-vote``: the other side, S-VolSDF without the vote (``fusion.surface=0``);
- ``volsdf-masks-released`` / ``mvs-only-masks-released``: the masks these modes had before issue
  50 (the released dilation, ``fusion.guided_dilation`` / ``unguided_dilation`` unset).

Only the fusion and mesh stages run again (`svolsdf reconstruct` reuses the others, whose keys
did not change); the depth-size variant writes the rendered depth into the copy's OUT/depth and
forgets its fusion and mesh stages. Renders are not copied: only the geometry is scored.

Usage:
    python benchmarks/fusion_differences.py --bench OUT --out DIR [--variants NAME ...]

Writes DIR/<variant>/<scene>/ (the run copies, kept: a rerun skips what is scored) and
DIR/fusion_differences.json.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import copy_run  # noqa: E402


@dataclass(frozen=True)
class Variant:
    """One difference changed on copies of one mode's runs."""

    name: str
    mode: str
    """The mode whose runs are copied."""
    what: str
    """What the change does, in words (no numbers: those are in ``sets`` or computed)."""
    sets: dict = field(default_factory=dict)
    """Config overrides of the copy (dotted option -> value), as ``--set``."""
    depth_size_of: str | None = None
    """Render the field's depth at the final depth size of this mode's run of the scene."""


VARIANTS = (
    Variant("volsdf-masks-released", "volsdf",
            "VolSDF's depth within the released masks, as before issue 50",
            {"fusion.guided_dilation": None}),
    Variant("volsdf-surface-vote", "volsdf",
            "VolSDF with S-VolSDF's surface vote: its depth is its rendered surface, so every "
            "pixel it renders passes", {"fusion.min_views": 0}),
    Variant("volsdf-depth-scaled", "volsdf",
            "VolSDF's depth rendered and fused at the size of S-VolSDF's fused MVS depth",
            depth_size_of="svolsdf"),
    Variant("mvs-only-masks-released", "mvs-only",
            "MVS only within the released masks, as before issue 50",
            {"fusion.unguided_dilation": None}),
    Variant("svolsdf-no-surface-vote", "svolsdf",
            "S-VolSDF without its surface vote: each depth needs a consistent source view",
            {"fusion.surface": 0.0}),
)


def _set(cfg, sets: dict) -> None:
    for key, value in sets.items():
        section, option = key.rsplit(".", 1)
        obj = cfg
        for part in section.split("."):
            obj = getattr(obj, part)
        setattr(obj, option, value)


def depth_size(run: Path) -> tuple[int, int]:
    """(W, H) of a run's final depth maps (OUT/depth/<view>.npy)."""
    f = sorted((run / "depth").glob("*.npy"))[0]
    h, w = np.load(f, mmap_mode="r").shape
    return int(w), int(h)


def render_depth_at(run_dir: Path, size: tuple[int, int]) -> dict[int, np.ndarray]:
    """The field's depth of each input view rendered at ``size`` (W, H), as the guide stage
    renders it at the working size (the pixels within ``guide.mask_dilation`` of the masks,
    docs/method.md 6.1's rule below weight 0.2): {view: (H, W) float32 world z-depth}."""
    import torch.nn.functional as F

    from svolsdf.pipeline import Run
    from svolsdf.render.views import guide_depths

    run = Run.open(run_dir)
    scene = run.load()
    w, h = size
    cams = scene.cameras_unit.resize(w, h)
    pixels = run.guide_pixels()  # at the working size
    if pixels is not None:
        pixels = F.interpolate(pixels[:, None].float(), size=(h, w), mode="nearest")[:, 0] > 0.5
    r = run.render_views(cams, run.unit_near_far().to(run.device), keys=("depth", "opacity"),
                         pixels=pixels)
    maps = guide_depths(r["depth"], r["opacity"], run.views, scene.normalization.scale,
                        run.cfg.guide.low_weight_rule)
    return {v: d.numpy().astype(np.float32) for v, d in maps.items()}


def scores(metrics: dict) -> dict:
    """The points' scores of an evaluate_run metrics dict."""
    c = metrics.get("chamfer") or {}
    return {k: c.get(k) for k in ("overall", "overall_dtu_rule", "accuracy", "completeness")}


def run_variant(v: Variant, bench: Path, scene: str, dst: Path) -> dict:
    """Copy ``bench/scene/v.mode`` to ``dst``, change it, rerun and score it; returns the scores
    with the points' count and the seconds it took (a scored copy is read back)."""
    from svolsdf.config import load_config
    from svolsdf.evaluate.scoring import EvaluateConfig, evaluate_run
    from svolsdf.io.ply import read_ply
    from svolsdf.pipeline import Pipeline, RunDir

    done = dst / "variant.json"
    if done.is_file():
        return json.loads(done.read_text())
    t0 = time.perf_counter()
    src = bench / scene / v.mode
    copy_run(src, dst, lambda cfg: _set(cfg, v.sets))
    for sub in ("renders", "renders_ibr", "report.html", "metrics.json"):
        p = dst / sub
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()
    extra = {}
    if v.depth_size_of is not None:
        size = depth_size(bench / scene / v.depth_size_of)
        for view, d in render_depth_at(dst, size).items():
            np.save(dst / "depth" / f"{view}.npy", d)
        RunDir(dst).unmark(("fusion", "mesh"))
        extra["depth_size"] = list(size)
    Pipeline(load_config(dst / "config.yaml"), dst, progress=False).run()
    m = evaluate_run(EvaluateConfig(out=dst, report=False))
    row = {**scores(m), "points": len(read_ply(dst / "points.ply")["points"]),
           "seconds": time.perf_counter() - t0, **extra}
    done.write_text(json.dumps(row, indent=1))
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bench", type=Path, required=True, help="a svolsdf benchmark folder")
    ap.add_argument("--out", type=Path, required=True, help="folder for the run copies")
    ap.add_argument("--variants", nargs="+", choices=[v.name for v in VARIANTS],
                    default=[v.name for v in VARIANTS])
    a = ap.parse_args()
    rows = [r for r in json.loads((a.bench / "benchmark.json").read_text())
            if r.get("status") == "ok"]
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    out = {"variants": []}
    for v in VARIANTS:
        if v.name not in a.variants:
            continue
        per = {}
        for s in scenes:
            if not (a.bench / s / v.mode / "points.ply").is_file():
                continue
            print(f"{v.name} {s} ...", flush=True)
            base = json.loads((a.bench / s / v.mode / "metrics.json").read_text())
            per[s] = {"base": {**scores(base), "points": _points(a.bench / s / v.mode)},
                      "changed": run_variant(v, a.bench, s, a.out / v.name / s)}
        out["variants"].append({"name": v.name, "mode": v.mode, "what": v.what,
                                "sets": v.sets, "depth_size_of": v.depth_size_of,
                                "scenes": per})
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "fusion_differences.json").write_text(json.dumps(out, indent=1))
    print(json.dumps({v["name"]: {s: round(d["changed"]["overall"] - d["base"]["overall"], 3)
                                  for s, d in v["scenes"].items()} for v in out["variants"]},
                     indent=1))


def _points(run: Path) -> int:
    from svolsdf.io.ply import read_ply

    return len(read_ply(run / "points.ply")["points"])


if __name__ == "__main__":
    main()
