"""``mvs1``: stage-1 probability volumes of the input views (OUT/mvs/stage1/<id>.npz)."""

from __future__ import annotations

from svolsdf.mvs.volume import ProbabilityVolume
from svolsdf.pipeline import options
from svolsdf.pipeline.stages.base import Stage, StageResult

__all__ = ["MVS1"]


class MVS1(Stage):
    """The backbone's coarsest stage on every input view (docs/method.md 2); its value is the
    list of `ProbabilityVolume` on the CPU."""

    name = "mvs1"
    scene_inputs = ("images", "cameras")

    def applies(self, cfg):
        return options.runs_mvs1(cfg)

    def reads(self, cfg):
        return ("mvs.*", "scene.use_masks")

    def key_ignores(self, cfg):
        # the options of stages 2-3 alone: the guide's start and the crop to the masks (which
        # scene.use_masks turns off), their widths (stage 1 spans the whole depth range under
        # every mvs.width), which of their volumes are kept, and the optimizations after them
        return ("mvs.guide_network", "mvs.crop_to_masks", "scene.use_masks", "mvs.width",
                "mvs.save_volumes", "mvs.finer_stage_optimization",
                "mvs.third_stage_optimization")

    def backbones(self, cfg):
        return ("mvs",)

    def outputs(self, ctx):
        return [ctx.dir.stage1_file(v) for v in ctx.views]

    def load(self, ctx):
        return ctx.reuse(self.name, self.outputs(ctx), ProbabilityVolume.load)

    def run(self, ctx, inputs):
        from svolsdf.mvs.cascade import run_cascade

        files = self.outputs(ctx)
        res = run_cascade(ctx.backbone(), ctx.load(), stages=(1,))
        files[0].parent.mkdir(parents=True, exist_ok=True)
        for v in res[1]:
            v.save(ctx.dir.stage1_file(v.view_id))
        return StageResult([v.to("cpu") for v in res[1]])  # as when read back from the files
