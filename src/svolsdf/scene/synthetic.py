"""Synthetic scenes with exact ground truth: procedural textured objects on a textured table.

`make_synthetic_scene` ray-casts an analytic signed distance function (a smooth union of spheres,
rounded boxes, tori and capsules, randomized by a seed) standing on a finite table plane, seen by
cameras on a DTU-like spherical cap, and writes the IDR / VolSDF layout (METHOD.md 1.1)::

    OUT/image/000000.png ...   RGB 8-bit renders (2x2 supersampled by default)
    OUT/mask/000.png ...       object mask, 8-bit greyscale: 255 object, 0 table or background
    OUT/cameras.npz            world_mat_i = K [R | t] (4x4), scale_mat_i (unit -> world),
                               camera_mat_i = K (4x4), and the inverses of all three
    OUT/pair.txt               MVSNet pair file (sources ranked by MVSNet's view-angle score)
    OUT/gt_depth/000.npy ...   float32 (H, W) z-depth in world units at pixel centres, table
                               included; 0 where the ray hits nothing (background)
    OUT/gt_points.ply          samples of the OBJECT surface above the table, world units
    OUT/gt_points_visibility.npy  uint8 (N,) number of views that see each gt point
    OUT/gt_mesh.ply            the object surface as a triangle mesh (marching cubes, world units)
    OUT/scene.json             the generator's config, objects, table, light, cameras' summary

World frame and units (DTU-like): millimetres; z is up, the table is the plane z = 0 (a square of
side ``table_size``), the object stands on it centred on the z axis, about 100-200 mm across; the
cameras look at the object's centre from ``distance`` (~600 mm) on a cap spanning ``azimuth_span``
degrees around the -y direction and elevations ``elevation`` degrees above the table, in rows like
DTU's. Intrinsics follow DTU's relative focal length (f ~ 1.8 x image width) with a slightly
off-centre principal point. Camera axes are OpenCV's (scene/cameras.py).

Normalization (METHOD.md 1.2, VolSDF convention): scale_mat = [[s,0,0,cx],[0,s,0,cy],[0,0,s,cz],
[0,0,0,1]] with c the object's bounding-sphere centre (where all optical axes meet) and
s = max(1.1 * (max camera distance to c) / 3, 1.05 * object radius): the object lies inside the
unit sphere and the cameras within radius ~2.7 (VolSDF's radius-3 region of interest).

Shading is Lambertian with an ambient term, a fixed directional light and soft shadows, so the
images are consistent across views (no view-dependent effects); the textures are solid (3D)
procedural patterns (multi-octave value noise, stripes, checkers) so that multi-view stereo has
texture to match everywhere. Output is byte-for-byte deterministic for a seed (every file,
including the zip inside ``cameras.npz``).

Borrowed cameras: ``cameras_from`` (an IDR scene folder with ``cameras.npz`` or
``cameras_sphere.npz`` and ``image/`` or ``images/``) renders the object with that scene's cameras
(resized to ``width`` x ``height``), placed at its scale_mat centre, scaled to its unit sphere, on a
table orthogonal to the cameras' mean "up" direction, in its world units.
"""

from __future__ import annotations

import io
import json
import logging
import math
import shutil
import zipfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from svolsdf.errors import InputError
from svolsdf.io.folders import ensure_writable_folder
from svolsdf.io.ply import atomic_path, write_mesh_ply, write_points_ply
from svolsdf.scene.cameras import Cameras, decompose_projection

__all__ = [
    "OBJECT_KINDS",
    "SynthConfig",
    "SynthObject",
    "make_object",
    "make_synthetic_scene",
    "parse_size",
    "render_view",
]

log = logging.getLogger(__name__)

OBJECT_KINDS = ("random", "sphere", "box", "torus", "capsule", "blobs")
"""Object kinds: ``random`` is a smooth union of 3-6 mixed primitives; the others are one primitive
(or, for ``blobs``, smooth-blended spheres only)."""

GENERATOR = "svolsdf.synth"
_SCENE_FILES = ("cameras.npz", "pair.txt", "gt_points.ply", "gt_points_visibility.npy",
                "gt_mesh.ply", "scene.json")
_SCENE_DIRS = ("image", "mask", "gt_depth")


@dataclass
class SynthConfig:
    """Configuration of a synthetic scene (``svolsdf synth``)."""

    seed: int = 0
    """Random seed: the object, its textures and the camera jitter. Same seed, same bytes."""
    views: int = 9
    """Number of views on the cap (the default 9 leaves room for 3 inputs and held-out views)."""
    width: int = 768
    """Image width in pixels."""
    height: int = 576
    """Image height in pixels."""
    object: str = "random"
    """Object kind, one of OBJECT_KINDS."""
    supersample: int = 2
    """Anti-aliasing samples per pixel axis for the images (1 = one ray through each pixel
    centre). Depth and masks always come from the pixel-centre ray."""
    distance: float = 600.0
    """Mean camera distance to the object centre, world units (DTU: 500-800 mm)."""
    distance_jitter: float = 0.05
    """Relative random variation of each camera's distance."""
    elevation: tuple[float, float] = (25.0, 60.0)
    """Lowest and highest camera elevation above the table, degrees (DTU spans about 45)."""
    azimuth_span: float = 80.0
    """Horizontal angle spanned by a row of cameras, degrees."""
    focal: float = 1.8
    """Focal length as a multiple of the image width (DTU: 2890 px at 1600 px wide)."""
    intrinsics_jitter: float = 1.0
    """Scale of the per-view random variation of the intrinsics (focal length +-1 %, principal
    point +-2 % of the image size, as a rig of different cameras); 0 gives every view the same
    camera with the principal point at the image centre, as photos from one camera."""
    table_size: float = 800.0
    """Side of the square table, world units."""
    light_dir: tuple[float, float, float] = (-0.35, -0.55, 0.76)
    """Direction towards the directional light (normalized on use), world frame."""
    ambient: float = 0.3
    """Ambient light fraction; the rest is Lambertian."""
    soft_shadows: bool = True
    """Cast soft shadows of the object (on the table and on itself)."""
    gt_points: int = 200_000
    """Number of object-surface samples drawn for gt_points.ply (before dropping those on or
    under the table)."""
    mesh_resolution: float = 1.5
    """Marching-cubes cell size for gt_mesh.ply and the surface sampling, world units."""
    chunk: int = 1 << 17
    """Rays per rendering chunk (memory bound)."""
    cameras_from: str | None = None
    """Borrow the cameras of this IDR scene folder instead of the synthetic cap."""
    camera_views: list[int] | None = None
    """With ``cameras_from``: which of its views to use (default: ``views`` evenly spaced ids)."""

    def __post_init__(self) -> None:
        if self.object not in OBJECT_KINDS:
            raise InputError(
                f"unknown object kind {self.object!r}; choose one of {', '.join(OBJECT_KINDS)}"
            )
        if self.views < 1:
            raise InputError(f"--views must be at least 1, got {self.views}")
        if self.width < 8 or self.height < 8:
            raise InputError(f"image size must be at least 8x8, got {self.width}x{self.height}")
        if self.supersample < 1:
            raise InputError(f"supersample must be >= 1, got {self.supersample}")


