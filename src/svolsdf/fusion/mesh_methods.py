"""The mesh methods, by name: what ``mesh.method`` may say and what each name runs.

A method is a function of one `MeshInputs` returning (vw (V, 3) world vertices, faces (F, 3),
colours (V, 3) uint8 or None), registered with ``@register_mesh_method("name")``. Adding one is
one file with one decorator: a module of `svolsdf.fusion` that uses it is imported the first
time a method is asked for (one elsewhere when it is imported), the config accepts its name,
and the mesh stage (`svolsdf.pipeline.mesh.build_mesh`) runs it, falls back to the field's
zero level when it gives no surface, and cleans what it returns like every other method.

Built in: "field" (the field's zero level), "poisson" (screened Poisson of the fused points),
"tsdf" (the TSDF of the observed final depth; with ``mesh.tsdf.fill_holes`` its small holes
filled from the Poisson surface); `svolsdf.fusion.meshing` holds their algorithms.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from torch import Tensor

from svolsdf.errors import raise_if_interrupted
from svolsdf.registry import DeclaresOptions, Registry
from svolsdf.scene.scene import Scene

__all__ = ["MESH_METHODS", "MeshInputs", "MeshMethod", "get_mesh_method",
           "register_mesh_method", "registered_mesh_methods", "run_mesh_method"]

log = logging.getLogger("svolsdf.pipeline")  # the mesh stage's messages, as they always were

MeshResult = tuple[Tensor, Tensor, "Tensor | None"]


@dataclass
class MeshInputs:
    """What a mesh method may read.

    Attributes:
        points, colours: the fused points (N, 3) world and their (N, 3) uint8 colours; None
            unless the method ``needs_points`` (or the cleaning reads them).
        scene: the loaded input views.
        observed: each input view's observed final depth (`svolsdf.fusion.observe`), or None
            (read when the method ``needs_observed`` or free-space culling is on).
        model: the optimized field (a `SurfaceModel`; the refined one after the finer stage).
        field_mesh: the field's zero level as the mesh stage makes it (fitted to the points,
            culled, coloured): () -> (vw, faces, colours).
        mesh: the run's `svolsdf.config.MeshConfig` (the method's options are read from it:
            ``mesh.poisson``, ``mesh.tsdf``, or a section of its own).
        depth_step: the final depth's step per view (`svolsdf.fusion.observe.final_depth_step`).
        use_masks: cull by the scene's masks.
        device: where the field is evaluated.
    """

    points: np.ndarray | None
    colours: np.ndarray | None
    scene: Scene
    observed: list[Tensor] | None
    model: Any
    field_mesh: Callable[[], MeshResult]
    mesh: Any
    depth_step: Tensor
    use_masks: bool
    device: Any = None


@dataclass(frozen=True)
class MeshMethod(DeclaresOptions):
    """A registered method and what it declares (the keywords of ``register_mesh_method``).

    Attributes:
        name: the name ``mesh.method`` accepts.
        run: ``run(inputs)`` -> (vw, faces, colours).
        needs_points: it meshes the fused points (the mesh stage then reads OUT/points.ply and
            needs at least 100 of them); implied by ``needs_observed``.
        needs_observed: it reads the observed final depth (and so the points too).
        needs_field: its surface is the field's zero level: it needs a fitted field (a run
            that fits none makes no mesh of it), and the mesh may be fitted to the fused points
            first (``mesh.fit_points``).
        closed: it can give the closed surface ``mesh.watertight`` asks for.
        options: the dotted config keys of the options it reads (``"mesh.poisson.depth"``), or
            a function of the run's `Config` returning them (options that act only with others
            set); the mesh stage's own options (resolution, culling) are not listed.
            ``reads(cfg)``: {key: value} of them (`svolsdf.registry.DeclaresOptions`).
    """

    name: str
    run: Callable[[MeshInputs], MeshResult]
    needs_points: bool = False
    needs_observed: bool = False
    needs_field: bool = False
    closed: bool = False
    options: tuple[str, ...] | Callable[[Any], tuple[str, ...]] = ()

    def __post_init__(self):
        # the observed depth is the views' depth where the fused points confirm it
        if self.needs_observed:
            object.__setattr__(self, "needs_points", True)



#: name -> method; the modules of `svolsdf.fusion` that use ``@register_mesh_method(...)`` are
#: imported the first time a name is asked for (`svolsdf.registry.Registry`)
MESH_METHODS: Registry[MeshMethod] = Registry("mesh method", "svolsdf.fusion",
                                              "register_mesh_method", entry=MeshMethod)

#: ``@register_mesh_method(name, **declared)``: a function decorator adding a mesh method
#: (`MeshMethod` lists what it may declare)
register_mesh_method = MESH_METHODS.register
#: the names ``mesh.method`` accepts, in registration order (the built-in ones first)
registered_mesh_methods = MESH_METHODS.names
#: the method registered as a name (InputError when none is)
get_mesh_method = MESH_METHODS.get


def run_mesh_method(method: MeshMethod, inputs: MeshInputs
                    ) -> tuple[Tensor, Tensor, Tensor | None, str]:
    """Run ``method`` on ``inputs``; when it gives no surface, the field's zero level instead.

    A method of the points needs at least 100 of them; one that raises RuntimeError, ValueError
    or ImportError (too few or too scattered points, no face left after culling, a missing
    library) is replaced by the "field" method, whose zero level always exists, so the run
    still ends with a mesh, and says which (a warning and the returned source).

    Returns:
        vw (V, 3) world vertices, faces (F, 3), colours (V, 3) uint8 or None, and the source:
        the method's name, or "field (NAME failed: REASON)".
    """
    if not method.needs_field:
        try:
            if method.needs_points and (inputs.points is None or len(inputs.points) < 100):
                n = 0 if inputs.points is None else len(inputs.points)
                raise RuntimeError(f"{n} fused points")
            vw, f, cols = method.run(inputs)
            if len(f) == 0:
                raise RuntimeError("no face left after culling")
            return vw, f, cols, method.name
        except (RuntimeError, ValueError, ImportError) as e:
            raise_if_interrupted()  # a Ctrl-C that pycolmap's import made an error: no fallback
            reason = " ".join(str(e).split())[:200]
            log.warning("mesh: no %s surface of the fused points (%s); the field's zero level "
                        "instead", method.name, reason)
            vw, f, cols = get_mesh_method(_FALLBACK).run(inputs)
            return vw, f, cols, f"field ({method.name} failed: {reason})"
    vw, f, cols = method.run(inputs)
    return vw, f, cols, method.name


# --------------------------------------------------------------------------- built in
#: the method every other one falls back to: the field's zero level always exists
_FALLBACK = "field"


@register_mesh_method("field", needs_field=True, closed=True)
def _field(m: MeshInputs) -> MeshResult:
    """The field's zero level (`svolsdf.fusion.meshing.field_mesh`), the paper's mesh."""
    return m.field_mesh()


_POISSON = ("mesh.poisson.depth", "mesh.poisson.trim")


def _tsdf_options(cfg) -> tuple[str, ...]:
    """The TSDF's options, and the Poisson surface's when it fills the TSDF's small holes."""
    own = ("mesh.tsdf.resolution", "mesh.tsdf.truncation_steps", "mesh.tsdf.fill_holes")
    return own + (_POISSON if cfg.mesh.tsdf.fill_holes > 0 else ())


