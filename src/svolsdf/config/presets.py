"""Named presets: each states only what it changes from the dataclass defaults. Why each value
was chosen, with the measurements: docs/presets.md."""

from __future__ import annotations

from svolsdf.config.schema import Config, FieldConfig, MeshConfig, MVSConfig, TrainConfig
from svolsdf.errors import InputError

__all__ = ["PRESETS", "preset"]


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
    c.field.init_unverified_weight = 0.05  # one-view stage-1 depth votes in the initial surface
    c.fusion.surface = 5e-4  # the optimized surface counts as one consistent view
    c.fusion.guided_dilation = 4  # a field's depth fused within 4 px of the masks (every mode)
    c.fusion.unguided_dilation = 4  # and the MVS cascade's alone (mvs-only, the unguided set)
    c.fusion.unguided = True  # the unguided stages 2-3 as a second depth hypothesis
    c.guide.mask_dilation = 32  # the guide rendered only near the object masks
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
    c.mvs.scale = 1.5  # the plane sweep at 1.5x the working size instead of 2x
    return c


PRESETS = {"fast": _fast, "draft": _draft, "paper": _paper}


def preset(name: str) -> Config:
    """A fresh `Config` of the named preset."""
    if not isinstance(name, str) or name not in PRESETS:
        raise InputError(f"unknown preset {name!r} (choose from {', '.join(PRESETS)})")
    return PRESETS[name]()


