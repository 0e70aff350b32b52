"""What a config turns on: the rules that decide which stages run and which options act, shared
by the stages, their keys and the commands that open a finished run. Each rule on the mode and
the ablation is written here once (the optimization's own, on `TrainConfig`, in
`svolsdf.optimize.modes`); callers ask by meaning."""

from __future__ import annotations

from svolsdf.config import Config
from svolsdf.optimize import modes

__all__ = ["field_from_mvs", "field_kind", "fits_to_mvs_depth", "grid_from_sphere",
           "guide_from_consistency", "guided_mvs", "has_field", "has_guide", "is_baseline",
           "mask_dilation", "mesh_from_points", "mesh_method", "refines_field", "runs_mvs1",
           "uses_prior", "wants_mesh_fit", "wants_network", "wants_unguided"]


def is_baseline(cfg: Config) -> bool:
    """The VolSDF baseline (volsdf mode): it never sees MVS, and its final depth is the field's
    rendered guide itself (no MVS stages 2-3, no confidence)."""
    return cfg.train.mode == "volsdf"


def guided_mvs(cfg: Config) -> bool:
    """svolsdf mode: the final depth (OUT/depth) is MVS stages 2-3 centred on a guide."""
    return cfg.train.mode == "svolsdf"


def mask_dilation(cfg: Config) -> int | None:
    """The object-mask dilation, in pixels, of the final depth (OUT/depth) in fusion; one rule
    for every mode, so that the modes' points are compared on the same region: depth a field
    made, the guided stages 2-3 (svolsdf mode) or the field's own rendering (volsdf mode), takes
    ``fusion.guided_dilation``; the MVS cascade alone (mvs-only mode, as the unguided set of
    ``fusion.unguided``) ``fusion.unguided_dilation``.
    None = the released 12 px (docs/method.md 6.3)."""
    if cfg.train.mode == "mvs-only":
        return cfg.fusion.unguided_dilation
    return cfg.fusion.guided_dilation


def refines_field(cfg: Config) -> bool:
    """The field is optimized again after MVS stage 2 against the stage-2 volumes
    (``mvs.finer_stage_optimization``, docs/method.md 9.2.13): the refined field and its
    rendered depth (OUT/field/stage2) are then the surface's, where they were written."""
    return bool(cfg.mvs.finer_stage_optimization)


def has_guide(cfg: Config) -> bool:
    """The run computes a guide depth (every mode but mvs-only)."""
    return cfg.train.mode != "mvs-only"


def guide_from_consistency(cfg: Config) -> bool:
    """The soft-consistency ablation: the guide is the stage-1 volumes' consistency depth, not a
    field's rendering (no field is fitted)."""
    return cfg.train.ablation == "soft-consistency-only"


def uses_prior(cfg: Config) -> bool:
    """The field is fitted under the stage-1 MVS prior (`svolsdf.optimize.modes.uses_prior`)."""
    return modes.uses_prior(cfg.train)


def fits_to_mvs_depth(cfg: Config) -> bool:
    """The field is fitted to the filtered stage-1 MVS depth (the "mse" and "no-prob-volume"
    ablations; `svolsdf.optimize.modes.supervised_by_mvs_depth`)."""
    return modes.supervised_by_mvs_depth(cfg.train)


def runs_mvs1(cfg: Config) -> bool:
    """The run computes the stage-1 MVS volumes (svolsdf and mvs-only modes, the ablations)."""
    return not is_baseline(cfg) or bool(cfg.train.ablation)


def has_field(cfg: Config) -> bool:
    """The run fits a neural field (svolsdf and volsdf modes, not the soft-consistency
    ablation)."""
    return has_guide(cfg) and not guide_from_consistency(cfg)


def field_kind(cfg: Config):
    """The registry entry of ``field.kind`` (`svolsdf.field.kinds.FieldKind`): what the kind can
    do."""
    from svolsdf.field.kinds import get_field_kind

    return get_field_kind(cfg.field.kind)


def field_from_mvs(cfg: Config) -> bool:
    """The field starts from the stage-1 MVS surface: its kind can (the grid), ``field.init`` is
    "mvs", and the field is fitted under the prior (svolsdf mode, not the soft-consistency
    ablation)."""
    from svolsdf.field.kinds import starts_from_mvs

    return starts_from_mvs(cfg.field, cfg.train)


def grid_from_sphere(cfg: Config) -> bool:
    """The field starts from VolSDF's sphere and reads the sphere start's options (a kind with
    ``sphere_options``, the grid; not one started from the stage-1 MVS surface)."""
    return field_kind(cfg).sphere_options and not field_from_mvs(cfg)


def wants_network(cfg: Config) -> bool:
    """``fusion.network`` applies: set, in svolsdf mode (which has a guide)."""
    return cfg.fusion.network is not None and guided_mvs(cfg)


def wants_unguided(cfg: Config) -> bool:
    """``fusion.unguided`` applies: svolsdf mode, whose stages 2-3 are guided."""
    return cfg.fusion.unguided and guided_mvs(cfg)


def mesh_method(cfg: Config):
    """The registry entry of ``mesh.method`` (`svolsdf.fusion.mesh_methods.MeshMethod`): what
    the method declares (the options it reads, whether it meshes the field or the points)."""
    from svolsdf.fusion.mesh_methods import get_mesh_method

    return get_mesh_method(cfg.mesh.method)


def wants_mesh_fit(cfg: Config) -> bool:
    """``mesh.fit_points`` applies: set, a mesh method of the field's zero level
    (``needs_field``), svolsdf mode (its points come from the finer MVS stages), a field kind
    that can be fitted to points (the grid)."""
    return (cfg.mesh.fit_points > 0 and mesh_method(cfg).needs_field
            and guided_mvs(cfg)
            and cfg.train.ablation is None and field_kind(cfg).fits_points)


def mesh_from_points(cfg: Config) -> str | None:
    """The mesh method that meshes the fused points and depth (one registered with
    ``needs_points``, `svolsdf.fusion.mesh_methods`), or None when the mesh is the field's (a
    method of the field, or a watertight mesh: a surface of the points opens where they stop;
    the watertight mesh is the field's closed zero level)."""
    return cfg.mesh.method if mesh_method(cfg).needs_points and not cfg.mesh.watertight \
        else None
