"""A texture atlas of a mesh baked from the input photos.

Every pair of faces gets one square cell of ``c`` x ``c`` texels in the atlas: the first face
the upper-left half-square, the second the lower-right one, each face's corners at texel centres
one texel inside its half (so bilinear filtering reads only that face's texels, and the texels
on the diagonal, which the first face's colour fills). A texel's colour is that of its point on
the face, averaged over the input views that see the point (`svolsdf.fusion.mesh_ops
.colors_from_images` with the views' depth of the mesh itself). No seam is shared between faces:
a simple atlas that any OBJ reader shows, at ``c``^2 / 2 texels per face.

UV coordinates follow OBJ's convention: u to the right, v up from the image's bottom row.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from svolsdf.scene.cameras import Cameras

__all__ = ["atlas_layout", "bake_atlas"]


def atlas_layout(n_faces: int, max_size: int = 4096, max_cell: int = 16,
                 texels: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Where each face lies in the atlas.

    Args:
        n_faces: F.
        max_size: the atlas's largest side in texels.
        max_cell: the largest cell side (texels per face pair along one side).
        texels: about how many texels the atlas should hold (the cell side follows, between 2
            and ``max_cell``); None: as many as ``max_size`` and ``max_cell`` allow.

    Returns:
        uv: (F, 3, 2) float64 OBJ texture coordinates in [0, 1] of each face's corners;
        face: (S, S) int64 the face each texel belongs to, -1 for unused texels;
        bary: (S, S, 3) float64 its barycentric weights on that face (clamped to the face);
        S: the atlas's side.

    Raises:
        ValueError: the faces do not fit ``max_size`` at two texels per cell side.
    """
    if n_faces < 1:
        raise ValueError("no faces to lay out")
    n = math.ceil(math.sqrt(math.ceil(n_faces / 2)))  # cells per side
    c = min(max_cell, max_size // n)
    if texels is not None:
        c = min(c, max(2, math.isqrt(max(1, 2 * texels // n_faces))))
    if c < 2:
        raise ValueError(f"{n_faces} faces do not fit a {max_size} x {max_size} atlas")
    S = n * c
    y, x = np.mgrid[0:S, 0:S]
    cell = (y // c) * n + x // c
    u, v = x % c + 0.5, y % c + 0.5  # texel centres in the cell
    second = (x % c + y % c) >= c  # the lower-right half
    face = 2 * cell + second
    d = max(c - 2, 1)
    b1 = np.where(second, (c - 0.5 - u) / d, (u - 0.5) / d)
    b2 = np.where(second, (c - 0.5 - v) / d, (v - 0.5) / d)
    bary = np.clip(np.stack([1 - b1 - b2, b1, b2], -1), 0, None)
    if c == 2:  # one texel per face: its centre
        bary = np.full_like(bary, 1 / 3)
    bary /= bary.sum(-1, keepdims=True)
    face = np.where(face < n_faces, face, -1)
    # corners in atlas texel coordinates: first face (0.5, 0.5), (c - 1.5, 0.5), (0.5, c - 1.5);
    # second face (c - 0.5, c - 0.5), (1.5, c - 0.5), (c - 0.5, 1.5)
    f = np.arange(n_faces)
    k = f // 2
    x0, y0 = (k % n) * c, (k // n) * c
    first = np.array([[0.5, 0.5], [c - 1.5, 0.5], [0.5, c - 1.5]])
    last = np.array([[c - 0.5, c - 0.5], [1.5, c - 0.5], [c - 0.5, 1.5]])
    local = np.where((f % 2 == 1)[:, None, None], last, first)
    px = local + np.stack([x0, y0], -1)[:, None, :]
    uv = np.stack([px[..., 0] / S, 1 - px[..., 1] / S], -1)
    return uv, face, bary, S


def bake_atlas(vertices: np.ndarray, faces: np.ndarray, images: Tensor, cameras: Cameras,
               depths: Tensor, rel_tol: float = 0.01, max_size: int = 4096,
               chunk: int = 1 << 20) -> tuple[np.ndarray, np.ndarray]:
    """The mesh's texture atlas from the photos.

    Args:
        vertices: (V, 3) world points; faces: (F, 3).
        images: (N, 3, H, W) float in [0, 1], the photos of ``cameras``.
        cameras: N world `Cameras`.
        depths: (N, H', W') each view's z-depth of this mesh (0 where it shows none): a texel's
            point is seen where its depth agrees within ``rel_tol``.
        max_size: the atlas's largest side (`atlas_layout`); it holds about four texels per
            photo pixel.
        chunk: texels coloured at once (bounds memory).

    Returns:
        uv (F, 3, 2) OBJ texture coordinates, texture (S, S, 3) uint8 (grey where no view sees
        the surface).
    """
    from svolsdf.fusion.mesh_ops import colors_from_images

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    # about four texels per photo pixel: finer only repeats the photos' pixels
    uv, face, bary, S = atlas_layout(len(f), max_size, texels=4 * images[0].numel() // 3
                                     * len(images))
    used = np.flatnonzero(face.ravel() >= 0)
    tri = v[f[face.ravel()[used]]]  # (M, 3, 3)
    pts = np.einsum("mk,mkj->mj", bary.reshape(-1, 3)[used], tri)
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30)
    texture = np.full((S * S, 3), 128, np.uint8)
    for s in range(0, len(used), chunk):
        texture[used[s:s + chunk]] = colors_from_images(
            torch.from_numpy(pts[s:s + chunk]), torch.from_numpy(fn[s:s + chunk]), images,
            cameras, depths=depths, depth_rel_tol=rel_tol).numpy()
    return uv, texture.reshape(S, S, 3)
