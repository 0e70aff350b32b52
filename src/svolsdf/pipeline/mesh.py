"""The mesh stage's inputs: the method ``mesh.method`` names in the registry
(`svolsdf.fusion.mesh_methods`: the field's zero level, the Poisson surface of the fused points,
the TSDF of the observed final depth, or any registered one), what it falls back to when that
fails (and says so), and the culling every method gets (`svolsdf.fusion.meshing` holds the
algorithms)."""

from __future__ import annotations

import copy
import logging
from pathlib import Path

import numpy as np
import torch

from svolsdf.field.saved import save_field
from svolsdf.pipeline import options
from svolsdf.pipeline.context import StageContext
from svolsdf.pipeline.loaded_run import Run, load_model

__all__ = ["build_mesh", "observed_depths_of"]

log = logging.getLogger("svolsdf.pipeline")


def observed_depths_of(run: Run | StageContext, points: np.ndarray) -> list[torch.Tensor] | None:
    """Each input view's final depth (OUT/depth) where the fused ``points`` (N, 3) confirm it,
    the unguided set (OUT/unguided/depth, when the config fuses it: files an earlier config left
    are not read) where the guided one is not confirmed (`svolsdf.fusion.observe.observed_depths`):
    one (H, W) map per input view, or None when a view's depth map is missing.

    Args:
        run: a `Run` whose depth stages are finished.
    """
    from svolsdf.fusion.observe import observed_depths

    sets = []
    for v in run.views:
        files = [run.out / "depth" / f"{v}.npy"]
        if options.wants_unguided(run.cfg):
            files.append(run.dir.unguided_dir / "depth" / f"{v}.npy")
        if not files[0].is_file():
            return None
        sets.append([torch.from_numpy(np.load(f)).float() for f in files if f.is_file()])
    return observed_depths(torch.from_numpy(np.asarray(points)), run.load().cameras, sets)


def _fused_points(p: StageContext) -> Path:
    """OUT/points.ply as the fusion stage left it.

    Raises:
        RuntimeError: the fusion stage has not written it (it runs before the mesh stage).
    """
    if not p.dir.points.is_file():
        raise RuntimeError(f"the fusion stage has not run: {p.dir.points} is missing")
    return p.dir.points


def build_mesh(p: StageContext, model
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, dict]:
    """The run's mesh as the ``mesh`` section asks: (vw (V, 3) world vertices, faces (F, 3), colours
    (V, 3) uint8 or None, timing extras: ``mesh_source``, ``method``, ``cleanup``, ``points``).

    The method is ``mesh.method``'s in the registry (`svolsdf.fusion.mesh_methods`;
    the field's with a watertight mesh). ``mesh_source`` is its name ("field", "poisson",
    "tsdf", ...), or "field (poisson failed: REASON)" (the same for any other method) when it
    gave no surface and the field's zero level, which always exists, replaced it.

    Args:
        p: the running pipeline (`StageContext`), its fusion stage finished.
        model: the field stage's `SurfaceModel` (its state replaced by the refined field's
            when the finer-stage optimization made one).

    Raises:
        RuntimeError: free-space culling and trimming left no face.
    """
    from svolsdf.fusion.mesh_methods import MeshInputs, get_mesh_method, run_mesh_method
    from svolsdf.fusion.meshing import clean_mesh
    from svolsdf.fusion.observe import final_depth_step
    from svolsdf.io.ply import read_ply

    if p.cfg.mvs.finer_stage_optimization and p.dir.refined_model.is_file():
        # the field after the finer-stage optimization
        load_model(model, p.dir.refined_model)
    scene = p.load()
    mc = p.cfg.mesh
    use_masks = scene.masks is not None and p.cfg.scene.use_masks
    step = final_depth_step(scene.depth_range, p.cfg.mvs.width)
    # the watertight mesh is the field's closed zero level, whatever the method
    chosen = get_mesh_method("field" if mc.watertight else mc.method)
    method = options.mesh_from_points(p.cfg)
    pts = cols_pts = observed = None
    if method is not None or mc.free_space or mc.support > 0:
        d = read_ply(_fused_points(p))
        pts, cols_pts = d["points"], d["colors"]
    if (chosen.needs_observed or mc.free_space) and len(pts):
        observed = observed_depths_of(p, pts)
    inputs = MeshInputs(points=pts, colours=cols_pts, scene=scene, observed=observed,
                        model=model, field_mesh=lambda: _field_mesh(p, model, scene, use_masks),
                        mesh=mc, depth_step=step, use_masks=use_masks, device=p.device)
    vw, f, cols, source = run_mesh_method(chosen, inputs)
    # the watertight mesh is the whole closed zero level by definition: no face is cut from it,
    # and timing.json / metrics.json say so (docs/meshing.md)
    closed = mc.watertight and source == "field"
    free = mc.free_space and not closed
    vw, f, cols, cleanup = clean_mesh(
        vw, f, cols, scene, observed=observed if free else None,
        free_space_tol=mc.free_space_steps * step if free else None,
        points=pts, support_k=0.0 if closed else mc.support)
    if len(f) == 0:
        raise RuntimeError("mesh: no face left after free-space culling and trimming")
    info = {"mesh_source": source, "method": source.split(" ")[0],
            "cleanup": cleanup.as_dict()}
    if closed and (mc.free_space or mc.support > 0):
        info["cleanup"]["not_applied"] = ("mesh.watertight: the closed surface is kept whole "
                                          "(no free-space culling or support trimming)")
    if method is not None:
        info["points"] = int(len(pts))
    return vw, f, cols, info


