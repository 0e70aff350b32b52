"""Mesh extraction from an SDF and mesh cleaning: marching cubes, world transform, largest
component, vertex colours, writing (culling by the input views: `svolsdf.fusion.cull`).

docs/method.md 8.3, "Mesh export": marching cubes at resolution 512 of the SDF in the unit frame,
mapped to world coordinates by the normalization (``scale_mat``), keeping the largest component.

Meshes are (vertices (V, 3) float32, faces (F, 3) int64) torch tensors on the CPU. Faces are
oriented so that their normals (right-hand rule) point outwards, i.e. towards SDF > 0.

Memory of `extract_mesh`: the dense grid is resolution^3 float32 values (512: 0.54 GB; 256:
67 MB) plus the marching-cubes output; with ``coarse_to_fine`` the SDF is evaluated only near the
surface, but the grid itself is still allocated.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from scipy import sparse
from skimage import measure
from torch import Tensor

from svolsdf.io.ply import write_mesh_ply, write_obj
from svolsdf.io.progress import progress_bar
from svolsdf.scene.cameras import Cameras
from svolsdf.scene.scene import Normalization

__all__ = [
    "colors_from_fn",
    "colors_from_images",
    "extract_mesh",
    "largest_component",
    "model_colour_fn",
    "save_mesh",
    "submesh",
    "to_world",
    "vertex_normals",
]

log = logging.getLogger(__name__)

SdfFn = Callable[[Tensor], Tensor]


# ---------------------------------------------------------------------------------------------
# marching cubes


def _bounds(bounds) -> np.ndarray:
    """(2, 3) float64 box from a (2, 3) box or a scalar radius (box [-r, r]^3)."""
    if isinstance(bounds, (int, float)):
        r = float(bounds)
        return np.array([[-r, -r, -r], [r, r, r]], dtype=np.float64)
    b = np.asarray(bounds.detach().cpu() if isinstance(bounds, Tensor) else bounds,
                   dtype=np.float64)
    if b.ndim == 0:
        return _bounds(float(b))
    if b.shape != (2, 3) or not (b[1] > b[0]).all():
        raise ValueError(f"bounds must be a radius or a (2, 3) box [min; max], got {b.tolist()}")
    return b


@torch.no_grad()
def _evaluate(sdf_fn: SdfFn, pts: np.ndarray, chunk: int, device, dtype) -> np.ndarray:
    """SDF at (N, 3) float64 points, in chunks -> (N,) float32."""
    out = np.empty(len(pts), dtype=np.float32)
    for s in range(0, len(pts), chunk):
        x = torch.from_numpy(pts[s : s + chunk]).to(device=device, dtype=dtype)
        v = sdf_fn(x).reshape(-1)
        if v.shape[0] != x.shape[0]:
            raise ValueError(
                f"sdf_fn returned {tuple(v.shape)} values for {x.shape[0]} points (expected (N,))"
            )
        out[s : s + chunk] = v.float().cpu().numpy()
    return out


def _axes(b: np.ndarray, n: int) -> list[np.ndarray]:
    return [np.linspace(b[0, i], b[1, i], n) for i in range(3)]


def _dense_grid(sdf_fn, b, n, chunk, device, dtype, progress) -> np.ndarray:
    """(n, n, n) float32 SDF on the grid, evaluated slab by slab along x."""
    xs, ys, zs = _axes(b, n)
    yy, zz = np.meshgrid(ys, zs, indexing="ij")
    slab_yz = np.stack([yy.ravel(), zz.ravel()], axis=-1)  # (n*n, 2)
    grid = np.empty((n, n, n), dtype=np.float32)
    for i in progress_bar(range(n), desc="mesh: marching-cubes grid", unit="slab",
                          show=None if progress else False):
        pts = np.concatenate([np.full((len(slab_yz), 1), xs[i]), slab_yz], axis=1)
        grid[i] = _evaluate(sdf_fn, pts, chunk, device, dtype).reshape(n, n)
    return grid


def _coarse_to_fine_grid(sdf_fn, b, n, step, margin, chunk, device, dtype, progress):
    """(n, n, n) float32 SDF, exact in coarse blocks near the surface, sign-filled elsewhere.

    A coarse grid at every ``step``-th fine point is evaluated first. A coarse block (step^3
    fine cells) is refined when its corners change sign or the smallest |sdf| at its corners is
    below ``margin`` times the block diagonal: for a 1-Lipschitz SDF a block whose corners all
    have |sdf| above its diagonal contains no surface. Fine points touched by no refined block get
    the sign of their nearest coarse point times ``margin`` x block diagonal; every cell where
    the sign changes then lies in a refined block, so marching cubes gives the dense result.
    """
    spacing = (b[1] - b[0]) / (n - 1)
    nc = math.ceil((n - 1) / step)  # coarse blocks per axis
    cidx = np.arange(nc + 1) * step  # fine index of each coarse point (may exceed n - 1)
    axes = [b[0, i] + cidx * spacing[i] for i in range(3)]
    cx, cy, cz = np.meshgrid(*axes, indexing="ij")
    cpts = np.stack([cx.ravel(), cy.ravel(), cz.ravel()], axis=-1)
    coarse = _evaluate(sdf_fn, cpts, chunk, device, dtype).reshape(nc + 1, nc + 1, nc + 1)
    diag = float(np.linalg.norm(spacing * step))

    corners = [coarse[i : i + nc, j : j + nc, k : k + nc]
               for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    cmin = np.minimum.reduce(corners)
    cmax = np.maximum.reduce(corners)
    amin = np.minimum.reduce([np.abs(c) for c in corners])
    active = (cmin <= 0) & (cmax >= 0) | (amin < margin * diag)  # (nc, nc, nc)

    # Fine point i belongs to blocks i // step and (i - 1) // step (two when on a block face).
    i = np.arange(n)
    blk_a = np.clip(i // step, 0, nc - 1)
    blk_b = np.clip((i - 1) // step, 0, nc - 1)
    fine_active = np.zeros((n, n, n), dtype=bool)
    for bx in (blk_a, blk_b):
        for by in (blk_a, blk_b):
            for bz in (blk_a, blk_b):
                fine_active |= active[np.ix_(bx, by, bz)]

    near = np.clip(np.rint(i / step).astype(np.int64), 0, nc)
    fill = np.float32(margin * diag)
    signed = np.where(coarse > 0, fill, -fill).astype(np.float32)
    del corners
    grid = signed[np.ix_(near, near, near)]  # the only resolution^3 float array

    idx = np.nonzero(fine_active)
    n_act = len(idx[0])
    log.info("coarse-to-fine marching cubes: evaluating %d of %d grid points (%.1f%%)",
             n_act, n ** 3, 100.0 * n_act / n ** 3)
    xs, ys, zs = _axes(b, n)
    big = max(chunk, 1 << 18)
    for s in progress_bar(range(0, n_act, big), desc="mesh: marching-cubes grid", unit="chunk",
                          show=None if progress else False):
        sl = slice(s, s + big)
        pts = np.stack([xs[idx[0][sl]], ys[idx[1][sl]], zs[idx[2][sl]]], axis=-1)
        grid[idx[0][sl], idx[1][sl], idx[2][sl]] = _evaluate(sdf_fn, pts, chunk, device, dtype)
    return grid


def extract_mesh(
    sdf_fn: SdfFn,
    bounds=1.0,
    resolution: int = 512,
    chunk: int = 1 << 16,
    level: float = 0.0,
    coarse_to_fine: bool = False,
    coarse_step: int = 4,
    margin: float = 1.5,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float32,
    progress: bool = False,
) -> tuple[Tensor, Tensor]:
    """Marching cubes of an SDF on a regular grid in the unit frame (docs/method.md 8.3).

    The grid has ``resolution`` points per axis spanning ``bounds`` (both ends included). The SDF
    is evaluated under ``torch.no_grad`` in chunks of ``chunk`` points (memory: the grid's
    resolution^3 float32 values, 0.54 GB at 512, plus one chunk of network activations).

    Args:
        sdf_fn: (N, 3) unit-frame points -> (N,) signed distances, > 0 outside.
        bounds: (2, 3) box [min; max] in the unit frame, or a radius r for [-r, r]^3.
        resolution: grid points per axis.
        chunk: points per ``sdf_fn`` call.
        level: iso-value of the surface.
        coarse_to_fine: evaluate a coarse grid first and the fine grid only in blocks near the
            surface (assumes |sdf| is roughly a distance; ``margin`` gives slack). Gives the same
            mesh as the dense grid for a true SDF at a fraction of the evaluations.
        coarse_step: fine cells per coarse block edge.
        margin: a block is refined when min |sdf - level| at its corners < margin * diagonal.
        device, dtype: where and in which precision ``sdf_fn`` receives its points.
        progress: show a progress bar.

    Returns:
        vertices: (V, 3) float32 unit-frame positions.
        faces: (F, 3) int64, oriented outwards (towards SDF > level).

    Raises:
        ValueError: on bad bounds or resolution, or if the level set is empty in the box.
    """
    b = _bounds(bounds)
    resolution = int(resolution)
    if resolution < 2:
        raise ValueError(f"resolution must be >= 2, got {resolution}")
    fn = sdf_fn if level == 0.0 else (lambda x: sdf_fn(x) - level)
    if coarse_to_fine and resolution > 2 * coarse_step:
        grid = _coarse_to_fine_grid(fn, b, resolution, int(coarse_step), float(margin), chunk,
                                    device, dtype, progress)
    else:
        grid = _dense_grid(fn, b, resolution, chunk, device, dtype, progress)
    if not (grid.min() < 0 < grid.max()):
        raise ValueError(
            f"the SDF does not cross level {level} inside the box {b.tolist()} at resolution "
            f"{resolution} (range [{grid.min():.4g}, {grid.max():.4g}])"
        )
    spacing = tuple(float(s) for s in (b[1] - b[0]) / (resolution - 1))
    # a node within a thousandth of a cell of the level set is moved off it (outwards, keeping
    # its sign): two sheets that meet at such a node would share a vertex there, an edge of four
    # faces once coincident float32 vertices are merged (a non-manifold, not closed, surface)
    eps = 1e-3 * min(spacing)
    near = np.abs(grid) < eps
    if near.any():
        grid = np.where(near, np.where(grid < 0, -eps, eps), grid).astype(grid.dtype)
    # skimage orders triangles by the left-hand rule; with SDF < 0 inside, 'descent' yields
    # faces whose right-hand-rule normals point outwards (checked in the tests).
    verts, faces, _, _ = measure.marching_cubes(
        grid, level=0.0, spacing=spacing, gradient_direction="descent", allow_degenerate=False
    )
    verts = verts.astype(np.float64) + b[0]
    return torch.from_numpy(verts.astype(np.float32)), torch.from_numpy(faces.astype(np.int64))


# ---------------------------------------------------------------------------------------------
# transforms and cleaning


def _check_mesh(vertices: Tensor, faces: Tensor) -> tuple[Tensor, Tensor]:
    vertices = torch.as_tensor(vertices)
    faces = torch.as_tensor(faces).long()
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3), got {tuple(vertices.shape)}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must be (F, 3), got {tuple(faces.shape)}")
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError(f"faces index vertices outside [0, {len(vertices)})")
    return vertices, faces


def to_world(vertices: Tensor, normalization: Normalization) -> Tensor:
    """(V, 3) unit-frame vertices -> (V, 3) world vertices (x_world = scale x_unit + center).

    A positive-scale similarity, so face orientation is unchanged.
    """
    return normalization.to_world(torch.as_tensor(vertices))


def submesh(vertices: Tensor, faces: Tensor, keep_faces: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Keep the faces where ``keep_faces`` is true and drop unreferenced vertices.

    Args:
        vertices: (V, 3); faces: (F, 3); keep_faces: (F,) bool.

    Returns:
        vertices (V', 3), faces (F', 3) re-indexed, vertex_index (V',) int64 indices of the kept
        vertices in the input (to carry per-vertex attributes along).
    """
    vertices, faces = _check_mesh(vertices, faces)
    kept = faces[keep_faces.to(torch.bool)]
    used = torch.zeros(len(vertices), dtype=torch.bool)
    used[kept.reshape(-1)] = True
    vertex_index = torch.nonzero(used)[:, 0]
    remap = torch.full((len(vertices),), -1, dtype=torch.int64)
    remap[vertex_index] = torch.arange(len(vertex_index))
    return vertices[vertex_index], remap[kept], vertex_index


