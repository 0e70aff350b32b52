"""The mesh against the points: mesh methods, free-space culling and support trimming on
finished runs (issues 37 and 47).

For every run folder (a finished `svolsdf reconstruct`), this script makes the mesh of each
method from the run's own fused points and depth maps (the Poisson surface, `poisson`, and the
TSDF of the observed final depth, `tsdf`; both culled by frusta, masks and visibility as the
mesh stage culls them), then cleans each one with every combination of free-space culling
(tolerance in final depth steps, 0 = off) and support trimming (k point spacings, 0 = off), as
`svolsdf.fusion.meshing.clean_mesh` does in the mesh stage, and scores the result beside the
run's points:

- synthetic scenes (`svolsdf synth`): `svolsdf evaluate`'s protocol, against the ground truth
  the input views observe;
- DTU scans: against the many-view pseudo ground truth of benchmarks/dtu_pseudo_gt.py (its
  cache in ``--pgt DIR``, made by running that script once with ``--out DIR``; the first
  reference: "object" with masks, "observed" inside the ObsMask without), as that script scores.

Either way a mesh is scored by its surface, as `svolsdf evaluate` scores it
(`svolsdf.evaluate.chamfer.mesh_surface_points` at `mesh_density` of the ground truth's diagonal,
0.1 % of it), never by its vertices; results written before that scored a synthetic scene's mesh
by its vertices (a DTU scan's by its surface sampled at 0.1 % without evening out).

Each row: accuracy, completeness and Chamfer of the mesh, their ratios to the points', faces,
and the seconds the mesh took (the method, plus the cleaning). The ``--summary`` lines give, per
(method, free space, k), the mean and worst ratio over the runs: the trade-off curve.

A method is a name with, optionally, options of the ``mesh`` section after a colon:
``poisson``, ``poisson:poisson.trim=7``, ``tsdf:tsdf.fill_holes=40``; ``support=K`` and
``free_space_steps=S`` there clean that method's mesh with that k and tolerance only (instead of
``--support`` and ``--free-steps``; its base mesh is made once); ``run`` is the run's own
OUT/mesh.ply; ``field`` is the field's zero level as the mesh stage makes it (fitted to the
points with the run's ``mesh.fit_points``), made by rerunning the mesh stage of a copy of the run
in ``--cache`` (issue 47).

The rows and the points' scores go to FILE.json beside FILE.md (``--json``), with the machine
and the command of each pass; ``--append`` adds a pass on the same runs (e.g. more methods on
the cached base meshes) to the rows already there. The Markdown is rendered from that JSON and
only from it: ``--from-json FILE.json`` renders it again without running anything.

Usage:
    python benchmarks/mesh_study.py --runs NAME=RUN [NAME=RUN ...] [--pgt NAME=DIR ...]
        [--free-steps 0 2 4 8] [--support 0 1.5 2 3 4 6]
        [--methods poisson poisson:poisson.trim=7 tsdf tsdf:tsdf.fill_holes=40 field]
        [--cache DIR] [--append] --results FILE.md
    python benchmarks/mesh_study.py --from-json FILE.json [--results FILE.md]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
from _machine import cpu_name, peak_rss_gb, public_argv

REPO = Path(__file__).resolve().parents[1]


def _dtu_reference(run, pgt_dir: Path, size: tuple[int, int]):
    """(reference points (M, 3) downsampled, obs mask or None) for a DTU run, from the cache of
    benchmarks/dtu_pseudo_gt.py in ``pgt_dir``."""
    sys.path.insert(0, str(Path(__file__).parent))
    from dtu_pseudo_gt import seen_by

    from svolsdf.evaluate.chamfer import (
        greedy_radius_downsample,
        load_obs_mask,
        obs_mask_filter,
    )
    from svolsdf.scene.loaders import load_scene

    scene_dir = Path(run.cfg.scene.path)
    probe = load_scene(scene_dir, load_images=False)
    has_masks = bool(probe.extras.get("mask_paths"))
    tag = "dil0" if has_masks else "dilnone"
    cache = next(iter(sorted(pgt_dir.glob(f"pseudo_gt_{size[0]}x{size[1]}_*_{tag}.npy"))), None)
    if cache is None:
        sys.exit(f"{pgt_dir}: no pseudo ground truth cache (run benchmarks/dtu_pseudo_gt.py "
                 f"--scene {scene_dir} --out {pgt_dir} first)")
    pts = np.load(cache)
    keep = seen_by(pts, scene_dir, run.views, size)
    obs = None
    if not has_masks:
        obs = load_obs_mask(probe.extras["obs_mask"])
        keep &= obs_mask_filter(pts, obs)[1]
    ref = pts[keep]
    diag = float(np.linalg.norm(ref.max(0) - ref.min(0)))
    ref = ref[np.random.default_rng(0).permutation(len(ref))]
    return ref[greedy_radius_downsample(ref, 0.001 * diag)], obs


class Scorer:
    """Scores points and meshes of one run by its scene's protocol."""

    def __init__(self, run, pgt_dir: Path | None):
        from svolsdf.evaluate.synthetic import is_synthetic_scene

        self.run = run
        self.scene_dir = Path(run.cfg.scene.path)
        self.synthetic = is_synthetic_scene(self.scene_dir)
        if not self.synthetic:
            if pgt_dir is None:
                sys.exit(f"{self.scene_dir}: not synthetic; give --pgt NAME=DIR for it")
            size = (run.load().width, run.load().height)
            self.ref, self.obs = _dtu_reference(run, pgt_dir, size)
            self.diag = float(np.linalg.norm(self.ref.max(0) - self.ref.min(0)))
            self.protocol = "pseudo ground truth (benchmarks/dtu_pseudo_gt.py)"
        else:
            self.protocol = "synthetic: ground truth the input views observe"

    def points(self, pts: np.ndarray) -> dict:
        return self._score(pts)

    def mesh(self, v: np.ndarray, f: np.ndarray) -> dict:
        """Scores of a mesh ((V, 3) vertices, (F, 3) faces) by its surface, as `svolsdf
        evaluate` scores it."""
        if self.synthetic:
            return self._score(v, faces=f)
        from svolsdf.evaluate.chamfer import mesh_density, mesh_surface_points

        return self._score(mesh_surface_points(v, f, mesh_density(self.diag)))

    def _score(self, x: np.ndarray, faces: np.ndarray | None = None) -> dict:
        x = np.asarray(x, dtype=np.float64)
        if self.synthetic:
            from svolsdf.evaluate.synthetic import synthetic_chamfer

            r = synthetic_chamfer(x, self.scene_dir, self.run.views, on_empty="clip",
                                  faces=faces)
            return {k: r[k] for k in ("accuracy", "completeness", "overall")}
        from dtu_pseudo_gt import score

        from svolsdf.evaluate.chamfer import obs_mask_filter

        if self.obs is not None:
            x = x[obs_mask_filter(x, self.obs)[1]]
        r = score(x, self.ref, self.ref)
        return {k: r[k] for k in ("accuracy", "completeness", "overall")}


