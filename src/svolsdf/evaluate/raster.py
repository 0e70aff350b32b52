"""A small CPU z-buffer rasterizer for pictures of a mesh in the report (no GPU, no OpenGL).

`rasterize_mesh` projects a triangle mesh through one pinhole camera (`svolsdf.scene.Cameras`
conventions: OpenCV axes, integer pixel centres) and keeps, per pixel centre, the nearest
triangle, its perspective-correct barycentric coordinates and the z-depth. It is vectorized over
(triangle, pixel-in-bounding-box) pairs, which suits meshes whose triangles cover a few pixels
each (the report renders at thumbnail size). `rasterize_mesh_reference` is the slow,
obviously correct twin the tests compare against. `shade` turns a raster into a picture (vertex
colours times a two-sided Lambert term with a light near the camera) and a camera-frame normal
map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Raster", "rasterize_mesh", "rasterize_mesh_reference", "shade", "vertex_normals"]

_NEAR = 1e-6
_CHUNK = 4_000_000  # (triangle, pixel) candidates per batch: bounds memory for large triangles


@dataclass
class Raster:
    """The visible triangle per pixel.

    Attributes:
        face: (H, W) int64 triangle index, -1 where no triangle covers the pixel centre.
        depth: (H, W) float64 z-depth in the camera frame (world units), 0 where ``face`` is -1.
        bary: (H, W, 3) float64 perspective-correct barycentric weights of the triangle's vertices.
    """

    face: np.ndarray
    depth: np.ndarray
    bary: np.ndarray


def _check(vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> None:
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must be (F, 3), got {faces.shape}")
    if K.shape != (3, 3) or w2c.shape != (4, 4):
        raise ValueError(f"K must be (3, 3) and w2c (4, 4), got {K.shape} and {w2c.shape}")


def _project(vertices, K, w2c):
    # einsum: numpy's (N, 3) @ (3, 3) matmul is ~10x slower on a million rows
    cam = np.einsum("nj,kj->nk", vertices, w2c[:3, :3]) + w2c[:3, 3]
    z = cam[:, 2]
    zs = np.where(np.abs(z) < _NEAR, _NEAR, z)
    uv = np.einsum("nj,kj->nk", cam, K[:2]) / zs[:, None]
    return uv, z


def rasterize_mesh(vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, w2c: np.ndarray,
                   width: int, height: int) -> Raster:
    """Z-buffer rasterization of a mesh at the pixel centres of one camera.

    Triangles with a vertex behind the camera (z <= 1e-6) are dropped; both sides of a triangle
    are drawn.

    Args:
        vertices: (V, 3) world points.
        faces: (F, 3) vertex indices.
        K: (3, 3) intrinsics in pixels at ``width`` x ``height``.
        w2c: (4, 4) world-to-camera matrix (OpenCV axes).
        width, height: image size in pixels.

    Returns:
        `Raster` of (height, width).
    """
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    K, w2c = np.asarray(K, np.float64), np.asarray(w2c, np.float64)
    _check(vertices, faces, K, w2c)
    W, H = int(width), int(height)
    depth = np.full(H * W, np.inf)
    face_buf = np.full(H * W, -1, np.int64)
    bary = np.zeros((H * W, 3))
    if len(faces) and len(vertices):
        uv, z = _project(vertices, K, w2c)
        tri_uv, tri_z = uv[faces], z[faces]  # (F, 3, 2), (F, 3)
        a, b, c = tri_uv[:, 0], tri_uv[:, 1], tri_uv[:, 2]
        area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
        x0 = np.clip(np.ceil(tri_uv[..., 0].min(1)), 0, W)
        x1 = np.clip(np.floor(tri_uv[..., 0].max(1)), -1, W - 1)
        y0 = np.clip(np.ceil(tri_uv[..., 1].min(1)), 0, H)
        y1 = np.clip(np.floor(tri_uv[..., 1].max(1)), -1, H - 1)
        bw = (x1 - x0 + 1).astype(np.int64)
        bh = (y1 - y0 + 1).astype(np.int64)
        keep = (tri_z.min(1) > _NEAR) & (np.abs(area) > 1e-12) & (bw > 0) & (bh > 0)
        fid = np.nonzero(keep)[0]
        count = bw[fid] * bh[fid]
        ends = np.cumsum(count)
        start = 0
        while start < len(fid):
            base = ends[start - 1] if start else 0
            stop = max(start + 1, int(np.searchsorted(ends, base + _CHUNK, side="right")))
            f = fid[start:stop]
            n = count[start:stop]
            rep = np.repeat(np.arange(len(f)), n)
            k = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
            fr = f[rep]
            px = x0[fr] + k % bw[fr]
            py = y0[fr] + k // bw[fr]
            _merge(px, py, fr, a, b, c, area, tri_z, W, depth, face_buf, bary)
            start = stop
    hit = face_buf >= 0
    depth[~hit] = 0.0
    return Raster(face_buf.reshape(H, W), depth.reshape(H, W), bary.reshape(H, W, 3))


def _merge(px, py, fr, a, b, c, area, tri_z, W, depth, face_buf, bary) -> None:
    """Screen-space barycentrics of candidate pixels, then keep the nearest per pixel."""
    ar = area[fr]
    w0 = ((b[fr, 0] - px) * (c[fr, 1] - py) - (b[fr, 1] - py) * (c[fr, 0] - px)) / ar
    w1 = ((c[fr, 0] - px) * (a[fr, 1] - py) - (c[fr, 1] - py) * (a[fr, 0] - px)) / ar
    w2 = 1.0 - w0 - w1
    eps = -1e-9
    inside = (w0 >= eps) & (w1 >= eps) & (w2 >= eps)
    if not inside.any():
        return
    w = np.stack([w0, w1, w2], 1)[inside]
    fr, pix = fr[inside], (py * W + px)[inside].astype(np.int64)
    inv = w / tri_z[fr]  # perspective-correct: interpolate 1/z in screen space
    zz = 1.0 / inv.sum(1)
    order = np.lexsort((zz, pix))
    pix, zz, fr, inv = pix[order], zz[order], fr[order], inv[order]
    first = np.ones(len(pix), bool)
    first[1:] = pix[1:] != pix[:-1]
    pix, zz, fr, inv = pix[first], zz[first], fr[first], inv[first]
    nearer = zz < depth[pix]
    pix, zz, fr, inv = pix[nearer], zz[nearer], fr[nearer], inv[nearer]
    depth[pix] = zz
    face_buf[pix] = fr
    bary[pix] = inv * zz[:, None]


def rasterize_mesh_reference(vertices: np.ndarray, faces: np.ndarray, K: np.ndarray,
                             w2c: np.ndarray, width: int, height: int) -> Raster:
    """`rasterize_mesh` by a loop over pixels and triangles (slow; for tests on tiny inputs)."""
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    uv, z = _project(vertices, np.asarray(K, np.float64), np.asarray(w2c, np.float64))
    face = np.full((height, width), -1, np.int64)
    depth = np.zeros((height, width))
    bary = np.zeros((height, width, 3))
    for y in range(height):
        for x in range(width):
            best = np.inf
            for f, (i, j, k) in enumerate(faces):
                if min(z[i], z[j], z[k]) <= _NEAR:
                    continue
                (ax, ay), (bx, by), (cx, cy) = uv[i], uv[j], uv[k]
                area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
                if abs(area) <= 1e-12:
                    continue
                l0 = ((bx - x) * (cy - y) - (by - y) * (cx - x)) / area
                l1 = ((cx - x) * (ay - y) - (cy - y) * (ax - x)) / area
                l2 = 1 - l0 - l1
                if min(l0, l1, l2) < -1e-9:
                    continue
                inv = np.array([l0 / z[i], l1 / z[j], l2 / z[k]])
                d = 1 / inv.sum()
                if d < best:
                    best = d
                    face[y, x], depth[y, x], bary[y, x] = f, d, inv * d
    return Raster(face, depth, bary)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) float64 unit vertex normals, area-weighted: `svolsdf.fusion.mesh_ops.vertex_normals`
    on numpy arrays."""
    import torch

    from svolsdf.fusion.mesh_ops import vertex_normals as mesh_vertex_normals

    v = torch.from_numpy(np.asarray(vertices, np.float64))
    f = torch.from_numpy(np.asarray(faces, np.int64))
    return mesh_vertex_normals(v, f).numpy()


