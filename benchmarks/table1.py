"""The paper's Table 1 from a `svolsdf benchmark` folder: per scene and mode the points' and the
default mesh's Chamfer, image metrics on the held-out views by volume rendering and by IBR, the
stage time; the checks of issue 28; how each mode's points are fused and what each difference
between the modes' fusion does (benchmarks/fusion_differences.py); which scenes were held out
from which choice.

    python benchmarks/table1.py --bench OUT [--fusion FILE.json] --results FILE.md
    python benchmarks/table1.py --from-json FILE.json --results FILE.md

The first form reads the run folders and writes FILE.json (every number the table shows, with
the commands, the commit, the date and the machine) and FILE.md, the whole of it made from the
JSON; the second makes FILE.md again from the JSON alone, byte for byte
(tests/test_table1.py checks the committed pair). Nothing in FILE.md is written by hand: the
reasoning behind the rules is in docs/table1.md.

``--bench``: a folder written by `svolsdf benchmark` (benchmark.json and OUT/<scene>/<mode>/).
``--fusion``: DIR/fusion_differences.json of benchmarks/fusion_differences.py on that folder.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import cpu_name  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
MODES = ("mvs-only", "volsdf", "svolsdf")

# The checks of issue 28: (key, what, target operator, target, unit)
CHECKS = (
    ("volsdf_points", "VolSDF points Chamfer", "<=", 4.0, " mm"),
    ("ratio_points", "S-VolSDF / VolSDF points Chamfer", "<=", 0.6, ""),
    ("ratio_points_dtu", "S-VolSDF / VolSDF points Chamfer, DTU rule", "<=", 0.6, ""),
    ("mesh_over_points", "S-VolSDF mesh / points Chamfer (issue 28's target was set when meshes "
     "were scored by their vertices)", "<=", 1.15, ""),
    ("ibr_gain_vr", "S-VolSDF IBR PSNR minus VolSDF's volume-rendered PSNR", ">=", 2.0, " dB"),
    ("ibr_gain_ibr", "S-VolSDF IBR PSNR minus VolSDF's IBR PSNR", ">=", 2.0, " dB"),
)

# Which choices of the pipeline were made on which scenes (docs/presets.md, docs/meshing.md,
# benchmarks/results/history/volsdf_baseline.md): the table's scenes are held out from a choice
# unless they are among its scenes
TUNING = (
    {"choice": "the fast preset's fusion (fusion.surface, fusion.guided_dilation, "
     "fusion.unguided_dilation, fusion.unguided) and field.init_unverified_weight",
     "scenes": ["synth --seed 0", "synth --seed 3", "synth --seed 7 --object blobs",
                "synth --seed 11", "DTU scan 65"], "source": "docs/presets.md"},
    {"choice": "the Poisson mesh's options (mesh.poisson.depth, mesh.poisson.trim, its normals)",
     "scenes": ["synth --seed 101", "synth --seed 103 --object blobs"],
     "source": "docs/table1.md"},
    {"choice": "free-space culling (mesh.free_space)",
     "scenes": ["synth --seed 401 (DTU cameras)", "synth --seed 402 (DTU cameras)"],
     "source": "docs/meshing.md"},
    {"choice": "support trimming (mesh.support)",
     "scenes": ["synth --seed 501 (DTU cameras)", "synth --seed 502 (DTU cameras)"],
     "source": "docs/meshing.md"},
    {"choice": "volsdf mode's start (field.sphere_radius and its schedule)",
     "scenes": ["synth --seed 101"], "source": "benchmarks/results/history/volsdf_baseline.md"},
    {"choice": "the Poisson mesh without the field mesh's largest-component step",
     "scenes": ["synth --seed 301", "synth --seed 302", "synth --seed 303",
                "synth --seed 304", "synth --seed 305"], "source": "docs/table1.md"},
)


# --------------------------------------------------------------------------- reading the runs
def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _mean(xs) -> float | None:
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return sum(xs) / len(xs) if xs else None


def _ratio(a, b) -> float | None:
    return a / b if a is not None and b else None


def _work(arg: str) -> str:
    """A path of the command line as the results show it: inside the repository relative to
    it, elsewhere under the placeholder WORK (no machine's folders in a committed file)."""
    p = Path(arg).absolute()
    try:
        return str(p.relative_to(REPO))
    except ValueError:
        pass
    try:
        return "WORK/" + str(p.relative_to(Path.cwd()))
    except ValueError:
        return "WORK/" + p.name


def _command(argv: list[str]) -> str:
    out = ["python", "benchmarks/table1.py"]
    for a in argv:
        out.append(a if a.startswith("-") else _work(a))
    return " ".join(out)


def _git(*args: str) -> str:
    return subprocess.run(["git", "-C", str(REPO), *args], capture_output=True, text=True,
                          check=True).stdout.strip()


def _commit() -> str:
    """The last commit that changed src/ (the code the runs ran), marked when src/ has
    uncommitted changes."""
    c = _git("log", "-1", "--format=%h", "--", "src")
    return c + (" with uncommitted changes" if _git("status", "--porcelain", "--", "src") else "")


def _machine() -> dict:
    import torch

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"arch": platform.machine(), "cpu": cpu_name(), "cores": cores,
            "torch": torch.__version__.split("+")[0]}


