"""The fusion stage's inputs: which depth sets of a run are fused, with which confidences,
masks and surface (`svolsdf.fusion.filter.fuse_depth_maps` does the fusion)."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch

from svolsdf.pipeline import options
from svolsdf.pipeline.context import StageContext
from svolsdf.pipeline.rundir import save_npy

__all__ = ["fuse", "network_depths"]

log = logging.getLogger("svolsdf.pipeline")


def network_depths(p: StageContext, guide: dict[int, torch.Tensor]
                   ) -> tuple[dict[int, torch.Tensor], dict[int, torch.Tensor]]:
    """``fusion.network``'s depth and confidence of every input view (H, W), the
    network started from ``guide`` (world z-depth); also written to
    OUT/network/{depth,confidence}/<view>.npy.

    Args:
        p: the running pipeline (`StageContext`).
    """
    from svolsdf.io.images import write_depth_preview

    bb = p.network_backbone()
    scene = p.load()
    depth, conf = {}, {}
    for v in p.views:
        depth[v], conf[v] = bb.prediction(scene, v, guide=guide[v])
        for sub, m in (("depth", depth[v]), ("confidence", conf[v])):
            save_npy(p.dir.network_dir / sub / f"{v}.npy", m.numpy().astype(np.float32))
        write_depth_preview(p.dir.network_dir / "depth" / f"{v}.png", depth[v])
    return depth, conf


def fuse(p: StageContext, path: Path) -> tuple[int, dict]:
    """Fuse the run's depth sets into ``path`` (PLY points with colours).

    Args:
        p: the running pipeline (`StageContext`), its earlier stages finished.

    Returns:
        (number of points, timing extras: ``points_per_set`` with several depth sets).
    """
    from svolsdf.fusion.filter import FusionFilterConfig, fuse_depth_maps
    from svolsdf.io.ply import write_points_ply

    scene = p.load()
    cfg, out, views = p.cfg, p.out, p.views
    f = cfg.fusion
    # every mode's final depth within the same masks (the modes compared on one region): a
    # depth a guide made, guided stages 2-3 or a field's rendering, within guided_dilation; the
    # MVS cascade's alone (mvs-only mode, the unguided set) within unguided_dilation; the
    # dilation of a set the mode never fuses is not read (mvs-only fuses no depth a guide made,
    # volsdf none of the cascade's own)
    unused = {**({} if options.has_guide(cfg) else {"guided_dilation": None}),
              **({"unguided_dilation": None} if options.is_baseline(cfg) else {})}
    fcfg = FusionFilterConfig.from_config(f, use_masks=cfg.scene.use_masks,
                                          guided_depths=options.has_guide(cfg), **unused)
    # the refined surface after the finer-stage optimization
    sdir = p.dir.render_depth_dir(refined=options.refines_field(cfg))
    # the rendered guide is the surface (the soft-consistency ablation's guide is not). In
    # volsdf mode OUT/depth is that guide itself: it must not count as its own consistent
    # source, so VolSDF's points pass the same multi-view check as every other mode's
    guide_is_depth = options.is_baseline(cfg)
    use_surface = (f.surface > 0 and not options.guide_from_consistency(cfg)
                   and not guide_is_depth
                   and all((sdir / f"{v}.npy").is_file() for v in views))
    cams = {v: scene.cameras[[i]] for i, v in enumerate(views)}
    images = {v: scene.images[i] for i, v in enumerate(views)}
    masks = None
    if scene.masks is not None and cfg.scene.use_masks:
        masks = {v: scene.masks[i, 0] for i, v in enumerate(views)}

    def load(d: Path, sub: str) -> dict[int, torch.Tensor] | None:
        files = {v: d / sub / f"{v}.npy" for v in views}
        if not all(f.is_file() for f in files.values()):
            return None
        return {v: torch.from_numpy(np.load(f)) for v, f in files.items()}

    depths = load(out, "depth")
    if guide_is_depth and depths is not None and cfg.guide.low_weight_rule == "max":
        from svolsdf.render.views import max_rule_filled

        # the pixels docs/method.md 6.1 filled with the map's maximum depth are no surface of the
        # field (they only centre MVS in svolsdf mode): no depth
        depths = {v: torch.where(max_rule_filled(d), torch.zeros_like(d), d)
                  for v, d in depths.items()}
    confs = load(out, "confidence") if not options.is_baseline(cfg) else None
    alt = alt_confs = None
    if options.wants_unguided(cfg):  # the unguided stages 2-3 as each view's second hypothesis
        alt, alt_confs = load(p.dir.unguided_dir, "depth"), \
            load(p.dir.unguided_dir, "confidence")
        if confs is None:
            alt_confs = None
    surface = None
    if use_surface:  # fuse_depth_maps resizes it to each hypothesis' size
        surface = {v: torch.from_numpy(np.load(sdir / f"{v}.npy")).float() for v in views}
    net = net_confs = None
    if options.wants_network(cfg):  # the learned network, started from the guide
        t1 = time.perf_counter()
        d, c = network_depths(p, p.guide_depth())
        net, net_confs = {"network": d}, ({"network": c} if confs is not None else None)
        log.info("fusion network %s: %d view(s) in %.1f s", f.network, len(views),
                 time.perf_counter() - t1)
    fused = fuse_depth_maps(depths, cams, images, confs, masks, fcfg, surface,
                            alt_depths=alt, alt_confidences=alt_confs,
                            extra_depths=net, extra_confidences=net_confs, device=p.device)
    extra = {}
    if alt is not None or net is not None:
        sets = {"guided": "", **({"unguided": ":alt"} if alt is not None else {}),
                **({"network": ":network"} if net is not None else {})}
        extra["points_per_set"] = {
            name: sum(fused.stats[f"{v}{sfx}" if sfx else v]["points"] for v in views)
            for name, sfx in sets.items()}
    pts = fused.points.numpy()
    cols = None if fused.colors is None else fused.colors.numpy()
    write_points_ply(path, pts, cols)
    return int(len(pts)), extra
