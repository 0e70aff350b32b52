"""``mesh``: the mesh the config asks for (OUT/mesh.ply or .obj;
`svolsdf.pipeline.mesh.build_mesh`)."""

from __future__ import annotations

from svolsdf.pipeline import options
from svolsdf.pipeline.stages.base import Stage, StageResult

__all__ = ["Mesh"]


class Mesh(Stage):
    """The field's zero level, the Poisson surface of the fused points or the TSDF of the
    observed final depth, culled by the input views, then by free space and support.
    ``mesh_source`` in OUT/timing.json says which surface it is, and why when it is not the one
    asked for. Its value is the mesh file's path."""

    name = "mesh"
    # the box of a field without one (mvs1), the observed depth (mvs23, unguided), the cull depth
    consumes = ("mvs1", "field", "guide", "mvs23", "unguided", "fusion")
    scene_inputs = ("masks", "cameras")

    def applies(self, cfg):
        return options.has_field(cfg)

    def reads(self, cfg):
        return ("mesh.*", "field.kind", "fusion.unguided", "mvs.finer_stage_optimization",
                "mvs.width", "scene.use_masks", "train.ablation", "train.mode", "train.seed")

    def uses(self, cfg):
        points = _reads_points(cfg)
        return ("mvs1", "field", *(("guide",) if cfg.mesh.cull_unseen else ()),
                *(("mvs23",) if points or cfg.mvs.finer_stage_optimization else ()),
                *(("unguided", "fusion") if points else ()))

    def key_ignores(self, cfg):
        out = [] if _reads_points(cfg) else ["fusion.unguided"]  # the observed depth's sets
        if not cfg.mesh.cull_unseen:
            out.append("mesh.cull_tol")
        if not options.wants_mesh_fit(cfg):
            out.append("mesh.fit_points")
        return tuple(out)

    def outputs(self, ctx):
        return [ctx.dir.mesh(ctx.cfg.mesh.format)]

    recorded = outputs

    def load(self, ctx):
        return self.outputs(ctx)[0]

    def run(self, ctx, inputs):
        from svolsdf.fusion.mesh_ops import save_mesh
        from svolsdf.pipeline.mesh import build_mesh

        path = self.outputs(ctx)[0]
        vw, f, cols, info = build_mesh(ctx, inputs["field"])
        save_mesh(path, vw, f, cols, format=ctx.cfg.mesh.format)
        return StageResult(path, vertices=int(len(vw)), faces=int(len(f)), **info)


def _reads_points(cfg) -> bool:
    """The mesh reads the fused points, and the observed depth where they confirm it
    (`svolsdf.pipeline.mesh.build_mesh`): a method of the points, the fit to them, free-space
    culling, support trimming."""
    return (options.mesh_from_points(cfg) is not None or options.wants_mesh_fit(cfg)
            or cfg.mesh.free_space or cfg.mesh.support > 0)