def parse_method(spec: str) -> tuple[str, dict[str, str]]:
    """``"poisson:poisson.trim=7,support=0"`` -> ("poisson", {"poisson.trim": "7", ...}): a
    mesh method and options of the ``mesh`` section it runs with."""
    name, _, opts = spec.partition(":")
    return name, dict(o.split("=", 1) for o in opts.split(",") if o)


def _mesh_options(mesh, opts: dict[str, str]):
    """A copy of the run's ``mesh`` section with ``opts`` (dotted names under it) set."""
    import copy

    from svolsdf.config import apply_overrides, parse_set
    from svolsdf.config.schema import Config

    c = Config()
    c.mesh = copy.deepcopy(mesh)
    c = apply_overrides(c, parse_set([f"mesh.{k}={v}" for k, v in opts.items()]))
    return c.mesh


def _field_mesh_of(out: Path, work: Path, opts: dict[str, str]):
    """The field's zero level as the mesh stage makes it (``mesh.method=field`` and the
    run's ``mesh.fit_points``: fitted to the points), with free-space culling and trimming off
    (the study cleans it): made by rerunning the mesh stage of a copy of the run in ``work``.
    Returns (vw, faces, mesh stage seconds)."""
    import subprocess

    from _machine import copy_run

    from svolsdf.io.ply import read_ply

    def edit(cfg):
        cfg.mesh = _mesh_options(cfg.mesh, {"method": "field", "free_space": "false",
                                            "support": "0", **opts})
        scene["path"] = cfg.scene.path

    scene = {}
    copy_run(out, work, edit)
    subprocess.run([sys.executable, "-m", "svolsdf", "reconstruct", scene["path"], "-o", str(work),
                    "--config", str(work / "config.yaml")], check=True)
    timing = json.loads((work / "timing.json").read_text())
    if timing["mesh"].get("mesh_source", "field") != "field":
        raise RuntimeError(f"{work}: mesh source {timing['mesh']['mesh_source']}")
    m = read_ply(work / "mesh.ply")
    return (torch.from_numpy(m["points"]).float(), torch.from_numpy(m["faces"]).long(),
            float(timing["mesh"]["seconds"]))


