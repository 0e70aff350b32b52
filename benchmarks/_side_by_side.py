"""Side-by-side mode of benchmarks/fast_preset.py (issue 39): the fast preset of this checkout
("new") against a baseline commit ("old") in one run on the same machine.

The baseline is checked out as a detached git worktree (OUT/baseline_src); each side runs
`python -m svolsdf reconstruct` in fresh processes with its own ``PYTHONPATH=<checkout>/src`` and
the same arguments, old then new, scene after scene. Everything is scored here, by this checkout's
code, the same way for both sides:

- synthetic scenes (`svolsdf synth`: gt_points.ply, gt_depth/): points and mesh (by its
  surface, `svolsdf.evaluate.chamfer.mesh_surface_points`) against the ground truth the input
  views observe (`svolsdf.evaluate.synthetic.synthetic_chamfer`, as the rest of fast_preset.py
  scores; results written before meshes were scored by their surface scored its vertices);
- DTU scans with ``--pgt NAME=DIR``: against the many-view pseudo ground truth of
  benchmarks/dtu_pseudo_gt.py, as benchmarks/mesh_study.py scores them (its `Scorer`: the mesh
  by its surface too);
- held-out views (the first ``--held-out-views`` test views of OUT/views.json, none of them an
  input): `svolsdf render` (volume rendering) at ``--held-out-scale`` x the working size by each
  side's code, then masked PSNR and SSIM against the scene's images (`svolsdf.evaluate.images`).

Run folders are OUT/old/<scene> and OUT/new/<scene> (OUT/<side>/<scene>_<N>views for the many-view
run); OUT/<side>/<scene>/bench.json records the commit and the process wall time. A rerun reuses a
finished run of the same commit, resumes an unfinished one (`svolsdf reconstruct` resumes) and
starts over a run of another commit. The wall time compared is the sum of the stages' recorded
times (timing.json), so a resumed run still reports its full cost; the reconstruct process's own
wall time (imports and loading included) is reported beside it when the run was not resumed.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent


# -------------------------------------------------------------------------------------------------
# the two checkouts


def _git(*args: str, cwd: Path = REPO) -> str:
    return subprocess.run(["git", "-C", str(cwd), *args], check=True, capture_output=True,
                          text=True).stdout.strip()


def commit_info(rev: str, cwd: Path = REPO) -> dict:
    sha = _git("rev-parse", f"{rev}^{{commit}}", cwd=cwd)
    subject = _git("log", "-1", "--format=%s", sha, cwd=cwd)
    return {"sha": sha, "short": sha[:9],
            "subject": subject if len(subject) <= 100 else subject[:97].rsplit(" ", 1)[0] + " ...",
            "date": _git("log", "-1", "--format=%cI", sha, cwd=cwd)}


def new_side() -> dict:
    """This checkout: its HEAD, marked "+ uncommitted changes" when tracked files differ."""
    info = commit_info("HEAD")
    dirty = bool(_git("status", "--porcelain", "--untracked-files=no"))
    info["dirty"] = dirty
    info["id"] = info["sha"] + ("-dirty" if dirty else "")
    info["src"] = str(REPO / "src")
    return info


def old_side(rev: str, out: Path) -> dict:
    """The baseline ``rev`` as a detached worktree at OUT/baseline_src (made once, reused)."""
    info = commit_info(rev)
    wt = out / "baseline_src"
    if wt.exists():
        have = _git("rev-parse", "HEAD", cwd=wt)
        if have != info["sha"]:
            sys.exit(f"{wt} holds commit {have[:9]}, not {rev} ({info['short']}): use another "
                     f"--out, or remove it (git worktree remove {wt})")
    else:
        out.mkdir(parents=True, exist_ok=True)
        # --force: also when a folder of that name was registered and then removed by hand
        _git("worktree", "add", "--force", "--detach", str(wt), info["sha"])
    info["dirty"] = False
    info["id"] = info["sha"]
    info["src"] = str(wt / "src")
    return info


def _env(side: dict) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = side["src"]
    return env


def check_import(side: dict) -> None:
    """The side's subprocesses import svolsdf from its own checkout (not an installed copy)."""
    f = subprocess.run([sys.executable, "-c", "import svolsdf; print(svolsdf.__file__)"],
                       check=True, capture_output=True, text=True, env=_env(side),
                       cwd=REPO).stdout.strip()
    if not Path(f).resolve().is_relative_to(Path(side["src"]).resolve()):
        sys.exit(f"PYTHONPATH={side['src']} imports svolsdf from {f}")