def parse_size(text: str) -> tuple[int, int]:
    """Parse ``"WxH"`` (e.g. ``"768x576"``) into (width, height); InputError when malformed."""
    parts = str(text).lower().replace("*", "x").split("x")
    try:
        if len(parts) != 2:
            raise ValueError
        w, h = int(parts[0]), int(parts[1])
    except ValueError:
        raise InputError(
            f"--size must look like WIDTHxHEIGHT (e.g. 768x576), got {text!r}"
        ) from None
    if w < 8 or h < 8 or w > 16384 or h > 16384:
        raise InputError(f"--size {text!r}: width and height must be within 8..16384")
    return w, h


# =============================================================================== noise
def _hash01(ix: Tensor, iy: Tensor, iz: Tensor, seed: int) -> Tensor:
    """Integer lattice hash -> float in [0, 1]; deterministic, int64 arithmetic."""
    m = 0xFFFFFFFF
    h = (ix * 73856093) ^ (iy * 19349663) ^ (iz * 83492791) ^ ((seed * 2654435761) & m)
    h = h & m
    h = (((h >> 16) ^ h) * 0x45D9F3B) & m
    h = (((h >> 16) ^ h) * 0x45D9F3B) & m
    h = (h >> 16) ^ h
    return (h & 0xFFFFFF).to(torch.float32) / float(0xFFFFFF)


class _Noise:
    """Smooth 3D value noise from a seeded periodic random lattice (``channels`` independent
    fields). Value noise with smoothstep weights is exactly trilinear interpolation at
    floor(q) + fade(frac(q)), which ``grid_sample`` does in one fused call."""

    def __init__(self, seed: int, size: int = 96, channels: int = 4) -> None:
        g = torch.Generator().manual_seed(int(seed))
        lat = torch.rand(channels, size, size, size, generator=g)
        lat = torch.cat([lat, lat[:, :1]], 1)  # wrap-around copies so i + 1 always exists
        lat = torch.cat([lat, lat[:, :, :1]], 2)
        lat = torch.cat([lat, lat[:, :, :, :1]], 3)
        self.vol = lat[None].contiguous()  # (1, C, L+1, L+1, L+1)
        self.size = size

    def fbm(self, p: Tensor, scale: float, octaves: int) -> Tensor:
        """Multi-octave noise in [0, 1]. p: (N, 3) world points; ``scale``: the largest feature
        size (world units). Returns (C, N)."""
        L = self.size
        grids = []
        for o in range(octaves):
            q = p * (2.0**o / scale) + 17.31 * (o + 1)
            fl = torch.floor(q)
            f = q - fl
            u = torch.remainder(fl, L) + f * f * (3.0 - 2.0 * f)
            grids.append(u * (2.0 / L) - 1.0)
        grid = torch.cat(grids, 0).to(torch.float32)[None, None, None]  # (1, 1, 1, O*N, 3)
        out = torch.nn.functional.grid_sample(self.vol, grid, mode="bilinear",
                                              padding_mode="border", align_corners=True)
        out = out.reshape(self.vol.shape[1], octaves, p.shape[0])
        w = torch.tensor([0.5**o for o in range(octaves)])
        return (out * (w / w.sum())[None, :, None]).sum(1)