def _scene_facts(scene_path: str | None) -> dict:
    """Seed, views, size and object kind of a synthetic scene (its scene.json), else {}."""
    meta = _read_json(Path(scene_path) / "scene.json") if scene_path else None
    if not isinstance(meta, dict) or meta.get("generator") != "svolsdf.synth":
        return {}
    c = meta.get("config") or {}
    return {"seed": c.get("seed"), "views": meta.get("views"),
            "size": [meta.get("width"), meta.get("height")], "object": c.get("object")}


def _fusion_rule(run: Path, cfg) -> dict:
    """How a run fused its final depth: the multi-view check, the surface vote, the masks and
    the depth's size, from its config.yaml and OUT/depth."""
    import numpy as np

    from svolsdf.fusion.filter import FusionFilterConfig
    from svolsdf.pipeline import options

    f = cfg.fusion
    dil = options.mask_dilation(cfg)
    depth = sorted((run / "depth").glob("*.npy"))
    h, w = np.load(depth[0], mmap_mode="r").shape if depth else (None, None)
    return {"dist": f.dist, "rel": f.rel, "min_views": f.min_views,
            # the vote of fusion_stage.fuse: a field's surface, and not the depth itself
            "surface": f.surface if options.guided_mvs(cfg) and f.surface > 0 else None,
            "mask_dilation": FusionFilterConfig().mask_dilation if dil is None else dil,
            "unguided_set": options.wants_unguided(cfg),
            "depth_size": [w, h] if depth else None}


