"""A mesh of the final depth maps by truncated signed-distance fusion (TSDF; Curless and Levoy
1996), ``mesh.method`` = "tsdf".

Each view's observed depth (`svolsdf.fusion.observe.observed_depths`: the final depth where the
fused points confirm it) is integrated into a dense voxel grid over the fused points' box: for a
voxel x at z-depth z(x) in a view whose observed depth at x's pixel is d, the projective signed
distance is s = d - z(x) (positive in front of the surface). Voxels with s >= -τ are updated
with the running mean of min(1, s/τ) (weight 1 per view); voxels farther behind a surface are
left unobserved. Marching cubes of the zero level over voxels that some view updated gives the
mesh: only where a view observed a surface, and nothing in space a view saw as empty.

Written here rather than taken from Open3D (not a dependency; its wheels are large and cover
fewer platforms) because it is about 60 lines of torch on top of scikit-image's marching cubes;
vectorized over voxel chunks, it integrates three views into a 384^3 grid in seconds on a CPU.

Points are (N, 3) world points; depth maps are (H, W) z-depth in world units (0 = none); the
mesh is (vertices (V, 3) float64, faces (F, 3) int64) numpy arrays in world units.
"""

from __future__ import annotations

import logging

import numpy as np
import torch
import torch.nn.functional as F
from skimage import measure
from torch import Tensor

from svolsdf.io.progress import progress_bar
from svolsdf.scene.cameras import Cameras

__all__ = ["near_points", "tsdf_grid", "tsdf_mesh"]

log = logging.getLogger(__name__)


def _bilinear_depth(d: Tensor, w: int, h: int, u: Tensor, v: Tensor) -> Tensor:
    """Depth of the flat (H*W,) map ``d`` at (M,) sub-pixel positions: bilinear where the four
    neighbours are observed and agree within 5 %, else the nearest pixel's (0 = none), so that
    no depth is interpolated across an edge."""
    u0 = u.floor().long().clamp(0, w - 1)
    v0 = v.floor().long().clamp(0, h - 1)
    u1, v1 = (u0 + 1).clamp(max=w - 1), (v0 + 1).clamp(max=h - 1)
    a, b = u - u0, v - v0
    d00, d01 = d[v0 * w + u0], d[v0 * w + u1]
    d10, d11 = d[v1 * w + u0], d[v1 * w + u1]
    quad = torch.stack([d00, d01, d10, d11])
    lo, hi = quad.min(0).values, quad.max(0).values
    smooth = (lo > 0) & (hi <= 1.05 * lo)
    bil = (d00 * (1 - a) + d01 * a) * (1 - b) + (d10 * (1 - a) + d11 * a) * b
    near = d[v.round().long().clamp(0, h - 1) * w + u.round().long().clamp(0, w - 1)]
    return torch.where(smooth, bil, near)