# -------------------------------------------------------------------------------------------------
# runs


def _stage_sum(timing: dict) -> float:
    return sum(v["seconds"] for k, v in timing.items() if k != "total")


def reconstruct(side: dict, scene: Path, out: Path, args: list[str]) -> dict:
    """`svolsdf reconstruct SCENE -o OUT ARGS` with the side's code, unless OUT holds a finished
    run of the same commit and arguments. Returns OUT/bench.json's record."""
    rec_f = out / "bench.json"
    rec = json.loads(rec_f.read_text()) if rec_f.is_file() else None
    if rec is not None and (rec.get("commit") != side["id"] or rec.get("args") != args):
        print(f"{out}: made by {rec.get('commit', '?')[:9]} with {rec.get('args')}; starting over",
              flush=True)
        shutil.rmtree(out)
        rec = None
    elif rec is None and out.exists():
        shutil.rmtree(out)  # no record: not ours, or killed before the record was written
    if rec is not None and rec.get("done"):
        return rec
    resumed = rec is not None
    rec = {"commit": side["id"], "args": args, "done": False, "resumed": resumed}
    out.mkdir(parents=True, exist_ok=True)
    rec_f.write_text(json.dumps(rec, indent=1))
    cmd = [sys.executable, "-m", "svolsdf", "reconstruct", str(scene), "-o", str(out),
           "--no-progress", *args]
    print(f"$ PYTHONPATH={side['src']}", " ".join(cmd), flush=True)
    t0 = time.perf_counter()
    p = subprocess.run(cmd, env=_env(side), cwd=REPO)
    rec["process_s"] = round(time.perf_counter() - t0, 2)
    if p.returncode != 0:
        rec["error"] = f"svolsdf reconstruct exited with {p.returncode}"
        print(rec["error"], flush=True)
    else:
        rec["done"] = True
    rec_f.write_text(json.dumps(rec, indent=1))
    return rec


def render_held_out(side: dict, out: Path, views: list[int], size: tuple[int, int]) -> dict:
    """Volume renderings of ``views`` at ``size`` by the side's code (reused when present)."""
    from PIL import Image

    def done() -> bool:
        for v in views:
            f = out / "renders" / f"{v}.png"
            if not f.is_file():
                return False
            with Image.open(f) as im:
                if im.size != size:
                    return False
        return True

    rec_f = out / "bench_render.json"
    if done() and rec_f.is_file():
        return json.loads(rec_f.read_text())
    cmd = [sys.executable, "-m", "svolsdf", "render", str(out), "--views", *map(str, views),
           "--size", f"{size[0]}x{size[1]}"]
    print(f"$ PYTHONPATH={side['src']}", " ".join(cmd), flush=True)
    t0 = time.perf_counter()
    p = subprocess.run(cmd, env=_env(side), cwd=REPO)
    rec = {"seconds": round(time.perf_counter() - t0, 2)}
    if p.returncode != 0 or not done():
        rec["error"] = f"svolsdf render exited with {p.returncode}"
        return rec
    rec_f.write_text(json.dumps(rec))
    return rec


# -------------------------------------------------------------------------------------------------
# scores (this checkout's code for both sides)