def largest_component(vertices: Tensor, faces: Tensor, return_index: bool = False):
    """The connected component (faces sharing vertices) with the largest surface area.

    As VolSDF's mesh export (docs/method.md 8.3: "the largest component is kept"), which splits the
    mesh and keeps the component of largest area.

    Args:
        vertices: (V, 3); faces: (F, 3).

    Returns:
        vertices (V', 3), faces (F', 3) of that component, and with ``return_index`` the
        (V',) indices of its vertices in the input.
    """
    vertices, faces = _check_mesh(vertices, faces)
    if len(faces) == 0:
        empty = torch.zeros(0, dtype=torch.long)
        return (vertices[:0], faces, empty) if return_index else (vertices[:0], faces)
    f = faces.numpy()
    nv = len(vertices)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    adj = sparse.coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(nv, nv))
    _, labels = sparse.csgraph.connected_components(adj, directed=False)
    face_label = labels[f[:, 0]]
    v = vertices.double()
    area = 0.5 * torch.linalg.cross(v[faces[:, 1]] - v[faces[:, 0]],
                                    v[faces[:, 2]] - v[faces[:, 0]]).norm(dim=-1)
    comp_area = np.bincount(face_label, weights=area.numpy())
    best = int(np.argmax(comp_area))
    n_comp = int((np.bincount(face_label) > 0).sum())
    log.info("largest component: %d of %d components, %.1f%% of the area", best, n_comp,
             100.0 * comp_area[best] / max(comp_area.sum(), 1e-30))
    v2, f2, idx = submesh(vertices, faces, torch.from_numpy(face_label == best))
    return (v2, f2, idx) if return_index else (v2, f2)


