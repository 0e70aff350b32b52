"""``field``: the S-VolSDF optimization (OUT/field/model.pt; checkpoints in OUT/field/)."""

from __future__ import annotations

import torch

from svolsdf.field.saved import save_field
from svolsdf.pipeline import builders, options
from svolsdf.pipeline.loaded_run import load_model
from svolsdf.pipeline.stages.base import Stage, StageResult

__all__ = ["Field", "field_trainer"]


def field_trainer(ctx, model, volumes1):
    """The `Trainer` of the field stage for a freshly built ``model`` (its grid initialised from
    the stage-1 MVS depth ``volumes1`` where configured)."""
    from svolsdf.optimize.trainer import Trainer
    from svolsdf.prior.consistency import MVSPrior

    cfg = ctx.cfg
    torch.manual_seed(cfg.train.seed)
    prior = None
    scene = ctx.load()
    if options.uses_prior(cfg) and volumes1 is not None:
        prior = MVSPrior(volumes1, scene.normalization, device=ctx.device,
                         sources=builders.prior_sources(cfg, scene, volumes1))
        if options.field_from_mvs(cfg):  # the kind's start from the MVS surface
            options.field_kind(cfg).init_from_mvs(
                model, ctx.regressed_volumes1(), scene.normalization,
                scene.masks if cfg.scene.use_masks else None, cfg.field.init_unverified_weight)
    return Trainer(model, ctx.train_data(), cfg.train, prior=prior,
                   sampler=builders.build_sampler(cfg, prior), out_dir=ctx.dir.field_dir,
                   device=ctx.device, grid_schedule=builders.grid_schedule(cfg))


def _fresh_model(ctx):
    torch.manual_seed(ctx.cfg.train.seed)  # the box (quantiles of a random subset) too
    return ctx.build_model()


class Field(Stage):
    """The field fitted to the input views (and to the stage-1 volumes' prior in svolsdf mode),
    resumed from OUT/field/checkpoint.pt after an interrupt; an unreadable model or checkpoint
    is discarded (with a warning) and the stage runs again. Its value is the model."""

    name = "field"
    consumes = ("mvs1",)
    scene_inputs = ("images", "masks", "cameras")

    def applies(self, cfg):
        return options.has_field(cfg)

    def reads(self, cfg):
        return ("field.*", "train.*", "scene.use_masks")

    def key_ignores(self, cfg):
        out = ["train.snapshot_every"]  # pictures of the surface as it trains
        if not options.grid_from_sphere(cfg):  # the sphere start's settings
            out += ["field.sphere_radius", "field.sphere_start_resolution",
                    "train.grid_eikonal_weight", "train.lr_sdf_sphere"]
        if not cfg.train.colour_steps:  # the colour phase's settings
            out += ["train.colour_rays", "train.colour_object_fraction"]
        if not cfg.field.background:
            out.append("field.background_model")
        return tuple(out)

    def outputs(self, ctx):
        return [ctx.dir.model]

    def load(self, ctx):
        model = _fresh_model(ctx)
        if ctx.reuse(self.name, [ctx.dir.model], lambda f: load_model(model, f), discard=True):
            return model.to(ctx.device)
        return None

    def run(self, ctx, inputs):
        volumes1 = inputs["mvs1"]
        model = _fresh_model(ctx)
        trainer = field_trainer(ctx, model, volumes1)
        if ctx.inputs_unchanged("field", "field_partial"):
            ckpt = trainer.checkpoint_path()
            if not ctx.reuse("field", [ckpt], trainer.load_checkpoint, discard=True):
                model = _fresh_model(ctx)  # start again, exactly as a fresh run
                trainer = field_trainer(ctx, model, volumes1)
        else:
            ctx.dir.mark("field_partial", ctx.keys["field"], **ctx.provenance("field"))
        ctx.trainer = trainer  # its step, for the message of an interrupt
        from svolsdf.pipeline.snapshots import snapshot_writer, write_snapshot_figure

        snap = snapshot_writer(ctx, model, trainer.step)  # train.snapshot_every
        trainer.fit(progress=ctx.progress, on_step=snap)
        ctx.trainer = None
        if snap is not None:
            write_snapshot_figure(ctx)
        final = ctx.dir.model
        final.parent.mkdir(parents=True, exist_ok=True)
        save_field(final, model)
        hist = trainer.history
        return StageResult(model, steps=ctx.cfg.train.steps,
                           steps_per_s=round(hist[-1]["steps_per_s"], 3) if hist else None)
