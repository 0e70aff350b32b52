"""``mvs23``: MVS stages 2 and 3 centred on the guide depth (OUT/depth/<id>.npy;
``mvs.save_volumes``), or the guide itself in the volsdf mode."""

from __future__ import annotations

import numpy as np
import torch

from svolsdf.pipeline import options
from svolsdf.pipeline.rundir import save_npy
from svolsdf.pipeline.stages.base import Stage, StageResult

__all__ = ["MVS23"]


class MVS23(Stage):
    """Final per-view depth ({view: (H, W) world z-depth}): MVS stage 3 guided by the field when
    there is one (after the finer-stage optimization with ``mvs.finer_stage_optimization``); for
    the ``volsdf`` mode, the field's rendered depth itself."""

    name = "mvs23"
    consumes = ("mvs1", "field", "guide")
    scene_inputs = ("images", "cameras")

    def reads(self, cfg):
        # the finer-stage optimization trains the field further: the train section
        return ("mvs.*", "guide.*", "scene.use_masks", "train.mode", "train.ablation",
                *(("train.*",) if cfg.mvs.finer_stage_optimization else ()))

    def key_ignores(self, cfg):
        from svolsdf.mvs.backbone import starts_from_depth

        if options.is_baseline(cfg):  # the guide itself: no MVS runs
            return ("mvs.*",)
        return ("mvs.save_volumes",  # which volumes are kept, not what they hold
                *(() if starts_from_depth(cfg.mvs.backbone) else ("mvs.guide_network",)))

    def backbones(self, cfg):
        return () if options.is_baseline(cfg) else ("mvs",)

    def _files(self, ctx):
        return ctx.dir.view_files(ctx.dir.depth_dir, ctx.views)

    def outputs(self, ctx):
        return list(self._files(ctx).values())

    def load(self, ctx):
        return ctx.reuse_maps(self.name, self._files(ctx))

    def run(self, ctx, inputs):
        from svolsdf.io.images import write_depth_preview

        cfg, ddir, files = ctx.cfg, ctx.dir.depth_dir, self._files(ctx)
        guide, volumes1 = ctx.guide_depth(), inputs["mvs1"]  # the guide as its files hold it
        if options.is_baseline(cfg):
            for v, d in guide.items():
                save_npy(files[v], d.numpy().astype(np.float32))
                write_depth_preview(ddir / f"{v}.png", d)
            return StageResult(guide)
        from svolsdf.mvs.cascade import run_and_save_cascade, save_cascade

        def picture(d, p):
            write_depth_preview(p, torch.from_numpy(d))

        prev = {v.view_id: v for v in volumes1} if guide is None else None
        stages = (2, 3)
        if guide is None and volumes1 is None:
            stages = (1, 2, 3)
        earlier = {1: volumes1} if volumes1 is not None else None
        # stages 2-3's volumes only on request (mvs.save_volumes): nothing reads them again;
        # stage 1's only when run here (the mvs1 stage's files are its own, with its record)
        keep = tuple(k for k in stages if k == 1 or cfg.mvs.save_volumes)
        if cfg.mvs.finer_stage_optimization and guide is not None:
            from svolsdf.pipeline.finer import finer_stage_cascade

            res = finer_stage_cascade(ctx, guide, inputs["field"])
            save_cascade({**res, **(earlier or {})}, ctx.out, picture=picture, volumes=keep)
            return StageResult({v.view_id: v.depth.float() for v in res[max(res)]})
        # one view at a time: only its finer volumes are in memory
        return StageResult(run_and_save_cascade(
            ctx.backbone(), ctx.load(), ctx.out, stages=stages, guide_depth=guide, prev=prev,
            earlier=earlier, picture=picture, volumes=keep))