def vertex_normals(vertices: Tensor, faces: Tensor) -> Tensor:
    """(V, 3) unit area-weighted vertex normals (zeros for unreferenced vertices)."""
    vertices, faces = _check_mesh(vertices, faces)
    v = vertices.double()
    fn = torch.linalg.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    n = torch.zeros_like(v)
    for k in range(3):
        n.index_add_(0, faces[:, k], fn)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    return n.to(vertices.dtype)


# ---------------------------------------------------------------------------------------------
# colours


def colors_from_fn(
    points: Tensor,
    normals: Tensor,
    colour_fn: Callable[[Tensor, Tensor], Tensor],
    chunk: int = 1 << 16,
    device: str | torch.device = "cpu",
) -> Tensor:
    """Vertex colours from a colour callable, e.g. the colour network seen along -normal.

    Args:
        points: (N, 3) in the frame ``colour_fn`` expects (the unit frame for the field, so call
            this before `to_world`).
        normals: (N, 3) unit normals.
        colour_fn: (points (n, 3), normals (n, 3)) -> (n, 3) rgb in [0, 1]; see `model_colour_fn`.
        chunk: points per call.
        device: where ``colour_fn`` receives its inputs.

    Returns:
        (N, 3) uint8.
    """
    out = []
    for s in range(0, len(points), chunk):
        p = points[s : s + chunk].to(device=device, dtype=torch.float32)
        n = normals[s : s + chunk].to(device=device, dtype=torch.float32)
        out.append(colour_fn(p, n).detach().float().cpu())
    if not out:
        return torch.zeros(0, 3, dtype=torch.uint8)
    return (torch.cat(out).clamp(0, 1) * 255).round().to(torch.uint8)


