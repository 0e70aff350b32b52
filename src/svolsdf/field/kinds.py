"""The field kinds, by name: what `FieldConfig.kind` may say, what each name builds and what the
kind can do.

A field kind is a function of one `FieldInputs` returning a fresh `SurfaceModel`
(`svolsdf.field.base`), registered with ``@register_field_kind("name", ...)``, whose keywords
are the kind's capabilities (`FieldKind`): whether it can start from the stage-1 MVS surface,
whether the mesh may be fitted to the fused points, its coarse-to-fine schedule, its own checks
of the config and the size of its background model. Adding one is one module of
`svolsdf.field` with one decorator: `field.kind` accepts the name,
`svolsdf.pipeline.builders.build_model` builds it (then attaches the background model and the
beta floor the config asks for), and the pipeline and the config's validation ask the registry
entry, never the name, what the kind can do.

Built in (in this order): "grid" (the fast preset's dense SDF grid, `svolsdf.field.grid`) and
"mlp" (the paper's VolSDF MLP, `svolsdf.field.volsdf`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import torch

from svolsdf.registry import DeclaresOptions, Registry

__all__ = ["FIELD_KINDS", "FieldInputs", "FieldKind", "Refusal", "check_grid", "check_mlp",
           "get_field_kind", "grid_memory", "grid_resolution_schedule", "register_field_kind",
           "registered_field_kinds", "starts_from_mvs"]


@dataclass
class FieldInputs:
    """What a field kind may read.

    Attributes:
        field: the run's `FieldConfig` (the kind's options are read from it).
        from_sphere: the field starts from VolSDF's sphere, not from the MVS surface (False only
            for a kind with ``init_from_mvs``: `svolsdf.pipeline.options.field_from_mvs`).
        bounds: () -> the (2, 3) unit-frame box of a field started from MVS
            (`svolsdf.field.bounds.field_bounds`); call it only when needed.
    """

    field: Any
    from_sphere: bool
    bounds: Callable[[], torch.Tensor]


FieldFactory = Callable[[FieldInputs], Any]

#: a refused pair of options: (dotted key, its value, the other dotted key, its value, why);
#: `svolsdf.config.validate` words it as ``key = value with other = value: why``
Refusal = tuple[str, Any, str, Any, str]

#: (model, stage-1 volumes, normalization, (V, 1, H, W) masks or None, init_unverified_weight)
MVSStart = Callable[[Any, list, Any, "torch.Tensor | None", float], Any]

#: (FieldConfig, TrainConfig, from_sphere) -> [(step, resolution)], ascending steps
Schedule = Callable[[Any, Any, bool], list[tuple[int, int]]]

#: (FieldConfig, TrainConfig, from_sphere) -> the first refused pair of options, or None
Check = Callable[[Any, Any, bool], "Refusal | None"]

#: (FieldConfig) -> [(the options that set an allocation, bytes, what it is)]
Memory = Callable[[Any], "list[tuple[tuple[str, ...], float, str]]"]


@dataclass(frozen=True)
class FieldKind(DeclaresOptions):
    """A field kind's registry entry: what it builds and what it can do (the keywords of
    `register_field_kind`).

    Attributes:
        build: `FieldInputs` -> a fresh `SurfaceModel`.
        init_from_mvs: writes the stage-1 MVS surface into a freshly built model, in place:
            ``fn(model, volumes, normalization, masks, init_unverified_weight)`` (field.init
            "mvs" in svolsdf mode; the model is then built in the MVS box, ``from_sphere``
            False). None:
            the kind always starts from VolSDF's sphere, and field.init "mvs" is refused in
            svolsdf mode.
        sphere_options: the kind started from a sphere reads the sphere start's options
            (field.sphere_radius, field.sphere_start_resolution, train.grid_eikonal_weight,
            train.lr_sdf_sphere), so they enter the field stage's key then
            (`svolsdf.pipeline.options.grid_from_sphere`).
        fits_points: ``mesh.fit_points`` applies: the model has an ``sdf_grid`` that
            `svolsdf.field.fit.fit_sdf_to_points` refines to the fused points.
        schedule: the coarse-to-fine schedule the `Trainer` follows ([(step, resolution)]);
            None: none.
        check: the kind's cross-checks of the config, run by `svolsdf.config.validate_config`
            after the general ones; None: none.
        background: `svolsdf.field.background.BackgroundConfig` fields other than the radius
            of the background model it gets with field.background (empty: the paper's sizes).
        memory: (FieldConfig) -> lower bounds of the largest allocations the kind makes,
            [(the options that set it, bytes, what it is)], for the memory check before a run
            (`svolsdf.config.validate.memory_needs`); None: none worth checking.
        options: the dotted config keys of the ``field.*`` options the kind reads (its build,
            schedule and checks), or a function of the run's config returning them;
            ``reads(cfg)``: {key: value} of them (`svolsdf.registry.DeclaresOptions`).
    """

    build: FieldFactory
    init_from_mvs: MVSStart | None = None
    sphere_options: bool = False
    fits_points: bool = False
    schedule: Schedule | None = None
    check: Check | None = None
    background: Mapping[str, Any] = field(default_factory=dict)
    memory: Memory | None = None
    options: tuple[str, ...] | Callable[[Any], tuple[str, ...]] = ()

    @property
    def starts_from_mvs(self) -> bool:
        """The kind can start from the stage-1 MVS surface (it has ``init_from_mvs``)."""
        return self.init_from_mvs is not None


def _kind_entry(name: str, build: FieldFactory, *, background: Mapping[str, Any] | None = None,
                **declared: Any) -> FieldKind:
    return FieldKind(build, background=dict(background or {}), **declared)


#: name -> field kind; the modules of `svolsdf.field` that use ``@register_field_kind(...)`` are
#: imported the first time a name is asked for (`svolsdf.registry.Registry`)
FIELD_KINDS: Registry[FieldKind] = Registry("field kind", "svolsdf.field", "register_field_kind",
                                            entry=_kind_entry)

#: ``@register_field_kind(name, **declared)``: a function decorator adding a field kind, whose
#: ``fn(FieldInputs)`` returns the `SurfaceModel`; the keywords are `FieldKind`'s fields
register_field_kind = FIELD_KINDS.register
#: the names `FieldConfig.kind` accepts, in registration order (the built-in ones first)
registered_field_kinds = FIELD_KINDS.names
#: the field kind registered as a name (InputError when none is; call its ``build`` for a model)
get_field_kind = FIELD_KINDS.get


def starts_from_mvs(field_cfg: Any, train_cfg: Any) -> bool:
    """The field of a run starts from the stage-1 MVS surface: its kind can (``init_from_mvs``),
    ``field.init`` is "mvs", and the field is fitted under the prior (``train.mode`` svolsdf,
    not the soft-consistency ablation, which fits no field). The one statement of this rule:
    `svolsdf.pipeline.options.field_from_mvs` and the config's validation ask it.

    Args:
        field_cfg: the run's `FieldConfig`; train_cfg: its `TrainConfig`.
    """
    return (get_field_kind(field_cfg.kind).starts_from_mvs and train_cfg.mode == "svolsdf"
            and field_cfg.init == "mvs" and train_cfg.ablation != "soft-consistency-only")


# --------------------------------------------------------------------------- built in
def _grid_from_mvs(model, volumes: list, normalization, masks: torch.Tensor | None,
                   init_unverified_weight: float) -> None:
    """The grid's start from the stage-1 MVS surface (`svolsdf.field.initial.init_grid_from_mvs`:
    ``model.sdf_grid`` set in place from ``volumes`` in the unit frame of ``normalization``,
    voting inside ``masks`` (V, 1, H, W) where given, the unconfirmed depths at
    ``init_unverified_weight``, ``field.init_unverified_weight``)."""
    from svolsdf.field.initial import init_grid_from_mvs

    init_grid_from_mvs(model, volumes, normalization, masks,
                       init_unverified_weight=init_unverified_weight)


def grid_resolution_schedule(f, t, from_sphere: bool) -> list[tuple[int, int]]:
    """The grid field's coarse-to-fine schedule.

    Args:
        f: the `FieldConfig` (its grid resolutions).
        t: the `TrainConfig` (its ``steps``).
        from_sphere: the grid starts from VolSDF's sphere (at ``sphere_start_resolution``),
            not from the MVS surface (at ``grid_start_resolution``).

    Returns:
        [(step, resolution)]: from a sphere, the doublings to ``grid_resolution``, evenly
        spaced, the last at 3/4 of the steps; from MVS, the geometric mean of the start and the
        final resolution at 1/4 of the steps and the final one at 1/2 ([] when the grid starts
        at its final resolution).
    """
    steps = t.steps
    if from_sphere:
        # doublings from sphere_start_resolution, evenly spaced, the last at 3/4 of the steps
        levels, r = [], f.sphere_start_resolution
        while r < f.grid_resolution:
            r = min(2 * r, f.grid_resolution)
            levels.append(r)
        n = len(levels)
        return [(int(steps * 0.75 * (i + 1) / n), r) for i, r in enumerate(levels)]
    if f.grid_resolution <= f.grid_start_resolution:
        return []
    r0, r1 = f.grid_start_resolution, f.grid_resolution
    mid = int(round((r0 * r1) ** 0.5))
    return [(int(steps * 0.25), mid), (int(steps * 0.5), r1)]


def check_grid(f, t, from_sphere: bool) -> Refusal | None:
    """The grid's start resolution (the sphere's or the MVS start's) must not exceed the final
    one.

    Args:
        f: the `FieldConfig`.
        t: the `TrainConfig` (unused: the start is given by ``from_sphere``).
        from_sphere: the grid starts from VolSDF's sphere, not from the MVS surface.

    Returns:
        the refused pair of options, or None.
    """
    key = "field.sphere_start_resolution" if from_sphere else "field.grid_start_resolution"
    start = f.sphere_start_resolution if from_sphere else f.grid_start_resolution
    if start > f.grid_resolution:
        return (key, start, "field.grid_resolution", f.grid_resolution,
                "the grid refines coarse to fine, so its start resolution must not exceed "
                "the final one")
    return None


def check_mlp(f, t, from_sphere: bool) -> Refusal | None:
    """VolSDF's MLP needs 5 hidden layers and 40 channels for its skip connection (at layer 4, a
    hidden layer: with 4 the skip would enter the last layer, where IDR's geometric init does not
    give the sphere), and starts from VolSDF's sphere only.

    Args:
        f: the `FieldConfig` (``mlp_depth``, ``mlp_width``, ``init``).
        t: the `TrainConfig` (``mode``: field.init "mvs" acts in svolsdf mode).
        from_sphere: unused (the MLP always starts from the sphere).

    Returns:
        the first refused pair of options, or None.
    """
    if f.mlp_depth < 5 or f.mlp_width <= 39:
        # VolSDF's MLP (docs/method.md 5.2) feeds gamma(x) (39 values) in again at layer 4, a
        # hidden layer
        bad = ("field.mlp_depth", f.mlp_depth) if f.mlp_depth < 5 else \
            ("field.mlp_width", f.mlp_width)
        return ("field.kind", f.kind, *bad, "the MLP's skip connection enters gamma(x) (39 "
                "values) again at layer 4, which must be a hidden layer for the sphere start: "
                "give field.mlp_depth >= 5 and field.mlp_width >= 40")
    if t.colour_steps > 0:
        return ("train.colour_steps", t.colour_steps, "field.kind", f.kind,
                "the colour steps train a grid field's colour features alone; the MLP's "
                "colour and surface share one network: use field.kind=grid or colour_steps=0")
    if f.init == "mvs" and t.mode == "svolsdf":
        return ("field.kind", f.kind, "field.init", f.init,
                "only the grid field starts from the MVS surface; the MLP starts from VolSDF's "
                "sphere: use field.init=sphere or field.kind=grid")
    return None


def grid_memory(f) -> list[tuple[tuple[str, ...], float, str]]:
    """The grid field's SDF grid, values and gradients, float32: a box with ``grid_resolution``
    nodes along its longest side and at least a fifth of that along the others (the field's box
    is padded by 0.15 of its longest side on each side, `svolsdf.field.bounds`),
    2 x R x (R / 5)^2 x 4 bytes.

    Args:
        f: the `FieldConfig`.
    """
    r = f.grid_resolution
    return [(("field.grid_resolution",), 2.0 * r * max(2, r // 5) ** 2 * 4,
             f"the {r}-node SDF grid")]


def _grid_options(cfg) -> tuple[str, ...]:
    """The grid's options: its final resolution and the background switch (the sphere clamp),
    and its start's: the sphere's, or the MVS start's resolution and vote weight."""
    start = (("field.sphere_start_resolution", "field.sphere_radius")
             if not starts_from_mvs(cfg.field, cfg.train) else
             ("field.grid_start_resolution", "field.init_unverified_weight"))
    return ("field.grid_resolution", "field.background", *start)


@register_field_kind("grid", init_from_mvs=_grid_from_mvs, sphere_options=True,
                     fits_points=True, schedule=grid_resolution_schedule, check=check_grid,
                     memory=grid_memory, options=_grid_options,
                     # a smaller background MLP than the paper's beside the fast field
                     background={"n_layers": 4, "d_hidden": 64, "skip_in": (),
                                 "feature_dim": 32, "colour_hidden": 32})
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


@register_field_kind("mlp", check=check_mlp,
                     options=("field.mlp_depth", "field.mlp_width", "field.background"))
def _mlp(i: FieldInputs):
    """The paper's VolSDF MLP (`VolSDFField`), ``mlp_depth`` x ``mlp_width``."""
    from svolsdf.field.volsdf import VolSDFField, VolSDFFieldConfig

    return VolSDFField(VolSDFFieldConfig.from_config(i.field))
