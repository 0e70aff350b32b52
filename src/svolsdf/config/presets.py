"""Named presets: each states only what it changes from the dataclass defaults. Why each value
was chosen, with the measurements: docs/presets.md."""

from __future__ import annotations

import logging

from svolsdf.config.schema import Config, FieldConfig, MeshConfig, MVSConfig, TrainConfig
from svolsdf.errors import InputError

__all__ = ["MVS_SCALE_BY_BACKBONE", "PAPER_BACKBONE", "PRESETS", "RELEASED_SCAN_OVERRIDES",
           "backbone_provenance", "follow_backbone", "preset", "preset_mvs_scale",
           "scene_overrides", "scene_scan"]

log = logging.getLogger(__name__)

MVS_SCALE_BY_BACKBONE: dict[str, dict[str, float]] = {"draft": {"planesweep": 1.5}}
"""The ``mvs.scale`` a preset gives each backbone, for the presets that set one: the draft runs
the plane sweep at 1.5x the working size. A backbone not listed keeps its own size (``mvs.scale``
unset: CasMVSNet at 2x, the adapters at the working size), since only the plane sweep's 1.5 was
measured (docs/presets.md) and the adapters run at the working size only."""


def _paper() -> Config:
    c = Config(preset="paper")
    c.field = FieldConfig(kind="mlp", init="sphere")  # the MLP starts from VolSDF's sphere
    c.train = TrainConfig(steps=100_000, sampler="error_bounded", lr=5e-4, checkpoint_every=5000)
    c.mvs = MVSConfig(backbone="planesweep", width="paper")
    c.mesh = MeshConfig(resolution=512)
    return c


def _released() -> Config:
    # the released code's settings where they differ from the paper's text (docs/method.md 9.2);
    # its per-scan constants are `RELEASED_SCAN_OVERRIDES`, applied by `scene_overrides`
    c = _paper()
    c.preset = "released"
    c.mvs.width = "released"  # r = 1, 0.5, 0.5 (9.2.1)
    c.train.gce_form = "released"  # -P' sg(w)^q log w (9.2.4)
    c.train.sparse_norm = "all"  # the sparsity loss over all rays (9.2.5)
    c.train.sparse_decay = True  # its linear decay over the warm-up (4.3)
    c.train.warmup_mask_supervised = True  # no RGB loss on supervised rays in it (9.2.6)
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


PRESETS = {"fast": _fast, "draft": _draft, "paper": _paper, "released": _released}

RELEASED_SCAN_OVERRIDES: dict[str, dict[int, dict[str, object]]] = {
    "dtu": {24: {"train.sparse_weight": 0.0}, 37: {"train.sparse_weight": 0.1}},
    "blendedmvs": {
        1: {"mvs.inverse_depth": True},
        2: {"train.sparse_weight": 0.0, "mvs.inverse_depth": True},
        3: {"train.sparse_weight": 0.0},
        5: {"mvs.inverse_depth": True},
        6: {"mvs.inverse_depth": True},
        7: {"train.sparse_weight": 0.0},
        8: {"mvs.inverse_depth": True},
        9: {"train.sparse_weight": 0.0, "mvs.inverse_depth": True},
    },
}
"""The constants the released code's runner changes for particular scans (docs/method.md 9.1),
which the ``released`` preset applies to a scene whose folder names the scan (`scene_overrides`):
DTU scan 24's sparsity weight 0 (which also drops the warm-up) and scan 37's 0.1; BlendedMVS
scans 2, 3, 7, 9 without sparsity and 1, 2, 5, 6, 8, 9 with stage-1 planes uniform in inverse
depth. Not reproduced: the far-depth cap of BlendedMVS scans 4 and 5 (2.197 x the near depth),
which is no option (the depth range comes from the scene's files)."""

PAPER_BACKBONE = "casmvsnet"
"""The paper's MVS backbone: CasMVSNet with the DTU-trained cascade-stereo checkpoint."""


def scene_scan(scene_path: str) -> tuple[str, int] | None:
    """(dataset, scan) from a scene folder's name: ``bmvs_scan2`` or ``blendedmvs_scan2`` ->
    ("blendedmvs", 2); ``scan24`` or ``dtu_scan24`` -> ("dtu", 24); else None."""
    import re
    from pathlib import Path

    name = Path(str(scene_path)).name.lower()
    m = re.search(r"scan_?(\d+)", name)
    if not name or m is None:
        return None
    return ("blendedmvs" if "bmvs" in name or "blended" in name else "dtu", int(m.group(1)))


def scene_overrides(cfg: Config, given: set[str] | frozenset = frozenset()) -> dict:
    """Apply, in place, the per-scan constants of ``cfg``'s preset to its scene
    (`RELEASED_SCAN_OVERRIDES`, the ``released`` preset only), except the keys in ``given``
    (options the user set, which win). Returns {dotted key: value} of what it set."""
    if cfg.preset != "released" or not cfg.scene.path:
        return {}
    scan = scene_scan(cfg.scene.path)
    if scan is None:
        return {}
    out = {k: v for k, v in RELEASED_SCAN_OVERRIDES.get(scan[0], {}).get(scan[1], {}).items()
           if k not in given}
    for key, value in out.items():
        section, option = key.split(".")
        setattr(getattr(cfg, section), option, value)
    if out:
        log.info("released preset, %s scan %d: %s (the released code's per-scan constants)",
                 scan[0], scan[1], ", ".join(f"{k} = {v}" for k, v in out.items()))
    return out


def backbone_provenance(cfg: Config) -> dict:
    """Which MVS backbone a run of ``cfg`` uses and whether it is the paper's:
    ``{"backbone", "weights" (file name or None), "papers" (bool), "note"}``; the note says, for
    the paper and released presets, when the run is not what the paper ran (the plane sweep
    without weights), so that the fallback is never silent."""
    from pathlib import Path

    name, weights = cfg.mvs.backbone, cfg.mvs.weights
    papers = name == PAPER_BACKBONE
    if papers:
        note = (f"mvs.backbone {name} (the paper's architecture) with weights "
                f"{Path(weights).name if weights else 'none'}; the paper's are the DTU-trained "
                "cascade-stereo checkpoint")
    else:
        note = (f"mvs.backbone {name}, not the paper's DTU-trained CasMVSNet"
                + (" (the training-free plane sweep: no CasMVSNet weights were given; "
                   "--backbone casmvsnet --weights FILE runs the paper's)"
                   if name == "planesweep" else ""))
    return {"backbone": name, "weights": Path(weights).name if weights else None,
            "papers": papers, "note": note}


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
