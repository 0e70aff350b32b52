"""Plane-sweep speed: the box filter and the SGM aggregation against their previous versions.

The plane-sweep backbone (svolsdf.mvs.planesweep) spent most of its CPU time in two places:
``F.avg_pool2d`` inside the box filter (ZNCC windows and the guided filter; a third of stages 2-3)
and the Python loop of the SGM scanline passes (another third). Both were rewritten:

- box filter: shifted in-place adds along each axis divided by the window's pixel count, instead
  of ``F.avg_pool2d(..., count_include_pad=False)`` (the same mean, to float rounding);
- SGM: the passes over the same slices run as one batch (a reverse pass is a forward pass over
  the flipped slices with the opposite shift; predecessors are gathered from a buffer padded by a
  constant column, which keeps C where a pass has no predecessor), so 8 directions take W + H
  Python steps instead of 2 W + 6 H, and the edge-aware P2 is computed once per volume.

Issue 39 then took another pass at the same code without changing its arithmetic (the volumes
are bit-identical): the SGM step writes into its output buffer (no per-step copies; the minima
in place), the ZNCC moments and the box filter's first add reuse their buffers, two sources are
merged by a minimum instead of a sort, and `ProbabilityVolume.save` deflates only the arrays that
shrink.

``--against REV`` (default: the commit before issue 39's) loads that revision's
``svolsdf/mvs/planesweep.py`` and ``volume.py`` from git next to the current ones and times both
on ``--scene`` (stages 1, 2, 3 of each ``--views`` view, interleaved old/new, ``--repeats``
rounds), with the maximum differences of depth, probability and confidence, and the time and
size of each stage's volume file. ``--micro`` also times the box filter and SGM against their
versions before the rewrite above (random inputs at the MVS sizes of a 768x576 scene).

Run (from the repo root):

    python benchmarks/mvs_speed.py --scene SCENE [--views 0 1 2] [--against REV] [--micro]
        [--out benchmarks/results/mvs_speed.md]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from _machine import cpu_name, write_results

from svolsdf.mvs.planesweep import box_filter
from svolsdf.mvs.sgm import sgm_aggregate

REPO = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------- previous versions
def box_filter_pool(x: torch.Tensor, radius: int) -> torch.Tensor:
    """The previous box filter: separable ``avg_pool2d`` without the padded pixels."""
    k = 2 * radius + 1
    x = F.avg_pool2d(x, (1, k), stride=1, padding=(0, radius), count_include_pad=False)
    return F.avg_pool2d(x, (k, 1), stride=1, padding=(radius, 0), count_include_pad=False)


def _sgm_pass_loop(c, g, p1, p2, sigma, reverse, shift):
    """The previous SGM pass: one direction at a time, P2 recomputed at every step."""
    n, _, m = c.shape
    out = torch.empty_like(c)
    if shift == 0:
        tgt, src = slice(0, m), slice(0, m)
    elif shift > 0:
        tgt, src = slice(1, m), slice(0, m - 1)
    else:
        tgt, src = slice(0, m - 1), slice(1, m)
    order = range(n - 1, -1, -1) if reverse else range(n)
    prev = None
    for i in order:
        if prev is None:
            cur = c[i].clone()
        else:
            j = i + 1 if reverse else i - 1
            P = prev[:, src]
            mval = P.min(dim=0, keepdim=True).values
            pen2 = p1 + (p2 - p1) * torch.exp(-(g[i, tgt] - g[j, src]).abs() / sigma)
            best = torch.minimum(P, mval + pen2[None])
            best[1:] = torch.minimum(best[1:], P[:-1] + p1)
            best[:-1] = torch.minimum(best[:-1], P[1:] + p1)
            cur = c[i].clone()
            cur[:, tgt] += best - mval
        out[i] = cur
        prev = cur
    return out


def sgm_loop(cost, guide, p1, p2, sigma, directions=8):
    """The previous `sgm_aggregate`: 2 passes per path, one after the other."""
    total = torch.zeros_like(cost)
    paths = [(2, 0), (1, 0)] + ([(1, 1), (1, -1)] if directions == 8 else [])
    for dim, shift in paths:
        c = cost.movedim(dim, 0)
        g = guide.movedim(dim - 1, 0)
        for reverse in (False, True):
            total += _sgm_pass_loop(c, g, p1, p2, sigma, reverse,
                                    -shift if reverse else shift).movedim(0, dim)
    return total / len(paths) / 2


# ---------------------------------------------------------------------- timing
def _interleaved(fns: dict, repeats: int) -> dict[str, float]:
    """Median wall seconds of each callable, timed round-robin."""
    times = {k: [] for k in fns}
    for f in fns.values():  # warm-up
        f()
    for _ in range(repeats):
        for k, f in fns.items():
            t0 = time.perf_counter()
            f()
            times[k].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in times.items()}


def _module_at(rev: str, rel: str, name: str):
    """The module ``src/svolsdf/mvs/<rel>`` of git revision ``rev``, imported as ``name``."""
    import importlib.util

    text = subprocess.run(["git", "-C", str(REPO), "show", f"{rev}:src/svolsdf/mvs/{rel}"],
                          check=True, capture_output=True, text=True).stdout
    tmp = Path(tempfile.mkdtemp()) / rel
    tmp.write_text(text)
    spec = importlib.util.spec_from_file_location(name, tmp)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def _against(scene_path: Path, views: list[int], refs: list[int] | None, rev: str,
             repeats: int) -> list[str]:
    """Stages 1-3 of the current plane sweep and of revision ``rev``'s, interleaved, per
    reference view (``refs``, default all ``views``); and their volumes' files (save time, size)."""
    from svolsdf.mvs import backbone as bb_mod
    from svolsdf.mvs import planesweep as new_ps
    from svolsdf.mvs.volume import ProbabilityVolume
    from svolsdf.scene.loaders import load_scene

    registered = dict(bb_mod._REGISTERED)
    old_ps = _module_at(rev, "planesweep.py", "planesweep_previous")
    old_vol = _module_at(rev, "volume.py", "volume_previous")
    bb_mod._REGISTERED.clear()
    bb_mod._REGISTERED.update(registered)  # the old module registered its class over ours
    scene = load_scene(scene_path, views=views)
    refs = list(views if refs is None else refs)
    impls = {"old": old_ps.PlaneSweepBackbone(), "new": new_ps.PlaneSweepBackbone()}
    times = {k: {1: [], 2: [], 3: []} for k in impls}
    cpu = {k: {1: [], 2: [], 3: []} for k in impls}
    diffs = {k: [0.0, 0.0, 0.0, True] for k in (1, 2, 3)}
    save = {k: {"old": [], "new": [], "size_old": 0, "size_new": 0} for k in (1, 2, 3)}
    shapes = {}
    with torch.no_grad():
        for b in impls.values():  # the images at each stage's size, cached by the backbone
            for k in (1, 2, 3):
                b._stage_inputs(scene, k)
        for rep in range(repeats):
            for vid in refs:
                res = {}
                for name in (["old", "new"] if rep % 2 == 0 else ["new", "old"]):
                    res[name] = {}
                    for k in (1, 2, 3):
                        prev = {vid: res[name][k - 1]} if k > 1 else None
                        t0, c0 = time.perf_counter(), time.process_time()
                        res[name][k] = impls[name].stage(k, scene, ref_ids=[vid], prev=prev)[0]
                        times[name][k].append(time.perf_counter() - t0)
                        cpu[name][k].append(time.process_time() - c0)
                    print(rep, vid, name, {k: round(v[-1], 2) for k, v in times[name].items()},
                          flush=True)
                for k in (1, 2, 3):
                    a, b = res["old"][k], res["new"][k]
                    shapes[k] = tuple(a.prob.shape)
                    d = diffs[k]
                    d[0] = max(d[0], float((a.depth - b.depth).abs().max()))
                    d[1] = max(d[1], float((a.prob - b.prob).abs().max()))
                    d[2] = max(d[2], float((a.confidence - b.confidence).abs().max()))
                    d[3] = d[3] and all(torch.equal(getattr(a, f), getattr(b, f)) for f in
                                        ("depths", "prob", "depth", "confidence"))
                    if rep == 0:  # the volume files, both writers on the new volume
                        with tempfile.TemporaryDirectory() as tmp:
                            for name, cls in (("old", old_vol.ProbabilityVolume),
                                              ("new", ProbabilityVolume)):
                                v = cls(b.depths, b.prob, b.depth, b.confidence, b.cameras,
                                        b.view_id, b.stage, b.inverse_depth)
                                f = Path(tmp) / f"{name}.npz"
                                t0 = time.perf_counter()
                                v.save(f)
                                save[k][name].append(time.perf_counter() - t0)
                                save[k][f"size_{name}"] += f.stat().st_size
                            back = [ProbabilityVolume.load(Path(tmp) / f"{n}.npz")
                                    for n in ("old", "new")]
                            assert all(torch.equal(getattr(back[0], f), getattr(back[1], f))
                                       for f in ("depths", "prob", "depth", "confidence"))
    med = {n: {k: statistics.median(v) for k, v in t.items()} for n, t in times.items()}
    mcpu = {n: {k: statistics.median(v) for k, v in t.items()} for n, t in cpu.items()}
    lines = [
        f"## Stages 1-3 against revision {rev}, on `{scene_path.name}` (views {views}, "
        f"references {refs})", "",
        f"Per stage and reference view, median over {len(refs)} view(s) x {repeats} "
        "round(s), old and new interleaved in one process; the differences are the largest "
        "over the views (depth in world units).", "",
        "| stage | volume (D, H, W) | previous (s) | current (s) | speed-up | CPU-time speed-up "
        "| max abs diff depth / prob / confidence | bit-identical |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for k in (1, 2, 3):
        d = diffs[k]
        lines.append(f"| {k} | {shapes[k]} | {med['old'][k]:.1f} | {med['new'][k]:.1f} | "
                     f"{med['old'][k] / med['new'][k]:.2f}x | "
                     f"{mcpu['old'][k] / mcpu['new'][k]:.2f}x | {d[0]:.1e} / {d[1]:.1e} / "
                     f"{d[2]:.1e} | {'yes' if d[3] else 'no'} |")
    tot = {n: sum(m.values()) for n, m in med.items()}
    tcpu = {n: sum(m.values()) for n, m in mcpu.items()}
    lines += [f"| 1-3 | | {tot['old']:.1f} | {tot['new']:.1f} | {tot['old'] / tot['new']:.2f}x "
              f"| {tcpu['old'] / tcpu['new']:.2f}x | | |", "",
              "Volume files (`ProbabilityVolume.save`, the current volumes written by both "
              "writers, one round; sizes summed over the views; the arrays read back equal):", "",
              "| stage | previous save (s) | current save (s) | previous size (MB) | "
              "current size (MB) |", "|---|---|---|---|---|"]
    for k in (1, 2, 3):
        sv = save[k]
        lines.append(f"| {k} | {statistics.median(sv['old']):.2f} | "
                     f"{statistics.median(sv['new']):.2f} | {sv['size_old'] / 1e6:.0f} | "
                     f"{sv['size_new'] / 1e6:.0f} |")
    return lines


def _micro(repeats: int) -> list[str]:
    """The box filter and SGM against their versions before the first rewrite."""
    g = torch.Generator().manual_seed(0)
    lines = [
        "## Box filter (radius 2), against `avg_pool2d`", "",
        "| input (N, C, H, W) | avg_pool2d (ms) | current (ms) | speed-up | max abs diff |",
        "|---|---|---|---|---|",
    ]
    for shape in [(1, 24, 288, 384), (1, 24, 576, 768), (1, 8, 1152, 1536)]:
        x = torch.rand(*shape, generator=g)
        diff = float((box_filter(x, 2) - box_filter_pool(x, 2)).abs().max())
        t = _interleaved({"old": lambda x=x: box_filter_pool(x, 2),
                          "new": lambda x=x: box_filter(x, 2)}, repeats)
        lines.append(f"| {shape} | {1e3 * t['old']:.1f} | {1e3 * t['new']:.1f} | "
                     f"{t['old'] / t['new']:.1f}x | {diff:.1e} |")
        print(lines[-1], flush=True)
    lines += ["", "## SGM, 8 directions (P1 0.03, P2 2.0, sigma 0.04: the backbone's defaults), "
              "against one pass at a time", "",
              "| cost volume (D, H, W) | one pass at a time (s) | current (s) | speed-up "
              "| max abs diff | argmin differs |", "|---|---|---|---|---|---|"]
    for shape in [(192, 288, 384), (32, 576, 768), (8, 1152, 1536)]:
        c = 2 * torch.rand(*shape, generator=g)
        gd = torch.rand(*shape[1:], generator=g)
        a, b = sgm_aggregate(c, gd, 0.03, 2.0, 0.04, 8), sgm_loop(c, gd, 0.03, 2.0, 0.04, 8)
        diff = float((a - b).abs().max())
        flips = int((a.argmin(0) != b.argmin(0)).sum())
        t = _interleaved({"old": lambda c=c, gd=gd: sgm_loop(c, gd, 0.03, 2.0, 0.04, 8),
                          "new": lambda c=c, gd=gd: sgm_aggregate(c, gd, 0.03, 2.0, 0.04, 8)},
                         max(1, repeats // 2))
        lines.append(f"| {shape} | {t['old']:.2f} | {t['new']:.2f} | {t['old'] / t['new']:.1f}x "
                     f"| {diff:.1e} | {flips} of {shape[1] * shape[2]} |")
        print(lines[-1], flush=True)
    return lines


def _command(args) -> str:
    """The command line's arguments, the scene and output named without their folders."""
    parts = []
    if args.scene is not None:
        parts += ["--scene", args.scene.name, "--views", *map(str, args.views),
                  *(["--refs", *map(str, args.refs)] if args.refs else []),
                  "--against", args.against]
    parts += ["--repeats", str(args.repeats)]
    parts += ["--threads", str(args.threads)] if args.threads else []
    parts += ["--micro"] if args.micro else []
    return " ".join(parts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", type=Path, default=None,
                    help="time stages 1-3 on this scene against --against")
    ap.add_argument("--views", type=int, nargs="+", default=[0, 1, 2],
                    help="the scene's views to load")
    ap.add_argument("--refs", type=int, nargs="+", default=None,
                    help="reference views to time (default all --views)")
    ap.add_argument("--against", default="4ce07e5",
                    help="git revision whose planesweep.py and volume.py are the 'previous'")
    ap.add_argument("--micro", action="store_true",
                    help="also time the box filter and SGM against their first versions")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--threads", type=int, default=None,
                    help="torch threads (default torch's); 1 makes timings on a loaded shared "
                    "machine steadier")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks/results/mvs_speed.md")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True).stdout.strip()
    dirty = bool(subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "src"],
                                capture_output=True, text=True).stdout.strip())
    lines = [
        "# Plane-sweep speed: current against previous",
        "",
        f"- machine: {cpu_name()}, nproc = {os.cpu_count()}, torch threads = "
        f"{torch.get_num_threads()}, torch {torch.__version__}, Python "
        f"{platform.python_version()}; shared machine, old and new interleaved",
        f"- command: `python benchmarks/mvs_speed.py {_command(args)}`",
        f"- date: {time.strftime('%Y-%m-%d %H:%M', time.gmtime())} UTC; commit {commit}"
        + (" with uncommitted changes under src/" if dirty else ""),
        "",
    ]
    if args.scene is not None:
        lines += _against(args.scene, args.views, args.refs, args.against,
                          args.repeats) + [""]
    if args.micro:
        lines += _micro(args.repeats) + [""]
    write_results(args.out, "\n".join(lines))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
