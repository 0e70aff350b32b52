"""``unguided`` (``fusion.unguided``, the fast preset's; not in the paper): MVS stages 2 and 3
centred on the stage-1 depth, as the backbone alone runs them (OUT/unguided/depth/<id>.npy)."""

from __future__ import annotations

from svolsdf.pipeline import options
from svolsdf.pipeline.stages.base import Stage, StageResult

__all__ = ["Unguided"]


class Unguided(Stage):
    """The backbone alone's cascade: OUT/unguided/{depth,confidence}/<view>.npy, confidence the
    product over stages 1-3 (docs/method.md 6.2); fusion takes it as every view's second depth
    hypothesis. Its value is {view: (H, W) world z-depth}."""

    name = "unguided"
    consumes = ("mvs1",)
    scene_inputs = ("images", "cameras")

    def applies(self, cfg):
        return options.wants_unguided(cfg)

    def reads(self, cfg):
        return ("mvs.*", "scene.use_masks")

    def key_ignores(self, cfg):
        # centred on the stage-1 depth, not on a guide; its volumes are never kept; the
        # optimizations act on the guided stages only
        return ("mvs.guide_network", "mvs.save_volumes", "mvs.finer_stage_optimization",
                "mvs.third_stage_optimization")

    def backbones(self, cfg):
        return ("mvs",)

    def _files(self, ctx):
        return ctx.dir.view_files(ctx.dir.unguided_dir / "depth", ctx.views)

    def outputs(self, ctx):
        return list(self._files(ctx).values())

    def load(self, ctx):
        return ctx.reuse_maps(self.name, self._files(ctx))

    def run(self, ctx, inputs):
        from svolsdf.mvs.cascade import run_and_save_cascade

        vols1 = inputs["mvs1"]
        # depth, confidence over stages 1-3, one view at a time
        return StageResult(run_and_save_cascade(
            ctx.backbone(), ctx.load(), ctx.dir.unguided_dir, stages=(2, 3),
            prev={v.view_id: v for v in vols1}, earlier={1: vols1}, volumes=False))