# =============================================================================== object SDF
def _smin(a: Tensor, b: Tensor, k: float) -> Tensor:
    """Polynomial smooth minimum (Lipschitz <= 1, so sphere tracing stays conservative)."""
    if k <= 0:
        return torch.minimum(a, b)
    h = (0.5 + 0.5 * (b - a) / k).clamp(0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _rot(angles: list[float]) -> np.ndarray:
    """Rotation matrix from Z-Y-X Euler angles (radians)."""
    a, b, c = angles
    rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    rx = np.array([[1, 0, 0], [0, math.cos(c), -math.sin(c)], [0, math.sin(c), math.cos(c)]])
    return rz @ ry @ rx


def _len3(x: Tensor, y: Tensor, z: Tensor) -> Tensor:
    return torch.sqrt(x * x + y * y + z * z)


def _prim_sdf(prim: dict, x: Tensor, y: Tensor, z: Tensor) -> Tensor:
    """Exact SDF of one primitive at points given as coordinate arrays x, y, z (N,) -> (N,).

    Coordinates are passed separately (structure of arrays): elementwise arithmetic on (N,)
    tensors is much faster on a CPU than reductions over a trailing axis of size 3.
    """
    kind = prim["kind"]
    if kind == "capsule":
        a, b = prim["a"], prim["b"]
        bx, by, bz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        px, py, pz = x - a[0], y - a[1], z - a[2]
        h = ((px * bx + py * by + pz * bz) / (bx * bx + by * by + bz * bz)).clamp(0.0, 1.0)
        return _len3(px - bx * h, py - by * h, pz - bz * h) - prim["radius"]
    c = prim["center"]
    qx, qy, qz = x - c[0], y - c[1], z - c[2]
    if kind == "sphere":
        return _len3(qx, qy, qz) - prim["radius"]
    R = prim["rotation"]  # local = R^T q
    lx = R[0][0] * qx + R[1][0] * qy + R[2][0] * qz
    ly = R[0][1] * qx + R[1][1] * qy + R[2][1] * qz
    lz = R[0][2] * qx + R[1][2] * qy + R[2][2] * qz
    if kind == "box":
        r = prim["rounding"]
        hx, hy, hz = (v - r for v in prim["half"])
        dx, dy, dz = lx.abs() - hx, ly.abs() - hy, lz.abs() - hz
        outside = _len3(dx.clamp(min=0.0), dy.clamp(min=0.0), dz.clamp(min=0.0))
        inside = torch.maximum(torch.maximum(dx, dy), dz).clamp(max=0.0)
        return outside + inside - r
    if kind == "torus":
        ring = torch.sqrt(lx * lx + ly * ly) - prim["major"]
        return torch.sqrt(ring * ring + lz * lz) - prim["minor"]
    raise ValueError(f"unknown primitive {kind}")


def _prim_bound(prim: dict) -> tuple[np.ndarray, float]:
    """A bounding sphere (centre, radius) of one primitive."""
    kind = prim["kind"]
    if kind == "capsule":
        a, b = np.asarray(prim["a"]), np.asarray(prim["b"])
        return (a + b) / 2, float(np.linalg.norm(b - a) / 2 + prim["radius"])
    c = np.asarray(prim["center"])
    if kind == "sphere":
        return c, float(prim["radius"])
    if kind == "box":
        return c, float(np.linalg.norm(prim["half"]))
    return c, float(prim["major"] + prim["minor"])


@dataclass
class SynthObject:
    """A textured object: a smooth union of primitives (local frame: millimetres, z up).

    Attributes:
        primitives: list of dicts (``kind`` in sphere/box/torus/capsule, geometry, and texture:
            ``colors`` (3, 3) RGB in [0, 1], ``pattern`` in noise/stripes/checker,
            ``period`` world units, ``stripe_dir`` (3,)).
        blend: smooth-union radius k (world units).
        seed: texture seed.
    """

    primitives: list[dict]
    blend: float
    seed: int

    def __post_init__(self) -> None:
        self._noise = _Noise(self.seed)

    def sdf_xyz(self, x: Tensor, y: Tensor, z: Tensor) -> Tensor:
        """Signed distance (negative inside) at coordinate arrays x, y, z (N,) -> (N,)."""
        d = _prim_sdf(self.primitives[0], x, y, z)
        for prim in self.primitives[1:]:
            d = _smin(d, _prim_sdf(prim, x, y, z), self.blend)
        return d

    def sdf(self, p: Tensor) -> Tensor:
        """Signed distance (negative inside). p: (N, 3) float -> (N,)."""
        x, y, z = p.T.contiguous()
        return self.sdf_xyz(x, y, z)

    def nearest_primitive(self, p: Tensor) -> Tensor:
        """(N,) int64 index of the primitive whose own SDF is smallest at p (N, 3)."""
        x, y, z = p.T.contiguous()
        return torch.stack([_prim_sdf(q, x, y, z) for q in self.primitives], -1).argmin(-1)

    def bound(self) -> tuple[np.ndarray, float]:
        """A conservative bounding sphere (centre (3,), radius) of the union."""
        cs, rs = zip(*(_prim_bound(q) for q in self.primitives), strict=True)
        cs = np.stack(cs)
        c = (cs.min(0) + cs.max(0)) / 2
        r = max(float(np.linalg.norm(ci - c)) + ri for ci, ri in zip(cs, rs, strict=True))
        return c, r + self.blend

    def translate(self, off: np.ndarray) -> None:
        """Move every primitive by ``off`` (3,)."""
        for q in self.primitives:
            for key in ("center", "a", "b"):
                if key in q:
                    q[key] = (np.asarray(q[key]) + off).tolist()

    def albedo(self, p: Tensor) -> Tensor:
        """Solid procedural texture. p: (N, 3) surface points -> (N, 3) RGB in [0, 1]."""
        out = torch.empty_like(p)
        idx = self.nearest_primitive(p)
        fine = self._noise.fbm(p, 2.5, 2)[3]
        for i, prim in enumerate(self.primitives):
            sel = idx == i
            if not bool(sel.any()):
                continue
            q = p[sel] + 101.0 * i  # decorrelate the primitives' noise
            n = self._noise.fbm(q, prim["period"], 4)  # (4, M): warp, pattern, spots
            s = _pattern(q, prim, n[0], n[1])
            cols = q.new_tensor(prim["colors"])
            c = cols[0] * (1 - s[:, None]) + cols[1] * s[:, None]
            spots = 0.6 * (n[2] > 0.6).to(q.dtype)[:, None]
            out[sel] = c * (1 - spots) + cols[2] * spots
        return (out * (0.8 + 0.4 * fine[:, None])).clamp(0.0, 1.0)


def _pattern(q: Tensor, prim: dict, warp: Tensor, noise: Tensor) -> Tensor:
    """Pattern value in [0, 1] for one primitive's texture. q: (N, 3), warp, noise (N,)."""
    period = prim["period"]
    kind = prim["pattern"]
    if kind == "stripes":
        d = q @ q.new_tensor(prim["stripe_dir"])
        return 0.5 + 0.5 * torch.sin(2 * math.pi * d / period + 6.0 * warp)
    if kind == "checker":
        cell = torch.floor((q + 2.0 * period * (warp[:, None] - 0.5)) / period).to(torch.int64)
        parity = (cell.sum(-1) % 2).to(q.dtype)
        return 0.15 + 0.7 * parity + 0.15 * noise
    return ((noise - 0.5) * 3.0 + 0.5).clamp(0.0, 1.0)  # contrast-stretched fbm


_PALETTE = np.array([
    [0.85, 0.25, 0.20], [0.95, 0.75, 0.20], [0.20, 0.55, 0.85], [0.25, 0.70, 0.35],
    [0.70, 0.30, 0.75], [0.95, 0.55, 0.20], [0.90, 0.90, 0.85], [0.15, 0.15, 0.20],
    [0.40, 0.80, 0.80], [0.60, 0.40, 0.25],
])


def _texture(rng: np.random.Generator) -> dict:
    cols = _PALETTE[rng.choice(len(_PALETTE), size=3, replace=False)]
    cols = np.clip(cols + rng.uniform(-0.08, 0.08, size=cols.shape), 0.02, 0.98)
    d = rng.normal(size=3)
    return {
        "colors": cols.round(4).tolist(),
        "pattern": str(rng.choice(["noise", "stripes", "checker"])),
        "period": float(round(rng.uniform(8.0, 20.0), 3)),
        "stripe_dir": (d / np.linalg.norm(d)).round(6).tolist(),
    }


def _random_prim(kind: str, rng: np.random.Generator, center, size: float) -> dict:
    c = np.asarray(center, dtype=np.float64)
    rot = _rot(rng.uniform(-math.pi, math.pi, size=3).tolist())
    if kind == "sphere":
        g = {"center": c, "radius": size}
    elif kind == "box":
        half = size * rng.uniform(0.6, 1.0, size=3)
        g = {"center": c, "half": half, "rotation": rot,
             "rounding": float(min(half) * rng.uniform(0.1, 0.3))}
    elif kind == "torus":
        g = {"center": c, "major": size, "minor": size * rng.uniform(0.25, 0.45),
             "rotation": rot}
    else:  # capsule
        d = rng.normal(size=3)
        d = d / np.linalg.norm(d) * size * rng.uniform(0.8, 1.3)
        g = {"a": c - d, "b": c + d, "radius": size * rng.uniform(0.3, 0.5)}
    out = {"kind": kind}
    for k, v in g.items():
        out[k] = np.round(np.asarray(v, dtype=np.float64), 6).tolist() if not isinstance(
            v, float) else round(v, 6)
    out.update(_texture(rng))
    return out


def make_object(kind: str, seed: int) -> SynthObject:
    """Build a random object of ``kind`` (OBJECT_KINDS), about 100-200 mm across, unplaced.

    The caller (`make_synthetic_scene`) then moves it to stand on the table.
    """
    rng = np.random.default_rng([seed, 1])
    prims: list[dict] = []
    if kind == "random":
        main = str(rng.choice(["sphere", "box", "torus", "capsule"]))
        size = {"sphere": 50.0, "box": 48.0, "torus": 45.0, "capsule": 38.0}[main]
        prims.append(_random_prim(main, rng, [0, 0, 0], size * rng.uniform(0.9, 1.1)))
        for _ in range(int(rng.integers(2, 6))):
            d = rng.normal(size=3)
            d = d / np.linalg.norm(d)
            k = str(rng.choice(["sphere", "box", "torus", "capsule"]))
            s = rng.uniform(14.0, 28.0)
            prims.append(_random_prim(k, rng, d * rng.uniform(40.0, 60.0), s))
        blend = float(rng.uniform(6.0, 12.0))
    elif kind == "blobs":
        for i in range(int(rng.integers(4, 7))):
            c = rng.normal(size=3) * 28.0 if i else np.zeros(3)
            prims.append(_random_prim("sphere", rng, c, rng.uniform(22.0, 45.0)))
        blend = float(rng.uniform(12.0, 20.0))
    else:
        size = {"sphere": 65.0, "box": 55.0, "torus": 55.0, "capsule": 40.0}[kind]
        prims.append(_random_prim(kind, rng, [0, 0, 0], size))
        blend = 0.0
    return SynthObject(prims, blend, seed=int(rng.integers(0, 2**31 - 1)))


# =============================================================================== rendering
@dataclass
class _World:
    """Everything a ray needs: the object, the table and the light, in the LOCAL frame
    (millimetres, z up, table z = 0), plus the similarity local -> world."""

    obj: SynthObject
    table_half: float
    light: Tensor  # (3,) unit, towards the light, local frame
    ambient: float
    soft_shadows: bool
    table_seed: int
    rot: Tensor  # (3, 3) float64 columns = local axes in world coordinates
    origin: Tensor  # (3,) float64 world position of the local origin
    scale: float  # world units per local unit

    def __post_init__(self) -> None:
        self.table_noise = _Noise(self.table_seed)

    def to_local(self, x: Tensor) -> Tensor:
        """(N, 3) world points -> local points."""
        return ((x - self.origin) @ self.rot) / self.scale

    def to_world(self, x: Tensor) -> Tensor:
        """(N, 3) local points -> world points."""
        return (x * self.scale) @ self.rot.T + self.origin


def _sphere_interval(o: Tensor, d: Tensor, c: Tensor, r: float) -> tuple[Tensor, Tensor]:
    """Ray-sphere entry and exit distances (inf, inf when missed). o, d: (N, 3) -> (N,), (N,)."""
    oc = o - c
    b = (oc * d).sum(-1)
    disc = b * b - ((oc * oc).sum(-1) - r * r)
    s = disc.clamp(min=0).sqrt()
    t0 = (-b - s).clamp(min=0.0)
    t1 = -b + s
    miss = (disc <= 0) | (t1 <= 0)
    inf = torch.full_like(t0, math.inf)
    return torch.where(miss, inf, t0), torch.where(miss, inf, t1)


def _sphere_trace(obj: SynthObject, o: Tensor, d: Tensor, t0: Tensor, t1: Tensor,
                  eps: float = 1e-3, min_step: float = 0.02, max_steps: int = 192) -> Tensor:
    """First t in [t0, t1] where the object SDF vanishes (inf where none).

    Sphere tracing (Hart 1996): the SDF is 1-Lipschitz so a step of the SDF value never crosses
    the surface. Steps are at least ``min_step`` so that rays grazing a surface do not crawl; a
    ray that thereby lands inside is bisected back onto the surface (error < 1e-5 world units).
    o, d: (N, 3) origins and unit directions; t0, t1: (N,). Returns (N,).
    """
    ox, oy, oz = o.T.contiguous()
    dx, dy, dz = d.T.contiguous()
    t = t0.clone()
    hit_t = torch.full_like(t0, math.inf)
    idx = torch.nonzero(torch.isfinite(t0) & (t0 < t1)).squeeze(1)
    for _ in range(max_steps):
        if idx.numel() == 0:
            break
        ti = t[idx]
        dist = obj.sdf_xyz(ox[idx] + ti * dx[idx], oy[idx] + ti * dy[idx], oz[idx] + ti * dz[idx])
        done = dist < eps
        hit_t[idx[done]] = ti[done]
        tn = ti + dist.clamp(min=min_step)
        t[idx] = tn
        idx = idx[~done & (tn < t1[idx])]
    # Overshoots by a minimum step: bisect within the last step, which started outside.
    hit = torch.nonzero(torch.isfinite(hit_t)).squeeze(1)
    th = hit_t[hit]

    def f(tt: Tensor, ii: Tensor) -> Tensor:
        return obj.sdf_xyz(ox[ii] + tt * dx[ii], oy[ii] + tt * dy[ii], oz[ii] + tt * dz[ii])

    inside = f(th, hit) < -eps
    ii, hi = hit[inside], th[inside]
    lo = hi - min_step
    for _ in range(12):
        mid = 0.5 * (lo + hi)
        neg = f(mid, ii) < 0
        hi = torch.where(neg, mid, hi)
        lo = torch.where(neg, lo, mid)
    hit_t[ii] = lo
    return hit_t


def _sdf_grad(obj: SynthObject, p: Tensor, h: float) -> Tensor:
    """SDF gradient by central differences (step h). p: (N, 3) -> (N, 3)."""
    x, y, z = p.T.contiguous()
    f = obj.sdf_xyz
    return torch.stack([f(x + h, y, z) - f(x - h, y, z), f(x, y + h, z) - f(x, y - h, z),
                        f(x, y, z + h) - f(x, y, z - h)], -1) / (2 * h)


def _normals(obj: SynthObject, p: Tensor, h: float = 0.02) -> Tensor:
    """Unit outward normals. p: (N, 3) -> (N, 3)."""
    g = _sdf_grad(obj, p, h)
    return g / g.norm(dim=-1, keepdim=True).clamp(min=1e-12)


def _soft_shadow(obj: SynthObject, p: Tensor, light: Tensor, k: float = 16.0,
                 max_steps: int = 64) -> Tensor:
    """Soft shadow factor in [0, 1] (1 = lit) for points p (N, 3) lit from direction ``light``
    (the classic min(k h / t) penumbra estimate along a sphere-traced shadow ray)."""
    c, r = obj.bound()
    d = light.expand_as(p)
    t0, t1 = _sphere_interval(p, d, p.new_tensor(c), r)
    res = torch.ones_like(p[:, 0])
    idx = torch.nonzero(torch.isfinite(t0)).squeeze(1)
    t = t0.clamp(min=0.5)
    px, py, pz = p.T.contiguous()
    lx, ly, lz = (float(v) for v in light)
    for _ in range(max_steps):
        if idx.numel() == 0:
            break
        ti = t[idx]
        h = obj.sdf_xyz(px[idx] + ti * lx, py[idx] + ti * ly, pz[idx] + ti * lz)
        res[idx] = torch.minimum(res[idx], (k * h / ti).clamp(0.0, 1.0))
        t[idx] = ti + h.clamp(0.3, 20.0)
        keep = (res[idx] > 1e-3) & (t[idx] < t1[idx])
        idx = idx[keep]
    return res * res * (3.0 - 2.0 * res)


def _table_albedo(world: _World, p: Tensor) -> Tensor:
    """Wood-and-tiles solid texture of the table. p: (N, 3) -> (N, 3)."""
    coarse = world.table_noise.fbm(p, 40.0, 3)  # warp, blotch
    fine = world.table_noise.fbm(p, 3.0, 2)[2]
    grain = 0.5 + 0.5 * torch.sin(2 * math.pi * (p[:, 0] + 60.0 * coarse[0]) / 9.0)
    wood_a = p.new_tensor([0.55, 0.36, 0.20])
    wood_b = p.new_tensor([0.80, 0.62, 0.40])
    c = wood_a * (1 - grain[:, None]) + wood_b * grain[:, None]
    tile = torch.floor(p[:, :2] / 60.0).to(torch.int64)
    tint = _hash01(tile[:, 0], tile[:, 1], torch.zeros_like(tile[:, 0]), world.table_seed)
    c = c * (0.75 + 0.5 * tint[:, None]) * (0.8 + 0.4 * fine[:, None])
    blot = 0.35 * (coarse[1] > 0.62).to(p.dtype)[:, None]
    c = c * (1 - blot) + p.new_tensor([0.2, 0.3, 0.45]) * blot
    return c.clamp(0.0, 1.0)


def _cast(world: _World, o: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
    """Cast local-frame rays. o, d: (N, 3) float32 -> t (N,) (inf: background), what (N,) int8
    (0 background, 1 table, 2 object)."""
    dz = d[:, 2]
    t_tab = torch.where(dz < -1e-9, -o[:, 2] / dz.clamp(max=-1e-9), torch.full_like(dz, math.inf))
    ptab = o + t_tab.nan_to_num(posinf=0.0)[:, None] * d
    on_table = torch.isfinite(t_tab) & (ptab[:, :2].abs() <= world.table_half).all(-1)
    t_tab = torch.where(on_table, t_tab, torch.full_like(t_tab, math.inf))
    c, r = world.obj.bound()
    t0, t1 = _sphere_interval(o, d, o.new_tensor(c), r)
    t1 = torch.minimum(t1, t_tab)
    t_obj = _sphere_trace(world.obj, o, d, t0, t1)
    what = torch.zeros_like(dz, dtype=torch.int8)
    what[torch.isfinite(t_tab)] = 1
    is_obj = torch.isfinite(t_obj) & (t_obj <= t_tab)
    what[is_obj] = 2
    t = torch.where(is_obj, t_obj, t_tab)
    return t, what


def _shade(world: _World, o: Tensor, d: Tensor, t: Tensor, what: Tensor) -> Tensor:
    """Colour of cast rays (N, 3) in [0, 1]: albedo * (ambient + (1 - ambient) max(0, n.l) vis)."""
    y = (d[:, 2].clamp(-1, 1) + 1) / 2  # background: a dim vertical gradient
    rgb = torch.stack([0.10 + 0.10 * y, 0.11 + 0.12 * y, 0.14 + 0.16 * y], -1)
    light = world.light.to(o.dtype)
    for kind in (1, 2):
        sel = what == kind
        if not bool(sel.any()):
            continue
        p = o[sel] + t[sel, None] * d[sel]
        if kind == 1:
            n = torch.zeros_like(p)
            n[:, 2] = 1.0
            alb = _table_albedo(world, p)
        else:
            n = _normals(world.obj, p)
            alb = world.obj.albedo(p)
        lam = (n @ light).clamp(min=0.0)
        if world.soft_shadows:
            lit = lam > 0
            vis = torch.ones_like(lam)
            if bool(lit.any()):
                vis[lit] = _soft_shadow(world.obj, p[lit] + 0.5 * n[lit], light)
            lam = lam * vis
        rgb[sel] = alb * (world.ambient + (1 - world.ambient) * lam[:, None])
    return rgb.clamp(0.0, 1.0)


def render_view(world: _World, cam: Cameras, supersample: int = 2,
                chunk: int = 1 << 17) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render one view by exact ray casting (sphere tracing of the object SDF, ray-plane table).

    Args:
        world: the scene (object, table, light) and its local -> world similarity.
        cam: one camera (world frame) at the output size.
        supersample: anti-aliasing samples per pixel axis for the colours.
        chunk: rays per chunk.

    Returns:
        image: (H, W, 3) uint8 RGB.
        depth: (H, W) float32 world z-depth at pixel centres, 0 where no surface.
        mask: (H, W) bool, True where the pixel-centre ray first hits the object.
    """
    H, W = cam.height, cam.width
    K = cam.K[0].to(torch.float64)
    w2c = cam.w2c[0].to(torch.float64)
    Kinv = torch.linalg.inv(K)
    R = w2c[:3, :3]
    centre = -(R.T @ w2c[:3, 3])
    o_loc = world.to_local(centre[None])[0]
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64),
                          torch.arange(W, dtype=torch.float64), indexing="ij")
    uv = torch.stack([u.reshape(-1), v.reshape(-1)], -1)
    n_pix = uv.shape[0]
    offs = [0.0] if supersample == 1 else [(k + 0.5) / supersample - 0.5
                                         for k in range(supersample)]

    def local_dirs(uvs: Tensor) -> tuple[Tensor, Tensor]:
        cam_d = torch.cat([uvs, torch.ones_like(uvs[:, :1])], -1) @ Kinv.T  # z = 1
        dw = cam_d @ R  # R^T d, world frame
        dl = dw @ world.rot  # local frame (rotation only)
        norm = dl.norm(dim=-1, keepdim=True)
        # z-depth = t_world * (z-component of the unit camera-frame direction)
        return (dl / norm).to(torch.float32), (1.0 / cam_d.norm(dim=-1)).to(torch.float32)

    depth = np.zeros(n_pix, np.float32)
    mask = np.zeros(n_pix, bool)
    rgb = np.zeros((n_pix, 3), np.float64)
    o32 = o_loc.to(torch.float32)
    # One cast per chunk for the pixel-centre rays (depth, mask) and the supersamples (colour),
    # concatenated: sphere tracing costs per step, not per ray.
    shifts = [(ox, oy) for oy in offs for ox in offs] if supersample > 1 else []
    n_ray = 1 + len(shifts)
    step = max(1, chunk // n_ray)
    for s in range(0, n_pix, step):
        uvc = uv[s:s + step]
        n = uvc.shape[0]
        all_uv = torch.cat([uvc] + [uvc + uvc.new_tensor(sh) for sh in shifts])
        dl, cos = local_dirs(all_uv)
        o = o32.expand_as(dl)
        t, what = _cast(world, o, dl)
        hit = torch.isfinite(t[:n])
        z = torch.where(hit, t[:n] * cos[:n] * world.scale, torch.zeros_like(t[:n]))
        depth[s:s + n] = z.numpy()
        mask[s:s + n] = (what[:n] == 2).numpy()
        first = 0 if supersample == 1 else n
        c = _shade(world, o[first:], dl[first:], t[first:], what[first:]).to(torch.float64)
        rgb[s:s + n] = c.reshape(-1, n, 3).mean(0).numpy()
    img = np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8).reshape(H, W, 3)
    return img, depth.reshape(H, W), mask.reshape(H, W)


# =============================================================================== cameras
def _look_at(pos: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """World-to-camera (4, 4), OpenCV axes, camera at ``pos`` looking at ``target``."""
    f = target - pos
    f = f / np.linalg.norm(f)
    x = np.cross(f, up)
    x = x / np.linalg.norm(x)
    y = np.cross(f, x)
    R = np.stack([x, y, f])
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ pos
    return w2c


def _cap_layout(n: int) -> list[int]:
    """Cameras per row (bottom to top), DTU-like rows."""
    rows = max(1, round(math.sqrt(n)))
    base, extra = divmod(n, rows)
    return [base + (1 if r < extra else 0) for r in range(rows)]


def _cap_cameras(cfg: SynthConfig, target: np.ndarray, rng: np.random.Generator) -> Cameras:
    W, H = cfg.width, cfg.height
    Ks, w2cs = [], []
    rows = _cap_layout(cfg.views)
    e_lo, e_hi = cfg.elevation
    for r, count in enumerate(rows):
        el = math.radians((e_lo + e_hi) / 2 if len(rows) == 1
                          else e_lo + (e_hi - e_lo) * r / (len(rows) - 1))
        for j in range(count):
            frac = 0.5 if count == 1 else j / (count - 1)
            # rows are offset like DTU's staggered rings
            span = cfg.azimuth_span * (1.0 - 0.25 * r / max(1, len(rows) - 1))
            az = math.radians(-span / 2 + span * frac)
            dist = cfg.distance * (1.0 + cfg.distance_jitter * rng.uniform(-1, 1))
            direction = np.array([math.cos(el) * math.sin(az), -math.cos(el) * math.cos(az),
                                  math.sin(el)])
            aim = target + rng.uniform(-3.0, 3.0, size=3)
            w2cs.append(_look_at(target + dist * direction, aim, np.array([0.0, 0.0, 1.0])))
            jit = cfg.intrinsics_jitter  # the draws happen at any jitter: same stream
            f = cfg.focal * W * (1.0 + jit * rng.uniform(-0.01, 0.01))
            K = np.array([[f, 0, (W - 1) / 2 + jit * rng.uniform(-0.02, 0.02) * W],
                          [0, f, (H - 1) / 2 + jit * rng.uniform(-0.02, 0.02) * H],
                          [0, 0, 1.0]])
            Ks.append(K)
    return Cameras(torch.tensor(np.stack(Ks)), torch.tensor(np.stack(w2cs)), W, H)


def _borrowed_cameras(cfg: SynthConfig) -> tuple[Cameras, list[int], np.ndarray]:
    """Cameras of an IDR scene, resized; returns (cameras, view ids, scale_mat (4, 4))."""
    root = Path(cfg.cameras_from)
    npz = next((root / n for n in ("cameras.npz", "cameras_sphere.npz") if (root / n).is_file()),
               None)
    if npz is None:
        raise InputError(f"{root}: no cameras.npz or cameras_sphere.npz to borrow cameras from")
    img_dir = next((root / n for n in ("image", "images") if (root / n).is_dir()), None)
    if img_dir is None:
        raise InputError(f"{root}: no image/ or images/ folder (needed for the original size)")
    files = sorted(p for p in img_dir.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    if not files:
        raise InputError(f"{img_dir}: no images")
    try:
        with Image.open(files[0]) as im:
            W0, H0 = im.size
    except OSError as e:
        raise InputError(f"{files[0]}: unreadable image ({e})") from None
    data = np.load(npz)
    n = sum(1 for k in data.files if k.startswith("world_mat_") and "inv" not in k)
    ids = list(cfg.camera_views) if cfg.camera_views else sorted(
        {int(round(x)) for x in np.linspace(0, n - 1, cfg.views)})
    Ks, w2cs = [], []
    for i in ids:
        if f"world_mat_{i}" not in data.files:
            raise InputError(f"{npz}: view id {i} does not exist (it has {n} cameras)")
        try:
            K, w2c = decompose_projection(torch.tensor(data[f"world_mat_{i}"], dtype=torch.float64))
        except ValueError as e:
            raise InputError(f"{npz}: world_mat_{i}: {e}") from None
        Ks.append(K)
        w2cs.append(w2c)
    cams = Cameras(torch.stack(Ks), torch.stack(w2cs), W0, H0).resize(cfg.width, cfg.height)
    scale_mat = np.asarray(data[f"scale_mat_{ids[0]}"], dtype=np.float64)
    return cams, ids, scale_mat


# =============================================================================== ground truth
def _object_mesh(obj: SynthObject, res: float, chunk: int) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes of the object SDF (local frame). Returns verts (V, 3), faces (F, 3)."""
    from skimage.measure import marching_cubes

    c, r = obj.bound()
    lo = c - r - 2 * res
    n = int(math.ceil((2 * r + 4 * res) / res)) + 1
    ax = [torch.arange(n, dtype=torch.float64) * res + lo[k] for k in range(3)]
    gx, gy, gz = torch.meshgrid(*ax, indexing="ij")
    pts = torch.stack([gx.reshape(-1), gy.reshape(-1), gz.reshape(-1)], -1).to(torch.float32)
    vals = torch.cat([obj.sdf(pts[s:s + chunk]) for s in range(0, len(pts), chunk)])
    vol = vals.reshape(n, n, n).numpy()
    verts, faces, _, _ = marching_cubes(vol, level=0.0, spacing=(res, res, res))
    return verts + lo, faces.astype(np.int64)


def _project_to_surface(obj: SynthObject, p: Tensor, iters: int = 4) -> Tensor:
    """Newton-project points onto the SDF zero set: p <- p - f grad f / |grad f|^2."""
    p = p.to(torch.float64)
    for _ in range(iters):
        g = _sdf_grad(obj, p, 1e-3)
        f = obj.sdf(p)
        p = p - (f / (g * g).sum(-1).clamp(min=1e-12))[:, None] * g
    return p


def _sample_surface(obj: SynthObject, verts: np.ndarray, faces: np.ndarray, n: int,
                    rng: np.random.Generator, chunk: int) -> np.ndarray:
    """Area-uniform samples on the object surface above the table (local frame), (M, 3)."""
    tri = verts[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    fi = rng.choice(len(faces), size=n, p=area / area.sum())
    a, b = rng.random(n), rng.random(n)
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    t = tri[fi]
    pts = t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0])
    p = torch.tensor(pts)
    out = torch.cat([_project_to_surface(obj, p[s:s + chunk]) for s in range(0, n, chunk)])
    res = obj.sdf(out.to(torch.float32)).abs()
    keep = (out[:, 2] > 0.05) & (res < 1e-2)
    return out[keep].numpy()


def _visibility(points: np.ndarray, cams: Cameras, depths: list[np.ndarray]) -> np.ndarray:
    """(V, N) bool: point in front of the rendered surface (within a few pixel footprints)."""
    uv, z = cams.project(torch.tensor(points, dtype=torch.float64))
    out = np.zeros((len(cams), len(points)), bool)
    for v in range(len(cams)):
        u = torch.round(uv[v, :, 0]).long()
        w = torch.round(uv[v, :, 1]).long()
        inside = (u >= 0) & (u < cams.width) & (w >= 0) & (w < cams.height) & (z[v] > 0)
        dm = torch.from_numpy(depths[v]).to(torch.float64)
        d = torch.zeros_like(z[v])
        d[inside] = dm[w[inside], u[inside]]
        fx = float(cams.K[v, 0, 0])
        tol = 3.0 * z[v] / fx + 0.002 * z[v]
        out[v] = (inside & (d > 0) & ((z[v] - d).abs() < tol)).numpy()
    return out


def _pairs(points: np.ndarray, vis: np.ndarray, cams: Cameras, rng: np.random.Generator,
           max_src: int = 10) -> list[list[tuple[int, float]]]:
    """MVSNet view selection score: sum over points seen by both views of a Gaussian of the
    triangulation angle (theta0 = 5 deg, sigma = 1 below / 10 above; MVSNet colmap2mvsnet)."""
    sel = rng.choice(len(points), size=min(len(points), 4000), replace=False)
    pts, vis = points[np.sort(sel)], vis[:, np.sort(sel)]
    centres = cams.centers.numpy()
    V = len(cams)
    out = []
    for i in range(V):
        scores = []
        for j in range(V):
            if j == i:
                continue
            both = vis[i] & vis[j]
            a = centres[i] - pts[both]
            b = centres[j] - pts[both]
            cosang = (a * b).sum(1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
            theta = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
            sig = np.where(theta <= 5.0, 1.0, 10.0)
            scores.append((j, float(np.exp(-((theta - 5.0) ** 2) / (2 * sig**2)).sum())))
        scores.sort(key=lambda x: (-x[1], x[0]))
        out.append(scores[:max_src])
    return out


# =============================================================================== writing
def _write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """np.savez-compatible archive with fixed zip timestamps (byte-deterministic)."""
    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED) as zf:
        for k in sorted(arrays):
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asarray(arrays[k]), allow_pickle=False)
            zf.writestr(zipfile.ZipInfo(k + ".npy", date_time=(1980, 1, 1, 0, 0, 0)),
                        buf.getvalue())


