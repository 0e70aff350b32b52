"""Stage keys: a hash per stage of the config values (and earlier keys) its result depends on.

A stage whose key in OUT/stages.json equals the one computed here is finished and reused. The
values must stay as they are for a given config: a changed key reruns the stage in every existing
run folder. Options added after run folders existed therefore enter their stage's key only when
set (the comments say which).

Inputs: `input_manifest` records what the stages read from the scene (the input views' image and
mask files by content, the cameras as loaded) and `input_keys` chains it per stage as the keys
chain the config, so a replaced photo reruns the stages that read it. Input keys are stored beside
the stage keys (OUT/stages.json "provenance"), not mixed into them: run folders made before they
existed keep their finished stages (docs/run-folder.md).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

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

__all__ = ["STAGES", "describe_changes", "input_keys", "input_manifest", "stage_keys"]

STAGES = ("mvs1", "field", "guide", "mvs23", "unguided", "fusion", "mesh")
"""The stages in order (`svolsdf.pipeline.Pipeline`)."""

# fusion options (under their old names, config.io.RENAMED) that enter the fusion stage's key
# only when not None: they came after finished runs, which keep their keys (and their fused
# points) while the option is unset
_FUSION_KEYS_WHEN_SET = ("fusion_network", "fusion_network_weights", "fusion_unguided_dilation")


# the mvs.width values under the names their ratios had in the keys of earlier run folders,
# and the values whose stages 2-3 ran otherwise under that name then (they carry _WIDTH_MARK)
_WIDTH_KEYS = {"half-default": "paper"}
_WIDTH_MARKED = ("paper",)
_WIDTH_MARK = "mvs.width paper = (1, 0.5, 0.5)"


def wants_poisson(cfg: Config) -> bool:
    """The Poisson surface of the fused points enters the mesh key (under the name these keys
    have always given it): ``mesh.method`` poisson without a watertight mesh."""
    return cfg.mesh.method == "poisson" and not cfg.mesh.watertight


def _hash(*parts) -> str:
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:12]


def stage_keys(cfg: Config, views: list[int]) -> dict[str, str]:
    """{stage: 12-hex key} of a run of ``cfg`` with input ``views`` (every stage of `STAGES`,
    whether the mode runs it or not)."""
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
        # the sphere start's settings (issue 28) do not act on a field started from MVS:
        # they stay out of its key, and lr_sdf_sphere keeps the value it had in every key
        # before then, so such run folders keep their finished stages
        for k in ("sphere_radius", "sphere_start_resolution"):
            c["field"].pop(k)
        c["train"].pop("grid_eikonal_weight")
        c["train"]["lr_sdf_sphere"] = 1e-3
    # scene.use_masks = false enters where the stage reads the masks (issue 40: it was left
    # out): the field started from the MVS surface (its grid's start votes inside the masks)
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
                     # issue 38: VolSDF's rendered depth is fused under the multi-view rule
                     # (before, its own surface passed every pixel): its old points are stale
                     *(["multi-view"] if is_baseline(cfg) else []),
                     # issue 50: volsdf and mvs-only depth within the masks of svolsdf's
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
                       k_fusion]) if wants_poisson(cfg) else []),
                   # the TSDF of the observed depth, free-space culling and support trimming
                   # (issue 37): each enters only when set, with the fusion it reads
                   *((["tsdf", c["output"]["tsdf_resolution"],
                       c["output"]["tsdf_truncation_steps"], k_fusion])
                     if mesh_from_points(cfg) == "tsdf" else []),
                   # issue 47: the TSDF's small holes filled from the Poisson surface; enters
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


# --------------------------------------------------------------------------- inputs
def _file_entry(path: Path, previous: dict | None) -> dict:
    """{path, size, mtime_ns, sha1} of a file; the content is hashed only when its size or
    modification time differ from ``previous`` (the entry recorded by the last run)."""
    st = os.stat(path)
    entry = {"path": str(path), "size": st.st_size, "mtime_ns": st.st_mtime_ns}
    if (isinstance(previous, dict) and previous.get("sha1")
            and all(previous.get(k) == entry[k] for k in ("path", "size", "mtime_ns"))):
        entry["sha1"] = previous["sha1"]
        return entry
    h = hashlib.sha1()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    entry["sha1"] = h.hexdigest()[:16]
    return entry


def _cameras_digest(scene) -> str:
    """Digest of the input views' cameras as the stages see them (intrinsics and extrinsics at
    the working size, the normalization, depth ranges and source views). Rounded to float32,
    so that a linear-algebra library's last bits do not count as a new camera."""
    import numpy as np

    def f32(t) -> bytes:
        return np.asarray(t.detach().cpu().double().numpy(), np.float32).tobytes()

    h = hashlib.sha1()
    for part in (scene.cameras.K, scene.cameras.w2c, scene.normalization.center,
                 scene.depth_range):
        h.update(f32(part))
    h.update(np.float32(float(scene.normalization.scale)).tobytes())
    ids = set(scene.view_ids)
    pairs = {int(v): [int(s) for s in (scene.pairs or {}).get(v, []) if s in ids]
             for v in scene.view_ids}
    h.update(json.dumps([scene.view_ids, pairs, [scene.width, scene.height]]).encode())
    return h.hexdigest()[:16]


