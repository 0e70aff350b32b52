"""Running the cascade (stages 1..3) for a set of views, and writing its outputs.

docs/method.md 0 and 6.1: stage 1 runs on the images; an optional guide depth per view (e.g. the
optimized surface's rendered depth) replaces stage 1's depth as the centre of stage 2's hypotheses;
stage 3 is centred on stage 2's depth.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from svolsdf.mvs.backbone import MVSBackbone
from svolsdf.mvs.volume import ProbabilityVolume
from svolsdf.scene.scene import Scene

__all__ = ["run_cascade", "run_and_save_cascade", "combined_confidence", "save_cascade"]

log = logging.getLogger(__name__)


def run_cascade(
    backbone: MVSBackbone,
    scene: Scene,
    guide_depth: dict[int, Tensor] | None = None,
    stages: tuple[int, ...] = (1, 2, 3),
    ref_ids: list[int] | None = None,
    prev: dict[int, ProbabilityVolume] | None = None,
) -> dict[int, list[ProbabilityVolume]]:
    """Run ``stages`` of ``backbone`` with every view (or ``ref_ids``) as reference.

    Args:
        backbone: an `MVSBackbone`.
        scene: the scene at the working size.
        guide_depth: view id -> (H', W') z-depth centring stage 2 instead of stage 1's depth
            (docs/method.md 6.1; the first listed stage > 1 if 2 is not listed). Stage 1 still runs
            when listed in ``stages`` (its volumes are the
            prior), but its depth is not used to centre stage 2 for views with a guide.
        stages: increasing stage numbers; a stage > 1 needs the stage before it, a guide depth,
            or ``prev``.
        ref_ids: reference views, default all.
        prev: view id -> volume of the stage before ``stages[0]`` (to resume a cascade).

    Returns:
        stage -> one `ProbabilityVolume` per reference view, in ``ref_ids`` order.
    """
    stages = tuple(int(s) for s in stages)
    if list(stages) != sorted(set(stages)) or not stages:
        raise ValueError(f"stages must be increasing and non-empty, got {stages}")
    out: dict[int, list[ProbabilityVolume]] = {}
    last = dict(prev) if prev else None
    first_fine = next((s for s in stages if s > 1), None)  # the stage a guide depth centres
    for k in stages:
        t0 = time.perf_counter()
        guide = guide_depth if k == first_fine else None
        vols = backbone.stage(k, scene, ref_ids=ref_ids, guide_depth=guide, prev=last)
        out[k] = vols
        last = {v.view_id: v for v in vols}
        log.info("mvs stage %d: %d view(s) in %.1f s", k, len(vols), time.perf_counter() - t0)
    return out


def combined_confidence(volumes: list[ProbabilityVolume], width: int, height: int) -> Tensor:
    """Product of the stages' confidences, each bilinearly resized to (height, width)
    (docs/method.md 6.2).

    Args:
        volumes: one view's volumes of the stages run.

    Returns:
        (height, width) confidence.
    """
    conf = torch.ones(height, width)
    for v in volumes:
        c = v.confidence.float()[None, None]
        if c.shape[-2:] != (height, width):
            c = F.interpolate(c, size=(height, width), mode="bilinear", align_corners=False)
        conf = conf * c[0, 0].cpu()
    return conf


def _save_npy(path: Path, arr: np.ndarray) -> None:
    tmp = path.with_name(path.name + ".tmp.npy")
    np.save(tmp, arr)
    os.replace(tmp, path)


def save_cascade(result: dict[int, list[ProbabilityVolume]], out_dir: Path | str,
                 picture=None, volumes: bool | tuple[int, ...] = True
                 ) -> dict[int, dict[str, Path]]:
    """Write the cascade's outputs under ``out_dir``.

    Files: ``mvs/stage{k}/{view_id}.npz`` (`ProbabilityVolume.save`, deflated where it pays) for
    every stage when ``volumes`` is True, for the stages listed when it is a tuple, none when
    False; for the last stage run: ``depth/{view_id}.npy`` (z-depth, world
    units, float32, at its size), ``confidence/{view_id}.npy`` (product over stages,
    docs/method.md 6.2) and, when ``picture`` is given, ``depth/{view_id}.png`` written by
    ``picture(depth (H,W) ndarray, path)``.

    Returns:
        view id -> {"depth": path, "confidence": path}.
    """
    out_dir = Path(out_dir)
    files: dict[int, dict[str, Path]] = {}
    keep = tuple(result) if volumes is True else tuple(volumes or ())
    for k, vols in result.items():
        if k not in keep:
            continue
        d = out_dir / "mvs" / f"stage{k}"
        d.mkdir(parents=True, exist_ok=True)
        for v in vols:
            v.save(d / f"{v.view_id}.npz")
    last = max(result)
    (out_dir / "depth").mkdir(parents=True, exist_ok=True)
    (out_dir / "confidence").mkdir(parents=True, exist_ok=True)
    for v in result[last]:
        H, W = v.depth.shape
        per_view = [vv for k in sorted(result) for vv in result[k] if vv.view_id == v.view_id]
        depth = v.depth.float().cpu().numpy().astype(np.float32)
        dp = out_dir / "depth" / f"{v.view_id}.npy"
        cp = out_dir / "confidence" / f"{v.view_id}.npy"
        _save_npy(dp, depth)
        _save_npy(cp, combined_confidence(per_view, W, H).numpy().astype(np.float32))
        if picture is not None:
            picture(depth, out_dir / "depth" / f"{v.view_id}.png")
        files[v.view_id] = {"depth": dp, "confidence": cp}
    return files


def run_and_save_cascade(
    backbone: MVSBackbone,
    scene: Scene,
    out_dir: Path | str,
    stages: tuple[int, ...] = (2, 3),
    guide_depth: dict[int, Tensor] | None = None,
    prev: dict[int, ProbabilityVolume] | None = None,
    earlier: dict[int, list[ProbabilityVolume]] | None = None,
    picture=None,
    volumes: bool | tuple[int, ...] = True,
) -> dict[int, Tensor]:
    """`run_cascade` and `save_cascade` one reference view at a time, so that only one view's
    finer volumes are in memory (at 2x the working size a view's stage-2 and stage-3 volumes are
    ~0.2 GB; nine views held together took the pipeline from 3.4 to 7.1 GB).

    The files are those of ``save_cascade(run_cascade(...) | earlier, out_dir)``.

    Args:
        backbone, scene, stages, guide_depth, prev: as `run_cascade`, for every view of ``scene``.
        out_dir, picture, volumes: as `save_cascade`.
        earlier: stage -> volumes of stages before ``stages`` (e.g. stage 1), which enter each
            view's combined confidence (docs/method.md 6.2) and, with ``volumes``, are saved too.

    Returns:
        view id -> (H, W) float32 depth of the last stage, on the CPU.
    """
    depths: dict[int, Tensor] = {}
    t0 = time.perf_counter()
    for vid in scene.view_ids:
        res = run_cascade(backbone, scene, guide_depth=guide_depth, stages=stages,
                          ref_ids=[vid], prev=prev)
        for k, vols in (earlier or {}).items():
            res[k] = [v for v in vols if v.view_id == vid]
        save_cascade(dict(sorted(res.items())), out_dir, picture=picture, volumes=volumes)
        depths[vid] = res[max(res)][0].depth.float().cpu()
        del res
    log.info("mvs stages %s: %d view(s) in %.1f s", ",".join(map(str, stages)), len(scene),
             time.perf_counter() - t0)
    return depths
