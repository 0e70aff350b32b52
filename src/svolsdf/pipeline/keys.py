"""Stage keys: a hash per stage of the config values (and earlier keys) its result depends on.

A stage whose key in OUT/stages.json equals the one computed here is finished and reused. The
values must stay as they are for a given config: a changed key reruns the stage in every existing
run folder. Options added after run folders existed therefore enter their stage's key only when
set (the comments say which).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict

from svolsdf.config import Config
from svolsdf.pipeline.builders import backbone_kwargs
from svolsdf.pipeline.options import (
    grid_from_sphere,
    wants_mesh_fit,
    wants_network,
    wants_poisson,
    wants_unguided,
)

__all__ = ["STAGES", "stage_keys"]

STAGES = ("mvs1", "field", "guide", "mvs23", "unguided", "fusion", "mesh")
"""The stages in order (`svolsdf.pipeline.Pipeline`)."""

# OutputConfig fusion options that enter the fusion stage's key only when not None: they came
# after finished runs, which keep their keys (and their fused points) while the option is unset
_FUSION_KEYS_WHEN_SET = ("fusion_network", "fusion_network_weights", "fusion_unguided_dilation")


def _hash(*parts) -> str:
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:12]


def stage_keys(cfg: Config, views: list[int]) -> dict[str, str]:
    """{stage: 12-hex key} of a run of ``cfg`` with input ``views`` (every stage of `STAGES`,
    whether the mode runs it or not)."""
    from svolsdf import __version__
    from svolsdf.mvs.backbone import backbone_signature

    c = asdict(cfg)
    # the backbone's full config (defaults included) and weights file: a changed default
    # or a replaced checkpoint must not reuse cached volumes
    sig = backbone_signature(cfg.mvs.backbone, weights=cfg.mvs.weights,
                             **backbone_kwargs(cfg))
    # mvs.guide_network (the adapters' guide_init) changes only the guided stages 2-3: it
    # enters their key alone, and only for the backbones that take it
    guide_init = sig["config"].pop("guide_init", None)
    # native_images enters only when set: the default (the released upsampling) keeps the
    # keys run folders had before the option existed
    if not sig["config"].get("native_images", True):
        del sig["config"]["native_images"]
    c["mvs"] = {**{k: v for k, v in c["mvs"].items() if k != "guide_network"},
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
    k_field = _hash(k_mvs1, c["field"], c["train"], c["preset"])
    # guide_mask_dilation enters only when set, so runs that render every pixel keep the
    # keys they had before the option existed (their stages are reused)
    gmd = c["output"]["guide_mask_dilation"]
    k_guide = _hash(k_field, c["output"]["low_weight_rule"], *([gmd] if gmd is not None
                                                                   else []))
    k_mvs23 = _hash(k_guide, c["mvs"], c["output"]["finer_stage_optimization"],
                    *([guide_init] if guide_init is not None else []))
    k_unguided = _hash(k_mvs1, c["mvs"], "unguided stages 2-3")
    # options added after runs existed enter only when set: those runs keep their keys
    fo = {k: v for k, v in c["output"].items() if (k.startswith("fusion") or k == "use_masks")
          and not (k in _FUSION_KEYS_WHEN_SET and v is None)}
    net = None
    if wants_network(cfg):
        net = backbone_signature(cfg.output.fusion_network,
                                 weights=cfg.output.fusion_network_weights,
                                 max_sources=cfg.mvs.max_sources)
    k_fusion = _hash(k_mvs23, fo, k_unguided if wants_unguided(cfg) else None,
                     *([net] if net is not None else []),
                     # issue 38: VolSDF's rendered depth is fused under the multi-view rule
                     # (before, its own surface passed every pixel): its old points are stale
                     *(["multi-view"] if cfg.train.mode == "volsdf" else []))
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
                       k_fusion]) if wants_poisson(cfg) else []))
    return {"mvs1": k_mvs1, "field": k_field, "guide": k_guide, "mvs23": k_mvs23,
            "unguided": k_unguided,
            "fusion": k_fusion, "mesh": k_mesh}
