"""``guide``: rendered z-depth of the input views, which replaces the stage-1 depth
(docs/method.md 6.1; OUT/field/render_depth/<id>.npy)."""

from __future__ import annotations

import numpy as np

from svolsdf.pipeline import options
from svolsdf.pipeline.rundir import save_npy
from svolsdf.pipeline.stages.base import Stage, StageResult

__all__ = ["Guide"]


class Guide(Stage):
    """World z-depth maps ({view: (H, W)}) that centre the finer MVS stages: the field's rendered
    depth, or the stage-1 volumes' consistency depth in the soft-consistency ablation."""

    name = "guide"
    consumes = ("mvs1", "field")
    scene_inputs = ("masks", "cameras")

    def applies(self, cfg):
        return options.has_guide(cfg)

    def reads(self, cfg):
        return ("guide.*", "scene.use_masks", "train.ablation", "train.mode", "train.sampler")

    def _files(self, ctx):
        return ctx.dir.view_files(ctx.dir.render_depth_dir(), ctx.views)

    def outputs(self, ctx):
        return list(self._files(ctx).values())

    def load(self, ctx):
        return ctx.reuse_maps(self.name, self._files(ctx))

    def run(self, ctx, inputs):
        files = self._files(ctx)
        if options.guide_from_consistency(ctx.cfg):
            from svolsdf.prior.consistency import consistency_depth

            guide, psnr = consistency_depth(inputs["mvs1"], ctx.load().normalization), None
        else:
            rendered = ctx.render_guide(inputs["field"], previews=True)
            guide, psnr = rendered.depth, rendered.field_psnr
        for v, d in guide.items():
            save_npy(files[v], d.numpy().astype(np.float32))
        return StageResult(guide, **({"field_psnr": psnr} if psnr is not None else {}))
