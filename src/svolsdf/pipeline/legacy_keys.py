"""The stage keys as run folders were marked before the keys were computed from the stages'
declarations (`svolsdf.pipeline.keys.stage_keys`), frozen: the runner uses them only to recognise
the finished stages of such a run folder once, and then marks them with the current keys
(`svolsdf.pipeline.records.StageRecords.recognise_old_markers`; docs/run-folder.md).

Nothing here may change: a changed value is an old run folder whose stages run again. The
formula hashes the options under the names they had when the first run folders were written
(`svolsdf.config.io.legacy_layout`), and options added after run folders existed enter only when
set (the comments say which).
"""

from __future__ import annotations

import hashlib
import json

from svolsdf.config import Config
from svolsdf.config.io import legacy_layout
from svolsdf.pipeline.builders import backbone_kwargs
from svolsdf.pipeline.options import (
    field_from_mvs,
    grid_from_sphere,
    guided_mvs,
    has_field,
    is_baseline,
    mask_dilation,
    mesh_from_points,
    wants_mesh_fit,
    wants_network,
    wants_unguided,
)

__all__ = ["legacy_stage_keys"]

# fusion options (under their old names, config.io.RENAMED) that enter the fusion stage's key
# only when not None: they came after finished runs, which keep their keys (and their fused
# points) while the option is unset
_FUSION_KEYS_WHEN_SET = ("fusion_network", "fusion_network_weights", "fusion_unguided_dilation")


# the mvs.width values under the names their ratios had in the keys of earlier run folders,
# and the values whose stages 2-3 ran otherwise under that name then (they carry _WIDTH_MARK)
_WIDTH_KEYS = {"half-default": "paper"}
_WIDTH_MARKED = ("paper",)
_WIDTH_MARK = "mvs.width paper = (1, 0.5, 0.5)"


def _wants_poisson(cfg: Config) -> bool:
    """The Poisson surface of the fused points enters the mesh key (under the name these keys
    have always given it): ``mesh.method`` poisson without a watertight mesh."""
    return cfg.mesh.method == "poisson" and not cfg.mesh.watertight


def _hash(*parts) -> str:
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:12]