def _field_mesh(p: StageContext, model, scene, use_masks: bool):
    """The field's zero level, culled (`svolsdf.fusion.meshing.field_mesh`), with colours from
    its colour network: (vw (V, 3), faces (F, 3), colours (V, 3) or None)."""
    from svolsdf.fusion.meshing import field_mesh, field_mesh_colours

    fit = options.wants_mesh_fit(p.cfg)
    if fit:
        model = _surface_fitted_to_points(p, model)
    model.eval()
    b = model.box()  # a grid's own box, else the field's (`SurfaceModel.box`)
    bounds = b.detach().cpu() if b is not None else p.field_bounds()
    # the fitted surface moved away from the rendered depth: the views' depth of the mesh
    # itself decides what they see
    mc = p.cfg.mesh
    depths = "mesh" if fit else (lambda: _mesh_cull_depths(p, options.refines_field(p.cfg)))
    v, vw, f = field_mesh(model, bounds, scene, mc.resolution, watertight=mc.watertight,
                          use_masks=use_masks, cull_unseen=mc.cull_unseen, depths=depths,
                          cull_tol=mc.cull_tol, device=p.device, progress=p.progress)
    return vw, f, field_mesh_colours(model, v, f, device=p.device)


def _mesh_cull_depths(p: StageContext, refined: bool) -> torch.Tensor | None:
    """(V, H, W) rendered depth of the input views (the refined field's with ``refined``), for
    `cull_unseen`; None when it is missing or is not the surface (the soft-consistency
    ablation's guide)."""
    if p.cfg.train.ablation == "soft-consistency-only":
        return None
    sdir = p.dir.render_depth_dir(refined and p.dir.refined_model.is_file())
    files = [sdir / f"{v}.npy" for v in p.views]
    if not all(f.is_file() for f in files):
        return None
    maps = [torch.from_numpy(np.load(f)).float() for f in files]
    if len({tuple(m.shape) for m in maps}) != 1:
        return None
    return torch.stack(maps)


def _surface_fitted_to_points(p: StageContext, model):
    """A copy of ``model`` whose SDF grid is refined to pass through OUT/points.ply
    (``mesh.fit_points``); saved as OUT/field/surface.pt."""
    from svolsdf.field.fit import fit_sdf_to_points
    from svolsdf.io.ply import read_ply

    scene = p.load()
    pts = read_ply(_fused_points(p))["points"]
    unit = scene.normalization.to_unit(torch.from_numpy(pts).double()).float()
    fitted = copy.deepcopy(model)
    fit_sdf_to_points(fitted, unit.to(p.device), fit_points=p.cfg.mesh.fit_points,
                      seed=p.cfg.train.seed)
    save_field(p.dir.surface_model, fitted)
    return fitted