def input_manifest(scene, previous: dict | None = None) -> dict[str, dict]:
    """What the stages read from ``scene`` (a loaded `svolsdf.scene.Scene` of the input views).

    Args:
        scene: the input views at the working size.
        previous: the manifest the last run recorded; files whose size and modification time
            did not change keep their recorded content hash (no read).

    Returns:
        {"image:<view>": {path, size, mtime_ns, sha1}, "mask:<view>": ..., "cameras": {sha1}}.
    """
    previous = previous if isinstance(previous, dict) else {}
    m: dict[str, dict] = {}
    masks = scene.extras.get("mask_paths") if scene.masks is not None else None
    for i, v in enumerate(scene.view_ids):
        m[f"image:{v}"] = _file_entry(Path(scene.image_paths[i]), previous.get(f"image:{v}"))
        if masks is not None:
            m[f"mask:{v}"] = _file_entry(Path(masks[i]), previous.get(f"mask:{v}"))
    m["cameras"] = {"sha1": _cameras_digest(scene)}
    return m


def input_keys(cfg: Config, manifest: dict[str, dict]) -> dict[str, str]:
    """{stage: 12-hex key} of the inputs each stage reads, directly or through the stages it
    follows (chained as `stage_keys` chains the config)."""
    def part(kind: str) -> list:
        return sorted((k, e.get("sha1")) for k, e in manifest.items() if k.startswith(kind))

    images, cams = part("image:"), part("cameras")
    masks = part("mask:") if cfg.scene.use_masks else []
    i_mvs1 = _hash("mvs1", images, cams)
    i_field = _hash(i_mvs1, images, cams, masks)  # rays in the masks, the grid's start
    i_guide = _hash(i_field, masks if cfg.guide.mask_dilation is not None else [])
    i_mvs23 = _hash(i_guide, i_mvs1)
    i_unguided = _hash(i_mvs1, "unguided")
    i_fusion = _hash(i_mvs23, i_unguided if wants_unguided(cfg) else None, images, cams, masks)
    i_mesh = _hash(i_field, cams, masks, i_mvs23 if cfg.mvs.finer_stage_optimization else None,
                   i_guide if cfg.mesh.cull_unseen else None,
                   i_fusion if (wants_mesh_fit(cfg) or wants_poisson(cfg)) else None)
    return {"mvs1": i_mvs1, "field": i_field, "guide": i_guide, "mvs23": i_mvs23,
            "unguided": i_unguided, "fusion": i_fusion, "mesh": i_mesh}


def describe_changes(old: dict | None, new: dict[str, dict]) -> list[str]:
    """The inputs of ``new`` whose content differs from ``old`` (a recorded manifest), named for
    the log: ``image of view 1 (scene/image/001.png)``, ``the cameras``."""
    if not isinstance(old, dict):
        return []
    out = []
    for k, e in new.items():
        before = old.get(k)
        if isinstance(before, dict) and before.get("sha1") == e.get("sha1"):
            continue
        if k == "cameras":
            out.append("the cameras")
        else:
            kind, view = k.split(":", 1)
            what = "new" if before is None else "changed"
            out.append(f"{kind} of view {view} ({e.get('path')}, {what})")
    return out
