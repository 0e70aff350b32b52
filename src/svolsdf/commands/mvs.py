"""The ``svolsdf mvs`` job: the MVS cascade alone on a scene, with its outputs on disk.

`run_mvs` loads the scene at the working size, runs stages 1-3 of a backbone with every input view
as the reference once (docs/method.md 0, 2.5; no field, so stage 2 is centred on stage 1's depth),
and writes under ``out``::

    mvs/stage{1,2,3}/<view id>.npz   `ProbabilityVolume`s (prob as float16; arrays deflated only
                                     where that halves them, `ProbabilityVolume.save`)
    depth/<view id>.npy              stage-3 z-depth, world units, float32 (H, W), MVS size (the
                                     backbone's scale x the working size: 2x for the plane
                                     sweep and CasMVSNet, docs/method.md 9.2.2)
    depth/<view id>.png              the same, colour-coded
    confidence/<view id>.npy         conf1 * conf2 * conf3 at the MVS size (docs/method.md 6.2)
    confidence/<view id>.png         the same as a grey picture
    points.ply                       MVS-only fused point cloud (docs/method.md 6.3, as released)
    mvs.json                         backbone, views, size, depth ranges, timings, fusion stats
    mvs/stages.json                  the finished stages (`svolsdf.io.runfolder.MVS_STATE`)

Each stage's volumes are written as it finishes and marked in mvs/stages.json with a key of what
decides them (the backbone's signature, the input images by content, the cameras, size and depth
ranges) and the size and digest of each file, as `svolsdf reconstruct` marks its stages
(docs/run-folder.md): a rerun of a stopped or killed job reads the finished stages back and
computes only the others; a changed option, input or file runs that stage and the later ones.

Depth range: the scene's per-view range (from the file, a dataset rule, or the object sphere; see
`svolsdf.scene.loaders`), unless ``depth_range`` gives one (near, far) for every view.
"""


from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from svolsdf.errors import InputError, raise_if_interrupted
from svolsdf.io.runfolder import MVS_STATE, atomic_write
from svolsdf.pipeline.rundir import RunDir, is_unreadable_file, one_line
from svolsdf.scene.scene import Scene
from svolsdf.scene.size import working_size

__all__ = ["MVSJobConfig", "run_mvs", "mvs_depth_range"]

log = logging.getLogger(__name__)

class _MVSFolder(RunDir):
    """The output folder of ``svolsdf mvs``: its stage state in mvs/stages.json (a top-level
    stages.json names a run of svolsdf reconstruct, `svolsdf.scene.checks`)."""

    @property
    def stages_file(self) -> Path:
        return self.root / MVS_STATE



@dataclass
class MVSJobConfig:
    """Options of ``svolsdf mvs``."""

    scene: Path
    """Scene folder (any format `svolsdf.scene.loaders.load_scene` reads)."""
    out: Path
    """Output folder (created; an earlier job's finished stages there are read back when they
    match, the other files of the same names replaced)."""
    views: list[int] | None = None
    """Input view ids (None: every view of the scene; the command's default is reconstruct's
    input views)."""
    backbone: str = "planesweep"
    """MVS backbone: planesweep (training-free), casmvsnet or patchmatchnet."""
    weights: Path | None = None
    """Weights file for casmvsnet / patchmatchnet (patchmatchnet defaults to ../shared)."""
    size: tuple[int, int] | None = None
    """Working (W, H); None: `svolsdf.scene.size.working_size`, the rule of svolsdf reconstruct
    (at most 768 wide, sides multiples of 8; docs/method.md 1.3)."""
    depth_range: tuple[float, float] | None = None
    """(near, far) z-depth in world units for every view; None: the scene's ranges."""
    fuse: bool = True
    """Write the fused MVS-only point cloud points.ply."""
    device: str = "auto"
    """Where the work runs: auto (the GPU when there is one), cpu, cuda or cuda:N (GPU N)."""