def gather_rows(bench: Path) -> tuple[list[dict], dict, dict]:
    """(rows, per-mode fusion rules, setup) of a benchmark folder's finished runs."""
    from svolsdf.config import load_config
    from svolsdf.evaluate.benchmark_tables import method_label

    rows, rules, setup = [], {}, {"scenes": {}, "render_size": None}
    for r in json.loads((bench / "benchmark.json").read_text()):
        if r.get("status") != "ok":
            continue
        run = bench / r["scene"] / r["mode"]
        cfg = load_config(run / "config.yaml")
        views = _read_json(run / "views.json") or {}
        metrics = _read_json(run / "metrics.json") or {}
        src = r.get("mesh_source")
        t = r.get("time_s")
        rows.append({
            "scene": r["scene"], "mode": r["mode"],
            "method": method_label(r["mode"], r.get("field") or cfg.field.kind),
            "points": r.get("overall"), "points_dtu": r.get("overall_dtu_rule"),
            "accuracy": r.get("accuracy"), "completeness": r.get("completeness"),
            "mesh": r.get("mesh_overall"), "mesh_dtu": r.get("mesh_overall_dtu_rule"),
            "mesh_source": src, "mesh_sampled": r.get("mesh_sampled"),
            "mesh_density": r.get("mesh_density"),
            # the mesh stage fell back to the field's zero level (mesh_source "field (...)")
            "mesh_fallback": bool(src and src.startswith("field (")),
            **{k: r.get(k) for k in ("psnr", "ssim", "lpips", "psnr_ibr", "ssim_ibr",
                                     "lpips_ibr")},
            "time_min": None if t is None else t / 60})
        rules.setdefault(r["mode"], {})[r["scene"]] = _fusion_rule(run, cfg)
        synthetic = (metrics.get("settings") or {}).get("synthetic") or {}
        setup["scenes"].setdefault(r["scene"], {**_scene_facts(cfg.scene.path),
                                                "path": _work(cfg.scene.path),
                                                "inputs": views.get("inputs"),
                                                "held_out": views.get("test"),
                                                "max_dist": synthetic.get("max_dist")})
        setup["preset"] = cfg.preset
        size = (metrics.get("settings") or {}).get("image_size")
        if size and r.get("psnr") is not None:
            setup["render_size"] = size
    setup["modes"] = list(dict.fromkeys(r["mode"] for r in rows))
    setup["date"] = datetime.datetime.fromtimestamp(
        (bench / "benchmark.json").stat().st_mtime, datetime.timezone.utc).date().isoformat()
    return rows, rules, setup


def _one_rule(per_scene: dict) -> dict:
    """The rule every scene's run of a mode used (they must agree)."""
    rules = list(per_scene.values())
    if any(r != rules[0] for r in rules):
        raise SystemExit(f"the runs of one mode were fused under different rules: {per_scene}")
    return rules[0]


# --------------------------------------------------------------------------- derived numbers
def _span(values: list) -> dict:
    xs = [x for x in values if x is not None]
    return {"values": values, "n": len(xs), "min": min(xs) if xs else None,
            "max": max(xs) if xs else None, "mean": _mean(xs)}


def checks(rows: list[dict]) -> list[dict]:
    cell = {(r["scene"], r["mode"]): r for r in rows}
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    vals = {k: [] for k, *_ in CHECKS}
    for s in scenes:
        v, sv = cell.get((s, "volsdf")), cell.get((s, "svolsdf"))
        if v is not None:
            vals["volsdf_points"].append(v["points"])
        if v is not None and sv is not None:
            vals["ratio_points"].append(_ratio(sv["points"], v["points"]))
            vals["ratio_points_dtu"].append(_ratio(sv["points_dtu"], v["points_dtu"]))
            gain = (sv["psnr_ibr"] is not None)
            vals["ibr_gain_vr"].append(sv["psnr_ibr"] - v["psnr"]
                                       if gain and v["psnr"] is not None else None)
            vals["ibr_gain_ibr"].append(sv["psnr_ibr"] - v["psnr_ibr"]
                                        if gain and v["psnr_ibr"] is not None else None)
        if sv is not None:
            vals["mesh_over_points"].append(_ratio(sv["mesh"], sv["points"]))
    out = []
    for key, what, op, target, unit in CHECKS:
        sp = _span(vals[key])
        met = [x for x in sp["values"] if x is not None
               and (x <= target if op == "<=" else x >= target)]
        out.append({"key": key, "what": what, "op": op, "target": target, "unit": unit, **sp,
                    "meeting": len(met)})
    return out


def means(rows: list[dict]) -> list[dict]:
    """Per mode the mean of each column over the scenes that have it."""
    keys = ("points", "points_dtu", "mesh", "mesh_dtu", "psnr", "ssim", "lpips", "psnr_ibr",
            "ssim_ibr", "lpips_ibr", "time_min")
    out = []
    for m in dict.fromkeys(r["mode"] for r in rows):
        mine = [r for r in rows if r["mode"] == m]
        out.append({"mode": m, "method": mine[0]["method"], "n": len(mine),
                    **{k: _mean([r[k] for r in mine]) for k in keys}})
    return out


