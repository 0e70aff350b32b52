"""VolSDF's two fields at equal wall time: the grid (`--mode volsdf`, "VolSDF (grid field, no
prior)") against the paper's VolSDF MLP (`--mode volsdf --set field.kind=mlp`, "VolSDF (MLP)",
docs/method.md 5.2), on one synthetic scene (issue 38).

Both start from the sphere with nothing from MVS and use the fast preset's rays and schedule.
The grid runs its 1000 steps (`svolsdf reconstruct --mode volsdf`, in a fresh process); the MLP
then gets the same seconds of optimization (its steps counted until the budget is spent, stopping
before a step that would overrun it). Each field is scored by its mesh, the zero level by
marching cubes at the same resolution (`mesh.method=field`, culled by the same views),
against the ground truth the input views observe (`svolsdf evaluate`'s synthetic protocol):
VolSDF's fused points need the rendered depth of every input pixel, which the MLP cannot render
within the budget on a CPU, so the mesh is the fair common output.

Usage:
    python benchmarks/volsdf_mlp_equal_time.py --scene SCENE --out DIR
        [--results benchmarks/results/volsdf_mlp_equal_time.md]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import torch
from _machine import cpu_name, peak_rss_gb, write_results
from fast_preset import _score_ply

REPO = Path(__file__).resolve().parents[1]


def _score_mesh(scene: Path, mesh: Path, views: list[int]) -> dict:
    """Synthetic-protocol Chamfer of a mesh by its surface (`fast_preset._score_ply`, as
    `svolsdf evaluate` scores it)."""
    return _score_ply(scene, mesh, views) if mesh.is_file() else {"error": "no mesh"}


def _grid(scene: Path, out: Path, res: int) -> dict:
    """The grid VolSDF, a whole `svolsdf reconstruct` (its field stage timed by the pipeline)."""
    cmd = [sys.executable, "-m", "svolsdf", "reconstruct", str(scene), "-o", str(out),
           "--mode", "volsdf", "--no-progress", "--set", "mesh.method=field",
           "--set", "mesh.free_space=false", "--set", f"mesh.resolution={res}"]
    print("$", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)
    timing = json.loads((out / "timing.json").read_text())
    views = json.loads((out / "views.json").read_text())["inputs"]
    return {"field_s": timing["field"]["seconds"], "steps": timing["field"].get("steps"),
            "mesh_s": timing["mesh"]["seconds"], "views": views,
            "mesh": _score_mesh(scene, out / "mesh.ply", views)}


def _mlp(scene: Path, out: Path, budget_s: float, res: int) -> dict:
    """The MLP VolSDF given ``budget_s`` seconds of optimization, then its mesh."""
    from svolsdf.config import preset
    from svolsdf.pipeline import Pipeline

    if out.exists():
        shutil.rmtree(out)
    cfg = preset("fast")
    cfg.scene.path = str(scene)
    cfg.train.mode = "volsdf"
    cfg.field.kind = "mlp"
    cfg.mesh.method = "field"
    cfg.mesh.free_space = False
    cfg.mesh.resolution = res
    p = Pipeline(cfg, out, progress=False)
    p.out.mkdir(parents=True, exist_ok=True)
    p.load()
    p.keys = p.stage_keys()
    (p.out / "views.json").write_text(json.dumps({"inputs": list(p.views)}))
    model = p.build_model()
    tr = p._field_trainer(model)  # as the field stage builds it (sphere start, no prior)
    t0 = time.perf_counter()
    steps, last = 0, 0.0
    while steps == 0 or time.perf_counter() - t0 + last <= budget_s:
        ts = time.perf_counter()
        tr.train_step()
        last = time.perf_counter() - ts
        steps += 1
    field_s = time.perf_counter() - t0
    model.eval()
    p.set_model(model)
    t1 = time.perf_counter()
    err = None
    try:
        p.run_stage("mesh")
    except (ValueError, RuntimeError) as e:  # no zero level inside the box yet
        err = " ".join(str(e).split())[:200]
    mesh_s = time.perf_counter() - t1
    res_ = {"field_s": field_s, "steps": steps, "mesh_s": mesh_s}
    res_["mesh"] = {"error": f"no mesh: {err}"} if err else \
        _score_mesh(scene, out / "mesh.ply", list(p.views))
    return res_


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--mesh-resolution", type=int, default=256)
    ap.add_argument("--results", type=Path,
                    default=REPO / "benchmarks/results/volsdf_mlp_equal_time.md")
    a = ap.parse_args()
    g = _grid(a.scene, a.out / "grid", a.mesh_resolution)
    m = _mlp(a.scene, a.out / "mlp", g["field_s"], a.mesh_resolution)

    def row(name, r):
        s = r["mesh"]
        cells = ["-"] * 4 if "error" in s else \
            [f"{s[k]:.2f}" for k in ("accuracy", "completeness", "overall", "overall_dtu_rule")]
        return (f"| {name} | {r['steps']} | {r['field_s']:.0f} | {r['steps'] / r['field_s']:.2f} | "
                + " | ".join(cells) + f" | {r['mesh_s']:.0f} |")

    lines = [
        "| field | steps | field s | steps/s | mesh acc | mesh comp | mesh Chamfer | DTU rule "
        "| mesh s |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
        row("VolSDF (grid field, no prior)", g),
        row("VolSDF (MLP), equal field time", m),
    ]
    if "error" in m["mesh"]:
        lines.append(f"\nVolSDF (MLP): {m['mesh']['error']}")
    cmd = " ".join(["python", "benchmarks/volsdf_mlp_equal_time.py", "--scene", str(a.scene),
                    "--out", "OUT", "--mesh-resolution", str(a.mesh_resolution)])
    head = [f"- machine: {torch.get_num_threads()} threads, CPU: {cpu_name()}; peak RSS "
            f"{peak_rss_gb():.2f} GB",
            f"- command: `{cmd}`",
            f"- input views {g['views']}; mesh: the field's zero level at "
            f"{a.mesh_resolution}^3, culled by the input views; Chamfer (mm) against the ground "
            "truth the input views observe (`svolsdf evaluate`'s synthetic protocol)"]
    text = "\n".join(["# VolSDF at equal wall time: grid field against the paper's MLP", "",
                      *head, "", *lines, ""])
    write_results(a.results, text)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