class SceneScorer:
    """Points, mesh and held-out images of the runs of one scene and one set of input views."""

    def __init__(self, scene: Path, inputs: list[int], size: tuple[int, int],
                 pgt: Path | None):
        from svolsdf.evaluate.synthetic import is_synthetic_scene

        self.scene, self.inputs = scene, inputs
        self.synthetic = is_synthetic_scene(scene)
        self.dtu = None
        if self.synthetic:
            self.protocol = "synthetic ground truth the input views observe"
        elif pgt is not None:
            sys.path.insert(0, str(BENCH))
            from mesh_study import Scorer

            # the attributes of a loaded run that mesh_study's Scorer reads
            run = SimpleNamespace(cfg=SimpleNamespace(scene=SimpleNamespace(path=str(scene))),
                                  views=inputs,
                                  load=lambda: SimpleNamespace(width=size[0], height=size[1]))
            self.dtu = Scorer(run, pgt)
            self.protocol = "pseudo ground truth (benchmarks/dtu_pseudo_gt.py, mesh_study.py)"
        else:
            self.protocol = None

    def geometry(self, out: Path) -> dict:
        from svolsdf.io.ply import read_ply

        res: dict = {}
        if self.protocol is None:
            return res
        for key in ("points", "mesh"):
            f = out / f"{key}.ply"
            if not f.is_file():
                continue
            d = read_ply(f)
            if self.synthetic:  # a mesh by its surface, as fast_preset.py and evaluate score
                from svolsdf.evaluate.synthetic import synthetic_chamfer

                r = synthetic_chamfer(d["points"], self.scene, self.inputs, on_empty="clip",
                                      faces=d["faces"] if key == "mesh" else None)
                res[key] = {k: r[k] for k in ("accuracy", "completeness", "overall",
                                              "overall_dtu_rule", "fscore")}
            elif key == "points":
                res[key] = self.dtu.points(d["points"])
            elif d.get("faces") is not None and len(d["faces"]):
                res[key] = self.dtu.mesh(d["points"], d["faces"])
        return res

    def images(self, out: Path, views: list[int]) -> dict:
        """Masked PSNR and SSIM of OUT/renders/<view>.png (docs/method.md 8.3)."""
        import numpy as np

        from svolsdf.evaluate.images import masked_psnr, ssim
        from svolsdf.io.images import read_image
        from svolsdf.scene.loaders import load_scene

        preds = {v: read_image(out / "renders" / f"{v}.png") for v in views}
        h, w = next(iter(preds.values())).shape[-2:]
        sc = load_scene(self.scene, views=views, image_size=(w, h))
        per = {}
        for i, v in enumerate(views):
            m = sc.masks[i] if sc.masks is not None else None
            per[str(v)] = {"psnr": float(masked_psnr(preds[v], sc.images[i], m)),
                           "ssim": float(ssim(preds[v], sc.images[i], m))}
        return {"per_view": per, "masked": sc.masks is not None,
                **{k: float(np.mean([p[k] for p in per.values()])) for k in ("psnr", "ssim")}}


# -------------------------------------------------------------------------------------------------
# the benchmark


def _views_json(out: Path) -> dict:
    f = out / "views.json"
    return json.loads(f.read_text()) if f.is_file() else {}


def _summary(out: Path, rec: dict) -> dict:
    t_f = out / "timing.json"
    timing = json.loads(t_f.read_text()) if t_f.is_file() else {}
    return {"dir": str(out), "commit": rec.get("commit"), "error": rec.get("error"),
            "resumed": rec.get("resumed", False),
            "process_s": None if rec.get("resumed") else rec.get("process_s"),
            "wall_s": _stage_sum(timing) if timing else None,
            "peak_gb": max((v.get("peak_memory_gb", 0) for v in timing.values()), default=None),
            "stages": {k: v["seconds"] for k, v in timing.items() if k != "total"},
            "inputs": _views_json(out).get("inputs")}


def _run_dir(sides: dict, name: str, tag: str) -> Path:
    """OUT/<side folder>/<tag>: OUT/old, OUT/new, or OUT/new-<preset> with --new-preset."""
    return sides["out"] / sides[name].get("folder", name) / tag


def run_scene(sides: dict, scene: Path, tag: str, args: list[str], pgt: Path | None,
              n_held_out: int, scale: float, which=("old", "new")) -> dict:
    """Reconstruct (old, then new), render the held-out views and score one scene."""
    runs = {}
    for name in which:
        out = _run_dir(sides, name, tag)
        rec = reconstruct(sides[name], scene, out, [*args, *sides[name].get("extra", [])])
        runs[name] = _summary(out, rec)
    done = [n for n in which if runs[n]["error"] is None and runs[n]["inputs"]]
    if not done:
        return {"scene": scene.name, "tag": tag, "runs": runs}
    ref = _run_dir(sides, done[-1], tag)  # the new side's views when it finished
    vj = _views_json(ref)
    inputs = vj["inputs"]
    w, h = vj.get("size") or _working_size(scene)
    held = [v for v in vj.get("test", []) if v not in inputs][:n_held_out]
    rsize = (max(8, round(w * scale)), max(8, round(h * scale)))
    scorer = SceneScorer(scene, inputs, (w, h), pgt)
    for name in done:
        out = _run_dir(sides, name, tag)
        r = runs[name]
        if r["inputs"] != inputs:
            r["error"] = f"input views {r['inputs']} differ from {inputs}"
            continue
        t0 = time.perf_counter()
        r.update(scorer.geometry(out))
        r["score_s"] = round(time.perf_counter() - t0, 1)
        if held:
            rr = render_held_out(sides[name], out, held, rsize)
            r["render"] = rr
            if "error" not in rr:
                r["images"] = scorer.images(out, held)
    return {"scene": scene.name, "tag": tag, "kind": "synthetic" if scorer.synthetic else "DTU",
            "protocol": scorer.protocol, "inputs": inputs, "size": [w, h],
            "held_out": held, "render_size": list(rsize), "runs": runs}