def legacy_stage_keys(cfg: Config, views: list[int]) -> dict[str, str]:
    """{stage: 12-hex key} that the stage-key formula before the declared stages gave a run of
    ``cfg`` with input ``views`` (every stage of `STAGES`, whether the mode runs it or not)."""
    from svolsdf import __version__
    from svolsdf.mvs.backbone import backbone_signature

    # the options under the names they had when the first run folders were written (the
    # output section's flat prefixes, `svolsdf.config.io.RENAMED`): their keys stay the same
    c = legacy_layout(cfg)
    # the backbone's full config (defaults included) and weights file: a changed default
    # or a replaced checkpoint must not reuse cached volumes
    sig = backbone_signature(cfg.mvs.backbone, weights=cfg.mvs.weights,
                             **backbone_kwargs(cfg))
    # mvs.guide_network (the adapters' guide_init) changes only the guided stages 2-3: it
    # enters their key alone, and only for the backbones that take it
    guide_init = sig["config"].pop("guide_init", None)
    # mvs.crop_to_masks (the plane sweep's crop_margin) changes only stages 2-3: it enters
    # their keys alone, and only when set
    crop = sig["config"].pop("crop_margin", None)
    # native_images enters only when set: the default (the released upsampling) keeps the
    # keys run folders had before the option existed
    if not sig["config"].get("native_images", True):
        del sig["config"]["native_images"]
    # ditto CasMVSNet's scale (mvs.scale other than 1 and 2): unset, its runs keep their keys
    if sig["config"].get("scale", 0) is None:
        del sig["config"]["scale"]
    # mvs.width "paper" meant r = (1, 1, 0.5) until it became the paper's explicit (1, 0.5,
    # 0.5): that reading, now "half-default", keeps every key "paper" gave it, and "paper"
    # keeps its name in the keys but marks stages 2-3 (`_WIDTH_MARK`): run folders of the old
    # default keep stage 1 and the field and rerun their finer stages
    for where, k in ((c["mvs"], "width"), (sig["config"], "width"),
                     (sig["config"], "width_mode")):
        if k in where:
            where[k] = _WIDTH_KEYS.get(where[k], where[k])
    width_mark = [_WIDTH_MARK] if cfg.mvs.width in _WIDTH_MARKED else []
    # mvs.save_volumes only says which files are kept, not what they hold
    c["mvs"] = {**{k: v for k, v in c["mvs"].items()
                   if k not in ("guide_network", "save_volumes", "crop_to_masks",
                                "third_stage_optimization")},
                "signature": sig}
    # how the views were picked does not matter once they are known (views), and run
    # folders from before the option keep their keys
    c["scene"].pop("view_selection", None)
    # every key chains from this one: a new release recomputes rather than mixing versions
    k_mvs1 = _hash(c["scene"], c["mvs"], views, __version__)
    if not grid_from_sphere(cfg):
        # the sphere start's settings do not act on a field started from MVS:
        # they stay out of its key, and lr_sdf_sphere keeps the value it had in every key
        # before then, so such run folders keep their finished stages
        for k in ("sphere_radius", "sphere_start_resolution"):
            c["field"].pop(k)
        c["train"].pop("grid_eikonal_weight")
        c["train"]["lr_sdf_sphere"] = 1e-3
    # scene.use_masks = false enters where the stage reads the masks (it was left
    # out before): the field started from the MVS surface (its grid's start votes inside the masks)
    # or drawing a share of its rays in them; the guide rendered within the dilated masks (a
    # field's: mvs-only and the soft-consistency ablation render none). True, the default,
    # stays out: run folders keep their keys
    # train.colour_min_weight and prior_floor enter only when set (0 is the exact computation)
    # and a field is trained: run folders from before, and mvs-only runs, keep their keys
    for k in ("colour_min_weight", "prior_floor"):
        if not (c["train"].get(k) and has_field(cfg)):
            c["train"].pop(k, None)
    # the colour phase's options enter only with train.colour_steps > 0: run folders from
    # before them keep their keys
    if not c["train"].get("colour_steps"):
        for k in ("colour_steps", "colour_rays", "colour_object_fraction"):
            c["train"].pop(k, None)
    # train.snapshot_every only writes pictures of the surface as it trains: in no key
    c["train"].pop("snapshot_every", None)
    # ditto train.prior_sources: only "selected", with a field
    if not (c["train"].get("prior_sources") == "selected" and has_field(cfg)):
        c["train"].pop("prior_sources", None)
    # field.background_model enters only with a background other than NeRF++'s: run folders
    # from before the option keep their keys
    if not (cfg.field.background and cfg.field.background_model != "nerf++"):
        c["field"].pop("background_model", None)
    no_masks = [] if cfg.scene.use_masks else ["no masks"]
    reads_masks = has_field(cfg) and (field_from_mvs(cfg) or cfg.train.object_ray_fraction > 0
                                      or cfg.train.colour_steps > 0)
    k_field = _hash(k_mvs1, c["field"], c["train"], c["preset"],
                    *(no_masks if reads_masks else []))
    # guide_mask_dilation enters only when set, so runs that render every pixel keep the
    # keys they had before the option existed (their stages are reused)
    gmd = c["output"]["guide_mask_dilation"]
    k_guide = _hash(k_field, c["output"]["low_weight_rule"],
                    *([gmd, *(no_masks if has_field(cfg) else [])] if gmd is not None else []))
    cropped = [("crop", crop)] if crop is not None else []
    k_mvs23 = _hash(k_guide, c["mvs"], c["output"]["finer_stage_optimization"],
                    *([guide_init] if guide_init is not None else []), *cropped, *width_mark,
                    # the optimization after stage 3 enters only when set (newer than runs)
                    *(["stage-3 optimization"] if cfg.mvs.third_stage_optimization else []))
    k_unguided = _hash(k_mvs1, c["mvs"], "unguided stages 2-3", *cropped, *width_mark)
    # options added after runs existed enter only when set: those runs keep their keys
    fo = {k: v for k, v in c["output"].items() if (k.startswith("fusion") or k == "use_masks")
          and not (k in _FUSION_KEYS_WHEN_SET and v is None)}
    net = None
    if wants_network(cfg):
        net = backbone_signature(cfg.fusion.network,
                                 weights=cfg.fusion.network_weights,
                                 max_sources=cfg.mvs.max_sources)
    k_fusion = _hash(k_mvs23, fo, k_unguided if wants_unguided(cfg) else None,
                     *([net] if net is not None else []),
                     # VolSDF's rendered depth is fused under the multi-view rule
                     # (before, its own surface passed every pixel): its old points are stale
                     *(["multi-view"] if is_baseline(cfg) else []),
                     # volsdf and mvs-only depth within the masks of svolsdf's
                     # (before, the released 12 px whatever the option): enters when set
                     *(["masks", mask_dilation(cfg)]
                       if not guided_mvs(cfg) and mask_dilation(cfg) is not None else []))
    # mesh_fit_points enters only when set (with the fused points it fits): run folders
    # made before the option keep their mesh key
    fit = ([c["output"]["mesh_fit_points"], k_fusion] if wants_mesh_fit(cfg) else [])
    k_mesh = _hash(k_field, c["output"]["mesh_resolution"], c["output"]["mesh_format"],
                   *fit,
                   k_mvs23 if c["output"]["finer_stage_optimization"] else None,
                   c["output"]["use_masks"],
                   (k_guide, c["output"]["mesh_cull_tol"]) if c["output"]["mesh_cull_unseen"]
                   else None,
                   # enters only when set: earlier run folders keep their mesh key
                   *(["watertight"] if c["output"]["mesh_watertight"] else []),
                   # ditto: the Poisson surface of the fused points
                   *((["poisson", c["output"]["poisson_depth"], c["output"]["poisson_trim"],
                       k_fusion]) if _wants_poisson(cfg) else []),
                   # the TSDF of the observed depth, free-space culling and support trimming
                   # each enters only when set, with the fusion it reads
                   *((["tsdf", c["output"]["tsdf_resolution"],
                       c["output"]["tsdf_truncation_steps"], k_fusion])
                     if mesh_from_points(cfg) == "tsdf" else []),
                   # the TSDF's small holes filled from the Poisson surface; enters
                   # only when set (mesh.tsdf.fill_holes is newer than the old layout)
                   *((["tsdf-fill", cfg.mesh.tsdf.fill_holes, cfg.mesh.poisson.depth,
                       cfg.mesh.poisson.trim])
                     if mesh_from_points(cfg) == "tsdf" and cfg.mesh.tsdf.fill_holes > 0
                     else []),
                   # a method registered beyond these three (svolsdf.fusion.mesh_methods)
                   # enters by name, with the fusion it reads when it meshes the points
                   *((["mesh-method", c["output"]["mesh_method"],
                       *([k_fusion] if mesh_from_points(cfg) else [])])
                     if c["output"]["mesh_method"] not in ("field", "poisson", "tsdf") else []),
                   *((["free-space", c["output"]["mesh_free_space_steps"], k_fusion])
                     if c["output"]["mesh_free_space"] else []),
                   *((["support", c["output"]["mesh_support"], k_fusion])
                     if c["output"]["mesh_support"] > 0 else []))
    return {"mvs1": k_mvs1, "field": k_field, "guide": k_guide, "mvs23": k_mvs23,
            "unguided": k_unguided,
            "fusion": k_fusion, "mesh": k_mesh}
