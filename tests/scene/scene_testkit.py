"""Builders of small scenes on disk in every supported format, from known random cameras."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.spatial.transform import Rotation

W, H = 40, 30


def look_at_w2c(center: np.ndarray, target: np.ndarray, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """World-to-camera (OpenCV axes) for a camera at ``center`` looking at ``target``."""
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross(np.asarray(up, dtype=np.float64), z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ center
    return w2c


def random_cameras(n: int = 4, seed: int = 0, radius: float = 5.0, target=(0.3, -0.2, 0.1)):
    """n cameras on a cap around ``target``, with random intrinsics (skew 0). Returns K, w2c."""
    rng = np.random.default_rng(seed)
    target = np.asarray(target, dtype=np.float64)
    Ks, w2cs = [], []
    for i in range(n):
        az = 2 * np.pi * i / n + rng.uniform(-0.2, 0.2)
        el = rng.uniform(0.3, 0.8)
        c = target + radius * np.array([np.cos(az) * np.cos(el), -np.sin(el),
                                        np.sin(az) * np.cos(el)])
        w2c = look_at_w2c(c, target + rng.normal(0, 0.05, 3))
        f = rng.uniform(35, 45)
        K = np.array([[f, 0, W / 2 + rng.uniform(-2, 2)], [0, f * rng.uniform(0.98, 1.02),
                                                           H / 2 + rng.uniform(-2, 2)],
                      [0, 0, 1]])
        Ks.append(K)
        w2cs.append(w2c)
    return np.stack(Ks), np.stack(w2cs)


def write_images(folder: Path, names: list[str], seed: int = 0, size=(W, H), mode="RGB"):
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    ch = len(mode)
    for n in names:
        a = rng.integers(0, 256, size=(size[1], size[0], ch), dtype=np.uint8)
        Image.fromarray(a, mode=mode).save(folder / n)


def write_idr(root: Path, K, w2c, masks: bool = True, scale_mat=None,
              name: str = "cameras.npz") -> Path:
    root.mkdir(parents=True, exist_ok=True)
    d = {}
    for i in range(len(K)):
        P = np.eye(4)
        P[:3, :4] = K[i] @ w2c[i][:3]
        d[f"world_mat_{i}"] = P
        if scale_mat is not None:
            d[f"scale_mat_{i}"] = scale_mat
    np.savez(root / name, **d)
    write_images(root / "image", [f"{i:06d}.png" for i in range(len(K))])
    if masks:
        (root / "mask").mkdir(exist_ok=True)
        for i in range(len(K)):
            m = np.zeros((H, W, 3), np.uint8)
            m[5:20, 10:30] = 255
            Image.fromarray(m).save(root / "mask" / f"{i:03d}.png")
    return root


def write_mvsnet(root: Path, K, w2c, depth_lines: list[str], pairs: dict | None = None,
                 image_dir: str = "images") -> Path:
    (root / "cams").mkdir(parents=True, exist_ok=True)
    for i in range(len(K)):
        txt = "extrinsic\n" + "\n".join(" ".join(f"{v:.12g}" for v in r) for r in w2c[i])
        txt += "\n\nintrinsic\n" + "\n".join(" ".join(f"{v:.12g}" for v in r) for r in K[i])
        txt += f"\n\n{depth_lines[i]}\n"
        (root / "cams" / f"{i:08d}_cam.txt").write_text(txt)
    write_images(root / image_dir, [f"{i:08d}.jpg" for i in range(len(K))])
    if pairs is not None:
        lines = [str(len(pairs))]
        for r, s in pairs.items():
            lines += [str(r), " ".join([str(len(s))] + [f"{v} {10.0 - k}" for k, v in
                                                        enumerate(s)])]
        (root / "cams" / "pair.txt").write_text("\n".join(lines) + "\n")
    return root


def random_points(n: int = 300, seed: int = 1, center=(0.3, -0.2, 0.1), r: float = 0.6):
    rng = np.random.default_rng(seed)
    return np.asarray(center) + rng.uniform(-r, r, size=(n, 3))


def _visible(K, w2c, pts):
    vis = []
    for k in range(len(K)):
        pc = pts @ w2c[k][:3, :3].T + w2c[k][:3, 3]
        uv = pc @ K[k].T
        uv = uv[:, :2] / uv[:, 2:]
        vis.append((pc[:, 2] > 0) & (uv[:, 0] > -0.5) & (uv[:, 0] < W - 0.5)
                   & (uv[:, 1] > -0.5) & (uv[:, 1] < H - 0.5))
    return np.stack(vis, 1)  # (N, V)


def write_colmap(root: Path, K, w2c, pts, binary: bool) -> Path:
    """COLMAP model (PINHOLE, one camera per image; COLMAP's +0.5 pixel convention), written
    by hand as COLMAP's documented formats lay it out: each point's track names, per image, the
    index of its observation among that image's 2D points."""
    sp = root / "sparse" / "0"
    sp.mkdir(parents=True, exist_ok=True)
    names = [f"img_{i:02d}.png" for i in range(len(K))]
    write_images(root / "images", names)
    vis = _visible(K, w2c, pts)
    ids = [10 + 3 * i for i in range(len(K))]  # non-contiguous COLMAP ids
    cams = [(i + 1, K[i][0, 0], K[i][1, 1], K[i][0, 2] + 0.5, K[i][1, 2] + 0.5)
            for i in range(len(K))]
    quats = []
    for i in range(len(K)):
        x, y, z, w = Rotation.from_matrix(w2c[i][:3, :3]).as_quat()
        quats.append((w, x, y, z))
    # images listed in reverse name order to check the reader sorts by name
    order = list(range(len(K)))[::-1]
    # each image's 2D points: its visible points' projections; obs[k][j] = the index there
    obs = np.full(vis.shape, -1)
    uvs = []
    for j in range(len(K)):
        seen = np.nonzero(vis[:, j])[0]
        obs[seen, j] = np.arange(len(seen))
        pc = pts[seen] @ w2c[j][:3, :3].T + w2c[j][:3, 3]
        uv = pc @ K[j].T
        uvs.append((seen, uv[:, :2] / uv[:, 2:] + 0.5))
    if not binary:
        (sp / "cameras.txt").write_text("# Camera list\n" + "".join(
            f"{c} PINHOLE {W} {H} {fx:.17g} {fy:.17g} {cx:.17g} {cy:.17g}\n"
            for c, fx, fy, cx, cy in cams))
        lines = ["# Image list"]
        for i in order:
            q, t = quats[i], w2c[i][:3, 3]
            lines.append(f"{ids[i]} {q[0]:.17g} {q[1]:.17g} {q[2]:.17g} {q[3]:.17g} "
                         f"{t[0]:.17g} {t[1]:.17g} {t[2]:.17g} {i + 1} {names[i]}")
            seen, uv = uvs[i]
            lines.append(" ".join(f"{x:.17g} {y:.17g} {k + 1}"
                                  for k, (x, y) in zip(seen, uv, strict=True)))
        (sp / "images.txt").write_text("\n".join(lines) + "\n")
        pl = ["# 3D point list"]
        for k, p in enumerate(pts):
            track = " ".join(f"{ids[j]} {obs[k, j]}" for j in np.nonzero(vis[k])[0])
            pl.append(f"{k + 1} {p[0]:.17g} {p[1]:.17g} {p[2]:.17g} 128 128 128 0.5 {track}")
        (sp / "points3D.txt").write_text("\n".join(pl) + "\n")
    else:
        b = struct.pack("<Q", len(cams))
        for c, fx, fy, cx, cy in cams:
            b += struct.pack("<iiQQ", c, 1, W, H) + struct.pack("<4d", fx, fy, cx, cy)
        (sp / "cameras.bin").write_bytes(b)
        b = struct.pack("<Q", len(K))
        for i in order:
            b += struct.pack("<i", ids[i]) + struct.pack("<4d", *quats[i])
            b += struct.pack("<3d", *w2c[i][:3, 3]) + struct.pack("<i", i + 1)
            b += names[i].encode() + b"\x00"
            seen, uv = uvs[i]
            b += struct.pack("<Q", len(seen)) + b"".join(
                struct.pack("<ddq", x, y, k + 1) for k, (x, y) in zip(seen, uv, strict=True))
        (sp / "images.bin").write_bytes(b)
        b = struct.pack("<Q", len(pts))
        for k, p in enumerate(pts):
            js = np.nonzero(vis[k])[0]
            b += struct.pack("<Q3d3BdQ", k + 1, *p, 128, 128, 128, 0.5, len(js))
            for j in js:
                b += struct.pack("<ii", ids[j], obs[k, j])
        (sp / "points3D.bin").write_bytes(b)
    return root


def write_nerf(root: Path, K, w2c, use_angle: bool = False, rgba: bool = False) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    frames = []
    for i in range(len(K)):
        c2w_gl = np.linalg.inv(w2c[i]) @ flip
        fr = {"file_path": f"./train/r_{i}", "transform_matrix": c2w_gl.tolist()}
        if not use_angle:
            fr.update(fl_x=K[i][0, 0], fl_y=K[i][1, 1], cx=K[i][0, 2] + 0.5, cy=K[i][1, 2] + 0.5)
        frames.append(fr)
    meta = {"frames": frames}
    if use_angle:
        meta["camera_angle_x"] = 2 * np.arctan(0.5 * W / K[0][0, 0])
    else:
        meta.update(w=W, h=H)
    (root / "transforms.json").write_text(json.dumps(meta))
    write_images(root / "train", [f"r_{i}.png" for i in range(len(K))],
                 mode="RGBA" if rgba else "RGB")
    return root
