"""``fusion``: geometric-consistency filtering and fusion of the depth sets (OUT/points.ply,
docs/method.md 6.3; `svolsdf.pipeline.fusion_stage.fuse`)."""

from __future__ import annotations

import logging

from svolsdf.errors import InputError
from svolsdf.pipeline import options
from svolsdf.pipeline.stages.base import Stage, StageResult

__all__ = ["Fusion"]

# the run's messages in OUT/log keep the logger name they always had
log = logging.getLogger("svolsdf.pipeline")


def no_points_message(ctx) -> str:
    """Why fusion kept no point, as far as the run can tell, and what to try."""
    why = []
    if ctx.load().masks is not None and ctx.cfg.scene.use_masks:
        why.append("the object masks")
    f = ctx.cfg.fusion
    return (f"{ctx.out}: fusion kept no point: no pixel's depth agrees in "
            f"{f.min_views} other input view(s) within {f.dist} px / "
            f"{f.rel:g} relative depth"
            + (f" inside {why[0]}" if why else "")
            + f" (views {ctx.views}). Check that the cameras look at the object and "
              "overlap (svolsdf info SCENE --sheet sheet.png), or pick views with more "
              "overlap (--views auto)")


class Fusion(Stage):
    """The depth sets (the final depth, the unguided set, the fusion network's, the surface)
    filtered and fused into coloured points; its value is the path of OUT/points.ply. It reads
    the depth stages' files, which the runner finished before."""

    name = "fusion"
    consumes = ("guide", "mvs23", "unguided")  # the surface's depth (fusion.surface): guide's
    scene_inputs = ("images", "masks", "cameras")

    def reads(self, cfg):
        return ("fusion.*", "guide.low_weight_rule", "mvs.finer_stage_optimization",
                "scene.use_masks", "train.ablation", "train.mode",
                # the fusion network's sources
                *(("mvs.max_sources",) if options.wants_network(cfg) else ()))

    def backbones(self, cfg):
        return ("fusion",) if options.wants_network(cfg) else ()

    def outputs(self, ctx):
        return [ctx.dir.points]

    def load(self, ctx):
        return ctx.dir.points

    def run(self, ctx, inputs):
        from svolsdf.pipeline import fusion_stage

        path = ctx.dir.points
        n, extra = fusion_stage.fuse(ctx, path)
        if n == 0:  # never a finished run: nothing downstream can use it
            path.unlink(missing_ok=True)
            raise InputError(no_points_message(ctx))
        log.info("fused %d points -> %s %s", n, path, extra.get("points_per_set", ""))
        return StageResult(path, points=n, **extra)