def fusion_effects(data: dict | None, rows: list[dict]) -> list[dict]:
    """Each variant of benchmarks/fusion_differences.py with its per-scene Chamfer as run and
    changed and the mean change; its "as run" must be the table's row (else it is stale)."""
    if not data:
        return []
    cell = {(r["scene"], r["mode"]): r for r in rows}
    out = []
    for v in data["variants"]:
        per = {}
        for s, d in v["scenes"].items():
            row = cell.get((s, v["mode"]))
            if row is None or row["points"] is None or \
                    abs(d["base"]["overall"] - row["points"]) > 1e-9:
                raise SystemExit(f"{v['name']} / {s}: its run is not the table's "
                                 f"({d['base']['overall']} against "
                                 f"{None if row is None else row['points']}): run "
                                 "benchmarks/fusion_differences.py on this benchmark again")
            b, c = d["base"], d["changed"]
            per[s] = {"base": b["overall"], "changed": c["overall"],
                      "diff": c["overall"] - b["overall"],
                      "base_dtu": b["overall_dtu_rule"], "changed_dtu": c["overall_dtu_rule"],
                      "accuracy": [b["accuracy"], c["accuracy"]],
                      "completeness": [b["completeness"], c["completeness"]],
                      "points": [b["points"], c["points"]],
                      "depth_size": c.get("depth_size")}
        diffs = [p["diff"] for p in per.values()]
        out.append({"name": v["name"], "mode": v["mode"], "what": v["what"],
                    "sets": v["sets"], "depth_size_of": v.get("depth_size_of"),
                    "scenes": per,
                    "mean_base": _mean([p["base"] for p in per.values()]),
                    "mean_changed": _mean([p["changed"] for p in per.values()]),
                    "mean_diff": _mean(diffs),
                    "mean_diff_dtu": _mean([p["changed_dtu"] - p["base_dtu"]
                                            for p in per.values()]),
                    "mean_accuracy": [_mean([p["accuracy"][i] for p in per.values()])
                                      for i in (0, 1)],
                    "mean_completeness": [_mean([p["completeness"][i] for p in per.values()])
                                          for i in (0, 1)],
                    "worse": sum(d > 0 for d in diffs), "better": sum(d < 0 for d in diffs)})
    return out


def commands(setup: dict, bench_arg: str, fusion_arg: str | None, argv: list[str]) -> dict:
    """The commands that made the table, paths under the placeholder WORK."""
    scenes = list(setup["scenes"].values())
    paths = [s["path"] for s in scenes]
    seeds = [s.get("seed") for s in scenes]
    bench = _work(bench_arg)
    loop = [p.replace(str(s), "N") for p, s in zip(paths, seeds, strict=True)]
    if None not in seeds and len(set(loop)) == 1 and all(str(s) in p for p, s
                                                        in zip(paths, seeds, strict=True)):
        synth = (f"for N in {' '.join(map(str, seeds))}; do svolsdf synth {loop[0]} --seed N; "
                 "done")
    else:
        synth = "; ".join(f"svolsdf synth {p} --seed {s}"
                          for p, s in zip(paths, seeds, strict=True))
    rs = setup.get("render_size")
    benchmark = ("svolsdf benchmark --scenes " + " ".join(paths)
                 + " --modes " + " ".join(setup["modes"]) + f" -o {bench}"
                 + (f" --preset {setup['preset']}" if setup.get("preset") != "fast" else "")
                 + (f" --render-size {rs[0]}x{rs[1]}" if rs else ""))
    out = {"scenes": synth, "benchmark": benchmark}
    if fusion_arg is not None:
        out["fusion"] = (f"python benchmarks/fusion_differences.py --bench {bench} "
                         f"--out {_work(str(Path(fusion_arg).parent))}")
    out["table"] = _command(argv)
    return out


