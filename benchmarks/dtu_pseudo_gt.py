"""Geometry on a real DTU scan without its STL: score runs against a many-view pseudo ground truth.

The shared DTU scans (../shared/data/dtu_scan65 in the IDR layout, with object masks;
../shared/data/dtu_raw, scan 9 in DTU's raw layout, without masks but with its real ObsMask) have
49 views but no ground-truth geometry, so the fast preset's Chamfer target ((d) at most 0.75x the
MVS backbone alone, issue 5) could only be checked on synthetic scenes. This script builds an
independent reference from all the scan's views and scores three-view runs against it:

1. Depth of every view with the DTU-trained PatchmatchNet (../shared/weights/patchmatchnet; a
   different MVS method from the plane-sweep backbone the runs use), each view with its
   ``--sources`` best source views by the scene's pair score (`Scene.source_views`, MVSNet's view
   selection, docs/method.md 1.4), at the working size.
2. Fusion: a pixel is kept when at least ``--min-views`` of its ``--fuse-neighbours`` best-paired
   views agree (`svolsdf.fusion.filter.check_geometric_consistency`: 1 px, 1 %); its depth is
   the mean of the agreeing depths. With object masks, two references: "object" (inside the
   masks as they are) and "object and rim" (the masks dilated as the runs' fusion dilates them,
   12 px at the working size, docs/method.md 6.3: what the runs may fill, the table around the
   object included; DTU's own ground truth holds the scanned table too). Without masks (the raw
   layout), one reference, "observed": the fused points inside DTU's observation mask
   (ObsMask<scan>_10.mat, docs/method.md 8.1), and the runs' points are scored inside it too, as
   DTU scores accuracy. Cached in OUT.
3. The reference is the part of that cloud the run's input views see: points within 0.5 % of
   the nearest pseudo-GT depth at their pixel (a 3x3 minimum of the splatted depth) in at least
   one input view.
4. Each run's points.ply (and mesh.ply by its surface, `svolsdf.evaluate.chamfer.
   mesh_surface_points` at `mesh_density`, 0.1 % of the first reference's diagonal; before
   meshes were scored that way everywhere, sampled at it without evening out) is scored as the
   synthetic benchmark scores
   (`svolsdf.evaluate.synthetic.truncated_chamfer`): both clouds evened out by greedy radius
   downsampling at 0.1 % of the first reference's diagonal, distances clipped at 5 % of it
   ("clipped"; holes cost the cut-off) or left out beyond it ("DTU rule", docs/method.md 8.1), and
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
        [--results benchmarks/results/dtu_pseudo_gt_dtu_scan<N>.md]
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
from _machine import cpu_name, peak_rss_gb, write_results

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def depth_maps(scene_dir: Path, out: Path, size: tuple[int, int], n_src: int) -> dict:
    """Step 1: view id -> (H, W) PatchmatchNet z-depth, with the ``n_src`` best source views by
    the scene's pair score (cached as OUT/depth_pairs<n_src>_<W>x<H>/<id>.npy)."""
    from svolsdf.commands.mvs import mvs_depth_range
    from svolsdf.mvs.backbone import get_backbone
    from svolsdf.mvs.cascade import run_cascade
    from svolsdf.scene.loaders import load_scene

    probe = load_scene(scene_dir, load_images=False)
    ddir = out / f"depth_pairs{n_src}_{size[0]}x{size[1]}"
    ddir.mkdir(parents=True, exist_ok=True)
    backbone = None
    res = {}
    for ref in probe.view_ids:
        f = ddir / f"{ref}.npy"
        if not f.is_file():
            backbone = backbone or get_backbone("patchmatchnet")
            t0 = time.perf_counter()
            views = [ref] + probe.source_views(ref)[:n_src]  # MVSNet's view selection
            sc = load_scene(scene_dir, views=views, image_size=size)
            sc = replace(sc, depth_range=mvs_depth_range(sc, None))
            torch.manual_seed(ref)  # PatchmatchNet's initial depth samples are random
            vol = run_cascade(backbone, sc, ref_ids=[ref])
            depth = vol[max(vol)][0].depth.float().numpy()
            np.save(ddir / f".{ref}.tmp.npy", depth)
            os.replace(ddir / f".{ref}.tmp.npy", f)  # a killed run keeps whole files
            print(f"view {ref} (sources {views[1:]}): {time.perf_counter() - t0:.1f} s",
                  flush=True)
        res[ref] = torch.from_numpy(np.load(f))
    return res


