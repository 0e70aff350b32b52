"""From a `Config` to the components a run uses: the MVS backbone (and the fusion network), the
field (`SurfaceModel`), its coarse-to-fine schedule, the ray sampler, the training data.

Used by the stages, by the stage keys (the backbone's full config) and by commands that open a
finished run (`svolsdf.pipeline.loaded_run.Run`). Imports of the components stay inside the
builders: only the built objects' modules are loaded, and tests may replace a component's class
in its own module.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from svolsdf.config import Config
from svolsdf.errors import InputError
from svolsdf.pipeline.options import field_from_mvs, field_kind
from svolsdf.scene.scene import Scene

__all__ = ["attach_background", "backbone_kwargs", "build_backbone", "build_model",
           "build_network_backbone", "build_sampler", "build_train_data", "grid_schedule",
           "prior_sources", "unit_near_far"]


def backbone_kwargs(cfg: Config) -> dict:
    """The configured MVS backbone's options (`svolsdf.mvs.backbone.get_backbone`'s ``**cfg``):
    the backbone's own reading of `MVSConfig` (`svolsdf.mvs.backbone.MVSBackbone.options`).

    Raises:
        InputError: ``mvs.scale`` the backbone cannot run at.
    """
    from svolsdf.mvs.backbone import backbone_options

    out = backbone_options(cfg.mvs.backbone, cfg.mvs)
    if not cfg.scene.use_masks:  # mvs.crop_to_masks crops to the masks the run uses
        out.pop("crop_to_masks", None)
    return out


def build_backbone(cfg: Config, device=None):
    """The configured `MVSBackbone` (its weights loaded) on ``device``."""
    from svolsdf.mvs.backbone import get_backbone

    m = cfg.mvs
    return get_backbone(m.backbone, weights=m.weights, device=device, **backbone_kwargs(cfg))


def build_network_backbone(cfg: Config, device=None):
    """The ``fusion.network`` backbone, its weights loaded and checked.

    Raises:
        InputError: the backbone cannot start from a depth map.
    """
    from svolsdf.mvs.backbone import get_backbone

    bb = get_backbone(cfg.fusion.network, weights=cfg.fusion.network_weights,
                      max_sources=cfg.mvs.max_sources, device=device)
    if not bb.can_start_from_depth:
        raise InputError(f"fusion.network: the {cfg.fusion.network!r} backbone "
                         "cannot start from a depth map (patchmatchnet can)")
    return bb


def build_model(cfg: Config, bounds: Callable[[], torch.Tensor]):
    """The configured `SurfaceModel` (`svolsdf.field.kinds`: the grid field for fast, the VolSDF
    MLP for paper, or any kind registered with ``@register_field_kind``).

    Args:
        bounds: returns the (2, 3) unit-frame box of a grid field started from MVS
            (`svolsdf.field.bounds.field_bounds`); not called otherwise.

    Raises:
        InputError: ``field.kind`` names no registered kind.
    """
    from svolsdf.field.kinds import FieldInputs

    f = cfg.field
    model = field_kind(cfg).build(FieldInputs(f, not field_from_mvs(cfg), bounds))
    if f.background:
        attach_background(model, f.kind, f.background_model)
    lap = model.laplace_density()
    if cfg.train.beta_min > 0 and lap is not None:
        lap.beta_min = float(cfg.train.beta_min)  # docs/method.md 5.4's floor
    return model


def attach_background(model, kind: str, background_model: str = "nerf++") -> None:
    """``model.background``: the NeRF++ inverted-sphere background (docs/method.md 5.5), or
    with ``background_model`` = "sphere_map" the colour map on the bounding sphere
    (`svolsdf.field.background.SphereMapBackground`, trained at the grid rate).

    A submodule of the field, so it moves with ``model.to(device)``, is saved in its
    state_dict (keys ``background.net.*``, ``background.colour_net.*``), trained by the
    Trainer at the network rate ``train.lr`` and passed to every ``render_rays`` call. The
    paper's network sizes unless the field kind asks for others (`FieldKind.background`: a
    smaller MLP beside the fast grid field).

    Args:
        model: the `SurfaceModel`, with a ``radius`` (its bounding sphere's).
        kind: its registered field kind (``field.kind``).
    """
    from svolsdf.field.background import (
        BackgroundConfig,
        NeRFPlusPlusBackground,
        SphereMapBackground,
    )
    from svolsdf.field.kinds import get_field_kind

    if background_model == "sphere_map":
        model.background = SphereMapBackground(float(model.radius))
        return
    bcfg = BackgroundConfig(radius=float(model.radius), **get_field_kind(kind).background)
    model.background = NeRFPlusPlusBackground(bcfg)


def grid_schedule(cfg: Config) -> list[tuple[int, int]]:
    """The field's coarse-to-fine schedule, [(step, resolution)], from its kind
    (`FieldKind.schedule`: the grid's; [] for a kind without one, the MLP)."""
    schedule = field_kind(cfg).schedule
    return schedule(cfg.field, cfg.train, not field_from_mvs(cfg)) if schedule else []


def build_sampler(cfg: Config, prior=None, training: bool = True):
    """The configured ray sampler (`svolsdf.render.sampler_registry`): the MVS-guided one (with
    ``prior`` in training; a lighter one without a prior for rendering), VolSDF's error-bounded
    one, or any registered with ``@register_sampler``.

    Raises:
        InputError: ``train.sampler`` names no registered sampler.
    """
    from svolsdf.render.sampler_registry import SamplerInputs, get_sampler

    return get_sampler(cfg.train.sampler)(SamplerInputs(cfg.train, prior, training))


def unit_near_far(scene: Scene) -> torch.Tensor:
    """(V, 2) unit-frame z-depth range of the input views, padded by 10% (rays are clipped
    to it in training, guide rendering and novel views)."""
    nf = (scene.depth_range / scene.normalization.scale).float()
    return torch.stack([nf[:, 0] * 0.9, nf[:, 1] * 1.1], -1)


def build_train_data(cfg: Config, scene: Scene, mvs_depth: torch.Tensor | None = None):
    """The field stage's `TrainData`: images (V, 3, H, W), unit-frame cameras, near/far,
    ``mvs_depth`` (V, H, W) unit-frame depth of the ablations, and with
    ``train.object_ray_fraction`` or ``train.colour_steps`` the object masks dilated by
    ``train.object_ray_dilation``."""
    from svolsdf.optimize.trainer import TrainData

    focus = None
    wants = cfg.train.object_ray_fraction > 0 or cfg.train.colour_steps > 0
    if wants and scene.masks is not None and cfg.scene.use_masks:
        from svolsdf.geometry import dilate_mask

        r = cfg.train.object_ray_dilation
        focus = torch.stack([dilate_mask(m[0], r) for m in scene.masks])
    return TrainData(scene.images, scene.cameras_unit, unit_near_far(scene), mvs_depth, focus)


def prior_sources(cfg: Config, scene: Scene, volumes: list) -> list[list[int]] | None:
    """``train.prior_sources = selected``: for each stage-1 volume of ``volumes``, the indices (in
    their order) of its view's MVS sources in ``scene`` (`svolsdf.mvs.backbone.select_sources`);
    None (every other view, docs/method.md 3) for ``all``."""
    if cfg.train.prior_sources == "all":
        return None
    from svolsdf.mvs.backbone import select_sources

    order = [v.view_id for v in volumes]
    return [[order.index(s) for s in select_sources(scene, vid, cfg.mvs.max_sources)
             if s in order] for vid in order]