def build(bench: Path, fusion: Path | None, argv: list[str]) -> dict:
    """The JSON document of the table: every number it shows and where it came from."""
    rows, rules, setup = gather_rows(bench)
    fusion_data = _read_json(fusion) if fusion is not None else None
    if fusion is not None and fusion_data is None:
        raise SystemExit(f"{fusion}: not a fusion_differences.json")
    scenes = setup["scenes"]
    these = {f"synth --seed {s['seed']}" for s in scenes.values() if s.get("seed") is not None}
    return {
        "title": "Table 1, reproduced: MVS only, VolSDF and S-VolSDF on synthetic scenes",
        "commands": commands(setup, str(bench), None if fusion is None else str(fusion), argv),
        "commit": _commit(), "date": setup.pop("date"), "machine": _machine(),
        "setup": setup, "rows": rows, "means": means(rows), "checks": checks(rows),
        "fusion_rules": {m: _one_rule(per) for m, per in rules.items()},
        "fusion_effects": fusion_effects(fusion_data, rows),
        "tuning": [{**t, "these_scenes": "used" if these & set(t["scenes"]) else "held out"}
                   for t in TUNING],
    }


# --------------------------------------------------------------------------- the Markdown
def _f(x, d=2) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.{d}f}"


def _signed(x, d=2) -> str:
    if x is None:
        return "-"
    text = f"{x:+.{d}f}"
    return text[1:] if float(text) == 0 else text  # no sign on a change that rounds to zero


def _size(s) -> str:
    return "-" if not s else f"{s[0]}x{s[1]}"


def _list(xs: list) -> str:
    xs = [str(x) for x in xs]
    return xs[0] if len(xs) == 1 else ", ".join(xs[:-1]) + " and " + xs[-1]


def _setup_lines(doc: dict) -> list[str]:
    st = doc["setup"]
    names = list(st["scenes"])
    sc = [st["scenes"][n] for n in names]
    first = sc[0]
    seeds = [s.get("seed") for s in sc]
    same = all(s.get(k) == first.get(k) for s in sc for k in ("views", "size", "object"))
    n = len(sc)
    if same and None not in seeds:
        scenes = (f"{n} synthetic scene{'s' if n > 1 else ''} (`svolsdf synth --seed "
                  f"{seeds[0]}`..`{seeds[-1]}`, {first['object']} objects), {first['views']} "
                  f"views at {_size(first['size'])} each")
    else:
        scenes = ", ".join(names)
    inputs = " ".join(map(str, first["inputs"] or []))
    lines = [f"- scenes: {scenes}; {len(first['inputs'] or [])} input views (the pipeline's "
             f"choice, {inputs} in {names[0]}), the other {len(first['held_out'] or [])} held "
             f"out for the image metrics; preset {st['preset']}"]
    clip = [s["max_dist"] for s in sc if s.get("max_dist") is not None]
    sampled = {r["mesh_sampled"] for r in doc["rows"] if r.get("mesh") is not None}
    sources = list(dict.fromkeys(r["mesh_source"] for r in doc["rows"] if r.get("mesh_source")))
    how = ("by its surface (the triangles sampled evenly, "
           "`svolsdf.evaluate.chamfer.mesh_surface_points`)" if sampled == {"surface"}
           else "by " + " / ".join(sorted(map(str, sampled))))
    lines.append(
        "- Chamfer in mm by the synthetic protocol of `svolsdf evaluate`: against the ground "
        "truth the input views observe, distances clipped at "
        + (f"{_f(min(clip))}-{_f(max(clip))} mm (a share of its diagonal)" if clip else "-")
        + "; 'DTU rule': distances beyond that left out. 'mesh': each run's default mesh ("
        + (" / ".join(sources) or "-") + f"), scored {how}; '*' marks a mesh that fell back "
        "to the field's zero level.")
    lines.append(
        f"- Images: the held-out views rendered at {_size(st.get('render_size'))}, ground truth "
        "resized to it; PSNR inside the object masks, SSIM, LPIPS (VGG); 'IBR': image-based "
        "rendering (docs/method.md 7). Time: the sum of each run's stage times.")
    return lines