def model_colour_fn(model) -> Callable[[Tensor, Tensor], Tensor]:
    """A ``colour_fn`` for `colors_from_fn` from a `SurfaceModel` (unit frame).

    The colour network sees each vertex along its inward normal (view direction = -normal), with
    the SDF gradient as its normal input and the SDF feature (docs/architecture.md, `SurfaceModel`).
    Gradients are computed (the field's normal may need autograd) but not kept.
    """

    def fn(points: Tensor, normals: Tensor) -> Tensor:
        with torch.enable_grad():
            _, grad, feature = model.sdf_and_grad(points, create_graph=False)
        grad = torch.nn.functional.normalize(grad.detach(), dim=-1)
        with torch.no_grad():
            return model.colour(points, -normals, grad, feature.detach())

    return fn


def _sample(img: Tensor, uv: Tensor, mode: str = "bilinear") -> Tensor:
    """img (C, H, W), uv (N, 2) pixel coordinates (integer centres) -> (N, C), zeros outside."""
    H, W = img.shape[-2:]
    g = torch.stack([2 * uv[:, 0] / max(W - 1, 1) - 1, 2 * uv[:, 1] / max(H - 1, 1) - 1], -1)
    out = torch.nn.functional.grid_sample(
        img[None], g[None, None].to(img.dtype), mode=mode, padding_mode="border",
        align_corners=True,
    )
    return out[0, :, 0].T


def _in_image(uv: Tensor, z: Tensor, width: int, height: int) -> Tensor:
    return (z > 0) & (uv[..., 0] >= -0.5) & (uv[..., 0] <= width - 0.5) & \
        (uv[..., 1] >= -0.5) & (uv[..., 1] <= height - 0.5)