def study_run(name: str, out: Path, pgt: Path | None, methods: list[str],
              free_steps: list[float], support: list[float], cache: Path | None = None
              ) -> tuple[dict, list[dict]]:
    """(the points' scores, one row per (method, free-space steps, k))."""
    from svolsdf.fusion.mesh_methods import MeshInputs, get_mesh_method
    from svolsdf.fusion.meshing import clean_mesh
    from svolsdf.fusion.observe import final_depth_step
    from svolsdf.io.ply import read_ply
    from svolsdf.pipeline.loaded_run import Run
    from svolsdf.pipeline.mesh import observed_depths_of

    run = Run.open(out)
    cfg = run.cfg
    scene = run.load()
    scorer = Scorer(run, pgt)
    d = read_ply(out / "points.ply")
    pts, cols = d["points"], d["colors"]
    pscore = scorer.points(pts)
    print(f"{name}: {len(pts):,} points, {json.dumps(pscore)}", flush=True)
    use_masks = scene.masks is not None and cfg.scene.use_masks
    step = final_depth_step(scene.depth_range, cfg.mvs.width)
    t0 = time.perf_counter()
    observed = observed_depths_of(run, pts)
    t_obs = time.perf_counter() - t0
    rows = []
    for spec in methods:
        method, opts = parse_method(spec)
        # the cleaning options of a method's own: its only (free, k) instead of the grid
        fs_list = [float(opts.pop("free_space_steps"))] if "free_space_steps" in opts \
            else free_steps
        k_list = [float(opts.pop("support"))] if "support" in opts else support
        t0 = time.perf_counter()
        tag = "_".join([method, *(f"{k}{v}" for k, v in sorted(opts.items()))])
        cached = None if cache is None else cache / f"{name}_{tag}.npz"
        if cached is not None and cached.is_file():  # the base mesh of an earlier pass
            z = np.load(cached)
            vw, f, t_method = torch.from_numpy(z["v"]), torch.from_numpy(z["f"]), float(z["t"])
        elif method == "run":  # the run's own OUT/mesh.ply, as its mesh stage made it
            m = read_ply(out / "mesh.ply")
            vw, f = torch.from_numpy(m["points"]).float(), torch.from_numpy(m["faces"]).long()
            t_method = float(json.loads((out / "timing.json").read_text())["mesh"]["seconds"])
        elif method == "field":  # the mesh stage of a copy of the run (it fits the field)
            if cache is None:
                sys.exit("method field: give --cache DIR (the run is copied there)")
            vw, f, t_method = _field_mesh_of(out, cache / f"{name}_{tag}", opts)
        else:  # a registered points method, as the mesh stage runs it
            inputs = MeshInputs(points=pts, colours=cols, scene=scene, observed=observed,
                                model=run.model(), field_mesh=None,
                                mesh=_mesh_options(cfg.mesh, opts), depth_step=step,
                                use_masks=use_masks, device=run.device)
            vw, f, _ = get_mesh_method(method).run(inputs)
        if method not in ("run", "field") and (cached is None or not cached.is_file()):
            t_method = time.perf_counter() - t0 + (t_obs if method == "tsdf" else 0.0)
            if cached is not None:
                cache.mkdir(parents=True, exist_ok=True)
                np.savez(cached, v=vw.numpy(), f=f.numpy(), t=t_method)
        for fs in fs_list:
            for k in k_list:
                t1 = time.perf_counter()
                v2, f2, _, info = clean_mesh(
                    vw, f, None, scene, observed=observed if fs > 0 else None,
                    free_space_tol=fs * step if fs > 0 else None, points=pts, support_k=k)
                t_clean = time.perf_counter() - t1 + (t_obs if fs > 0 and method != "tsdf"
                                                       else 0.0)
                s = scorer.mesh(v2.double().numpy(), f2.numpy()) if len(f2) else None
                row = {"run": name, "method": spec, "free_steps": fs, "k": k,
                       "faces": int(len(f2)), "seconds": round(t_method + t_clean, 1),
                       **({f"mesh_{a}": s[a] for a in s} if s else {}),
                       **({f"ratio_{a}": s[a] / pscore[a] for a in s} if s else {})}
                rows.append(row)
                print(json.dumps(row), flush=True)
    return pscore, rows