def fuse(scene_dir: Path, depths: dict, size: tuple[int, int], k: int, min_views: int,
         dilation: int) -> np.ndarray:
    """Step 2: (N, 3) world points of the pixels ``min_views`` of their ``k`` best-paired views
    confirm, inside the object masks dilated by ``dilation`` pixels when the scene has masks
    (module docstring)."""
    from svolsdf.geometry.masks import dilate_mask, mask_to_depth_resolution
    from svolsdf.geometry.reproject import check_geometric_consistency
    from svolsdf.scene.loaders import load_scene

    # not `fuse_depth_maps`: it checks every reference against all other views (49 x 48
    # checks); here each reference is checked against its k best-paired views only
    sc = load_scene(scene_dir, image_size=size, load_images=False)
    ids = sc.view_ids
    pts = []
    for i, ref in enumerate(ids):
        d_ref = depths[ref]
        H, W = d_ref.shape
        cam = sc.cameras[[i]]
        count = torch.zeros(H, W, dtype=torch.int32)
        d_sum = d_ref.double().clone()
        for src in sc.source_views(ref)[:k]:
            m, d_rep, _ = check_geometric_consistency(d_ref, cam, depths[src],
                                                      sc.cameras[[ids.index(src)]])
            count += m.int()
            d_sum += torch.where(m, d_rep.double(), torch.zeros_like(d_sum))
        keep = (d_ref > 0) & (count >= min_views)
        if sc.extras.get("mask_paths"):  # the region the runs' fusion may fill (docs/method.md 6.3)
            mask = load_scene(scene_dir, views=[ref], image_size=size).masks[0, 0]  # one image
            keep &= mask_to_depth_resolution(dilate_mask(mask, dilation), H, W)
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


def references(scene_dir: Path, out: Path, inputs: list[int], size: tuple[int, int],
               n_src: int = 4, k: int = 8, min_views: int = 3, dilation: int = 12,
               has_masks: bool = True, obs=None, depths: dict | None = None
               ) -> tuple[dict, np.ndarray, float]:
    """Steps 1-3: the pseudo ground truths of ``inputs``' run, each evened out at 0.1 % of the
    first one's diagonal.

    Returns:
        ``({name: (points fused, (M, 3) points kept)}, (K, 3) object reference before
        evening out (it sets the scale of `score`), its diagonal)``: with masks "object" and
        "object and rim (<dilation> px)", without them "observed (DTU ObsMask)" (``obs``, the
        loaded observation mask, keeps its points). ``depths``: `depth_maps`' result when the
        caller has it (else read from ``out``).
    """
    from svolsdf.evaluate.chamfer import greedy_radius_downsample, obs_mask_filter

    depths = depth_maps(scene_dir, out, size, n_src) if depths is None else depths
    dils = (0, dilation) if has_masks else (0,)
    names = ({0: "object", dilation: f"object and rim ({dilation} px)"}
             if has_masks else {0: "observed (DTU ObsMask)"})
    tag = f"{size[0]}x{size[1]}"
    refs = {}
    for dil in dils:
        cache = out / (f"pseudo_gt_{tag}_pairs{n_src}_k{k}_"
                       f"min{min_views}_dil{dil if has_masks else 'none'}.npy")
        if cache.is_file():
            pts = np.load(cache)
        else:
            pts = fuse(scene_dir, depths, size, k, min_views, dil)
            np.save(cache, pts)
        keep = seen_by(pts, scene_dir, inputs, size)
        if obs is not None:
            keep &= obs_mask_filter(pts, obs)[1]
        refs[names[dil]] = (len(pts), pts[keep])
    obj = next(iter(refs.values()))[1]
    diag = float(np.linalg.norm(obj.max(0) - obj.min(0)))
    rng = np.random.default_rng(0)
    for key, (n, pts) in refs.items():
        pts = pts[rng.permutation(len(pts))]
        refs[key] = (n, pts[greedy_radius_downsample(pts, 0.001 * diag)])
    return refs, obj, diag