def colors_from_images(
    vertices: Tensor,
    normals: Tensor,
    images: Tensor,
    cameras: Cameras,
    depths: Tensor | None = None,
    depth_rel_tol: float = 0.01,
    min_cos: float = 0.0,
    default: float = 0.5,
) -> Tensor:
    """Vertex colours averaged over the input views that see each vertex.

    A view sees a vertex if the vertex projects inside its image in front of the camera and
    - with ``depths``: |z - depth(x, y)| < depth_rel_tol * z (depth test against the view's
      depth map, bilinear, at the depth map's resolution);
    - without: the normal faces the camera, cos(normal, vertex->camera) > ``min_cos``.

    Args:
        vertices: (N, 3) world points (the cameras' frame).
        normals: (N, 3) unit outward normals.
        images: (V, 3, H, W) float in [0, 1] at the cameras' size.
        cameras: `Cameras` with V views.
        depths: optional (V, Hd, Wd) z-depth maps in world units (any resolution).
        depth_rel_tol: relative depth tolerance of the depth test.
        min_cos: normal-facing threshold when no depths are given.
        default: grey level for vertices seen by no view.

    Returns:
        (N, 3) uint8.
    """
    if images.ndim != 4 or images.shape[1] != 3 or images.shape[0] != len(cameras):
        raise ValueError(f"images must be ({len(cameras)}, 3, H, W), got {tuple(images.shape)}")
    if depths is not None and (depths.ndim != 3 or depths.shape[0] != len(cameras)):
        raise ValueError(f"depths must be ({len(cameras)}, H, W), got {tuple(depths.shape)}")
    images = images.float() / 255.0 if images.dtype == torch.uint8 else images.float()
    x = vertices.double()
    acc = torch.zeros(len(x), 3, dtype=torch.float64)
    cnt = torch.zeros(len(x), dtype=torch.float64)
    cams = cameras.to(dtype=torch.float64)
    centers = cams.centers
    for v in range(len(cams)):
        cam = cams[v]
        uv, z = cam.project(x)
        uv, z = uv[0], z[0]
        vis = _in_image(uv, z, cam.width, cam.height)
        if depths is not None:
            dmap = depths[v].double()
            dc = cam.resize(dmap.shape[1], dmap.shape[0])
            uvd, _ = dc.project(x)
            ok = torch.isfinite(dmap) & (dmap > 0)
            dmap = torch.where(ok, dmap, torch.zeros_like(dmap))
            # Sample depth and validity together: a bilinear sample is only trusted when all
            # its neighbours have a depth (no blending with holes or the background).
            ds = _sample(torch.stack([dmap, ok.double()]), uvd[0], "bilinear").double()
            d = ds[:, 0]
            vis &= (ds[:, 1] > 1 - 1e-6) & ((z - d).abs() < depth_rel_tol * z)
        else:
            to_cam = centers[v] - x
            cos = (normals.double() * to_cam).sum(-1) / to_cam.norm(dim=-1).clamp_min(1e-30)
            vis &= cos > min_cos
        if vis.any():
            acc[vis] += _sample(images[v], uv[vis].float()).double()
            cnt[vis] += 1
    rgb = torch.where(cnt[:, None] > 0, acc / cnt.clamp_min(1)[:, None],
                      torch.full_like(acc, default))
    log.info("image colours: %.1f%% of vertices seen by at least one view",
             100.0 * float((cnt > 0).double().mean()) if len(cnt) else 0.0)
    return (rgb.clamp(0, 1) * 255).round().to(torch.uint8)


# ---------------------------------------------------------------------------------------------
# writing


def save_mesh(path, vertices: Tensor, faces: Tensor, vertex_colors: Tensor | None = None,
              format: str | None = None) -> Path:
    """Write a mesh atomically as binary PLY (default) or OBJ (``format="obj"`` or a .obj path).

    Args:
        path: output file.
        vertices: (V, 3) world points; faces: (F, 3); vertex_colors: (V, 3) uint8 or [0, 1].
        format: "ply" or "obj" (``mesh.format``); default from the suffix (PLY unless it is
            .obj).

    Returns:
        The written path.
    """
    vertices, faces = _check_mesh(vertices, faces)
    path = Path(path)
    fmt = (format or ("obj" if path.suffix.lower() == ".obj" else "ply")).lower()
    if fmt == "ply":
        return write_mesh_ply(path, vertices, faces, vertex_colors)
    if fmt == "obj":
        return write_obj(path, vertices, faces, vertex_colors)
    raise ValueError(f"mesh format must be 'ply' or 'obj', got {fmt!r}")
