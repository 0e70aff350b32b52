"""The field kinds, by name: what `FieldConfig.kind` may say and what each name builds.

A field kind is a function of one `FieldInputs` returning a fresh `SurfaceModel`
(`svolsdf.field.base`), registered with ``@register_field_kind("name")``. Adding one is one
module of `svolsdf.field` with one decorator: `field.kind` accepts the name and
`svolsdf.pipeline.builders.build_model` builds it (then attaches the background model and the
beta floor the config asks for).

Built in (in this order): "grid" (the fast preset's dense SDF grid, `svolsdf.field.grid`) and
"mlp" (the paper's VolSDF MLP, `svolsdf.field.volsdf`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from svolsdf.registry import Registry

__all__ = ["FieldInputs", "get_field_kind", "register_field_kind", "registered_field_kinds"]


@dataclass
class FieldInputs:
    """What a field kind may read.

    Attributes:
        field: the run's `FieldConfig` (the kind's options are read from it).
        from_sphere: the field starts from VolSDF's sphere, not from the MVS surface
            (`svolsdf.pipeline.options.grid_from_sphere`).
        bounds: () -> the (2, 3) unit-frame box of a field started from MVS
            (`svolsdf.field.bounds.field_bounds`); call it only when needed.
    """

    field: Any
    from_sphere: bool
    bounds: Callable[[], torch.Tensor]


FieldFactory = Callable[[FieldInputs], Any]

_KINDS: Registry[FieldFactory] = Registry("field kind", "svolsdf.field", "register_field_kind")


def register_field_kind(name: str):
    """Function decorator adding a field kind under ``name``: ``fn(FieldInputs)`` returns the
    `SurfaceModel`."""
    return _KINDS.decorator(name)


def registered_field_kinds() -> list[str]:
    """The names `FieldConfig.kind` accepts, in registration order (the built-in ones first)."""
    return _KINDS.names()


def get_field_kind(name: str) -> FieldFactory:
    """The field kind registered as ``name``.

    Raises:
        InputError: no field kind has that name.
    """
    return _KINDS.get(name)


# --------------------------------------------------------------------------- built in
@register_field_kind("grid")
def _grid(i: FieldInputs):
    """The dense SDF grid (`GridSDFField`), from VolSDF's sphere in the bounding sphere's box
    or from a sphere in the MVS box (the MVS surface is written into it by the field stage)."""
    from svolsdf.field.grid import GridFieldConfig, GridSDFField

    f = i.field
    if i.from_sphere:
        # VolSDF's start (docs/method.md 5.2): a sphere at the origin in the box of the
        # bounding sphere; nothing from MVS
        box = torch.tensor([[-1.0] * 3, [1.0] * 3])
        res, radius, centre = f.sphere_start_resolution, f.sphere_radius, (0.0,) * 3
    else:
        box = i.bounds()
        ext = (box[1] - box[0]).max()
        res, radius = f.grid_start_resolution, float(0.35 * ext)
        centre = tuple(((box[0] + box[1]) / 2).tolist())
    gcfg = GridFieldConfig(resolution=res, init_radius=radius, init_centre=centre,
                           # docs/method.md 5.5: no sphere clamp under a background model
                           sphere_clamp_scale=None if f.background else 20.0)
    return GridSDFField(box, gcfg)


@register_field_kind("mlp")
def _mlp(i: FieldInputs):
    """The paper's VolSDF MLP (`VolSDFField`), ``mlp_depth`` x ``mlp_width``."""
    from svolsdf.field.volsdf import VolSDFField, VolSDFFieldConfig

    f = i.field
    return VolSDFField(VolSDFFieldConfig(n_layers=f.mlp_depth, d_hidden=f.mlp_width,
                                         render_hidden=f.mlp_width,
                                         sphere_clamp=not f.background))
