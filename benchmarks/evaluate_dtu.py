"""DTU-protocol evaluation time (docs/method.md 8.1) of a 3-view-like cloud of a few million points.

Target (issue 8): at most 2 minutes on two cores for the whole protocol.

Inputs. The observation mask is DTU's real ``ObsMask9_10.mat`` (``shared/data/dtu_raw``) and the
cameras are scan 9's real calibration (``Calibration/cal18/pos_026/023/029.txt``: the paper's input
views 25, 22, 28). That folder has no ``stl009_total.ply`` and no ``Plane9.mat``, so the ground
truth and the plane are SUBSTITUTES built here, and the Chamfer values printed are not DTU numbers:

- substitute STL: the ObsMask is the volume the scanner observed, so its far boundary is where
  the scanned surface was. Every voxel face between an observed and an unobserved voxel (inside
  the grid) gets two uniform random points: ~2.5M points on a 1 mm staircase surface.
- substitute plane: normal against the cameras' mean viewing direction, placed so that 90% of
  the substitute STL points are "above" it (DTU's plane removes the table the same way).
- prediction ("3-view-like"): for each of the three cameras at the full 1600x1200 resolution,
  the boundary faces that face the camera are z-buffered (at quarter resolution, then bilinearly
  upsampled), every valid pixel is unprojected at its depth plus N(0, 0.3 mm) noise along the
  ray, and 2% of the pixels become outliers (depth +- up to 30 mm). One point per pixel and
  view, three overlapping views: the density (far above 1 / 0.2 mm^2) and the point count of a
  fused full-resolution 3-view MVS cloud.

Phases are timed separately (wall time; peak resident memory of the process during the phase via
/proc/self/clear_refs + VmHWM), then the public `dtu_chamfer` is run end to end on the same data
written in DTU's own layout (ObsMask linked, substitute Plane9.mat and stl009_total.ply) and must
give the same numbers.

Run (from the repo root):

    python benchmarks/evaluate_dtu.py --out benchmarks/results/evaluate_dtu.md
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy
import torch
from scipy.io import savemat
from scipy.ndimage import zoom

from svolsdf.evaluate import chamfer as ch
from svolsdf.io.ply import write_points_ply
from svolsdf.scene.cameras import decompose_projection

SHARED = Path(__file__).resolve().parents[2] / "shared"
DTU_RAW = SHARED / "data" / "dtu_raw"
SCAN = 9
CAM_FILES = (26, 23, 29)  # pos_XXX.txt is 1-based: views 25, 22, 28
W, H = 1600, 1200


# --------------------------------------------------------------------------- memory / machine
def _status(key: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024  # MiB
    return float("nan")


def _reset_peak() -> bool:
    try:
        Path("/proc/self/clear_refs").write_text("5")  # resets VmHWM (Linux >= 4.0)
        return True
    except OSError:
        return False


class Phase:
    """Times a block; records wall time, CPU time, RSS at start and the peak RSS during it."""

    rows: list[tuple[str, float, float, float, float]] = []

    def __init__(self, name: str):
        self.name = name

    def __enter__(self):
        _reset_peak()
        self.rss0 = _status("VmRSS")
        self.t0 = time.perf_counter()
        self.c0 = time.process_time()
        return self

    def __exit__(self, *exc):
        wall = time.perf_counter() - self.t0
        cpu = time.process_time() - self.c0
        Phase.rows.append((self.name, wall, cpu, self.rss0, _status("VmHWM")))
        print(f"  {self.name:<48s} {wall:7.2f} s wall {cpu:7.2f} s CPU  "
              f"peak RSS {_status('VmHWM'):7.0f} MiB", flush=True)


def _machine() -> str:
    cpu = "unknown"
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            cpu = line.split(":", 1)[1].strip()
            break
    load = ", ".join(f"{v:.1f}" for v in os.getloadavg())
    return (f"- CPU: {cpu}; `nproc` = {os.cpu_count()} (cKDTree queries use workers=-1)\n"
            f"- Python {platform.python_version()}, numpy {np.__version__}, scipy "
            f"{scipy.__version__}, {platform.system()} {platform.release()}\n"
            f"- load average at start: {load} (the 2 cores are shared with other engineers' "
            "jobs, so wall times are upper bounds of an idle machine's)")


# --------------------------------------------------------------------------- inputs
def boundary_faces(obs: ch.ObsMask) -> tuple[np.ndarray, np.ndarray]:
    """Faces between observed and unobserved voxels: centres (F, 3) mm and unit normals (F, 3)
    pointing into the observed voxel (towards the scanner)."""
    m = obs.mask
    centres, normals = [], []
    for ax in range(3):
        a, b = np.swapaxes(m, 0, ax)[:-1], np.swapaxes(m, 0, ax)[1:]
        for sel, sign in ((a & ~b, -1.0), (~a & b, 1.0)):
            idx = np.argwhere(sel).astype(np.float64)
            idx[:, 0] += 0.5
            idx[:, [0, ax]] = idx[:, [ax, 0]]  # undo the swap
            centres.append(obs.bb[0].astype(np.float64) + idx * obs.res)
            n = np.zeros((len(idx), 3))
            n[:, ax] = sign
            normals.append(n)
    return np.concatenate(centres), np.concatenate(normals)


def substitute_stl(centres, normals, res, rng, per_face=2) -> np.ndarray:
    """``per_face`` uniform points on each face square (float32-rounded, as a PLY stores them)."""
    pts = np.repeat(centres, per_face, axis=0)
    n = np.repeat(normals, per_face, axis=0)
    off = rng.uniform(-0.5, 0.5, size=pts.shape) * res
    off[n != 0] = 0.0
    return (pts + off).astype(np.float32).astype(np.float64)


def cameras() -> list[tuple[np.ndarray, np.ndarray]]:
    out = []
    for i in CAM_FILES:
        P = np.loadtxt(DTU_RAW / "Calibration" / "cal18" / f"pos_{i:03d}.txt")
        K, w2c = decompose_projection(torch.from_numpy(P))
        out.append((K.numpy(), w2c.numpy()))
    return out


def three_view_cloud(centres, normals, cams, rng, noise=0.3, outliers=0.02) -> np.ndarray:
    """One point per valid pixel of each camera's depth map of the boundary faces."""
    clouds = []
    q = 4  # z-buffer at quarter resolution: a 1 mm face covers ~1.2 quarter pixels at 600 mm
    for K, w2c in cams:
        R, t = w2c[:3, :3], w2c[:3, 3]
        C = -R.T @ t
        facing = np.einsum("ij,ij->i", normals, C - centres) > 0
        Xc = centres[facing] @ R.T + t
        z = Xc[:, 2]
        uv = Xc[:, :2] / z[:, None] @ K[:2, :2].T + K[:2, 2]
        u4 = np.floor((uv[:, 0] + 0.5) / q).astype(np.int64)
        v4 = np.floor((uv[:, 1] + 0.5) / q).astype(np.int64)
        ok = (z > 0) & (u4 >= 0) & (u4 < W // q) & (v4 >= 0) & (v4 < H // q)
        lin, z = v4[ok] * (W // q) + u4[ok], z[ok]
        zbuf = np.full((H // q) * (W // q), np.inf)
        np.minimum.at(zbuf, lin, z)
        valid = np.isfinite(zbuf).reshape(H // q, W // q)
        zq = np.where(valid, zbuf.reshape(valid.shape), 0.0)
        # bilinear upsampling of depth and validity (pixel centres: c' = s(c + 0.5) - 0.5)
        num = zoom(zq, q, order=1, grid_mode=True, mode="nearest")
        den = zoom(valid.astype(np.float64), q, order=1, grid_mode=True, mode="nearest")
        good = den > 0.999
        depth = num[good] / den[good]
        vv, uu = np.nonzero(good)
        depth = depth + rng.normal(scale=noise, size=depth.shape)
        bad = rng.random(len(depth)) < outliers
        depth[bad] += rng.uniform(-30, 30, size=int(bad.sum()))
        pix = np.stack([uu, vv, np.ones_like(uu)], 1).astype(np.float64)
        rays = pix @ np.linalg.inv(K).T  # z = 1
        Xw = (rays * depth[:, None] - t) @ R  # R^T (X_c - t)
        clouds.append(Xw)
    return np.concatenate(clouds).astype(np.float32).astype(np.float64)


def substitute_plane(stl, cams, above_fraction=0.9) -> np.ndarray:
    d = np.mean([w2c[2, :3] for _, w2c in cams], axis=0)  # optical axes in world
    d /= np.linalg.norm(d)
    s = stl @ d
    c = np.quantile(s, above_fraction)
    return np.array([-d[0], -d[1], -d[2], c])  # above: -d.x + c > 0, i.e. d.x < c


# --------------------------------------------------------------------------- run
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None, help="write the Markdown result here")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    obs_path = DTU_RAW / "ObsMask" / f"ObsMask{SCAN}_10.mat"
    if not obs_path.is_file():
        raise SystemExit(f"{obs_path}: missing (needs ../shared/data/dtu_raw)")
    rng = np.random.default_rng(args.seed)

    print("building inputs (not timed)", flush=True)
    t = time.perf_counter()
    obs0 = ch.load_obs_mask(obs_path)
    centres, normals = boundary_faces(obs0)
    stl = substitute_stl(centres, normals, obs0.res, rng)
    cams = cameras()
    pred = three_view_cloud(centres, normals, cams, rng)
    plane = substitute_plane(stl, cams)
    del obs0, centres, normals
    build_s = time.perf_counter() - t
    print(f"  {len(pred):,} predicted points, {len(stl):,} substitute STL points "
          f"({build_s:.0f} s)", flush=True)

    print("phases", flush=True)
    Phase.rows.clear()
    with Phase("load ObsMask9_10.mat"):
        obs = ch.load_obs_mask(obs_path)
    with Phase("shuffle (seeded)"):
        data = ch.shuffle_rows(pred, args.seed)
    with Phase("downsample 0.2 mm (KD-tree, radius pairs, greedy)"):
        data = data[ch.greedy_radius_downsample(data, 0.2)]
    with Phase("ObsMask filter (BB, patch 60, voxel lookup)"):
        in_bb, in_obs = ch.obs_mask_filter(data, obs, 60.0)
        data_in, data_in_obs = data[in_bb], data[in_obs]
    with Phase("accuracy: KD-tree on STL + query data_in_obs"):
        d2s = ch.nn_distances(data_in_obs, stl, upper_bound=20.0)
    with Phase("completeness: plane + KD-tree on data_in + query"):
        above = stl @ plane[:3] + plane[3] > 0
        s2d = ch.nn_distances(stl[above], data_in, upper_bound=20.0)
    acc = float(d2s[d2s < 20].mean())
    comp = float(s2d[s2d < 20].mean())
    phases = list(Phase.rows)
    total_wall = sum(r[1] for r in phases)
    total_cpu = sum(r[2] for r in phases)
    peak = max(r[4] for r in phases)
    counts = {"pred": len(pred), "down": len(data), "in_bb": int(in_bb.sum()),
              "in_obs": int(in_obs.sum()), "stl": len(stl), "above": int(above.sum())}
    del data, data_in, data_in_obs, d2s, s2d

    print("end to end: dtu_chamfer on files in DTU's layout", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        (root / "ObsMask").mkdir()
        (root / "Points" / "stl").mkdir(parents=True)
        os.symlink(obs_path, root / "ObsMask" / obs_path.name)
        savemat(root / "ObsMask" / f"Plane{SCAN}.mat", {"P": plane.reshape(4, 1)})
        write_points_ply(root / "Points" / "stl" / f"stl{SCAN:03d}_total.ply", stl)
        write_points_ply(root / "pred.ply", pred)
        del stl, pred
        Phase.rows.clear()
        with Phase("end to end: read pred.ply + dtu_chamfer(...)"):
            from svolsdf.io.ply import read_ply

            points = read_ply(root / "pred.ply")["points"]
            res = ch.dtu_chamfer(points, root, SCAN, seed=args.seed)
        e2e = Phase.rows[0]
    same = np.allclose([res["accuracy"], res["completeness"]], [acc, comp], rtol=1e-12)
    print(f"  accuracy {res['accuracy']:.4f} completeness {res['completeness']:.4f} "
          f"(phase-wise {acc:.4f} {comp:.4f}; identical: {same})", flush=True)

    lines = [
        "# DTU-protocol evaluation time (issue 8 target: <= 2 min on two cores)",
        "",
        "Command (from the repo root):",
        "",
        "    python benchmarks/evaluate_dtu.py --out benchmarks/results/evaluate_dtu.md",
        "",
        "Machine:",
        "",
        _machine(),
        "",
        "Inputs (see the script's docstring): DTU's real `ObsMask9_10.mat` and scan 9's real "
        "cameras for views 25, 22, 28 at 1600x1200. **There is no `stl009_total.ply` or "
        "`Plane9.mat` in `shared/data/dtu_raw`, so the ground truth is a substitute**: two random "
        "points on every voxel face between observed and unobserved ObsMask voxels (the "
        "mask's boundary, where the scanned surface was), and a substitute plane keeping 90% of "
        "them. The prediction is a 3-view-like cloud: those faces z-buffered into the three "
        "cameras, one point per valid pixel per view, 0.3 mm depth noise, 2% outliers. The "
        "Chamfer values below are therefore not DTU scan 9 numbers; the timing is what the "
        "benchmark measures.",
        "",
        f"- predicted points: {counts['pred']:,}; after 0.2 mm downsampling: {counts['down']:,}; "
        f"in BB (data_in): {counts['in_bb']:,}; observed (data_in_obs): {counts['in_obs']:,}",
        f"- substitute STL points: {counts['stl']:,}; above the substitute plane: "
        f"{counts['above']:,}",
        f"- accuracy {acc:.4f} mm, completeness {comp:.4f} mm, overall {(acc + comp) / 2:.4f} mm "
        f"(substitute ground truth)",
        "",
        "| phase | wall (s) | CPU (s) | RSS at start (MiB) | peak RSS during phase (MiB) |",
        "|---|---:|---:|---:|---:|",
    ]
    for name, wall, cpu, rss0, hwm in phases:
        lines.append(f"| {name} | {wall:.2f} | {cpu:.2f} | {rss0:.0f} | {hwm:.0f} |")
    lines += [
        f"| **sum of phases** | **{total_wall:.2f}** | **{total_cpu:.2f}** | | **{peak:.0f}** |",
        f"| end to end: read pred.ply + `dtu_chamfer` (reads ObsMask, Plane, STL PLY) | "
        f"{e2e[1]:.2f} | {e2e[2]:.2f} | {e2e[3]:.0f} | {e2e[4]:.0f} |",
        "",
        f"End to end and phase by phase give identical accuracy and completeness: {same}.",
        f"Building the inputs (not timed above) took {build_s:.0f} s.",
        "",
        "Peak RSS is the whole process's resident high-water mark during the phase (reset with "
        "/proc/self/clear_refs before each phase), so it includes the inputs held in memory.",
        "",
        "Before the speed-up (same inputs, same machine, load average 4.6): shuffle 9.75 s "
        "(`Generator.shuffle(axis=0)` swaps rows one at a time), downsampling 6.1 s, accuracy "
        "33.3 s (random-order queries into a 2.5M-point tree), completeness 7.8 s; end to end "
        "63.6 s wall, 42.0 s CPU. The speed-up (`chamfer.py`: rows shuffled through "
        "`permutation`, which is the same Fisher-Yates result; trees built on and queries issued "
        "in Morton order) changes no result: accuracy and completeness are bit-identical, and "
        "the tests compare both paths with the slow reference.",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)


if __name__ == "__main__":
    main()
