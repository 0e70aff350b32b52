"""Object-mask helpers: dilation with a disk and resizing to a depth map's resolution, as
docs/method.md 6.3's evaluation mask does.

Fusion, the field's initialisation from MVS depth, mesh culling and the pipeline's ray selection
all dilate masks, so the helpers live below those stages, not in one stage's folder.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from scipy import ndimage
from torch import Tensor

__all__ = [
    "dilate_mask",
    "mask_to_depth_resolution",
]


def dilate_mask(mask: Tensor, radius: int) -> Tensor:
    """Binary dilation with a disk of ``radius`` pixels (docs/method.md 6.3, "Evaluation mask").

    Equal to ``scipy.ndimage.binary_dilation`` with ``skimage.morphology.disk(radius)`` (pixels
    with dx^2 + dy^2 <= radius^2), computed with a Euclidean distance transform so the cost does
    not grow with the radius.

    Args:
        mask: (H, W) or (1, H, W) bool or {0, 1} float; > 0.5 is inside.
        radius: disk radius in pixels; 0 returns the mask unchanged.

    Returns:
        (H, W) bool.
    """
    m = mask.reshape(mask.shape[-2:]) if mask.ndim == 3 else mask
    if m.ndim != 2:
        raise ValueError(f"mask must be (H, W) or (1, H, W), got {tuple(mask.shape)}")
    m = (m > 0.5) if m.is_floating_point() else m.bool()
    if radius <= 0 or not bool(m.any()):
        return m.clone()
    dist = ndimage.distance_transform_edt(~m.cpu().numpy())
    return torch.from_numpy(dist <= radius).to(m.device)


def mask_to_depth_resolution(mask: Tensor, height: int, width: int) -> Tensor:
    """Resize a binary mask to the depth resolution: bilinear, then > 0 (docs/method.md 6.3).

    Args:
        mask: (H, W) bool or float.
        height, width: target size.

    Returns:
        (height, width) bool.
    """
    if tuple(mask.shape) == (height, width):
        return mask > 0 if mask.is_floating_point() else mask.bool()
    m = mask.float()[None, None]
    # cv2.resize(INTER_LINEAR) semantics: half-pixel centres, no antialiasing.
    r = F.interpolate(m, size=(height, width), mode="bilinear", align_corners=False)
    return r[0, 0] > 0