def score_run(run: Path, refs: dict, obj: np.ndarray, diag: float, obs=None) -> dict:
    """Step 4 for one run folder: ``{reference: {"points": score, "mesh": score}}`` of its
    points.ply and (when it has one) mesh.ply's surface sampled at `mesh_density` (``refs``,
    ``obj``, ``diag`` and ``obs`` as `references` returns and takes them)."""
    from svolsdf.evaluate.chamfer import mesh_density, mesh_surface_points, obs_mask_filter
    from svolsdf.io.ply import read_ply

    pred = read_ply(run / "points.ply")["points"].astype(np.float64)
    mesh = None
    if (run / "mesh.ply").is_file():
        m = read_ply(run / "mesh.ply")
        mesh = mesh_surface_points(m["points"].astype(np.float64), m["faces"],
                                   mesh_density(diag))
    if obs is not None:  # DTU's accuracy counts only predictions inside the ObsMask
        pred = pred[obs_mask_filter(pred, obs)[1]]
        mesh = None if mesh is None else mesh[obs_mask_filter(mesh, obs)[1]]
    out = {}
    for key, (_, gt) in refs.items():
        out[key] = {"points": score(pred, gt, obj)}
        if mesh is not None:
            out[key]["mesh"] = score(mesh, gt, obj)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", type=Path, default=SHARED / "data/dtu_scan65")
    ap.add_argument("--runs", nargs="+", required=True, metavar="NAME=DIR",
                    help="run folders (svolsdf reconstruct outputs) to score; ratios are to the "
                         "first")
    ap.add_argument("--out", type=Path, default=Path("/tmp/dtu_pseudo_gt"))
    ap.add_argument("--results", type=Path, default=None,
                    help="default benchmarks/results/dtu_pseudo_gt_dtu_scan<N>.md")
    ap.add_argument("--size", default="768x576")
    ap.add_argument("--sources", type=int, default=4)
    ap.add_argument("--fuse-neighbours", type=int, default=8)
    ap.add_argument("--min-views", type=int, default=3)
    ap.add_argument("--mask-dilation", type=int, default=12,
                    help="pixels at the working size; 12 as the runs' fusion (docs/method.md 6.3)")
    args = ap.parse_args()

    from svolsdf.evaluate.chamfer import load_obs_mask
    from svolsdf.scene.loaders import load_scene

    try:
        probe = load_scene(args.scene, load_images=False)
    except Exception as e:  # noqa: BLE001 - the loader's message names the file
        sys.exit(f"{args.scene}: {e}")
    if not probe.extras.get("dtu"):
        sys.exit(f"{args.scene}: not a DTU scan (IDR layout with cameras_sphere.npz, or DTU's "
                 "raw Rectified/ + Calibration/ layout)")
    has_masks = bool(probe.extras.get("mask_paths"))
    obs = None
    if not has_masks:  # the region to score is DTU's observation mask (docs/method.md 8.1)
        if not probe.extras.get("obs_mask"):
            sys.exit(f"{args.scene}: no object masks and no ObsMask/ObsMask<scan>_10.mat; "
                     "without either the pseudo ground truth has no region to cover")
        obs = load_obs_mask(probe.extras["obs_mask"])
    scan_name = f"dtu_scan{probe.extras['scan']}" if "scan" in probe.extras else args.scene.name
    results = args.results or REPO / f"benchmarks/results/dtu_pseudo_gt_{scan_name}.md"
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
    refs, obj, diag = references(args.scene, args.out, inputs, size, args.sources,
                                 args.fuse_neighbours, args.min_views, args.mask_dilation,
                                 has_masks, obs, depths)
    t_fuse = time.perf_counter() - t0
    rows = {}
    for name, d in runs.items():
        for key, r in score_run(d, refs, obj, diag, obs).items():
            rows[(name, key)] = r
            print(name, key, json.dumps(r), flush=True)

    region = ("inside the object masks" if has_masks else
              "inside DTU's observation mask (ObsMask, as DTU scores accuracy; the scan has no "
              "object masks, so the reference holds the table and the runs are mask-free)")
    lines = ["# Real DTU geometry against a many-view pseudo ground truth", "",
             f"- machine: nproc = {os.cpu_count()}, CPU: {cpu_name()}; peak RSS "
             f"{peak_rss_gb():.2f} GB",
             f"- command: `python benchmarks/dtu_pseudo_gt.py {' '.join(sys.argv[1:])}`",
             f"- scene: {scan_name} (`{args.scene}`), {len(depths)} views at {args.size}; "
             f"pseudo ground truth: PatchmatchNet (DTU-trained, ../shared/weights) with the "
             f"{args.sources} best-paired source views per view, fused where >= "
             f"{args.min_views} of the {args.fuse_neighbours} best-paired views agree, "
             f"{region}; depth {t_depth:.0f} s, fusion {t_fuse:.0f} s (~0 when cached)",
             *(f"  - reference \"{key}\": {n:,} points, {len(gt):,} after keeping what input "
               f"views {inputs} see and downsampling at 0.1 % of the first reference's diagonal"
               for key, (n, gt) in refs.items()),
             f"- scores as benchmarks/fast_preset.py, scaled by the first reference's diagonal "
             f"({diag:.0f} mm): clipped at 5 % ({0.05 * diag:.1f} mm), \"DTU rule\" = distances "
             f"beyond it left out, F-score at 0.5 % ({0.005 * diag:.1f} mm); predictions scored "
             "inside the first reference's box grown by the cut-off. The reference carries "
             "PatchmatchNet's errors: compare runs, not absolute values.", "",
             "| run | reference | points acc | points comp | points Chamfer | Chamfer, DTU rule "
             "| F | ratio to the first run | ratio, DTU rule | mesh Chamfer | mesh, DTU rule |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    f = lambda x: "-" if x is None else f"{x:.2f}"  # noqa: E731
    first = next(iter(runs))
    for key in refs:
        for name in runs:
            p, m = rows[(name, key)]["points"], rows[(name, key)].get("mesh", {})
            p0 = rows[(first, key)]["points"]
            lines.append(f"| {name} (`{runs[name]}`) | {key} | {f(p['accuracy'])} | "
                         f"{f(p['completeness'])} | {f(p['overall'])} | "
                         f"{f(p['overall_dtu_rule'])} | {p['fscore']:.3f} | "
                         f"{p['overall'] / p0['overall']:.2f} | "
                         f"{p['overall_dtu_rule'] / p0['overall_dtu_rule']:.2f} | "
                         f"{f(m.get('overall'))} | {f(m.get('overall_dtu_rule'))} |")
    write_results(results, "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
