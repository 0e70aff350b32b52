"""What a config turns on: the rules that decide which stages run and which options act, shared
by the stages, their keys and the commands that open a finished run."""

from __future__ import annotations

from svolsdf.config import Config

__all__ = ["grid_from_sphere", "has_field", "mesh_from_points", "runs_mvs1", "wants_mesh_fit",
           "wants_network", "wants_poisson", "wants_unguided"]


def runs_mvs1(cfg: Config) -> bool:
    """The run computes the stage-1 MVS volumes (svolsdf and mvs-only modes, the ablations)."""
    return cfg.train.mode in ("svolsdf", "mvs-only") or bool(cfg.train.ablation)


def has_field(cfg: Config) -> bool:
    """The run fits a neural field (svolsdf and volsdf modes, not the soft-consistency
    ablation)."""
    return cfg.train.mode in ("svolsdf", "volsdf") and \
        cfg.train.ablation != "soft-consistency-only"


def grid_from_sphere(cfg: Config) -> bool:
    """The grid field starts from VolSDF's sphere, not from the stage-1 MVS surface."""
    f = cfg.field
    return f.kind == "grid" and not (cfg.train.mode == "svolsdf" and f.init == "mvs"
                                     and cfg.train.ablation != "soft-consistency-only")


def wants_network(cfg: Config) -> bool:
    """`OutputConfig.fusion_network` applies: set, in svolsdf mode (which has a guide)."""
    return cfg.output.fusion_network is not None and cfg.train.mode == "svolsdf"


def wants_unguided(cfg: Config) -> bool:
    """`OutputConfig.fusion_unguided` applies: svolsdf mode, whose stages 2-3 are guided."""
    return cfg.output.fusion_unguided and cfg.train.mode == "svolsdf"


def wants_mesh_fit(cfg: Config) -> bool:
    """`OutputConfig.mesh_fit_points` applies: set, svolsdf mode (its points come from the
    finer MVS stages), a grid field."""
    return (cfg.output.mesh_fit_points > 0 and cfg.output.mesh_method == "field"
            and cfg.train.mode == "svolsdf"
            and cfg.train.ablation is None and cfg.field.kind == "grid")


def wants_poisson(cfg: Config) -> bool:
    """`OutputConfig.mesh_method` = "poisson" applies: set and no watertight mesh (a Poisson
    surface opens where it meets its octree's box; the watertight mesh is the field's)."""
    o = cfg.output
    return o.mesh_method == "poisson" and not o.mesh_watertight


def mesh_from_points(cfg: Config) -> str | None:
    """The mesh method that meshes the fused points and depth ("poisson" or "tsdf"), or None
    when the mesh is the field's (method field, or a watertight mesh: a surface of the points
    opens where they stop; the watertight mesh is the field's closed zero level)."""
    o = cfg.output
    return o.mesh_method if o.mesh_method in ("poisson", "tsdf") and not o.mesh_watertight \
        else None