def shade(raster: Raster, faces: np.ndarray, normals: np.ndarray, w2c: np.ndarray,
          colors: np.ndarray | None = None, background: float = 1.0
          ) -> tuple[np.ndarray, np.ndarray]:
    """A shaded picture and a normal map of a rasterized mesh.

    Args:
        raster: `rasterize_mesh` output, (H, W).
        faces: (F, 3) the rasterized faces.
        normals: (V, 3) unit vertex normals (`vertex_normals`), world frame.
        w2c: (4, 4) the camera's world-to-camera matrix.
        colors: (V, 3) uint8 vertex colours, or None for light grey.
        background: grey level of empty pixels in the picture, in [0, 1].

    Returns:
        picture: (H, W, 3) uint8, colour x (0.3 + 0.7 |n . l|), l a light above-left of the
            camera; normals: (H, W, 3) uint8, (n + 1) / 2 of the camera-frame normal (OpenCV
            axes: x right, y down, z forward), black where empty.
    """
    hit = raster.face >= 0
    H, W = raster.face.shape
    pic = np.full((H, W, 3), background, np.float64)
    nmap = np.zeros((H, W, 3), np.float64)
    if hit.any():
        tri = np.asarray(faces, np.int64)[raster.face[hit]]  # (P, 3)
        wts = raster.bary[hit][..., None]  # (P, 3, 1)
        n = (np.asarray(normals)[tri] * wts).sum(1) @ np.asarray(w2c)[:3, :3].T
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        n[n[:, 2] > 0] *= -1  # two-sided: the side facing the camera
        light = np.array([-0.35, -0.45, -1.0])
        light /= np.linalg.norm(light)
        lam = 0.3 + 0.7 * np.abs(n @ light)
        if colors is None:
            base = np.full((len(tri), 3), 0.8)
        else:
            base = (np.asarray(colors, np.float64)[tri] * wts).sum(1) / 255.0
        pic[hit] = base * lam[:, None]
        nmap[hit] = (n + 1) / 2
    return ((pic.clip(0, 1) * 255 + 0.5).astype(np.uint8),
            (nmap.clip(0, 1) * 255 + 0.5).astype(np.uint8))