def mvs_depth_range(scene: Scene, depth_range: tuple[float, float] | None = None
                    ) -> torch.Tensor:
    """(V, 2) float64 [near, far] per view: ``depth_range`` for every view, or the scene's."""
    if depth_range is None:
        return scene.depth_range.double()
    near, far = (float(x) for x in depth_range)
    if not 0 < near < far:
        raise InputError(f"--depth-range {near:g},{far:g}: it must satisfy 0 < near < far")
    return torch.tensor([[near, far]] * len(scene), dtype=torch.float64)


def _save_grey_png(path: Path, a: np.ndarray) -> None:
    from svolsdf.io.images import write_image

    write_image(path, np.clip(a, 0, 1).astype(np.float32))


def run_mvs(cfg: MVSJobConfig) -> dict:
    """Run the MVS cascade on ``cfg.scene`` and write the outputs (module docstring).

    Returns:
        The summary also written to ``out/mvs.json``: backbone, views, size, depth ranges, seconds
        per stage, and the fusion stats per view (share of pixels kept, number of points).

    Raises:
        InputError: bad scene, view ids, backbone, weights or depth range.
    """
    from svolsdf.io.images import write_depth_preview
    from svolsdf.io.paths import output_dir
    from svolsdf.mvs.backbone import backbone_signature, get_backbone
    from svolsdf.mvs.cascade import run_cascade, save_cascade
    from svolsdf.pipeline.keys import input_manifest
    from svolsdf.pipeline.machine import resolve_device
    from svolsdf.scene.loaders import load_scene

    t_start = time.perf_counter()
    cfg = replace(cfg, device=str(resolve_device(cfg.device)))
    out = output_dir(cfg.out, "output folder", create=False)
    probe = load_scene(cfg.scene, views=cfg.views, load_images=False)
    if len(probe) < 2:
        raise InputError(f"{cfg.scene}: MVS needs at least 2 views, got {len(probe)} "
                         f"({probe.view_ids})")
    W, H = working_size(*probe.extras.get("native_size", (probe.width, probe.height)),
                        image_size=cfg.size)
    # weights errors before loading
    backbone = get_backbone(cfg.backbone, weights=cfg.weights, device=cfg.device)
    output_dir(out)  # before the cascade's minutes
    t0 = time.perf_counter()
    scene = load_scene(cfg.scene, views=cfg.views, image_size=(W, H))
    scene = replace(scene, depth_range=mvs_depth_range(scene, cfg.depth_range))
    if cfg.device != "cpu":
        scene = replace(scene, images=scene.images.to(cfg.device),
                        masks=None if scene.masks is None else scene.masks.to(cfg.device))
    t_load = time.perf_counter() - t0
    log.info("mvs: %d views %s at %dx%d, backbone %s", len(scene), scene.view_ids, W, H,
             cfg.backbone)

    timings: dict[str, float] = {"load": t_load}
    folder = _MVSFolder(out)
    inputs = {k: e.get("sha1") for k, e in input_manifest(scene).items()}
    base = [backbone_signature(cfg.backbone, weights=cfg.weights), inputs]
    res = {}
    last = None
    for k in (1, 2, 3):
        t0 = time.perf_counter()
        key = hashlib.sha1(json.dumps([*base, k], sort_keys=True, default=str).encode()
                           ).hexdigest()[:12]
        vols = _finished_stage(folder, k, key, scene.view_ids)
        if vols is None:
            folder.unmark([f"stage{j}" for j in range(k, 4)])
            vols = run_cascade(backbone, scene, stages=(k,), prev=last)[k]
            files = [out / "mvs" / f"stage{k}" / f"{v.view_id}.npz" for v in vols]
            for v, f in zip(vols, files, strict=True):
                v.save(f)
            folder.mark(f"stage{k}", key, outputs=files)
        res[k] = vols
        last = {v.view_id: v for v in vols}
        timings[f"stage{k}"] = time.perf_counter() - t0

    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    ranges = {v: scene.depth_range[scene.index(v)].tolist() for v in scene.view_ids}

    def picture(depth: np.ndarray, path: Path) -> None:
        vid = int(path.stem)
        m = None if scene.masks is None else scene.masks[scene.index(vid), 0].cpu()
        if m is not None and m.shape != depth.shape:
            m = None
        write_depth_preview(path, torch.from_numpy(depth), mask=m)

    files = save_cascade(res, out, picture=picture, volumes=False)  # the volumes are saved
    for f in files.values():
        _save_grey_png(f["confidence"].with_suffix(".png"), np.load(f["confidence"]))
    timings["save"] = time.perf_counter() - t0

    summary: dict = {
        # absolute: `svolsdf evaluate` finds the scene's ground truth from any folder
        "scene": str(Path(cfg.scene).absolute()),
        "format": scene.format,
        "units": scene.units,
        "views": scene.view_ids,
        "backbone": cfg.backbone,
        "weights": None if cfg.weights is None else str(cfg.weights),
        "size": [W, H],
        "depth_range": {str(v): r for v, r in ranges.items()},
        "depth_range_source": ("given" if cfg.depth_range is not None else
                               str(scene.extras.get("depth_range_source", "?"))),
        "stage_sizes": {str(k): list(res[k][0].depth.shape[::-1]) for k in res},
        "hypotheses": {str(k): res[k][0].num_depths for k in res},
    }
    if cfg.fuse:
        t0 = time.perf_counter()
        summary["fusion"] = _fuse(scene, files, out / "points.ply", cfg.device)
        timings["fusion"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_start
    summary["seconds"] = {k: round(v, 3) for k, v in timings.items()}
    text = json.dumps(summary, indent=1) + "\n"
    atomic_write(out / "mvs.json", lambda tmp: tmp.write_text(text))
    log.info("mvs: wrote %s in %.1f s", out, timings["total"])
    return summary


def _finished_stage(folder: _MVSFolder, k: int, key: str, views: list[int]) -> list | None:
    """Stage ``k``'s volumes read back from an earlier run of the job, None when it has not
    finished under ``key``, a file differs from the one it finished with (OUT/log says which), or
    cannot be read."""
    from svolsdf.mvs.volume import ProbabilityVolume

    files = [folder.root / "mvs" / f"stage{k}" / f"{v}.npz" for v in views]
    if not folder.done(f"stage{k}", key) or not all(f.is_file() for f in files):
        return None
    why = folder.changed_output(f"stage{k}")
    if why is None:
        try:
            vols = [ProbabilityVolume.load(f) for f in files]
            log.info("mvs: stage %d read back from %s", k, files[0].parent)
            return vols
        except Exception as e:
            raise_if_interrupted()
            if not is_unreadable_file(e):
                raise
            why = f"a volume could not be read ({one_line(e)})"
    log.warning("mvs: stage %d: %s; running it again", k, why)
    return None


def _fuse(scene: Scene, files: dict, path: Path, device: str = "cpu") -> dict:
    """Fuse the stage-3 depth maps (docs/method.md 6.3) into ``path`` on ``device``; returns the
    stats."""
    from svolsdf.fusion.filter import FusionFilterConfig, fuse_depth_maps
    from svolsdf.io.ply import write_points_ply

    ids = list(files)
    depths = {v: torch.from_numpy(np.load(files[v]["depth"])) for v in ids}
    confs = {v: torch.from_numpy(np.load(files[v]["confidence"])) for v in ids}
    cams = {v: scene.cameras[scene.index(v)] for v in ids}
    images = {v: scene.images[scene.index(v)].cpu() for v in ids}
    masks = None if scene.masks is None else {v: scene.masks[scene.index(v)].cpu() for v in ids}
    fused = fuse_depth_maps(depths, cams, images=images, confidences=confs, masks=masks,
                            cfg=FusionFilterConfig(), device=device)
    write_points_ply(path, fused.points.numpy(), fused.colors.numpy())
    stats = {str(v): s for v, s in fused.stats.items()}
    stats["points_total"] = int(len(fused.points))
    return stats