def _write_png(path: Path, arr: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        Image.fromarray(arr).save(tmp, format="PNG")


def _write_npy(path: Path, arr: np.ndarray) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.save(fh, arr)


def _write_text(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def _prepare_out(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is a file; give a folder for the synthetic scene")
    ensure_writable_folder(out, "scene folder")  # before anything is removed or rendered
    if any(out.iterdir()):
        meta = out / "scene.json"
        ok = False
        if meta.is_file():
            try:
                ok = json.loads(meta.read_text()).get("generator") == GENERATOR
            except (OSError, ValueError):
                ok = False
        if not ok:
            raise InputError(
                f"{out}: folder exists, is not empty and is not a synthetic scene; "
                "choose a new or empty folder"
            )
        # an earlier synthetic scene: remove its files so no stale view survives
        for d in _SCENE_DIRS:
            shutil.rmtree(out / d, ignore_errors=True)
        for f in _SCENE_FILES:
            (out / f).unlink(missing_ok=True)


def _json_ready(x):
    if isinstance(x, dict):
        return {k: _json_ready(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_ready(v) for v in x]
    if isinstance(x, (np.ndarray, Tensor)):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x


def make_synthetic_scene(out_dir, cfg: SynthConfig | None = None) -> Path:
    """Render a synthetic scene with ground truth and write it in the IDR layout (module docstring).

    Args:
        out_dir: output folder; created if missing. It must be empty or an earlier synthetic
            scene (whose files are then replaced).
        cfg: generator settings (default `SynthConfig()`: 9 views at 768x576, random object).

    Returns:
        ``out_dir`` as a Path.

    Raises:
        InputError: ``out_dir`` is a file or a non-empty foreign folder; bad ``cameras_from``.
    """
    from tqdm import tqdm

    cfg = cfg or SynthConfig()
    out = Path(out_dir)
    _prepare_out(out)
    rng = np.random.default_rng([cfg.seed, 2])

    obj = make_object(cfg.object, cfg.seed)
    # Stand the object on the table: lowest point 3 mm under z = 0, centred on the z axis.
    verts, faces = _object_mesh(obj, max(cfg.mesh_resolution, 4.0), cfg.chunk)
    lo, hi = verts.min(0), verts.max(0)
    obj.translate(np.array([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -3.0 - lo[2]]))
    verts, faces = _object_mesh(obj, cfg.mesh_resolution, cfg.chunk)
    lo, hi = verts.min(0), verts.max(0)
    vis_lo = np.array([lo[0], lo[1], max(lo[2], 0.0)])
    centre_loc = (vis_lo + hi) / 2
    radius_loc = float(np.linalg.norm(verts[verts[:, 2] > 0] - centre_loc, axis=1).max())

    light = torch.tensor(cfg.light_dir, dtype=torch.float64)
    light = light / light.norm()
    if cfg.cameras_from:
        cams, view_ids, borrowed_scale = _borrowed_cameras(cfg)
        c_world = torch.tensor(borrowed_scale[:3, 3])
        s_world = float(borrowed_scale[0, 0])
        up = -cams.w2c[:, 1, :3].mean(0)
        up = up / up.norm()
        xa = cams.w2c[:, 0, :3].mean(0)
        xa = xa - (xa @ up) * up
        xa = xa / xa.norm()
        rot = torch.stack([xa, torch.linalg.cross(up, xa), up], 1)
        scale = 0.6 * s_world / radius_loc  # the object fills ~60% of the unit sphere
        origin = c_world - scale * (rot @ torch.tensor(centre_loc))
    else:
        view_ids = list(range(cfg.views))
        rot = torch.eye(4, dtype=torch.float64)[:3, :3]
        origin = torch.zeros(3, dtype=torch.float64)
        scale = 1.0
        cams = _cap_cameras(cfg, centre_loc, rng)
    world = _World(obj=obj, table_half=cfg.table_size / 2,
                   light=(rot.T @ light).to(torch.float32),  # the light is given in world axes
                   ambient=cfg.ambient, soft_shadows=cfg.soft_shadows, table_seed=obj.seed + 1000,
                   rot=rot, origin=origin, scale=scale)
    centre_w = world.to_world(torch.tensor(centre_loc)[None])[0].numpy()
    radius_w = radius_loc * scale

    # Normalization, METHOD.md 1.2 (VolSDF): s = 1.1 * max camera distance / 3, but never so
    # small that the object leaves the unit sphere.
    if cfg.cameras_from:
        scale_mat = borrowed_scale
    else:
        max_dist = float(np.linalg.norm(cams.centers.numpy() - centre_w, axis=1).max())
        s = max(1.1 * max_dist / 3.0, 1.05 * radius_w)
        scale_mat = np.eye(4)
        scale_mat[:3, :3] *= s
        scale_mat[:3, 3] = centre_w

    (out / "image").mkdir(exist_ok=True)
    (out / "mask").mkdir(exist_ok=True)
    (out / "gt_depth").mkdir(exist_ok=True)
    depths = []
    npz: dict[str, np.ndarray] = {}
    for i in tqdm(range(len(cams)), desc="synth: rendering", unit="view", disable=None):
        img, depth, mask = render_view(world, cams[i], cfg.supersample, cfg.chunk)
        _write_png(out / "image" / f"{i:06d}.png", img)
        _write_png(out / "mask" / f"{i:03d}.png", (mask * 255).astype(np.uint8))
        _write_npy(out / "gt_depth" / f"{i:03d}.npy", depth)
        depths.append(depth)
        K4 = np.eye(4)
        K4[:3, :3] = cams.K[i].numpy()
        P = K4 @ cams.w2c[i].numpy()
        for name, m in (("world_mat", P), ("scale_mat", scale_mat), ("camera_mat", K4)):
            npz[f"{name}_{i}"] = m
            npz[f"{name}_inv_{i}"] = np.linalg.inv(m)
    _write_npz(out / "cameras.npz", npz)

    # Ground-truth surface: marching cubes, area-uniform samples Newton-projected onto the SDF.
    pts_loc = _sample_surface(obj, verts, faces, cfg.gt_points, rng, cfg.chunk)
    pts_w = world.to_world(torch.tensor(pts_loc)).numpy()
    cols = obj.albedo(torch.tensor(pts_loc, dtype=torch.float32)).numpy()
    write_points_ply(out / "gt_points.ply", pts_w, cols)
    vis = _visibility(pts_w, cams, depths)
    _write_npy(out / "gt_points_visibility.npy", vis.sum(0).astype(np.uint8))
    keepf = verts[faces].mean(1)[:, 2] > 0
    write_mesh_ply(out / "gt_mesh.ply", world.to_world(torch.tensor(verts)).numpy(),
                   faces[keepf])

    pairs = _pairs(pts_w, vis, cams, rng)
    lines = [str(len(cams))]
    for i, src in enumerate(pairs):
        lines.append(str(i))
        lines.append(" ".join([str(len(src))] + [f"{j} {sc:.2f}" for j, sc in src]))
    _write_text(out / "pair.txt", "\n".join(lines) + "\n")

    meta = {
        "generator": GENERATOR,
        "format": "idr",
        "units": "mm" if not cfg.cameras_from else "as in cameras_from",
        "config": asdict(cfg),
        "views": len(cams),
        "view_ids_source": view_ids,
        "width": cfg.width,
        "height": cfg.height,
        "depth": "float32 z-depth at pixel centres in world units; 0 = no surface; table included",
        "mask": "255 = object (first hit at the pixel centre), 0 = table or background",
        "object": {"kind": cfg.object, "blend": obj.blend, "primitives": obj.primitives,
                   "bounding_sphere_world": {"center": centre_w, "radius": radius_w}},
        "local_to_world": {"rotation": world.rot, "origin": world.origin, "scale": world.scale,
                           "note": "object and table are defined in a local frame (z up, table "
                                   "z = 0); world = scale * rotation @ local + origin"},
        "table": {"plane_world": {"normal": world.rot[:, 2], "point": world.origin},
                  "size": cfg.table_size * scale},
        "light_dir_world": light.tolist(),
        "gt_points": int(len(pts_w)),
        "scale_mat": scale_mat,
        "camera_centers": cams.centers.numpy(),
        "depth_range": [[float(d[d > 0].min()) if (d > 0).any() else 0.0, float(d.max())]
                        for d in depths],
    }
    _write_text(out / "scene.json", json.dumps(_json_ready(meta), indent=1, sort_keys=True) + "\n")
    log.info("synthetic scene: %d views %dx%d, %d gt points -> %s", len(cams), cfg.width,
             cfg.height, len(pts_w), out)
    return out
