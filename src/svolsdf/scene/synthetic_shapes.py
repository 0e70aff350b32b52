"""Procedural objects of the synthetic scenes (`svolsdf.scene.synthetic`): solid textures from
seeded value noise, exact signed distance functions of spheres, rounded boxes, tori and capsules,
and their smooth union (`SynthObject`, built by `make_object`).

Objects live in a local frame: millimetres, z up; `make_synthetic_scene` stands them on the table.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "OBJECT_KINDS",
    "SynthObject",
    "make_object",
]

OBJECT_KINDS = ("random", "sphere", "box", "torus", "capsule", "blobs")
"""Object kinds: ``random`` is a smooth union of 3-6 mixed primitives; the others are one primitive
(or, for ``blobs``, smooth-blended spheres only)."""


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
        contrast: texture contrast; 1 is the full pattern, lower values pull every colour
            towards the primitive's mean colour (a low-texture object, hard for MVS).
    """

    primitives: list[dict]
    blend: float
    seed: int
    contrast: float = 1.0

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
            c = c * (1 - spots) + cols[2] * spots
            if self.contrast != 1.0:
                c = cols.mean(0) + self.contrast * (c - cols.mean(0))
            out[sel] = c
        if self.contrast != 1.0:
            fine = 0.5 + self.contrast * (fine - 0.5)
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


def _sdf_grad(obj: SynthObject, p: Tensor, h: float) -> Tensor:
    """SDF gradient by central differences (step h). p: (N, 3) -> (N, 3)."""
    x, y, z = p.T.contiguous()
    f = obj.sdf_xyz
    return torch.stack([f(x + h, y, z) - f(x - h, y, z), f(x, y + h, z) - f(x, y - h, z),
                        f(x, y, z + h) - f(x, y, z - h)], -1) / (2 * h)