def _working_size(scene: Path) -> tuple[int, int]:
    from svolsdf.scene.loaders import load_scene

    sc = load_scene(scene, load_images=False)
    w = min(768, sc.width)
    return w, round(sc.height * w / sc.width)


def all_views(scene: Path, n: int) -> list[str]:
    """``--views`` for an ``n``-view run: the scene's ids when it has exactly n, else auto n."""
    from svolsdf.scene.loaders import load_scene

    ids = load_scene(scene, load_images=False).view_ids
    return [str(v) for v in ids] if len(ids) == n else ["auto", str(n)]


# -------------------------------------------------------------------------------------------------
# the results file


def _f(x, nd=2) -> str:
    return "-" if x is None else (f"{x:.{nd}f}" if isinstance(x, float) else str(x))


def _rel(new, old) -> float | None:
    return None if new is None or not old else 100.0 * (new / old - 1.0)


def _pct(x) -> str:
    return "-" if x is None else f"{x:+.1f} %"


def _get(r: dict, key: str, what: str = "overall"):
    return (r.get(key) or {}).get(what)


def public_path(p: str | Path, out: Path) -> str:
    """A path as the results print it: relative to the repository when it is beside it, OUT/...
    inside OUT, else DATA/<name> (no machine path in a committed file)."""
    p = Path(p).resolve()
    if p.is_relative_to(out.resolve()):
        return str(Path("OUT") / p.relative_to(out.resolve()))
    if p.is_relative_to(REPO) or p.is_relative_to(REPO.parent / "shared"):
        return os.path.relpath(p, REPO)
    return f"DATA/{p.name}"


def public_command(argv: list[str], out: Path) -> str:
    """The command line with `public_path`'s paths (also in NAME=PATH)."""
    def one(a: str) -> str:
        name, eq, rest = a.partition("=")
        if eq and rest.startswith("/") and not name.startswith("-"):
            return f"{name}={public_path(rest, out)}"
        return public_path(a, out) if a.startswith("/") else a

    return " ".join(one(a) for a in argv)