def _table(doc: dict) -> list[str]:
    head = ("| scene | method | points Chamfer | points, DTU rule | mesh | mesh, DTU rule "
            "| PSNR | SSIM | LPIPS | PSNR IBR | SSIM IBR | LPIPS IBR | time (min) |")
    lines = [head, "|---|---|" + "---:|" * 11]

    def cells(r: dict) -> list[str]:
        mark = "*" if r.get("mesh_fallback") else ""
        return [_f(r["points"]), _f(r["points_dtu"]), _f(r["mesh"]) + mark,
                _f(r["mesh_dtu"]), _f(r["psnr"]), _f(r["ssim"], 3), _f(r["lpips"], 3),
                _f(r["psnr_ibr"]), _f(r["ssim_ibr"], 3), _f(r["lpips_ibr"], 3),
                _f(r["time_min"], 1)]

    for r in doc["rows"]:
        lines.append("| " + " | ".join([r["scene"], r["method"], *cells(r)]) + " |")
    for m in doc["means"]:
        lines.append("| " + " | ".join([f"mean of {m['n']}", m["method"],
                                        *cells({**m, "mesh_fallback": False})]) + " |")
    return lines


def _checks(doc: dict) -> list[str]:
    out = []
    for c in doc["checks"]:
        u = c["unit"]
        if not c["n"]:
            out.append(f"- {c['what']} (target {c['op']} {c['target']:g}{u}): no data")
            continue
        out.append(f"- {c['what']} (target {c['op']} {c['target']:g}{u}): "
                   f"{_f(c['min'])}-{_f(c['max'])}{u}, mean {_f(c['mean'])}; "
                   f"{c['meeting']} of {c['n']} scenes meet it")
    return out


def _rules(doc: dict) -> list[str]:
    rules = doc["fusion_rules"]
    modes = [m for m in MODES if m in rules]
    label = {m["mode"]: m["method"] for m in doc["means"]}
    what = {"mvs-only": "MVS stage 3, centred on stage 1",
            "volsdf": "the field's rendered depth",
            "svolsdf": "MVS stage 3 centred on the field's depth"}
    lines = ["| | " + " | ".join(label[m] for m in modes) + " |",
             "|---|" + "---|" * len(modes)]

    def row(name, fn):
        lines.append(f"| {name} | " + " | ".join(fn(m, rules[m]) for m in modes) + " |")

    row("depth fused", lambda m, r: what.get(m, m) + (", and the unguided set"
                                                       if r["unguided_set"] else ""))
    row("its size", lambda m, r: _size(r["depth_size"]))
    row("consistent source", lambda m, r: f"< {r['dist']:g} px and < {r['rel'] * 100:g} %")
    row("sources needed", lambda m, r: f"{r['min_views']}"
        + (", the surface counting as one" if r["surface"] else ""))
    row("surface vote", lambda m, r: "-" if r["surface"] is None
        else f"within {r['surface'] * 100:g} % of the rendered depth")
    row("mask dilation", lambda m, r: f"{r['mask_dilation']} px")
    return lines


def _shared(doc: dict) -> str:
    """The sentence saying which parts of the fusion rule every mode shares and which differ,
    from the rules themselves."""
    rules = list(doc["fusion_rules"].values())
    parts = {"the multi-view check": ("dist", "rel"), "the number of sources needed":
             ("min_views",), "the object masks": ("mask_dilation",),
             "the surface vote": ("surface",), "the depth's size": ("depth_size",)}
    same = [n for n, ks in parts.items() if all(r[k] == rules[0][k] for r in rules for k in ks)]
    differ = [n for n in parts if n not in same]
    if len(rules) < 2:
        return "One mode only."
    text = "Every mode shares " + (_list(same) if same else "nothing of the rule")
    if differ:
        text += "; " + _list(differ) + (" differs" if len(differ) == 1 else " differ")
    return text + " (why: docs/table1.md):"


