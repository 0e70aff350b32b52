"""The ground truth of a novel view as the official evaluation prepares it (docs/method.md 8.3).

The released ``eval_vsdf.py`` resizes the test photo to the rendering size with OpenCV's
``INTER_CUBIC`` (bicubic, a = -0.75, no antialiasing when shrinking) and the mask with a bilinear
resize (the INTER_NEAREST flag lands in the ``dst`` argument, docs/method.md 9.2 item 14), then
keeps mask values > 0.5. ``torch.nn.functional.interpolate`` with ``mode="bicubic"``,
``align_corners=False`` and ``antialias=False`` is the same kernel (a = -0.75, half-pixel
centres); the working images of a run are resized with antialiasing instead
(`svolsdf.io.images.resize_image`), which differs from this by about 42 dB inside DTU masks.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["official_resize", "official_resize_mask", "official_test_images"]


def official_resize(image: Tensor, width: int, height: int) -> Tensor:
    """OpenCV INTER_CUBIC resize, no antialiasing (docs/method.md 8.3).

    Args:
        image: (3, H, W) float in [0, 1].
        width, height: target size.

    Returns:
        (3, height, width) float in [0, 1].
    """
    if image.ndim != 3:
        raise ValueError(f"official_resize expects (C, H, W), got {tuple(image.shape)}")
    if image.shape[-2:] == (height, width):
        return image
    return F.interpolate(image[None].float(), size=(height, width), mode="bicubic",
                         align_corners=False, antialias=False)[0].clamp(0, 1)


def official_resize_mask(mask: Tensor, width: int, height: int) -> Tensor:
    """The released evaluation's mask: bilinear resize (no antialiasing), then > 0.5.

    Args:
        mask: (1, H, W) or (H, W) float in {0, 1}.

    Returns:
        (height, width) bool.
    """
    m = mask[0] if mask.ndim == 3 else mask
    if m.shape == (height, width):
        return m > 0.5
    return F.interpolate(m[None, None].float(), size=(height, width), mode="bilinear",
                         align_corners=False, antialias=False)[0, 0] > 0.5


def official_test_images(scene_dir: str | Path, view_ids: list[int], size: tuple[int, int],
                         lighting: int | None = None) -> tuple[Tensor, Tensor | None]:
    """The scene's photos and masks of ``view_ids`` prepared as the official evaluation does.

    Args:
        scene_dir: a scene folder (any layout `svolsdf.scene.loaders.load_scene` reads).
        view_ids: the view ids.
        size: (width, height) of the renders.
        lighting: DTU raw layout's lighting index, as the run's ``scene.lighting``.

    Returns:
        images (N, 3, H, W) float in [0, 1]; masks (N, H, W) bool, or None when the scene has no
        masks.
    """
    from svolsdf.scene.loaders import load_scene

    kw = {} if lighting is None else {"lighting": lighting}
    w, h = size
    images, masks = [], []
    for v in view_ids:  # one photo at a time at its native size: DTU's are 1600x1200
        sc = load_scene(scene_dir, views=[int(v)], **kw)
        images.append(official_resize(sc.images[0], w, h))
        if sc.masks is not None:
            masks.append(official_resize_mask(sc.masks[0], w, h))
    return torch.stack(images), (torch.stack(masks) if len(masks) == len(images) else None)
