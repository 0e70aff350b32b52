"""Human-readable scene summaries and contact sheets (``svolsdf info``)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

from svolsdf.io.images import write_image
from svolsdf.scene.scene import Scene, SceneError, _id_summary

__all__ = ["contact_sheet", "describe_scene"]

def _format_title(name: str) -> str:
    """The registered format's title (`svolsdf.scene.formats.SceneFormat.title`), else its
    name."""
    from svolsdf.scene.formats import scene_formats

    return next((f.title for f in scene_formats() if f.name == name and f.title), name)


def _stats(x: torch.Tensor) -> str:
    x = x.double()
    return f"min {float(x.min()):.4g}, median {float(x.median()):.4g}, max {float(x.max()):.4g}"


def describe_scene(scene: Scene, max_pairs: int = 5) -> str:
    """A multi-line, human-readable summary of ``scene``.

    Lists the format, the views, image size, units, depth ranges (min / median / max of near and
    far), the normalization, where the cameras sit in the unit frame, masks, the source views of
    the first ``max_pairs`` views, and format extras (e.g. DTU's ObsMask file).
    """
    ex = scene.extras
    lines = [f"scene        {scene.path}"]
    lines.append(f"format       {scene.format}: {_format_title(scene.format)}")
    if "cameras_file" in ex:
        lines.append(f"cameras      {ex['cameras_file']}")
    ids = scene.view_ids
    shown = (_id_summary(ids) if ids == sorted(ids)
             else ", ".join(str(v) for v in ids[:20]) + (" ..." if len(ids) > 20 else ""))
    lines.append(f"views        {len(scene)} (ids {shown})")
    native = ex.get("native_size")
    size = f"{scene.width}x{scene.height}"
    if native and tuple(native) != (scene.width, scene.height):
        size += f" (resized from {native[0]}x{native[1]})"
    lines.append(f"image size   {size} (W x H)")
    units = scene.units + (" (DTU)" if ex.get("dtu") else "")
    lines.append(f"units        {units}")
    dr = scene.depth_range
    lines.append(f"depth near   {_stats(dr[:, 0])}")
    lines.append(f"depth far    {_stats(dr[:, 1])}")
    lines.append(f"  source     {ex.get('depth_range_source', 'unknown')}")
    n = scene.normalization
    c = ", ".join(f"{float(v):.4g}" for v in n.center)
    lines.append(f"normalize    centre ({c}), scale {n.scale:.4g} {scene.units} per unit, "
                 f"region radius {n.radius:g} units")
    lines.append(f"  source     {ex.get('normalization_source', 'unknown')}")
    d = n.to_unit(scene.cameras.centers.double()).norm(dim=-1)
    lines.append(f"cameras      distance to centre in units: {_stats(d)}")
    mask_paths = ex.get("mask_paths")
    if mask_paths:
        src = Path(mask_paths[0]).parent
        same = mask_paths[0] in [str(p) for p in scene.image_paths]
        where = "alpha channel of the images" if same else f"{src}/"
        lines.append(f"masks        yes ({len(mask_paths)}, {where})")
    else:
        lines.append("masks        no")
    lines.append(f"pairs        {ex.get('pairs_source', 'unknown')}")
    for vid in scene.view_ids[:max_pairs]:
        srcs = scene.pairs.get(vid, [])
        lines.append(f"  {vid:>4} -> {' '.join(str(s) for s in srcs) or '(none)'}")
    if len(scene) > max_pairs:
        lines.append(f"  ... ({len(scene) - max_pairs} more)")
    for key, label in (("scan", "scan"), ("lighting", "lighting"), ("obs_mask", "ObsMask"),
                       ("plane", "plane"), ("stl", "STL points"), ("pair_file", "pair file"),
                       ("num_points", "sparse points"), ("distortion_ignored",
                                                         "distortion ignored")):
        if key in ex:
            lines.append(f"{label:<12} {ex[key]}")
    if ex.get("dtu") and "obs_mask" not in ex:
        lines.append("ObsMask      not found (DTU Chamfer evaluation needs "
                     "ObsMask/ObsMask{N}_10.mat)")
    return "\n".join(lines)


def _thumb(path: Path, width: int, height: int, mode: str = "RGB") -> np.ndarray:
    try:
        with Image.open(path) as im:
            if im.format == "JPEG":
                im.draft(mode, (width, height))  # fast reduced-size JPEG decoding
            if mode == "L" and "A" in im.getbands():
                im = im.getchannel("A")
            im = im.convert(mode).resize((width, height), Image.BILINEAR)
            return np.asarray(im)
    except (OSError, Image.DecompressionBombError) as e:
        raise SceneError(f"{path}: cannot read image ({e})") from None


def contact_sheet(scene: Scene, path: str | Path, thumb_width: int = 240,
                  columns: int | None = None) -> Path:
    """Write a grid of thumbnails of the scene's views, masks overlaid, labelled by view id.

    Pixels outside the mask are dimmed and tinted blue and the mask outline drawn in yellow.
    Thumbnails are decoded from ``scene.image_paths`` (JPEG draft mode), so the scene may be
    loaded with ``load_images=False``.

    Args:
        scene: the scene (its ``image_paths`` and ``extras["mask_paths"]`` are read).
        path: output image (.png or .jpg).
        thumb_width: thumbnail width in pixels (height keeps the aspect ratio).
        columns: grid columns; default ~sqrt(V * 4 / 3) for a roughly 4:3 sheet.

    Returns:
        The path written.
    """
    from scipy.ndimage import binary_erosion

    V = len(scene)
    tw = int(thumb_width)
    th = max(1, round(tw * scene.height / scene.width))
    cols = columns or max(1, min(V, math.ceil(math.sqrt(V * 4 / 3 * th / tw))))
    rows = math.ceil(V / cols)
    pad, label = 4, 16
    sheet = Image.new("RGB", (cols * (tw + pad) + pad, rows * (th + pad + label) + pad),
                      (32, 32, 32))
    draw = ImageDraw.Draw(sheet)
    masks = scene.extras.get("mask_paths")
    for k, vid in enumerate(scene.view_ids):
        img = _thumb(scene.image_paths[k], tw, th).astype(np.float32) / 255.0
        if masks:
            m = _thumb(Path(masks[k]), tw, th, mode="L") > 127
            tint = np.array([0.1, 0.15, 0.45], dtype=np.float32)
            img = np.where(m[..., None], img, 0.35 * img + 0.65 * tint)
            edge = m & ~binary_erosion(m, iterations=1)
            img[edge] = (1.0, 0.9, 0.1)
        r, c = divmod(k, cols)
        x0, y0 = pad + c * (tw + pad), pad + r * (th + pad + label)
        sheet.paste(Image.fromarray((img * 255 + 0.5).astype(np.uint8)), (x0, y0 + label))
        draw.text((x0 + 2, y0 + 2), f"view {vid}", fill=(235, 235, 235))
    arr = torch.from_numpy(np.asarray(sheet).transpose(2, 0, 1).copy()).float() / 255.0
    return write_image(path, arr)