def _effects(doc: dict) -> list[str]:
    eff = doc["fusion_effects"]
    if not eff:
        return ["Not measured for this table (no `--fusion`)."]
    scenes = list(eff[0]["scenes"])
    label = {m["mode"]: m["method"] for m in doc["means"]}
    lines = ["| mode | change | " + " | ".join(scenes) + " | mean as run | mean changed | "
             "change (DTU rule) | scenes worse | accuracy | completeness |",
             "|---|---|" + "---:|" * (len(scenes) + 6)]
    for v in eff:
        how = ([f"`--set {k}={'null' if x is None else x}`" for k, x in v["sets"].items()]
               + ([f"depth at {_size(next(iter(v['scenes'].values()))['depth_size'])}"]
                  if v["depth_size_of"] else []))
        acc, comp = v["mean_accuracy"], v["mean_completeness"]
        lines.append(
            "| " + " | ".join([label.get(v["mode"], v["mode"]), v["what"] + " (" + ", ".join(how)
                               + ")",
                               *[f"{_f(p['base'])} -> {_f(p['changed'])}"
                                 for p in v["scenes"].values()],
                               _f(v["mean_base"]), _f(v["mean_changed"]),
                               f"{_signed(v['mean_diff'])} ({_signed(v['mean_diff_dtu'])})",
                               f"{v['worse']} of {len(v['scenes'])}",
                               f"{_f(acc[0])} -> {_f(acc[1])}",
                               f"{_f(comp[0])} -> {_f(comp[1])}"]) + " |")
    return lines


def _tuning(doc: dict) -> list[str]:
    out = []
    for t in doc["tuning"]:
        out.append(f"- {t['choice']}: chosen on {_list(t['scenes'])} ({t['source']}); "
                   + ("these scenes were used for it" if t["these_scenes"] == "used"
                      else "these scenes held out"))
    return out


def render(doc: dict) -> str:
    """The Markdown of the table from its JSON document alone."""
    m = doc["machine"]
    c = doc["commands"]
    lines = [
        f"# {doc['title']}", "",
        "Generated by benchmarks/table1.py from table1.json beside it; nothing here is edited "
        "by hand. Why the modes are fused as they are: docs/table1.md.", "",
        f"- code: commit {doc['commit']}; runs of {doc['date']}; machine: {m['arch']}, "
        f"{m['cpu']}, {m['cores']} cores, PyTorch {m['torch']}",
        "- commands (WORK: a folder outside the repository):", "",
        *[f"      {c[k]}" for k in ("scenes", "benchmark", "fusion", "table") if k in c], "",
        *_setup_lines(doc), "",
        *_table(doc), "",
        "## What issue 28 checks", "",
        *_checks(doc), "",
        "## How each mode's points are fused", "",
        _shared(doc), "",
        *_rules(doc), "",
        "What each difference does to the points' Chamfer (mm, as run -> changed; a copy of "
        "each run fused again with one change, benchmarks/fusion_differences.py; accuracy and "
        "completeness are means):", "",
        *_effects(doc), "",
        "## Which scenes were held out from which choice", "",
        *_tuning(doc), "",
    ]
    return "\n".join(lines)


def write_atomic(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--bench", type=Path, help="a svolsdf benchmark folder")
    src.add_argument("--from-json", type=Path, help="a table1.json this script wrote")
    ap.add_argument("--fusion", type=Path, help="fusion_differences.json of the same folder")
    ap.add_argument("--results", type=Path, required=True, help="the Markdown file to write")
    a = ap.parse_args()
    if a.from_json is not None:
        doc = json.loads(a.from_json.read_text())
    else:
        doc = build(a.bench, a.fusion, sys.argv[1:])
        write_atomic(a.results.with_suffix(".json"),
                     json.dumps(doc, indent=1, allow_nan=False) + "\n")
    text = render(doc)
    write_atomic(a.results, text)
    print(text)


if __name__ == "__main__":
    main()
