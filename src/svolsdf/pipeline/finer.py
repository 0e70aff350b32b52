"""The paper's optional optimization at the finer MVS stages (docs/method.md 9.2.13)."""

from __future__ import annotations

import copy
import logging

import numpy as np
import torch

from svolsdf.field.saved import save_field
from svolsdf.pipeline.context import StageContext
from svolsdf.pipeline.rundir import save_npy

__all__ = ["finer_stage_cascade"]

log = logging.getLogger("svolsdf.pipeline")


def finer_stage_cascade(p: StageContext, guide: dict[int, torch.Tensor], model) -> dict:
    """The paper's optional optimization at the finer stages (docs/method.md 9.2.13; the released
    code forbids it): stage 2 runs centred on the rendered depth, the field is optimized
    further against the soft-consistency prior of the stage-2 volumes, its depth is rendered
    again, and stage 3 runs centred on that depth; with ``mvs.third_stage_optimization`` the
    field is then optimized once more against the stage-3 volumes and rendered again.

    Args:
        p: the running pipeline (`StageContext`: its field, backbone, scene and folder).
        guide: {view: (H, W) world z-depth} the field's rendered depth.
        model: the field stage's `SurfaceModel`, optimized further in place.

    Returns:
        {2: stage-2 volumes, 3: stage-3 volumes}.
    """
    from svolsdf.mvs.cascade import run_cascade
    from svolsdf.optimize.trainer import Trainer
    from svolsdf.pipeline.builders import build_sampler
    from svolsdf.prior.consistency import MVSPrior

    bb = p.backbone()
    scene = p.load()
    res2 = run_cascade(bb, scene, guide_depth=guide, stages=(2,))
    t = p.cfg.train
    # continue at the end of the stage-1 schedule: fixed final beta, no warm-up
    # (a copy, then the changed fields: `replace` would read every field, the colour steps'
    # too, which this schedule never runs)
    t2 = copy.copy(t)
    t2.steps, t2.anneal_rgb, t2.colour_steps = max(1, t.steps // 5), 0, 0
    t2.beta_start = t.beta_end if t.beta_start > 0 else 0.0

    def optimize(volumes, stage: int) -> dict:
        """steps/5 more steps against ``volumes``' prior; the refined field and its depth."""
        prior = MVSPrior(volumes, scene.normalization, device=p.device)
        trainer = Trainer(model, p.train_data(), t2, prior=prior,
                          sampler=build_sampler(p.cfg, prior),
                          out_dir=p.dir.field_dir / f"stage{stage}", device=p.device)
        trainer.fit(progress=p.progress)
        log.info("finer-stage optimization: %d more steps against the stage-%d volumes",
                 t2.steps, stage)
        save_field(p.dir.refined_model, model)
        depth = p.render_guide(model).depth
        for v, d in depth.items():  # the refined surface, for fusion (fusion.surface)
            save_npy(p.dir.render_depth_dir(refined=True) / f"{v}.npy",
                     d.numpy().astype(np.float32))
        return depth

    guide2 = optimize(res2[2], 2)
    res3 = run_cascade(bb, scene, guide_depth=guide2, stages=(3,),
                       prev={v.view_id: v for v in res2[2]})
    if p.cfg.mvs.third_stage_optimization:  # stages 1, 2, 3: once more, against stage 3
        optimize(res3[3], 3)
    return {2: res2[2], 3: res3[3]}