def near_points(points: np.ndarray, lo: np.ndarray, voxel: float,
                shape: tuple[int, int, int], radius: float, block: int = 8) -> Tensor:
    """(M,) int64 flat indices of the voxels of a grid within about ``radius`` of some point
    (blocks of ``block``^3 voxels that hold a point, grown by whole blocks): the band in which
    a surface observed at the points can cross zero.

    Args:
        points: (N, 3) world points; lo, voxel, shape: the grid (as `tsdf_grid`).
        radius: world units.
    """
    nb = [int(np.ceil(n / block)) for n in shape]
    ijk = np.floor((np.asarray(points, np.float64) - lo) / voxel + 0.5).astype(np.int64)
    ok = ((ijk >= 0) & (ijk < np.array(shape))).all(axis=1)
    b = torch.from_numpy(ijk[ok] // block)
    occ = torch.zeros(nb, dtype=torch.float32)
    occ[b[:, 0], b[:, 1], b[:, 2]] = 1.0
    r = int(np.ceil(radius / (voxel * block)))
    occ = F.max_pool3d(occ[None, None], 2 * r + 1, stride=1, padding=r)[0, 0] > 0
    blocks = occ.nonzero()  # (B, 3)
    off = torch.stack(torch.meshgrid(*[torch.arange(block)] * 3, indexing="ij"),
                      dim=-1).reshape(-1, 3)
    vox = (blocks[:, None] * block + off[None]).reshape(-1, 3)
    vox = vox[(vox < torch.tensor(shape)).all(dim=1)]
    return (vox[:, 0] * shape[1] + vox[:, 1]) * shape[2] + vox[:, 2]


def tsdf_grid(observed: list[Tensor], cameras: Cameras, lo: np.ndarray, voxel: float,
              shape: tuple[int, int, int], trunc: float, active: Tensor | None = None,
              chunk: int = 1 << 20) -> tuple[np.ndarray, np.ndarray]:
    """Integrate observed depth maps into a TSDF grid.

    Args:
        observed: V (H, W) z-depth maps (0 = not observed).
        cameras: world `Cameras` of the V views (resized to each map).
        lo: (3,) world position of voxel (0, 0, 0)'s centre; voxel: voxel size.
        shape: (nx, ny, nz) voxels.
        trunc: truncation distance τ, world units.
        active: (M,) int64 flat indices of the voxels to integrate (`near_points`); the
            others stay unobserved. None: every voxel.
        chunk: voxels per integration step (memory bound).

    Returns:
        tsdf (nx, ny, nz) float32 in [-1, 1], weight (nx, ny, nz) float32 (views that updated
        each voxel).
    """
    nx, ny, nz = shape
    n = nx * ny * nz
    tsdf = torch.zeros(n, dtype=torch.float32)
    weight = torch.zeros(n, dtype=torch.float32)
    cams = []
    for k, d in enumerate(observed):
        h, w = d.shape
        cam = cameras[[k]].resize(w, h).to(dtype=torch.float32)
        cams.append((cam.K[0], cam.w2c[0], d.float().reshape(-1), w, h))
    origin = torch.as_tensor(lo, dtype=torch.float32)
    m = n if active is None else len(active)
    for s in progress_bar(range(0, m, chunk), desc="mesh: TSDF", unit="chunk"):
        i = torch.arange(s, min(m, s + chunk), dtype=torch.int64)
        if active is not None:
            i = active[i]
        ijk = torch.stack([i // (ny * nz), (i // nz) % ny, i % nz], dim=-1).float()
        x = origin + voxel * ijk  # (M, 3) world
        acc = torch.zeros(len(i))
        cnt = torch.zeros(len(i))
        free = torch.zeros(len(i), dtype=torch.bool)
        for K, w2c, d, w, h in cams:
            xc = x @ w2c[:3, :3].T + w2c[:3, 3]
            z = xc[:, 2]
            uvw = xc @ K.T
            uf = uvw[:, 0] / uvw[:, 2].clamp(min=1e-6)
            vf = uvw[:, 1] / uvw[:, 2].clamp(min=1e-6)
            ok = (z > 0) & (uf >= 0) & (uf <= w - 1) & (vf >= 0) & (vf <= h - 1)
            dv = torch.zeros(len(i))
            dv[ok] = _bilinear_depth(d, w, h, uf[ok], vf[ok])
            sdist = dv - z
            upd = ok & (dv > 0) & (sdist >= -trunc)
            acc += torch.where(upd, (sdist / trunc).clamp(max=1.0), 0.0)
            cnt += upd.float()
            free |= ok & (dv > 0) & (sdist > trunc)
        # a voxel some view saw clearly in front of its surface is empty, whatever the views
        # that see it from behind their surface say (the band behind a surface is thin only
        # in theory: past a silhouette it reaches into empty space)
        tsdf[i] = torch.where(free, 1.0, torch.where(cnt > 0, acc / cnt.clamp(min=1), 0.0))
        weight[i] = cnt
    return tsdf.reshape(shape).numpy(), weight.reshape(shape).numpy()


def tsdf_mesh(points: np.ndarray, observed: list[Tensor], cameras: Cameras, trunc: float,
              resolution: int = 384, margin: float | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """The zero level of the TSDF of ``observed`` depth maps over the fused points' box.

    Args:
        points: (N, 3) fused world points (the grid's box: their 0.1-99.9 % range, grown by
            ``margin``).
        observed: V (H, W) observed z-depth maps (`svolsdf.fusion.observe.observed_depths`).
        cameras: world `Cameras` of the V views.
        trunc: truncation τ, world units (a few final depth steps).
        resolution: voxels along the box's longest side; the voxel is at most τ / 2 (a
            finer voxel is taken when the box is small).
        margin: box growth, world units (default 2 τ).

    Returns:
        vertices (V, 3) float64 world, faces (F, 3) int64, oriented outwards (normals towards
        the cameras' side of the surface).

    Raises:
        ValueError: fewer than 4 points, or no zero crossing (nothing observed).
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 4:
        raise ValueError(f"{len(pts)} fused points: too few for a TSDF box")
    margin = 2 * trunc if margin is None else margin
    lo = np.percentile(pts, 0.1, axis=0) - margin
    hi = np.percentile(pts, 99.9, axis=0) + margin
    voxel = min(float((hi - lo).max()) / resolution, trunc / 2)
    shape = tuple(int(np.ceil((hi[a] - lo[a]) / voxel)) + 1 for a in range(3))
    while np.prod(shape) > resolution ** 3:  # a box finer than `resolution` on every side
        voxel *= 1.25
        shape = tuple(int(np.ceil((hi[a] - lo[a]) / voxel)) + 1 for a in range(3))
    # the zero level lies at the observed depth, which the fused points confirm: voxels
    # within a few voxels of a point hold every crossing
    active = near_points(pts, lo, voxel, shape, radius=3 * voxel, block=4)
    tsdf, weight = tsdf_grid(observed, cameras, lo, voxel, shape, trunc, active=active)
    seen = weight > 0
    if not (seen.any() and (tsdf[seen] < 0).any() and (tsdf[seen] > 0).any()):
        raise ValueError("the TSDF has no zero crossing (no observed surface)")
    # the surface is where s = d - z changes sign, s > 0 in front, so skimage's faces point
    # towards s > 0, i.e. outwards. Only crossings between two observed voxels count: a vertex
    # on an edge with an unobserved end (filled with +1 here) is dropped with its faces
    v, f, _, _ = measure.marching_cubes(np.where(seen, tsdf, 1.0).astype(np.float32),
                                        level=0.0, allow_degenerate=False)
    on_grid = np.abs(v - np.round(v)) < 1e-4  # the two axes along which the edge does not run
    lo_end = np.where(on_grid, np.round(v), np.floor(v)).astype(np.int64)
    hi_end = np.minimum(np.where(on_grid, np.round(v), np.ceil(v)).astype(np.int64),
                        np.array(shape) - 1)
    ok = seen[tuple(lo_end.T)] & seen[tuple(hi_end.T)]
    f = f[ok[f].all(axis=1)]
    used = np.unique(f)
    remap = np.full(len(v), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    v, f = v[used] * voxel, remap[f]
    if len(f) == 0:
        raise ValueError("the TSDF has no zero crossing between observed voxels")
    log.info("TSDF: %s voxels of %.4g, truncation %.4g: %d vertices, %d faces",
             "x".join(map(str, shape)), voxel, trunc, len(v), len(f))
    return v.astype(np.float64) + lo, np.asarray(f, dtype=np.int64)