def _fmt(x, digits=2):
    return "-" if x is None else f"{x:.{digits}f}"


def render(data: dict) -> str:
    """The results file of a study, from its JSON (``{"meta", "points", "rows"}``)."""
    meta, points, all_rows = data["meta"], data["points"], data["rows"]
    passes = meta["passes"]
    lines = ["# The mesh against the points: methods, free-space culling, support trimming", "",
             f"- machine: nproc = {meta['nproc']}, CPU: {meta['cpu']}"]
    first = 1
    for i, ps in enumerate(passes, 1):
        peak = ("peak RSS not recorded" if ps.get("peak_rss_gb") is None
                else f"peak RSS {ps['peak_rss_gb']:.2f} GB")
        label = "command" if len(passes) == 1 else (
            f"pass {i} (rows {first}-{first + ps['rows'] - 1} of Every run"
            + ("" if i == 1 else "; the same runs and cached base meshes") + ")")
        lines.append(f"- {label}: `python benchmarks/mesh_study.py {ps['command']}`; {peak}")
        first += ps["rows"]
    lines += ["- columns: the mesh's accuracy / completeness / Chamfer (the scene's units), their "
              "ratios to the points' (mesh / points; 1 = as good), faces, and the seconds the "
              "mesh took (method + cleaning). free = free-space tolerance in final depth steps "
              "(0 = off); k = support trimming in point spacings (0 = off).", ""]
    lines += ["## Points", "", "| run | acc | comp | Chamfer |", "|---|---:|---:|---:|"]
    lines += [f"| {n} | {_fmt(s['accuracy'])} | {_fmt(s['completeness'])} | "
              f"{_fmt(s['overall'])} |" for n, s in points.items()]
    lines += ["", "## Trade-off curve (over the runs: mean and worst ratio)", "",
              "| method | free | k | Chamfer ratio mean | worst | acc ratio mean | worst | "
              "comp ratio mean | worst | seconds mean |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    order = [m for ps in passes for m in ps["methods"]]
    keys = sorted({(r["method"], r["free_steps"], r["k"]) for r in all_rows},
                  key=lambda t: (order.index(t[0]), t[1], t[2]))
    means = []
    for m, fs, k in keys:
        rs = [r for r in all_rows if (r["method"], r["free_steps"], r["k"]) == (m, fs, k)
              and "ratio_overall" in r]
        if not rs:
            continue

        def agg(key, rs=rs):
            v = [r[key] for r in rs]
            return f"{np.mean(v):.3f} | {max(v):.3f}"

        means.append((float(np.mean([r["ratio_overall"] for r in rs])), m, fs, k, len(rs)))
        lines.append(f"| {m} | {fs:g} | {k:g} | {agg('ratio_overall')} | {agg('ratio_accuracy')}"
                     f" | {agg('ratio_completeness')} | "
                     f"{np.mean([r['seconds'] for r in rs]):.1f} |")
    lines += ["", "## Every run", "",
              "| run | method | free | k | acc | comp | Chamfer | acc ratio | comp ratio | "
              "Chamfer ratio | faces | s |", "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"
              "---:|---:|"]
    for r in all_rows:
        lines.append(f"| {r['run']} | {r['method']} | {r['free_steps']:g} | {r['k']:g} | "
                     f"{_fmt(r.get('mesh_accuracy'))} | {_fmt(r.get('mesh_completeness'))} | "
                     f"{_fmt(r.get('mesh_overall'))} | {_fmt(r.get('ratio_accuracy'), 3)} | "
                     f"{_fmt(r.get('ratio_completeness'), 3)} | "
                     f"{_fmt(r.get('ratio_overall'), 3)} | {r['faces']:,} | {r['seconds']} |")
    if means:
        lines += ["", "## Notes (computed from the JSON beside this file)", "",
                  "Ranked by the mean Chamfer ratio over the runs (mesh / points; lower is "
                  "better):", "", "| rank | method | free | k | Chamfer ratio mean | runs |",
                  "|---:|---|---:|---:|---:|---:|"]
        for i, (mean, m, fs, k, n) in enumerate(sorted(means, key=lambda t: t[0]), 1):
            lines.append(f"| {i} | {m} | {fs:g} | {k:g} | {mean:.3f} | {n} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", nargs="+", metavar="NAME=DIR")
    ap.add_argument("--pgt", nargs="*", default=[], metavar="NAME=DIR",
                    help="pseudo ground truth cache (benchmarks/dtu_pseudo_gt.py --out) per "
                         "DTU run name")
    ap.add_argument("--methods", nargs="+", default=["poisson", "tsdf"],
                    help="poisson, tsdf, field, or run (the run's own mesh.ply, e.g. the "
                         "fast preset's Poisson mesh, without making it again); NAME:OPT=V,... "
                         "sets options of the mesh section (poisson.trim=7)")
    ap.add_argument("--free-steps", nargs="+", type=float, default=[0, 2, 4, 8])
    ap.add_argument("--support", nargs="+", type=float, default=[0, 1.5, 2, 3, 4, 6])
    ap.add_argument("--results", type=Path, default=None)
    ap.add_argument("--cache", type=Path, default=None,
                    help="keep each run's base meshes here; a rerun only cleans and scores")
    ap.add_argument("--json", type=Path, default=None, help="rows as JSON (default: next to "
                    "--results)")
    ap.add_argument("--append", action="store_true",
                    help="add this pass's rows to those of the JSON already there (the same "
                         "runs), as a further pass")
    ap.add_argument("--from-json", type=Path, default=None, metavar="FILE.json",
                    help="render the Markdown from this JSON (to --results, default FILE.md) "
                         "and run nothing")
    args = ap.parse_args()
    if args.from_json is not None:
        results = args.results or args.from_json.with_suffix(".md")
        results.write_text(render(json.loads(args.from_json.read_text())))
        print(f"wrote {results}")
        return
    if not args.runs or args.results is None:
        ap.error("--runs and --results are needed (or --from-json)")
    jpath = args.json or args.results.with_suffix(".json")
    data = {"meta": {"nproc": os.cpu_count(), "cpu": cpu_name(), "passes": []}, "points": {},
            "rows": []}
    if args.append:
        data = json.loads(jpath.read_text())
    pgt = dict(item.split("=", 1) for item in args.pgt)
    all_rows, points = [], {}
    for item in args.runs:
        name, _, d = item.rpartition("=")
        name = name or Path(d).name
        p = Path(pgt[name]) if name in pgt else None
        points[name], rows = study_run(name, Path(d), p, args.methods, args.free_steps,
                                       args.support, args.cache)
        all_rows += rows
    if args.append and set(points) != set(data["points"]):
        sys.exit(f"--append: runs {sorted(points)} differ from {sorted(data['points'])} in "
                 f"{jpath}")
    data["points"] = points
    data["rows"] += all_rows
    data["meta"]["passes"].append({"command": public_argv(sys.argv[1:]),
                                   "peak_rss_gb": round(peak_rss_gb(), 2),
                                   "methods": args.methods, "rows": len(all_rows)})
    jpath.write_text(json.dumps(data, indent=1))
    # rendered from the JSON as written, so --from-json reproduces it
    args.results.write_text(render(json.loads(jpath.read_text())))
    print(f"wrote {args.results}")


if __name__ == "__main__":
    torch.set_grad_enabled(True)
    main()
