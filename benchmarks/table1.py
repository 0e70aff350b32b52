"""The paper's Table 1 from `svolsdf benchmark` folders: per scene and mode the points' and the
mesh's Chamfer, image metrics on held-out views by volume rendering and by IBR, time; then the
ratios issue 28 checks (S-VolSDF / VolSDF points Chamfer, mesh / points, IBR PSNR gain).

    python benchmarks/table1.py --bench OUT [OUT2 ...] [--poisson DIR] --results FILE.md

``--bench``: folders written by `svolsdf benchmark` (their ``benchmark.json`` rows).
``--poisson``: a folder of ``<scene>/metrics.json`` of the svolsdf runs with
``--set mesh.method=poisson`` (only the mesh stage rerun), scored by `svolsdf evaluate`;
its mesh becomes the "poisson mesh" column.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import cpu_name, write_results  # noqa: E402

from svolsdf.evaluate.benchmark_tables import method_label  # noqa: E402

MODES = ("mvs-only", "volsdf", "svolsdf")


def _f(x, d=2) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.{d}f}"


def _mean(xs) -> float | None:
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return sum(xs) / len(xs) if xs else None


def load_rows(benches: list[Path]) -> list[dict]:
    """The finished rows of the benchmark folders, each with its ``field`` kind (rows written
    before it was recorded: from the run's config.yaml, OUT/<scene>/<mode>/; None if gone)."""
    import yaml

    rows = []
    for b in benches:
        for r in json.loads((b / "benchmark.json").read_text()):
            if r.get("status") != "ok":
                continue
            if r.get("field") is None:
                cfg = b / r["scene"] / r["mode"] / "config.yaml"
                if cfg.is_file():
                    r["field"] = (yaml.safe_load(cfg.read_text()).get("field") or {}).get("kind")
            rows.append(r)
    return rows


def poisson_rows(folder: Path | None) -> dict[str, dict]:
    out = {}
    if folder is None:
        return out
    for m in sorted(folder.glob("*/metrics.json")):
        cm = json.loads(m.read_text()).get("chamfer_mesh") or {}
        out[m.parent.name] = {"mesh": cm.get("overall"), "mesh_dtu": cm.get("overall_dtu_rule"),
                              "sampled": cm.get("sampled")}
    return out


def mesh_scoring(rows: list[dict], poisson: dict[str, dict]) -> str:
    """The line saying how the mesh columns were scored: by the mesh's surface (`svolsdf
    evaluate` since meshes are scored that way), else which runs' meshes were scored by their
    vertices (metrics written before), so that the two are not mixed unsaid."""
    old = [f"{r['scene']} / {r['mode']}" for r in rows
           if r.get("mesh_overall") is not None and r.get("mesh_sampled") != "surface"]
    old += [f"{s} / Poisson" for s, pz in poisson.items()
            if pz.get("mesh") is not None and pz.get("sampled") != "surface"]
    line = ("- meshes scored by their surface, the triangles sampled at 0.1 % of the ground "
            "truth's diagonal (svolsdf.evaluate.chamfer.mesh_density), not by their vertices")
    if old:
        line += ("; except these, scored by their vertices (metrics written before), not "
                 "comparable with the rest: " + ", ".join(old))
    return line


def table(rows: list[dict], poisson: dict[str, dict]) -> tuple[list[str], dict]:
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    cell = {(r["scene"], r["mode"]): r for r in rows}
    head = ("| scene | method | points Chamfer | points, DTU rule | mesh (field) | mesh, DTU rule "
            "| mesh (Poisson) | mesh (Poisson), DTU rule | PSNR | SSIM | LPIPS | PSNR IBR | "
            "SSIM IBR | LPIPS IBR | time (min) |")
    lines = [head, "|---|---|" + "---:|" * 13]
    checks: dict[str, list] = {"sv_over_v": [], "sv_over_v_dtu": [], "fit_over_pts": [],
                               "poisson_over_pts": [], "poisson_over_pts_dtu": [],
                               "ibr_gain_vr": [], "ibr_gain_ibr": [], "volsdf_chamfer": []}
    for s in scenes:
        for m in MODES:
            r = cell.get((s, m))
            if r is None:
                continue
            pz = poisson.get(s, {}) if m == "svolsdf" else {}
            t = r.get("time_s")
            lines.append("| " + " | ".join([
                s, method_label(m, r.get("field")), _f(r.get("overall")),
                _f(r.get("overall_dtu_rule")),
                _f(r.get("mesh_overall")), _f(r.get("mesh_overall_dtu_rule")),
                _f(pz.get("mesh")), _f(pz.get("mesh_dtu")), _f(r.get("psnr")),
                _f(r.get("ssim"), 3), _f(r.get("lpips"), 3), _f(r.get("psnr_ibr")),
                _f(r.get("ssim_ibr"), 3), _f(r.get("lpips_ibr"), 3),
                _f(None if t is None else t / 60, 1)]) + " |")
        v, sv = cell.get((s, "volsdf")), cell.get((s, "svolsdf"))
        if v and sv and v.get("overall") and sv.get("overall"):
            checks["sv_over_v"].append(sv["overall"] / v["overall"])
            checks["sv_over_v_dtu"].append(_ratio(sv.get("overall_dtu_rule"),
                                                  v.get("overall_dtu_rule")))
            checks["volsdf_chamfer"].append(v["overall"])
            if sv.get("psnr_ibr") is not None:
                if v.get("psnr") is not None:
                    checks["ibr_gain_vr"].append(sv["psnr_ibr"] - v["psnr"])
                if v.get("psnr_ibr") is not None:
                    checks["ibr_gain_ibr"].append(sv["psnr_ibr"] - v["psnr_ibr"])
        if sv and sv.get("overall"):
            if sv.get("mesh_overall"):
                checks["fit_over_pts"].append(sv["mesh_overall"] / sv["overall"])
            pz = poisson.get(s)
            if pz and pz.get("mesh"):
                checks["poisson_over_pts"].append(pz["mesh"] / sv["overall"])
                checks["poisson_over_pts_dtu"].append(_ratio(pz.get("mesh_dtu"),
                                                             sv.get("overall_dtu_rule")))
    return lines, checks


def _ratio(a, b) -> float | None:
    return a / b if a is not None and b else None


def _span(xs, d=2) -> str:
    xs = [x for x in xs if x is not None]
    if not xs:
        return "-"
    return f"{_f(min(xs), d)}-{_f(max(xs), d)} (mean {_f(_mean(xs), d)}, {len(xs)} scenes)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bench", type=Path, nargs="+", required=True)
    ap.add_argument("--poisson", type=Path)
    ap.add_argument("--results", type=Path, required=True)
    a = ap.parse_args()
    rows = load_rows(a.bench)
    poisson = poisson_rows(a.poisson)
    lines, c = table(rows, poisson)
    volsdf = " / ".join(dict.fromkeys(method_label("volsdf", r.get("field")) for r in rows
                                      if r["mode"] == "volsdf")) or "not in these folders"
    text = [
        "# Table 1, reproduced: MVS only, VolSDF and S-VolSDF on held-out scenes", "",
        f"- machine: {platform.machine()}, CPU: {cpu_name()}",
        "- command: `python benchmarks/table1.py " + " ".join(sys.argv[1:]) + "`",
        "- Chamfer in the scene's units (synthetic: mm; the synthetic protocol of `svolsdf "
        "evaluate`: the ground truth the input views observe, distances clipped at 5 % of its "
        "diagonal; 'DTU rule': distances beyond that left out). Image metrics: masked PSNR, "
        "SSIM, LPIPS (VGG) on the held-out views; 'IBR': image-based rendering (docs/method.md 7).",
        mesh_scoring(rows, poisson), "", *lines, "",
        "## What issue 28 checks", "",
        f"- VolSDF is {volsdf}.",
        f"- VolSDF points Chamfer (target <= 4 mm): {_span(c['volsdf_chamfer'])}",
        f"- S-VolSDF / VolSDF points Chamfer (target <= 0.6): {_span(c['sv_over_v'])}; "
        f"DTU rule {_span(c['sv_over_v_dtu'])}",
        f"- mesh / points Chamfer, field mesh (fitted to the points): {_span(c['fit_over_pts'])}",
        f"- mesh / points Chamfer, Poisson mesh (target <= 1.15): "
        f"{_span(c['poisson_over_pts'])}; DTU rule {_span(c['poisson_over_pts_dtu'])}",
        f"- S-VolSDF IBR PSNR minus VolSDF's volume-rendered PSNR (target >= 2 dB): "
        f"{_span(c['ibr_gain_vr'])}; minus VolSDF's IBR PSNR: {_span(c['ibr_gain_ibr'])}",
        "",
    ]
    write_results(a.results, "\n".join(text))
    print("\n".join(text))


if __name__ == "__main__":
    main()
