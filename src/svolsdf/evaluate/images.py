"""Novel-view image metrics with masks, as the paper evaluates them (docs/method.md 8.3).

- PSNR: -10 log10 of the MSE over the masked pixel-channels (background pixels excluded).
- SSIM: both images composited onto a white background, x * m + (1 - m), then the SSIM of
  Wang et al. (2004) with scikit-image's defaults: a uniform 7x7 window, K1 = 0.01, K2 = 0.03,
  sample covariances (N / (N - 1)), per channel, averaged over the valid region (the border of
  (7 - 1) / 2 pixels is cropped) and then over channels.
  ``data_range=1.0`` is the default; ``data_range=2.0`` reproduces the released evaluation, where
  scikit-image 0.17 took the float dtype range [-1, 1] (docs/method.md 8.3, 9.2 item 14).

Images are (3, H, W) float tensors in [0, 1]; masks are (1, H, W) or (H, W), 1 = object.
Masks that are not binary are thresholded at 0.5, as the released code does after resizing.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from svolsdf.errors import InputError

__all__ = ["composite_white", "masked_psnr", "ssim"]


def _check_pair(pred: Tensor, gt: Tensor) -> None:
    if pred.ndim != 3 or pred.shape[0] != 3 or pred.shape != gt.shape:
        raise InputError(f"image metrics expect two (3, H, W) images, got {tuple(pred.shape)} "
                         f"and {tuple(gt.shape)}")


def _mask(mask: Tensor | None, h: int, w: int) -> Tensor | None:
    if mask is None:
        return None
    if mask.ndim == 3:
        if mask.shape[0] != 1:
            raise InputError(f"mask must be (1, H, W) or (H, W), got {tuple(mask.shape)}")
        mask = mask[0]
    if mask.shape != (h, w):
        raise InputError(f"mask is {tuple(mask.shape)} but the images are {(h, w)}")
    return (mask > 0.5) if mask.dtype != torch.bool else mask


def composite_white(image: Tensor, mask: Tensor | None) -> Tensor:
    """x * m + (1 - m): the image on a white background (docs/method.md 8.3).

    Args:
        image: (3, H, W) float in [0, 1].
        mask: (1, H, W) or (H, W), or None (image returned unchanged).

    Returns:
        (3, H, W) float.
    """
    m = _mask(mask, image.shape[-2], image.shape[-1])
    if m is None:
        return image
    m = m.to(image.dtype)[None]
    return image * m + (1 - m)


def masked_psnr(pred: Tensor, gt: Tensor, mask: Tensor | None = None,
                data_range: float = 1.0) -> float:
    """PSNR over the masked pixel-channels (docs/method.md 8.3).

    PSNR = 10 log10(data_range^2 / MSE), MSE = sum_{c, p in mask} (pred - gt)^2 / (3 |mask|).

    Args:
        pred: (3, H, W) float in [0, 1].
        gt: (3, H, W) float in [0, 1].
        mask: (1, H, W) or (H, W) object mask, or None for all pixels.
        data_range: the images' value range.

    Returns:
        PSNR in dB (``inf`` for identical images, NaN for an empty mask).
    """
    _check_pair(pred, gt)
    m = _mask(mask, pred.shape[-2], pred.shape[-1])
    diff = (pred.double() - gt.double()) ** 2
    if m is not None:
        if not m.any():
            return float("nan")
        diff = diff[:, m]
    mse = float(diff.mean())
    return math.inf if mse == 0 else 10 * math.log10(data_range**2 / mse)


def ssim(pred: Tensor, gt: Tensor, mask: Tensor | None = None, data_range: float = 1.0,
         win_size: int = 7, k1: float = 0.01, k2: float = 0.03) -> float:
    """Mean SSIM, images composited on white first when a mask is given (docs/method.md 8.3).

    SSIM = (2 mu_x mu_y + C1)(2 s_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(s_x^2 + s_y^2 + C2)) with
    C1 = (K1 L)^2, C2 = (K2 L)^2, L = ``data_range``; local statistics over a uniform
    ``win_size`` window with sample (co)variances, as scikit-image's ``structural_similarity``
    with ``gaussian_weights=False``. Computed in float64.

    Args:
        pred: (3, H, W) float in [0, 1].
        gt: (3, H, W) float in [0, 1].
        mask: (1, H, W) or (H, W) object mask, or None.
        data_range: L; 1.0 by default, 2.0 reproduces the released code's numbers.
        win_size: odd window side (7).
        k1, k2: SSIM constants.

    Returns:
        mean SSIM over the valid region and the channels.
    """
    _check_pair(pred, gt)
    if win_size % 2 != 1 or min(pred.shape[-2:]) < win_size:
        raise InputError(f"SSIM window {win_size} must be odd and fit the {tuple(pred.shape[-2:])}"
                         " image")
    x = composite_white(pred, mask).double()[:, None]  # (3, 1, H, W): channels as a batch
    y = composite_white(gt, mask).double()[:, None]
    n = win_size * win_size
    cov_norm = n / (n - 1)

    def mean(t: Tensor) -> Tensor:
        return F.avg_pool2d(t, win_size, stride=1)  # valid region only

    ux, uy = mean(x), mean(y)
    vx = cov_norm * (mean(x * x) - ux * ux)
    vy = cov_norm * (mean(y * y) - uy * uy)
    vxy = cov_norm * (mean(x * y) - ux * uy)
    c1 = (k1 * data_range) ** 2
    c2 = (k2 * data_range) ** 2
    s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2))
    return float(s.mean(dim=(1, 2, 3)).mean())