@register_mesh_method("poisson", needs_points=True, options=_POISSON)
def _poisson(m: MeshInputs) -> MeshResult:
    """Screened Poisson of the fused points (`svolsdf.fusion.meshing.poisson_mesh`)."""
    from svolsdf.fusion.meshing import poisson_mesh

    o = m.mesh
    return poisson_mesh(m.points, m.colours, m.model, m.scene, o.poisson.depth, o.poisson.trim,
                        use_masks=m.use_masks, cull_unseen=o.cull_unseen,
                        cull_tol=o.cull_tol, device=m.device)


@register_mesh_method("tsdf", needs_observed=True, options=_tsdf_options)
def _tsdf(m: MeshInputs) -> MeshResult:
    """The TSDF of the final depth the fused points confirm
    (`svolsdf.fusion.meshing.points_tsdf_mesh`)."""
    from svolsdf.fusion.meshing import points_tsdf_mesh

    if m.observed is None:
        raise RuntimeError("no final depth maps to fuse")
    o = m.mesh
    trunc = float(o.tsdf.truncation_steps * m.depth_step.mean())
    vw, f, c = points_tsdf_mesh(m.points, m.colours, m.scene, m.observed, trunc=trunc,
                                resolution=o.tsdf.resolution, use_masks=m.use_masks,
                                cull_unseen=o.cull_unseen, cull_tol=o.cull_tol)
    if o.tsdf.fill_holes > 0:  # the small holes from the Poisson surface (docs/meshing.md)
        from svolsdf.fusion.meshing import fill_small_holes
        from svolsdf.fusion.observe import point_spacing

        pv, pf, pc = _poisson(m)
        size = o.tsdf.fill_holes * point_spacing(m.points)
        vw, f, c, _ = fill_small_holes(vw, f, c, pv, pf, pc, gap=trunc, max_size=size)
    return vw, f, c
