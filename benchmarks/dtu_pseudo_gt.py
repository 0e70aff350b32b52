"""Geometry on a real DTU scan without its STL: score runs against a many-view pseudo ground truth.

The shared DTU scan (../shared/data/dtu_scan65, IDR layout) has 49 views and object masks but no
ground-truth geometry, so the fast preset's Chamfer target ((d) at most 0.75x the MVS backbone
alone, issue 5) could only be checked on synthetic scenes. This script builds an independent
reference from all the scan's views and scores three-view runs against it:

1. Depth of every view with the DTU-trained PatchmatchNet (../shared/weights/patchmatchnet; a
   different MVS method from the plane-sweep backbone the runs use), each view with its
   ``--sources`` nearest views (camera centres) as sources, at the working size.
2. Fusion: a pixel is kept when at least ``--min-views`` of its ``--fuse-neighbours`` nearest
   views agree (`svolsdf.fusion.filter.check_geometric_consistency`: 1 px, 1 %), inside the
   view's object mask; its depth is the mean of the agreeing depths. Two references: "object"
   (the masks as they are) and "object and rim" (dilated as the runs' fusion dilates them,
   12 px at the working size, METHOD.md 6.3: what the runs may fill, the table around the
   object included; DTU's own ground truth holds the scanned table too). Cached in OUT.
3. The reference is the part of that cloud the run's input views see: points within 0.5 % of
   the nearest pseudo-GT depth at their pixel (a 3x3 minimum of the splatted depth) in at least
   one input view.
4. Each run's points.ply (and mesh.ply, sampled) is scored as the synthetic benchmark scores
   (`svolsdf.evaluate.synthetic.synthetic_chamfer`): both clouds evened out by greedy radius
   downsampling at 0.1 % of the object reference's diagonal, distances clipped at 5 % of it
   ("clipped"; holes cost the cut-off) or left out beyond it ("DTU rule", METHOD.md 8.1), and
   the F-score at 0.5 %.

PatchmatchNet draws its initial depth samples at random (seeded per view here): two views rerun
unseeded differed by a median 0.06 / 0.17 mm, with 3 % / 27 % of their pixels (mostly
background) more than 1 mm apart; the fused reference keeps only what three views agree on.

The pseudo ground truth carries PatchmatchNet's own errors (and covers what 49 views see, not a
structured-light scan), so absolute numbers are not DTU numbers; ratios between runs scored
against the same reference are the point. Depth maps are cached in OUT (a rerun skips them).

Usage:
    python benchmarks/dtu_pseudo_gt.py --runs "(a) MVS alone=RUN_A" "(d) fast=RUN_D"
        [--scene ../shared/data/dtu_scan65] [--out /tmp/dtu_pseudo_gt]
        [--results benchmarks/results/dtu_pseudo_gt.md]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from _machine import cpu_name, peak_rss_gb

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def _nearest(centers: np.ndarray, i: int, k: int) -> list[int]:
    """Indices of the ``k`` camera centres nearest to centre ``i`` (itself excluded)."""
    d = np.linalg.norm(centers - centers[i], axis=1)
    d[i] = np.inf
    return [int(j) for j in np.argsort(d)[:k]]


def depth_maps(scene_dir: Path, out: Path, size: tuple[int, int], n_src: int) -> dict:
    """Step 1: view id -> (H, W) PatchmatchNet z-depth (cached as OUT/depth/<id>.npy)."""
    from svolsdf.mvs.backbone import get_backbone
    from svolsdf.mvs.cascade import run_cascade
    from svolsdf.mvs.run import mvs_depth_range
    from svolsdf.scene.loaders import load_scene

    probe = load_scene(scene_dir, load_images=False)
    ids = probe.view_ids
    centers = probe.cameras.centers.double().numpy()
    (out / "depth").mkdir(parents=True, exist_ok=True)
    backbone = None
    res = {}
    for i, ref in enumerate(ids):
        f = out / "depth" / f"{ref}.npy"
        if not f.is_file():
            backbone = backbone or get_backbone("patchmatchnet")
            t0 = time.perf_counter()
            views = [ref] + [ids[j] for j in _nearest(centers, i, n_src)]
            sc = load_scene(scene_dir, views=views, image_size=size)
            sc = replace(sc, depth_range=mvs_depth_range(sc, None))
            torch.manual_seed(ref)  # PatchmatchNet's initial depth samples are random
            vol = run_cascade(backbone, sc, ref_ids=[ref])
            depth = vol[max(vol)][0].depth.float().numpy()
            np.save(out / "depth" / f".{ref}.tmp.npy", depth)
            os.replace(out / "depth" / f".{ref}.tmp.npy", f)  # a killed run keeps whole files
            print(f"view {ref} (sources {views[1:]}): {time.perf_counter() - t0:.1f} s",
                  flush=True)
        res[ref] = torch.from_numpy(np.load(f))
    return res


def fuse(scene_dir: Path, depths: dict, size: tuple[int, int], k: int, min_views: int,
         dilation: int) -> np.ndarray:
    """Step 2: (N, 3) world points of the pixels ``min_views`` of their ``k`` nearest views
    confirm, inside the object masks dilated by ``dilation`` pixels (module docstring)."""
    from svolsdf.fusion.filter import (
        check_geometric_consistency,
        dilate_mask,
        mask_to_depth_resolution,
    )
    from svolsdf.scene.loaders import load_scene

    # not `fuse_depth_maps`: it checks every reference against all other views (49 x 48
    # checks); here each reference is checked against its k nearest only
    sc = load_scene(scene_dir, image_size=size)  # with images, for the masks
    ids = sc.view_ids
    centers = sc.cameras.centers.double().numpy()
    pts = []
    for i, ref in enumerate(ids):
        d_ref = depths[ref]
        H, W = d_ref.shape
        cam = sc.cameras[[i]]
        count = torch.zeros(H, W, dtype=torch.int32)
        d_sum = d_ref.double().clone()
        for j in _nearest(centers, i, k):
            m, d_rep, _ = check_geometric_consistency(d_ref, cam, depths[ids[j]],
                                                      sc.cameras[[j]])
            count += m.int()
            d_sum += torch.where(m, d_rep.double(), torch.zeros_like(d_sum))
        keep = (d_ref > 0) & (count >= min_views)
        if sc.masks is not None:  # the region the runs' fusion may fill (METHOD.md 6.3)
            keep &= mask_to_depth_resolution(dilate_mask(sc.masks[i, 0], dilation), H, W)
        fused = d_sum / (1 + count).double()
        c64 = cam.resize(W, H).to(dtype=torch.float64)
        uv = c64.pixel_grid(dtype=torch.float64).reshape(1, -1, 2)
        p = c64.unproject(uv, fused.reshape(1, -1))[0].reshape(H, W, 3)[keep]
        pts.append(p.numpy())
    return np.concatenate(pts)


def seen_by(points: np.ndarray, scene_dir: Path, views: list[int],
            size: tuple[int, int]) -> np.ndarray:
    """Step 3: (N,) bool, points some input view sees (z-buffer of the points themselves)."""
    import torch.nn.functional as F

    from svolsdf.scene.loaders import load_scene

    sc = load_scene(scene_dir, views=views, image_size=size, load_images=False)
    cams = sc.cameras.to(dtype=torch.float64)
    uv, z = cams.project(torch.from_numpy(points))
    W, H = cams.width, cams.height
    vis = torch.zeros(len(points), dtype=torch.bool)
    for i in range(len(views)):
        u, v = uv[i, :, 0].round().long(), uv[i, :, 1].round().long()
        ok = (u >= 0) & (u < W) & (v >= 0) & (v < H) & (z[i] > 0)
        idx = (v * W + u)[ok]
        zb = torch.full((H * W,), 1e30, dtype=torch.float64)
        zb.scatter_reduce_(0, idx, z[i][ok], reduce="amin")
        zb = -F.max_pool2d(-zb.reshape(1, 1, H, W), 3, 1, 1).reshape(-1)  # close splat gaps
        m = ok.clone()
        m[ok] = z[i][ok] <= zb[idx] * 1.005
        vis |= m
    return vis.numpy()


def score(pred: np.ndarray, gt: np.ndarray, obj: np.ndarray) -> dict:
    """Step 4: truncated Chamfer (clipped and DTU rule) and F-score of (N, 3) ``pred`` against
    (M, 3) ``gt``; the scale (cut-off, F threshold, downsampling) and the box in which predictions
    are scored come from (K, 3) ``obj``, the object-only reference."""
    from svolsdf.evaluate.synthetic import truncated_chamfer

    diag = float(np.linalg.norm(obj.max(0) - obj.min(0)))
    max_dist, thr = 0.05 * diag, 0.005 * diag
    lo, hi = obj.min(0) - max_dist, obj.max(0) + max_dist
    pred = pred[((pred >= lo) & (pred <= hi)).all(1)]
    if len(pred) == 0:
        return {"accuracy": max_dist, "completeness": max_dist, "overall": max_dist,
                "overall_dtu_rule": max_dist, "fscore": 0.0, "points": 0}
    # ``gt`` is downsampled once in main(), at 0.1 % of the diagonal = thr / 5
    t = truncated_chamfer(pred, gt, max_dist, thr, gt_downsampled=True)
    return {"accuracy": t["accuracy"], "completeness": t["completeness"],
            "overall": (t["accuracy"] + t["completeness"]) / 2,
            "overall_dtu_rule": (t["accuracy_dtu_rule"] + t["completeness_dtu_rule"]) / 2,
            "fscore": t["fscore"], "points": t["pred_points"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", type=Path, default=SHARED / "data/dtu_scan65")
    ap.add_argument("--runs", nargs="+", required=True, metavar="NAME=DIR",
                    help="run folders (svolsdf reconstruct outputs) to score; ratios are to the "
                         "first")
    ap.add_argument("--out", type=Path, default=Path("/tmp/dtu_pseudo_gt"))
    ap.add_argument("--results", type=Path, default=REPO / "benchmarks/results/dtu_pseudo_gt.md")
    ap.add_argument("--size", default="768x576")
    ap.add_argument("--sources", type=int, default=4)
    ap.add_argument("--fuse-neighbours", type=int, default=8)
    ap.add_argument("--min-views", type=int, default=3)
    ap.add_argument("--mask-dilation", type=int, default=12,
                    help="pixels at the working size; 12 as the runs' fusion (METHOD.md 6.3)")
    args = ap.parse_args()

    from svolsdf.evaluate.chamfer import greedy_radius_downsample, sample_mesh_surface
    from svolsdf.io.ply import read_ply

    if not (args.scene / "cameras_sphere.npz").is_file():
        sys.exit(f"{args.scene}: not a DTU scan in the IDR layout (no cameras_sphere.npz)")
    if not (SHARED / "weights/patchmatchnet").is_dir():
        sys.exit("../shared/weights/patchmatchnet is missing: the pseudo ground truth needs it")
    runs = {}
    for item in args.runs:
        name, _, d = item.rpartition("=")
        d = Path(d)
        if not (d / "points.ply").is_file():
            sys.exit(f"{d}: no points.ply (a finished `svolsdf reconstruct` folder is needed)")
        runs[name or d.name] = d
    size = tuple(int(x) for x in args.size.split("x"))
    t0 = time.perf_counter()
    depths = depth_maps(args.scene, args.out, size, args.sources)
    t_depth = time.perf_counter() - t0
    inputs = None
    for d in runs.values():
        views = json.loads((d / "views.json").read_text())["inputs"]
        if inputs is not None and views != inputs:
            sys.exit(f"{d}: input views {views} differ from the first run's {inputs}")
        inputs = views
    t0 = time.perf_counter()
    refs = {}
    for dil in (0, args.mask_dilation):
        cache = args.out / (f"pseudo_gt_{args.size}_src{args.sources}_k{args.fuse_neighbours}_"
                            f"min{args.min_views}_dil{dil}.npy")
        if cache.is_file():
            pts = np.load(cache)
        else:
            pts = fuse(args.scene, depths, size, args.fuse_neighbours, args.min_views, dil)
            np.save(cache, pts)
        refs[dil] = (len(pts), pts[seen_by(pts, args.scene, inputs, size)])
    t_fuse = time.perf_counter() - t0
    obj = refs[0][1]
    diag = float(np.linalg.norm(obj.max(0) - obj.min(0)))
    rng = np.random.default_rng(0)
    for dil, (n, pts) in refs.items():
        pts = pts[rng.permutation(len(pts))]
        refs[dil] = (n, pts[greedy_radius_downsample(pts, 0.001 * diag)])
    names = {0: "object", args.mask_dilation: f"object and rim ({args.mask_dilation} px)"}
    rows = {}
    for name, d in runs.items():
        pred = read_ply(d / "points.ply")["points"].astype(np.float64)
        mesh = None
        if (d / "mesh.ply").is_file():
            m = read_ply(d / "mesh.ply")
            mesh = sample_mesh_surface(m["points"].astype(np.float64), m["faces"],
                                       density=0.001 * diag)
        for dil, (_, gt) in refs.items():
            rows[(name, dil)] = {"points": score(pred, gt, obj)}
            if mesh is not None:
                rows[(name, dil)]["mesh"] = score(mesh, gt, obj)
            print(name, names[dil], json.dumps(rows[(name, dil)]), flush=True)

    lines = ["# Real DTU geometry against a many-view pseudo ground truth", "",
             f"- machine: nproc = {os.cpu_count()}, CPU: {cpu_name()}; peak RSS "
             f"{peak_rss_gb():.2f} GB",
             f"- command: `python benchmarks/dtu_pseudo_gt.py {' '.join(sys.argv[1:])}`",
             f"- scene: {args.scene.name}, {len(depths)} views at {args.size}; pseudo ground "
             f"truth: PatchmatchNet (DTU-trained, ../shared/weights) with {args.sources} sources "
             f"per view, fused where >= {args.min_views} of the {args.fuse_neighbours} nearest "
             f"views agree; depth {t_depth:.0f} s, fusion {t_fuse:.0f} s (~0 when cached)",
             *(f"  - reference \"{names[dil]}\": inside the object masks"
               f"{f' dilated by {dil} px' if dil else ''}: {n:,} points, {len(gt):,} after "
               f"keeping what input views {inputs} see and downsampling at 0.1 % of the object's "
               f"diagonal" for dil, (n, gt) in refs.items()),
             f"- scores as benchmarks/fast_preset.py, scaled by the object reference's diagonal "
             f"({diag:.0f} mm): clipped at 5 % ({0.05 * diag:.1f} mm), \"DTU rule\" = distances "
             f"beyond it left out, F-score at 0.5 % ({0.005 * diag:.1f} mm); predictions scored "
             "inside the object reference's box grown by the cut-off. The reference carries "
             "PatchmatchNet's errors: compare runs, not absolute values.", "",
             "| run | reference | points acc | points comp | points Chamfer | Chamfer, DTU rule "
             "| F | ratio to the first run | ratio, DTU rule | mesh Chamfer | mesh, DTU rule |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    f = lambda x: "-" if x is None else f"{x:.2f}"  # noqa: E731
    first = next(iter(runs))
    for dil in refs:
        for name in runs:
            p, m = rows[(name, dil)]["points"], rows[(name, dil)].get("mesh", {})
            p0 = rows[(first, dil)]["points"]
            lines.append(f"| {name} (`{runs[name]}`) | {names[dil]} | {f(p['accuracy'])} | "
                         f"{f(p['completeness'])} | {f(p['overall'])} | "
                         f"{f(p['overall_dtu_rule'])} | {p['fscore']:.3f} | "
                         f"{p['overall'] / p0['overall']:.2f} | "
                         f"{p['overall_dtu_rule'] / p0['overall_dtu_rule']:.2f} | "
                         f"{f(m.get('overall'))} | {f(m.get('overall_dtu_rule'))} |")
    notes = ""
    if args.results.is_file():  # hand-written notes (from the first "## Notes" on) are kept
        old = args.results.read_text()
        i = old.find("\n## Notes")
        notes = old[i:] if i >= 0 else ""
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text("\n".join(lines) + "\n" + notes)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