def report(meta: dict, scenes: list[dict], many: list[dict], targets: dict) -> str:
    old, new = meta["old"], meta["new"]
    title = (f"# Fast preset, side by side: {new['short']} against {old['short']} (issue 39)"
             if not new.get("preset") else
             f"# {new['preset'].capitalize()} preset of {new['short']} against the fast preset "
             f"of {old['short']}, side by side (issue 39)")
    L = [title, "",
         f"- machine: nproc = {meta['nproc']}, CPU: {meta['cpu']}; load average at the start "
         f"{meta['load_start']}, at the end {meta.get('load_end', '-')} (a shared machine: other "
         "jobs may have been running; compare the ratio, not the seconds)",
         f"- date: {meta['date']} (UTC)",
         f"- command: `python benchmarks/fast_preset.py {meta['command']}`",
         f"- old: {old['short']} ({old['date'][:10]}) {old['subject']}",
         f"- new: {new['short']} ({new['date'][:10]}) {new['subject']}"
         + (" + uncommitted changes" if new.get("dirty") else "")
         + (f"; the new side runs `--preset {new['preset']}`" if new.get("preset") else ""),
         "- each scene: old, then new, each a fresh `svolsdf reconstruct SCENE -o OUT "
         f"--no-progress{' ' + ' '.join(meta['args']) if meta['args'] else ''}` "
         "with its own checkout's code (fast preset); wall = the sum of the stages' times "
         "(timing.json); process = the reconstruct process's wall time (imports and loading "
         "included; - when resumed from a cache); peak = the largest stage peak resident memory "
         "(timing.json)",
         _protocol_line(meta),
         f"- held-out PSNR: volume rendering (`svolsdf render`, each side's code) of the first "
         f"{meta['held_out_views']} test views (never inputs) at {meta['held_out_scale']:g} x "
         "the working size, masked PSNR against the scene's images at that size "
         "(svolsdf.evaluate.images)", ""]
    L += ["## Summary", "",
          "| scene | views | old wall (s) | new wall (s) | new/old | old peak (GB) | "
          "new peak (GB) | points Chamfer old | new | change | mesh Chamfer old | new | "
          "change | PSNR old (dB) | new | difference |",
          "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    ratios, chamfer_changes, psnr_diffs, peaks3 = [], [], [], []
    for s in scenes + many:
        o, n = s["runs"].get("old", {}), s["runs"].get("new", {})
        ratio = (n["wall_s"] / o["wall_s"] if o.get("wall_s") and n.get("wall_s") else None)
        pc = [_rel(_get(n, k), _get(o, k)) for k in ("points", "mesh")]
        po, pn = _get(o, "images", "psnr"), _get(n, "images", "psnr")
        dpsnr = None if po is None or pn is None else pn - po
        nv = len(s.get("inputs") or [])
        if s in scenes:
            if ratio is not None:
                ratios.append((ratio, s["tag"]))
            chamfer_changes += [(c, f"{s['tag']} {k}")
                                for c, k in zip(pc, ("points", "mesh"), strict=True)
                                if c is not None]
            if dpsnr is not None:
                psnr_diffs.append((dpsnr, s["tag"]))
            if n.get("peak_gb") is not None:
                peaks3.append((n["peak_gb"], s["tag"]))
        L.append(f"| {s['tag']} | {nv} | {_f(o.get('wall_s'), 0)} | {_f(n.get('wall_s'), 0)} | "
                 f"{_f(ratio)} | {_f(o.get('peak_gb'))} | {_f(n.get('peak_gb'))} | "
                 f"{_f(_get(o, 'points'))} | {_f(_get(n, 'points'))} | {_pct(pc[0])} | "
                 f"{_f(_get(o, 'mesh'))} | {_f(_get(n, 'mesh'))} | {_pct(pc[1])} | "
                 f"{_f(po)} | {_f(pn)} | {_f(dpsnr)} |")
    L.append("")

    def verdict(ok: bool | None) -> str:
        return "-" if ok is None else ("PASS" if ok else "FAIL")

    if ratios:
        mean = sum(r for r, _ in ratios) / len(ratios)
        worst = max(ratios)
        o_sum = sum(s["runs"]["old"]["wall_s"] for s in scenes
                    if s["runs"].get("old", {}).get("wall_s") and
                    s["runs"].get("new", {}).get("wall_s"))
        n_sum = sum(s["runs"]["new"]["wall_s"] for s in scenes
                    if s["runs"].get("old", {}).get("wall_s") and
                    s["runs"].get("new", {}).get("wall_s"))
        L.append(f"- wall new/old, three views: mean {mean:.2f} over {len(ratios)} scene(s), "
                 f"worst {worst[0]:.2f} ({worst[1]}), summed walls {n_sum / o_sum:.2f} (target "
                 f"<= {targets['ratio']}): {verdict(mean <= targets['ratio'])}")
    for s in many:
        n = s["runs"].get("new", {})
        w, pk = n.get("wall_s"), n.get("peak_gb")
        L.append(f"- {len(s.get('inputs') or [])} views ({s['tag']}): new wall {_f(w, 0)} s "
                 f"(target <= {targets['many_s']:g} s): "
                 f"{verdict(None if w is None else w <= targets['many_s'])}; peak {_f(pk)} GB "
                 f"(target <= {targets['many_gb']:g} GB): "
                 f"{verdict(None if pk is None else pk <= targets['many_gb'])}")
    if chamfer_changes:
        worst = max(chamfer_changes)
        L.append(f"- Chamfer, each scene's points and mesh: worst change {worst[0]:+.1f} % "
                 f"({worst[1]}) (target <= +{targets['chamfer_pct']:g} %): "
                 f"{verdict(worst[0] <= targets['chamfer_pct'])}")
    if psnr_diffs:
        worst = min(psnr_diffs)
        L.append(f"- held-out PSNR: worst difference {worst[0]:+.2f} dB ({worst[1]}) (target >= "
                 f"-{targets['psnr_db']:g} dB): {verdict(worst[0] >= -targets['psnr_db'])}")
    if peaks3:
        worst = max(peaks3)
        L.append(f"- peak memory, three views: new at most {worst[0]:.2f} GB ({worst[1]}) "
                 f"(target <= {targets['three_gb']:g} GB): "
                 f"{verdict(worst[0] <= targets['three_gb'])}")
    for s in scenes + many:
        L += ["", f"## {s['tag']}" + (f" ({s['kind']}, views {' '.join(map(str, s['inputs']))}, "
                                      f"{s['size'][0]}x{s['size'][1]})" if s.get("inputs")
                                      else ""), ""]
        runs = s["runs"]
        names = [n for n in ("old", "new") if n in runs]
        stages: list[str] = []
        for n in names:
            stages += [k for k in runs[n]["stages"] if k not in stages]
        both = len(names) == 2
        L += ["| | " + " | ".join(names) + (" | new/old |" if both else " |"),
              "|---|" + "---:|" * (len(names) + both)]

        def row(label: str, vals: list, ratio: str | None = None, nd: int = 1,
                both: bool = both) -> str:
            return (f"| {label} | " + " | ".join(_f(v, nd) for v in vals)
                    + (f" | {ratio or '-'} |" if both else " |"))

        def rat(vals: list, both: bool = both) -> str | None:
            return f"{vals[1] / vals[0]:.2f}" if both and vals[0] and vals[1] is not None \
                else None

        for st in stages:
            vals = [runs[n]["stages"].get(st) for n in names]
            L.append(row(f"{st} (s)", vals, rat(vals)))
        for label, key, nd in (("wall: sum of the stages (s)", "wall_s", 1),
                               ("process wall (s)", "process_s", 1),
                               ("peak memory (GB)", "peak_gb", 2)):
            vals = [runs[n].get(key) for n in names]
            L.append(row(label, vals, rat(vals), nd))
        for key in ("points", "mesh"):
            for what in ("accuracy", "completeness", "overall"):
                vals = [_get(runs[n], key, what) for n in names]
                ch = _pct(_rel(vals[1], vals[0])) if both else None
                L.append(row(f"{key} {'Chamfer' if what == 'overall' else what}", vals, ch, 3))
        if s.get("held_out"):
            for what, nd in (("psnr", 2), ("ssim", 3)):
                vals = [_get(runs[n], "images", what) for n in names]
                d = (f"{vals[1] - vals[0]:+.{nd}f}" if both and None not in vals else None)
                L.append(row(f"held-out {what.upper()} (views "
                             f"{' '.join(map(str, s['held_out']))}, "
                             f"{s['render_size'][0]}x{s['render_size'][1]})", vals, d, nd))
        for n in names:
            notes = [runs[n].get("error"), (runs[n].get("render") or {}).get("error")]
            if any(notes):
                L.append(f"\n- {n}: " + "; ".join(x for x in notes if x))
    L += computed_notes(meta, scenes, many, targets)
    return "\n".join(L) + "\n"


def _protocol_line(meta: dict) -> str:
    """How the Chamfer was scored. Results written before meshes were scored by their surface
    (no ``mesh_scored`` in their meta) scored a synthetic scene's mesh by its vertices."""
    if meta.get("mesh_scored") == "surface":
        return ("- Chamfer (acc + comp) / 2 in the scene's units, scored for both by the new "
                "checkout: synthetic scenes against the ground truth the input views observe, DTU "
                "against the many-view pseudo ground truth (benchmarks/dtu_pseudo_gt.py, scored "
                "as benchmarks/mesh_study.py); a mesh by its surface, sampled at 0.1 % of the "
                "ground truth's diagonal (svolsdf.evaluate.chamfer.mesh_density), not by its "
                "vertices")
    return ("- Chamfer (acc + comp) / 2 in the scene's units, scored for both by the new "
            "checkout: synthetic scenes against the ground truth the input views observe (mesh by "
            "its vertices), DTU against the many-view pseudo ground truth "
            "(benchmarks/dtu_pseudo_gt.py, scored as benchmarks/mesh_study.py: mesh sampled on "
            "its surface)")


# -------------------------------------------------------------------------------------------------
# the notes: computed from the same data as the tables (no hand-written notes in a results file;
# the reasoning about them belongs in docs/, e.g. docs/presets.md)


def _span(vals: list[float], fmt: str, unit: str = "") -> str:
    """"a-b" (or "a" when they round alike) for unsigned values, "a to b" for signed ones."""
    lo, hi = fmt.format(min(vals)), fmt.format(max(vals))
    if lo == hi:
        return lo + unit
    return f"{lo}{' to ' if '+' in fmt else '-'}{hi}{unit}"


def _by_kind(scenes: list[dict], value) -> list[tuple[str, list[float], list[str]]]:
    """[(kind, values, tags)] of ``value(scene)`` (None skipped) per scene kind, in the order the
    kinds first appear."""
    out: dict[str, tuple[list, list]] = {}
    for s in scenes:
        v = value(s)
        if v is not None:
            vals, tags = out.setdefault(s.get("kind") or "other", ([], []))
            vals.append(v)
            tags.append(s["tag"])
    return [(k, v, t) for k, (v, t) in out.items()]


def _per_kind(scenes: list[dict], value, fmt: str, unit: str = "") -> str:
    """The span over all scenes, then per kind: "x to y % over the 6 scenes (synthetic x to z %;
    dtu_scan65 y %)" (a kind of one scene is named by the scene)."""
    groups = _by_kind(scenes, value)
    every = [v for _, vals, _ in groups for v in vals]
    if not every:
        return "-"
    parts = [f"{kind} {_span(vals, fmt, unit)}" if len(vals) > 1 else
             f"{tags[0]} {fmt.format(vals[0])}{unit}" for kind, vals, tags in groups]
    n = len(every)
    return (f"{_span(every, fmt, unit)} over the {n} scene{'s' if n > 1 else ''}"
            + (f" ({'; '.join(parts)})" if len(groups) > 1 else ""))


def computed_notes(meta: dict, scenes: list[dict], many: list[dict], targets: dict) -> list[str]:
    """The "Notes" section: ranges, counts and shares over the scenes, computed from the data."""
    def run(s, side):
        return s["runs"].get(side) or {}

    def ratio(a, b):
        return a / b if a is not None and b else None

    def wall_ratio(s):
        return ratio(run(s, "new").get("wall_s"), run(s, "old").get("wall_s"))

    def change(key):
        return lambda s: _rel(_get(run(s, "new"), key), _get(run(s, "old"), key))

    def psnr_diff(s):
        o, n = _get(run(s, "old"), "images", "psnr"), _get(run(s, "new"), "images", "psnr")
        return None if o is None or n is None else n - o

    both = [s for s in scenes if wall_ratio(s) is not None]
    if not both and not many:
        return []
    L = ["", "## Notes (computed from the JSON beside this file)", ""]
    if both:
        rs = [wall_ratio(s) for s in both]
        met = [s for s in both if wall_ratio(s) <= targets["ratio"]]
        missed = [s for s in both if wall_ratio(s) > targets["ratio"]]

        def listed(group):
            return ", ".join(f"{s['tag']} {wall_ratio(s):.2f}" for s in group)

        walls = {side: _span([run(s, side)["wall_s"] for s in both], "{:.0f}", " s")
                 for side in ("old", "new")}
        L.append(f"- Three-view wall new/old: {_span(rs, '{:.2f}')} (mean "
                 f"{sum(rs) / len(rs):.2f}); new wall {walls['new']}, old {walls['old']}. The "
                 f"target (<= {targets['ratio']}) is met on {len(met)} of {len(both)} scenes"
                 + (f" ({listed(met)})" if met else "")
                 + (f" and missed on {len(missed)} ({listed(missed)})" if missed else "") + ".")
        stages: list[str] = []
        for s in both:
            for side in ("old", "new"):
                stages += [k for k in run(s, side).get("stages", {}) if k not in stages]
        L += ["- Stage times new/old, per stage (range over the scenes of each kind):", "",
              "| stage | " + " | ".join(k for k, _, _ in _by_kind(both, lambda s: 1.0)) + " |",
              "|---|" + "---:|" * len(_by_kind(both, lambda s: 1.0))]
        for st in stages:
            def st_ratio(s, st=st):
                return ratio(run(s, "new").get("stages", {}).get(st),
                             run(s, "old").get("stages", {}).get(st))
            cells = [_span(v, "{:.2f}") for _, v, _ in _by_kind(both, st_ratio)]
            L.append(f"| {st} | " + " | ".join(cells) + " |")
        L.append("")

        def field_share(s):
            st = run(s, "new").get("stages", {})
            return 100.0 * st["field"] / run(s, "new")["wall_s"] if "field" in st else None

        L.append(f"- The field's share of the new side's wall: "
                 f"{_per_kind(both, field_share, '{:.0f}', ' %')}.")
        for key in ("points", "mesh"):
            L.append(f"- {key.capitalize()} Chamfer, new against old: "
                     f"{_per_kind(both, change(key), '{:+.1f}', ' %')}.")
        L.append(f"- Held-out PSNR, new minus old: {_per_kind(both, psnr_diff, '{:+.2f}', ' dB')}.")
        for side in ("old", "new"):
            pk = [run(s, side).get("peak_gb") for s in both]
            pk = [x for x in pk if x is not None]
            if pk:
                L.append(f"- Peak memory, three views, {side}: {_span(pk, '{:.2f}', ' GB')}.")
    for s in many:
        n = run(s, "new")
        if n.get("wall_s") is None:
            continue
        st = n.get("stages", {})
        line = (f"- {len(s.get('inputs') or [])} views ({s['tag']}), new: wall {n['wall_s']:.0f} s "
                f"(" + ", ".join(f"{k} {v:.0f}" for k, v in st.items()) + " s), peak "
                f"{_f(n.get('peak_gb'))} GB")
        three = next((x for x in scenes if x["scene"] == s["scene"]), None)
        f3 = run(three, "new").get("stages", {}).get("field") if three else None
        if f3 and st.get("field"):
            line += (f"; its field stage {st['field'] / f3:.2f} x the {three['tag']} three-view "
                     f"run's ({f3:.0f} s)")
        L.append(line + ".")
    return L


def render(data: dict) -> str:
    """The results file of one side-by-side run, from its JSON (``--from-json``)."""
    return report(data["meta"], data["scenes"], data["many_views"], data["targets"])


def side_by_side(args, argv: list[str]) -> None:
    """The mode's main (fast_preset.py --against REV)."""
    sys.path.insert(0, str(REPO / "src"))  # score with this checkout's code
    import svolsdf

    if not Path(svolsdf.__file__).resolve().is_relative_to((REPO / "src").resolve()):
        sys.exit(f"svolsdf imported from {svolsdf.__file__}, not from {REPO / 'src'}")
    from _machine import cpu_name

    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    sides = {"old": old_side(args.against, out), "new": new_side(), "out": out}
    if args.new_preset:
        sides["new"].update(extra=["--preset", args.new_preset], folder=f"new-{args.new_preset}",
                            preset=args.new_preset)
    for n in ("old", "new"):
        check_import(sides[n])
    pgt: dict[str, Path] = {}
    for item in args.pgt:
        name, _, d = item.partition("=")
        d = Path(d).resolve()
        if d.is_file():  # mesh_study takes the folder and picks the file by the working size
            d = d.parent
        if not d.is_dir():
            sys.exit(f"--pgt {item}: no such folder")
        pgt[name] = d
    scenes = [p.resolve() for p in args.scenes]
    if args.dtu:
        scenes.append((REPO.parent / "shared/data/dtu_scan65").resolve())
    scenes += [p.resolve() for p in args.dtu_scenes]
    for sc in scenes + ([args.many_views.resolve()] if args.many_views else []):
        if not sc.is_dir():
            sys.exit(f"scene {sc} does not exist")
    run_args = [x for kv in args.set for x in ("--set", kv)]
    meta = {"old": sides["old"], "new": sides["new"], "nproc": os.cpu_count(),
            "cpu": cpu_name(), "load_start": " ".join(f"{x:.1f}" for x in os.getloadavg()),
            "date": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
            "command": public_command(argv, out), "args": run_args, "mesh_scored": "surface",
            "held_out_views": args.held_out_views, "held_out_scale": args.held_out_scale}
    meta["old"] = {k: v for k, v in sides["old"].items() if k != "src"}
    meta["new"] = {k: v for k, v in sides["new"].items() if k != "src"}
    targets = {"ratio": 0.45, "many_s": 360.0, "chamfer_pct": 3.0, "psnr_db": 0.2,
               "three_gb": 3.0, "many_gb": 5.0}
    done, many = [], []
    results = args.results.resolve()

    def write() -> None:
        meta["load_end"] = " ".join(f"{x:.1f}" for x in os.getloadavg())
        data = {"meta": meta, "targets": targets, "scenes": done, "many_views": many}
        public = _public(data, out)
        # the Markdown is rendered from the JSON as written, so --from-json reproduces it
        results.with_suffix(".json").write_text(json.dumps(public, indent=1))
        results.write_text(render(json.loads(json.dumps(public))))
        (out / "side_by_side.json").write_text(json.dumps(data, indent=1))

    for sc in scenes:
        done.append(run_scene(sides, sc, sc.name, run_args, pgt.get(sc.name),
                              args.held_out_views, args.held_out_scale))
        write()
    if args.many_views:
        sc = args.many_views.resolve()
        n = args.many_views_n
        which = ("old", "new") if args.many_views_old else ("new",)
        many.append(run_scene(sides, sc, f"{sc.name}_{n}views",
                              ["--views", *all_views(sc, n), *run_args], pgt.get(sc.name), 0,
                              args.held_out_scale, which))
        write()
    write()
    print(results.read_text())


def _public(x, out: Path):
    """``x`` with its absolute paths as `public_path` prints them."""
    if isinstance(x, dict):
        return {k: (None if k == "src" else _public(v, out)) for k, v in x.items()}
    if isinstance(x, list):
        return [_public(v, out) for v in x]
    if isinstance(x, str) and x.startswith("/"):
        return public_path(x, out)
    return x
