"""A reconstruction's mesh: the zero level of the field (marching cubes, docs/method.md 8.3), the
screened Poisson surface of the fused points, or the TSDF of the observed final depth, each
culled to what the input views can judge (`svolsdf.fusion.cull.cull_to_views`), then, as
options, to what they did not see as empty and to what the fused points support
(`clean_mesh`).

Meshes are (vertices (V, 3) float32, faces (F, 3) int64) torch tensors on the CPU; ``vw`` names
world vertices (the cameras' units), ``v`` the same vertices in the field's unit frame.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from svolsdf.errors import raise_if_interrupted
from svolsdf.io.progress import progress_bar
from svolsdf.scene.scene import Scene

__all__ = ["MeshCleanup", "clean_mesh", "field_mesh", "field_mesh_colours", "fill_small_holes",
           "oriented_normals", "poisson_mesh", "points_tsdf_mesh"]

log = logging.getLogger(__name__)


def field_mesh(
    model,
    bounds: Tensor,
    scene: Scene,
    resolution: int,
    watertight: bool = False,
    use_masks: bool = True,
    cull_unseen: bool = False,
    depths: Callable[[], Tensor | None] | str | None = "mesh",
    cull_tol: float = 0.01,
    device=None,
    progress: bool = False,
) -> tuple[Tensor, Tensor, Tensor]:
    """Marching cubes of ``model``'s SDF in ``bounds``, culled by the input views of ``scene``.

    With ``watertight`` the closed zero level: a surface that leaves the field's box is capped
    on the box's faces, and only the largest component is kept (no culling).

    Args:
        model: a `SurfaceModel` (``sdf(x)`` on (N, 3) unit-frame points -> (N,)).
        bounds: (2, 3) unit-frame box to mesh.
        scene: the input views (world cameras, masks at the cameras' size, normalization).
        resolution: marching-cubes cells along the box's longest side.
        use_masks: cull by the scene's masks when it has them.
        cull_unseen, cull_tol: `cull_to_views`'s visibility culling (its ``unseen`` and
            ``rel_tol``; ``mesh.cull_unseen``, ``mesh.cull_tol``).
        depths: what the views see for ``cull_unseen``: a callable returning (N, H, W) z-depth maps
            or None, or "mesh" (`cull_to_views`).
        device: where the SDF is evaluated.

    Returns:
        v (V, 3) unit-frame vertices, vw (V, 3) world vertices, faces (F, 3).
    """
    from svolsdf.fusion.cull import cull_to_views
    from svolsdf.fusion.mesh_ops import extract_mesh, largest_component, to_world

    def sdf_fn(x):
        return model.sdf(x.to(device)).cpu()

    if watertight:
        # a surface that leaves the field's box is closed by a cap on the box's faces: the
        # grid reaches two mesh cells beyond the box, where everything counts as outside
        lo, hi = bounds[0].clone(), bounds[1].clone()
        pad = 2 * float((hi - lo).max()) / resolution
        field_sdf = sdf_fn

        def sdf_fn(x):  # noqa: F811
            out = ((x < lo) | (x > hi)).any(-1)
            return torch.where(out, torch.full_like(x[:, 0], pad), field_sdf(x))

        bounds = torch.stack([lo - pad, hi + pad])
    v, f = extract_mesh(sdf_fn, bounds, resolution=resolution, coarse_to_fine=True,
                        progress=progress)
    vw = to_world(v, scene.normalization)
    if watertight:
        vw, f, idx = largest_component(vw, f, return_index=True)
        return v[idx], vw, f
    masks = scene.masks if use_masks else None
    if cull_unseen and callable(depths):
        depths = depths()
    vw, f, idx = cull_to_views(vw, f, scene.cameras, masks, unseen=cull_unseen, depths=depths,
                               rel_tol=cull_tol)
    return v[idx], vw, f


def field_mesh_colours(model, v: Tensor, faces: Tensor, device=None) -> Tensor | None:
    """(V, 3) vertex colours of a field's mesh from its colour network (unit-frame vertices
    ``v``, faces (F, 3)); None, with a warning, when that fails (colours are a convenience)."""
    from svolsdf.fusion.mesh_ops import colors_from_fn, model_colour_fn, vertex_normals

    try:
        return colors_from_fn(v, vertex_normals(v, faces), model_colour_fn(model), device=device)
    except Exception as e:  # colours are a convenience
        raise_if_interrupted()
        log.warning("mesh colours failed: %s", e)
        return None


def poisson_mesh(
    points: np.ndarray,
    colours: np.ndarray | None,
    model,
    scene: Scene,
    depth: int,
    trim: float,
    use_masks: bool = True,
    cull_unseen: bool = False,
    cull_tol: float = 0.01,
    device=None,
) -> tuple[Tensor, Tensor, Tensor | None]:
    """The screened Poisson surface of fused points, normals oriented by the input cameras and,
    where they straddle a point's tangent plane, by the field's gradient; culled like the
    field's mesh (every component kept), with the mesh's own depth deciding what the views see;
    vertex colours from the points.

    Args:
        points: (N, 3) world points; colours: (N, 3) uint8 or None.
        model: the field (``sdf`` on unit-frame points), for the normals' orientation.
        scene: the input views (world cameras, masks, normalization).
        depth, trim: `svolsdf.fusion.poisson.poisson_surface`'s octree depth and trim.
        use_masks, cull_unseen, cull_tol: as `field_mesh`.
        device: where the field's gradient is evaluated.

    Returns:
        vw (V, 3) world vertices, faces (F, 3), colours (V, 3) or None.
    """
    from svolsdf.fusion.cull import cull_to_views
    from svolsdf.fusion.poisson import poisson_surface

    bar = progress_bar(desc="mesh: Poisson", total=4, unit="step")  # steps of unequal length
    bar.set_postfix_str("normals and orientation")
    normals = oriented_normals(points, scene, model, device=device)
    bar.update(2)
    bar.set_postfix_str("surface")
    # PoissonRecon with one thread: with more, its parallel sums make the mesh differ from run
    # to run on the same points, and it was no faster
    # (benchmarks/results/history/poisson_threads.md)
    v, f, c = poisson_surface(points, normals, colours, depth=depth, trim=trim, threads=1)
    bar.update()
    bar.set_postfix_str("culling")
    vw, f = torch.from_numpy(v), torch.from_numpy(f)
    c = None if c is None else torch.from_numpy(c)
    masks = scene.masks if use_masks else None
    # every part: a Poisson surface trimmed by sample density has no floaters, and separate
    # parts of the object are separate components (the largest alone dropped 15 % of a
    # synthetic object's surface; docs/table1.md, "History of the table")
    vw, f, idx = cull_to_views(vw, f, scene.cameras, masks, unseen=cull_unseen, depths="mesh",
                               rel_tol=cull_tol, largest=False)
    bar.update()
    bar.close()
    return vw, f, (None if c is None else c[idx])


def oriented_normals(points: np.ndarray, scene: Scene, model=None, device=None) -> np.ndarray:
    """Outward normals of fused points: PCA of each point's neighbourhood
    (`svolsdf.fusion.poisson.estimate_normals`), each given the sign that faces the input
    cameras and, where they straddle its tangent plane, the field's SDF gradient (without a
    ``model``, the directions to the cameras; `svolsdf.fusion.poisson.orient_normals`).

    Args:
        points: (N, 3) float64 world points, N > 16.
        scene: the input views (world cameras, normalization).
        model: the field (``sdf`` on unit-frame points), or None.
        device: where the field's gradient is evaluated.

    Returns:
        (N, 3) float64 unit normals.
    """
    from svolsdf.fusion.poisson import estimate_normals, orient_normals

    points = np.asarray(points, np.float64)
    normals = estimate_normals(points, workers=max(1, torch.get_num_threads()))
    guide = None
    if model is not None:
        unit = scene.normalization.to_unit(torch.from_numpy(points)).float()
        grads = []
        for x in unit.split(65536):  # the field's outward direction at each point
            x = x.to(device).requires_grad_(True)
            (g,) = torch.autograd.grad(model.sdf(x).sum(), x)
            grads.append(g.detach().cpu())
        guide = torch.cat(grads).double().numpy()
    return orient_normals(points, normals, scene.cameras.centers.double().numpy(), guide=guide)


def points_tsdf_mesh(
    points: np.ndarray,
    colours: np.ndarray | None,
    scene: Scene,
    observed: list[Tensor],
    trunc: float,
    resolution: int,
    use_masks: bool = True,
    cull_unseen: bool = False,
    cull_tol: float = 0.01,
) -> tuple[Tensor, Tensor, Tensor | None]:
    """The TSDF mesh of the observed final depth (`svolsdf.fusion.tsdf.tsdf_mesh`), culled like
    the Poisson mesh (every component kept); vertex colours of the nearest fused point.

    Args:
        points: (N, 3) fused world points; colours: (N, 3) uint8 or None.
        scene: the input views (world cameras, masks).
        observed: one (H, W) observed z-depth map per input view
            (`svolsdf.fusion.observe.observed_depths`).
        trunc: truncation distance, world units; resolution: voxels along the box's longest
            side.
        use_masks, cull_unseen, cull_tol: as `field_mesh`.

    Returns:
        vw (V, 3) world vertices, faces (F, 3), colours (V, 3) or None.
    """
    from scipy.spatial import cKDTree

    from svolsdf.fusion.cull import cull_to_views
    from svolsdf.fusion.tsdf import tsdf_mesh

    v, f = tsdf_mesh(points, observed, scene.cameras, trunc, resolution=resolution)
    c = None
    if colours is not None:
        _, nn = cKDTree(points).query(v, workers=max(1, torch.get_num_threads()))
        c = torch.from_numpy(np.asarray(colours)[nn])
    vw, f = torch.from_numpy(v).float(), torch.from_numpy(f)
    masks = scene.masks if use_masks else None
    vw, f, idx = cull_to_views(vw, f, scene.cameras, masks, unseen=cull_unseen, depths="mesh",
                               rel_tol=cull_tol, largest=False)
    return vw, f, (None if c is None else c[idx])


def fill_small_holes(
    vw: Tensor,
    faces: Tensor,
    colours: Tensor | None,
    patch_vw: Tensor,
    patch_faces: Tensor,
    patch_colours: Tensor | None,
    gap: float,
    max_size: float,
) -> tuple[Tensor, Tensor, Tensor | None, int]:
    """The mesh (``vw``, ``faces``) with the small holes in it filled from a second surface of
    the same object (the TSDF mesh's holes from the Poisson surface, ``mesh.tsdf.fill_holes``).

    The second surface's faces whose centroid lies farther than ``gap`` from every vertex of the
    mesh are where the mesh has no surface; grouped in connected parts (faces sharing vertices),
    a part is added when it spans at most ``max_size`` (the diagonal of its box) and touches the
    mesh (a vertex within 2 ``gap`` of it): a patch over a hole the mesh surrounds. Larger
    parts (surface extrapolated over a large hole or past a silhouette) and parts away from the
    mesh (islands) are left out. The patch is not stitched to the mesh: its border lies within
    about ``gap`` of the hole's rim.

    Args:
        vw: (V, 3) world vertices of the mesh; faces: (F, 3); colours: (V, 3) uint8 or None.
        patch_vw, patch_faces, patch_colours: the second surface, likewise.
        gap: distance beyond which the mesh has no surface there, world units (more than the
            mesh's vertex spacing, e.g. the TSDF's truncation).
        max_size: the largest part added, world units.

    Returns:
        vw (V + P, 3), faces (F + Q, 3), colours or None (None when a patch is added and either
        mesh has none), and the number of faces added.
    """
    from scipy import sparse
    from scipy.sparse import csgraph
    from scipy.spatial import cKDTree

    from svolsdf.fusion.mesh_ops import _check_mesh, submesh

    vw, faces = _check_mesh(vw, faces)
    patch_vw, patch_faces = _check_mesh(patch_vw, patch_faces)
    if gap <= 0 or max_size < 0:
        raise ValueError(f"gap must be > 0 and max_size >= 0, got {gap} and {max_size}")
    none = (vw, faces, colours, 0)
    if len(faces) == 0 or len(patch_faces) == 0 or max_size == 0:
        return none
    workers = max(1, torch.get_num_threads())
    used = np.unique(faces.numpy())  # vertices no face uses are no surface
    tree = cKDTree(vw.double().numpy()[used])
    pv = patch_vw.double().numpy()
    pf = patch_faces.numpy()
    d, _ = tree.query(pv[pf].mean(axis=1), distance_upper_bound=gap, workers=workers)
    hole = ~np.isfinite(d)
    if not hole.any():
        return none
    hv, hf, hidx = submesh(patch_vw, patch_faces, torch.from_numpy(hole))
    f = hf.numpy()
    n = len(hv)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    adj = sparse.coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n, n))
    n_parts, label = csgraph.connected_components(adj, directed=False)
    x = hv.double().numpy()
    lo = np.full((n_parts, 3), np.inf)
    hi = np.full((n_parts, 3), -np.inf)
    np.minimum.at(lo, label, x)
    np.maximum.at(hi, label, x)
    size = np.linalg.norm(hi - lo, axis=1)
    dv, _ = tree.query(x, distance_upper_bound=2 * gap, workers=workers)
    touches = np.zeros(n_parts, dtype=bool)
    touches[label[np.isfinite(dv)]] = True
    keep_part = touches & (size <= max_size)
    keep = torch.from_numpy(keep_part[label[f[:, 0]]])
    if not keep.any():
        return none
    kv, kf, kidx = submesh(hv, hf, keep)
    log.info("small holes: %d of %d parts outside the mesh filled (%d faces; at most %.4g "
             "across)", int(keep_part.sum()), n_parts, len(kf), max_size)
    out_c = None
    if colours is not None and patch_colours is not None:
        out_c = torch.cat([colours, patch_colours[hidx[kidx]].to(colours.dtype)])
    return (torch.cat([vw, kv.to(vw.dtype)]), torch.cat([faces, kf + len(vw)]), out_c,
            int(len(kf)))


@dataclass
class MeshCleanup:
    """What `clean_mesh` removed: faces before, after free-space culling, after trimming."""

    faces_in: int = 0
    free_space_removed: int = 0
    support_removed: int = 0
    steps: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        return {"faces_in": self.faces_in, "free_space_removed": self.free_space_removed,
                "support_removed": self.support_removed, "steps": list(self.steps)}


def clean_mesh(
    vw: Tensor,
    faces: Tensor,
    colours: Tensor | None,
    scene: Scene,
    observed: list[Tensor] | None = None,
    free_space_tol: Tensor | float | None = None,
    points: np.ndarray | None = None,
    support_k: float = 0.0,
) -> tuple[Tensor, Tensor, Tensor | None, MeshCleanup]:
    """Free-space culling (with ``observed`` and ``free_space_tol``) and support trimming (with
    ``points`` and ``support_k`` > 0) of any mesh, in that order (`svolsdf.fusion.observe`).

    Args:
        vw: (V, 3) world vertices; faces: (F, 3); colours: (V, 3) or None.
        scene: the input views (world cameras).
        observed: one (H, W) observed z-depth map per input view, or None (no free-space
            culling).
        free_space_tol: depth tolerance, world units, a float or (V,) per view.
        points: (N, 3) fused world points, or None (no trimming).
        support_k: the trimming distance in point spacings; 0 = off.

    Returns:
        vw (V', 3), faces (F', 3), colours (V', 3) or None, and what was removed.
    """
    from svolsdf.fusion.observe import cull_free_space, trim_by_support

    info = MeshCleanup(faces_in=int(len(faces)))
    if observed is not None and free_space_tol is not None and len(faces):
        n = len(faces)
        radius = max(1, round(2 * observed[0].shape[1] / scene.cameras.width))
        vw, faces, idx = cull_free_space(vw, faces, scene.cameras, observed, free_space_tol,
                                         radius=radius)
        colours = None if colours is None else colours[idx]
        info.free_space_removed = n - int(len(faces))
        info.steps.append("free-space")
    if points is not None and support_k > 0 and len(faces) and len(points) > 1:
        n = len(faces)
        vw, faces, idx = trim_by_support(vw, faces, points, support_k,
                                         workers=max(1, torch.get_num_threads()))
        colours = None if colours is None else colours[idx]
        info.support_removed = n - int(len(faces))
        info.steps.append(f"support {support_k:g}")
    return vw, faces, colours, info
