"""What the guide stage shows of the field: its PSNR on the input views (OUT/timing.json) and
preview pictures of its colour and normals (OUT/field/render_rgb, OUT/normals)."""

from __future__ import annotations

import logging

import torch

from svolsdf.pipeline.rundir import RunDir
from svolsdf.scene.scene import Scene

__all__ = ["field_psnr", "write_previews"]

log = logging.getLogger("svolsdf.pipeline")


def field_psnr(scene: Scene, views: list[int], rgb: torch.Tensor, pixels: torch.Tensor | None,
               use_masks: bool) -> dict:
    """Log the field's PSNR on its own input views (how well the field fits what it saw); returns
    it for timing.json.

    A field that only copies MVS scores well on the points and badly here; a field that
    explains the photos scores > 20 dB. Masked as the paper's PSNR (docs/method.md 8.3): inside the
    object masks when the scene has them (rendered pixels only), else over every pixel.

    Args:
        rgb: (V, H, W, 3) rendered colours of the input views (0 where not rendered).
        pixels: (V, H, W) bool rendered pixels, or None (all).

    Returns:
        {"masked": bool, "per_view_db": {view: dB}, "mean_db": dB}.
    """
    from svolsdf.evaluate.images import masked_psnr

    vals = {}
    for i, v in enumerate(views):
        m = None
        if scene.masks is not None and use_masks:
            m = scene.masks[i, 0] > 0.5
        if pixels is not None:
            m = pixels[i] if m is None else m & pixels[i].to(m.device)
        vals[v] = round(float(masked_psnr(rgb[i].permute(2, 0, 1).clamp(0, 1),
                                          scene.images[i].cpu(), m)), 2)
    mean = round(sum(vals.values()) / len(vals), 2)
    where = "inside the object masks" if scene.masks is not None and use_masks \
        else "whole images"
    log.info("field: PSNR on the input views (%s): %s; mean %.2f dB", where,
             ", ".join(f"{v}: {p:.2f}" for v, p in vals.items()), mean)
    return {"masked": scene.masks is not None and use_masks,
            "per_view_db": {str(v): p for v, p in vals.items()}, "mean_db": mean}


def write_previews(run_dir: RunDir, v: int, r: dict, i: int) -> None:
    """OUT/field/render_rgb/<v>.png and OUT/normals/<v>.png of view ``v`` (index ``i`` of the
    rendered maps ``r``: rgb (V, H, W, 3), normals (V, H, W, 3), opacity (V, H, W))."""
    from svolsdf.io.images import write_image

    d = run_dir.field_dir
    write_image(d / "render_rgb" / f"{v}.png", r["rgb"][i].permute(2, 0, 1).clamp(0, 1))
    n = r["normals"][i]
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    write_image(run_dir.root / "normals" / f"{v}.png",
                ((n * 0.5 + 0.5) * r["opacity"][i][..., None].clamp(0, 1)).permute(2, 0, 1))
