"""Named presets: each states only what it changes from the dataclass defaults. Why each value
was chosen, with the measurements: docs/presets.md."""

from __future__ import annotations

import logging

from svolsdf.config.schema import Config, FieldConfig, MeshConfig, MVSConfig, TrainConfig
from svolsdf.errors import InputError

__all__ = ["MVS_SCALE_BY_BACKBONE", "PRESETS", "follow_backbone", "preset", "preset_mvs_scale"]

log = logging.getLogger(__name__)

MVS_SCALE_BY_BACKBONE: dict[str, dict[str, float]] = {"draft": {"planesweep": 1.5}}
"""The ``mvs.scale`` a preset gives each backbone, for the presets that set one: the draft runs
the plane sweep at 1.5x the working size. A backbone not listed keeps its own size (``mvs.scale``
unset: CasMVSNet at 2x, the adapters at the working size), since 1.5 is no size CasMVSNet runs
at (1 or 2) and only the plane sweep's was measured (docs/presets.md)."""


def _paper() -> Config:
    c = Config(preset="paper")
    c.field = FieldConfig(kind="mlp", init="sphere")  # the MLP starts from VolSDF's sphere
    c.train = TrainConfig(steps=100_000, sampler="error_bounded", lr=5e-4, checkpoint_every=5000)
    c.mvs = MVSConfig(backbone="planesweep", width="paper")
    c.mesh = MeshConfig(resolution=512)
    return c


def _fast() -> Config:
    # minutes on two CPU cores for three 768x576 views; docs/presets.md gives each value's evidence
    c = Config(preset="fast")
    c.train.beta_start = 0.05  # beta annealed, not learned: a short run cannot wait for it
    c.train.anneal_rgb = 50  # the paper's 200 warm-up steps would be 20 % of this run
    c.train.colour_min_weight = 1e-4  # colour only at samples whose weight counts (as rendering)
    c.train.prior_floor = 1e-4  # the prior's sources only where P_ref counts
    c.field.init_unverified_weight = 0.05  # one-view stage-1 depth votes in the initial surface
    c.fusion.surface = 5e-4  # the optimized surface counts as one consistent view
    c.fusion.guided_dilation = 4  # a field's depth fused within 4 px of the masks (every mode)
    c.fusion.unguided_dilation = 4  # and the MVS cascade's alone (mvs-only, the unguided set)
    c.fusion.unguided = True  # the unguided stages 2-3 as a second depth hypothesis
    c.guide.mask_dilation = 32  # the guide rendered only near the object masks
    c.mvs.crop_to_masks = 16  # stages 2-3 only near the masks (fusion keeps 4 px of them)
    c.mesh.cull_unseen = True  # the mesh keeps the surface the input views see
    c.mesh.method = "poisson"  # the mesh of the fused points, not of the field
    c.mesh.fit_points = 300  # with mesh.method field: that surface refined to the points
    c.mesh.free_space = True  # no face in space an input view saw empty (docs/meshing.md)
    c.mesh.support = 4.0  # no face farther than 4 point spacings from a point (docs/meshing.md)
    return c


def _draft() -> Config:
    # the fast preset in about half its time, for a few % of Chamfer and ~0.5 dB (docs/presets.md)
    c = _fast()
    c.preset = "draft"
    c.train.steps = 500  # half the field steps
    # the plane sweep at 1.5x the working size instead of 2x; another backbone keeps its own
    # size (MVS_SCALE_BY_BACKBONE, follow_backbone)
    c.mvs.scale = preset_mvs_scale("draft", c.mvs.backbone)
    return c


PRESETS = {"fast": _fast, "draft": _draft, "paper": _paper}


def preset(name: str) -> Config:
    """A fresh `Config` of the named preset."""
    if not isinstance(name, str) or name not in PRESETS:
        raise InputError(f"unknown preset {name!r} (choose from {', '.join(PRESETS)})")
    return PRESETS[name]()




def preset_mvs_scale(name: str, backbone: str) -> float | None:
    """The ``mvs.scale`` the preset ``name`` gives the backbone ``backbone``
    (`MVS_SCALE_BY_BACKBONE`); None: the backbone's own size."""
    return MVS_SCALE_BY_BACKBONE.get(name, {}).get(backbone)


def follow_backbone(cfg: Config, before: str) -> None:
    """``mvs.backbone`` changed from ``before`` and ``mvs.scale`` was not given with it: a scale
    that is the preset's for ``before`` (unset included) becomes the preset's for the new backbone
    (`preset_mvs_scale`), in place, with a line in the log. ``--preset draft --backbone
    casmvsnet`` thus runs CasMVSNet at its own 2x instead of the plane sweep's 1.5, which it
    cannot run at; a scale the user gave stays as given (and `validate_config` refuses one the
    backbone cannot run at). Presets without a per-backbone scale are left as they are."""
    now, scale = cfg.mvs.backbone, cfg.mvs.scale
    if now == before or not isinstance(cfg.preset, str) or cfg.preset not in \
            MVS_SCALE_BY_BACKBONE or isinstance(scale, bool) or \
            not isinstance(scale, (int, float, type(None))):
        return  # unchanged, no such preset, or a value validate_config refuses itself
    mine = preset_mvs_scale(cfg.preset, before)
    if (scale is None) != (mine is None) or (mine is not None and float(scale) != mine):
        return  # not the preset's value: the user's
    cfg.mvs.scale = preset_mvs_scale(cfg.preset, now)
    if cfg.mvs.scale != scale:
        own = "its own size (mvs.scale unset)"
        log.info("mvs.scale: the %s preset runs %s at %s and %s at %s", cfg.preset, before,
                 own if mine is None else f"{mine:g}x", now,
                 own if cfg.mvs.scale is None else f"{cfg.mvs.scale:g}x")
