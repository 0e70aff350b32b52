"""Stage keys: a hash per stage of what its result depends on, computed from the stages'
declarations (`svolsdf.pipeline.stages`).

A stage whose key in OUT/stages.json equals the one computed here is finished and reused. A
stage's key hashes its name, the release, the input views, the values of the options it declares
reading for the config (`Stage.reads`, a section's ``section.*`` expanded to its options, less
`Stage.key_ignores`), the options the scene is loaded with (`SCENE_OPTIONS`), the signature of
each network it runs (`Stage.backbones`) and the keys of the stages it consumes (`Stage.uses`:
those of `Stage.consumes` it reads for the config), so a changed option reruns the stages that
read it and those that consume them. A stage that does not apply to the config has a fixed key.
Run folders marked by the formula before this one are recognised once, by
`svolsdf.pipeline.legacy_keys`.

Inputs: `input_manifest` records what the stages read from the scene (the input views' image and
mask files by content, the cameras as loaded) and `input_keys` chains it per stage as the keys
chain the config, so a replaced photo reruns the stages that read it. Input keys are stored beside
the stage keys (OUT/stages.json "provenance"), not mixed into them: run folders made before they
existed keep their finished stages (docs/run-folder.md).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from svolsdf.config import Config
from svolsdf.config.io import known_keys
from svolsdf.pipeline.options import wants_mesh_fit, wants_unguided

if TYPE_CHECKING:  # the stages import this module (field.py through loaded_run): no cycle
    from svolsdf.pipeline.stages import Stage

__all__ = ["STAGES", "config_options", "describe_changes", "input_keys", "input_manifest",
           "option_value", "stage_keys"]

STAGES = ("mvs1", "field", "guide", "mvs23", "unguided", "fusion", "mesh")
"""The stages in order (`svolsdf.pipeline.Pipeline`)."""


def wants_poisson(cfg: Config) -> bool:
    """The mesh reads the Poisson surface of the fused points: ``mesh.method`` poisson without
    a watertight mesh."""
    return cfg.mesh.method == "poisson" and not cfg.mesh.watertight


def _hash(*parts) -> str:
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:12]


@functools.cache
def config_options() -> tuple[str, ...]:
    """Every option of `Config` by its dotted name ("preset", "scene.path", ...,
    "mesh.tsdf.resolution"); the sections themselves are not options."""
    return tuple(known_keys(Config()))


def option_value(cfg: Config, option: str) -> Any:
    """The value of ``option`` (a dotted name of `config_options`) in ``cfg``."""
    return functools.reduce(getattr, option.split("."), cfg)


def _signature(cfg: Config, network: str, stage: Stage) -> dict:
    """`backbone_signature` of the network ``network`` ("mvs" or "fusion") of ``cfg`` as
    ``stage`` keys it: the ``mvs`` options of its `Stage.key_ignores` (and ``scene.use_masks``,
    which the backbone's options read) at their defaults."""
    from svolsdf.mvs.backbone import backbone_signature
    from svolsdf.pipeline.builders import backbone_kwargs

    if network == "mvs":
        defaults = {f.name: (f.default if f.default_factory is dataclasses.MISSING
                             else f.default_factory())
                    for f in dataclasses.fields(cfg.mvs)
                    if not stage.keyed(cfg, f"mvs.{f.name}")}
        keyed = dataclasses.replace(cfg, mvs=dataclasses.replace(cfg.mvs, **defaults))
        if not stage.keyed(cfg, "scene.use_masks"):
            keyed.scene = dataclasses.replace(cfg.scene, use_masks=type(cfg.scene)().use_masks)
        return backbone_signature(cfg.mvs.backbone, weights=cfg.mvs.weights,
                                  **backbone_kwargs(keyed))
    if network == "fusion":
        return backbone_signature(cfg.fusion.network, weights=cfg.fusion.network_weights,
                                  max_sources=cfg.mvs.max_sources)
    raise ValueError(f"unknown network {network!r} (mvs or fusion)")


def stage_keys(cfg: Config, views: list[int]) -> dict[str, str]:
    """{stage: 12-hex key} of a run of ``cfg`` with input ``views`` (every stage of `STAGES`,
    whether the mode runs it or not; see the module docstring).

    Raises:
        InputError: a backbone option the backbone refuses (as building it would).
    """
    from svolsdf import __version__
    from svolsdf.pipeline.stages import PIPELINE_STAGES, SCENE_OPTIONS

    keys: dict[str, str] = {}
    for stage in PIPELINE_STAGES:
        if not stage.applies(cfg):
            keys[stage.name] = _hash(stage.name, "does not apply")
            continue
        scene = SCENE_OPTIONS if stage.scene_inputs else ()
        opts = {o: option_value(cfg, o) for o in config_options()
                if o in scene or stage.keyed(cfg, o)}
        keys[stage.name] = _hash(stage.name, __version__, list(views), opts,
                                 {n: _signature(cfg, n, stage) for n in stage.backbones(cfg)},
                                 {c: keys[c] for c in stage.uses(cfg)})
    return keys


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
