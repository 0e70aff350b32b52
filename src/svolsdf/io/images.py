"""Reading and writing images, masks and depth previews.

Images in memory are (3, H, W) float32 in [0, 1]; masks are (1, H, W) float32 in {0, 1}
(1 = object). Writers are atomic: they write a temporary file beside the target and rename it.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image, UnidentifiedImageError
from torch import Tensor

__all__ = [
    "ImageReadError",
    "depth_to_colormap",
    "image_size",
    "read_image",
    "read_mask",
    "resize_image",
    "resize_mask",
    "save_figure",
    "write_depth_preview",
    "write_image",
]


class ImageReadError(OSError):
    """An image file exists but cannot be decoded. ``str(e)`` names the file and the cause."""


def _open(path: Path) -> Image.Image:
    path = Path(path)
    try:
        im = Image.open(path)
        im.load()
    except FileNotFoundError:
        raise
    except Image.DecompressionBombError as e:
        raise ImageReadError(_too_large(path, e)) from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        raise ImageReadError(f"{path}: cannot read image ({e.__class__.__name__}: {e})") from e
    return im


def _too_large(path: Path, e: Exception) -> str:
    """The message for an image whose header declares more pixels than Pillow decodes (a
    decompression bomb, or a real panorama: both would need gigabytes)."""
    return (f"{path}: the image declares too many pixels to read ({' '.join(str(e).split())}); "
            "downscale it (e.g. to 1600 pixels wide)")


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image file, from its header only (no pixel decoding).

    Raises:
        ImageReadError: the file is not a readable image.
    """
    path = Path(path)
    try:
        with Image.open(path) as im:
            return int(im.width), int(im.height)
    except FileNotFoundError:
        raise
    except Image.DecompressionBombError as e:
        raise ImageReadError(_too_large(path, e)) from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        raise ImageReadError(f"{path}: cannot read image ({e.__class__.__name__}: {e})") from e


def _to_float(a: np.ndarray) -> np.ndarray:
    if a.dtype == np.uint8:
        return a.astype(np.float32) / 255.0
    if a.dtype == np.uint16:
        return a.astype(np.float32) / 65535.0
    if a.dtype == bool:
        return a.astype(np.float32)
    a = a.astype(np.float32)
    return a / 65535.0 if a.max(initial=0.0) > 1.0 else a


def read_image(path: str | Path, background: float | None = None) -> Tensor:
    """Read an image as RGB.

    Grey images are replicated to three channels; 16-bit images are scaled by 1/65535.
    An alpha channel is ignored unless ``background`` is given, in which case the colour is
    composited onto that grey level (NeRF-synthetic style: ``rgb * a + background * (1 - a)``).

    Args:
        path: image file (anything Pillow reads: PNG, JPEG, TIFF, ...).
        background: grey level in [0, 1] to composite transparent pixels onto, or None.

    Returns:
        (3, H, W) float32 in [0, 1].

    Raises:
        FileNotFoundError: the file does not exist.
        ImageReadError: the file cannot be decoded (the message names it).
    """
    im = _open(Path(path))
    alpha = None
    if im.mode in ("I;16", "I;16B", "I;16L", "I"):
        a = _to_float(np.asarray(im).astype(np.uint16) if im.mode != "I" else np.asarray(im))
        rgb = np.repeat(a[..., None], 3, axis=-1)
    else:
        if "A" in im.getbands() or (im.mode == "P" and "transparency" in im.info):
            im = im.convert("RGBA")
            a = np.asarray(im)
            alpha = _to_float(a[..., 3])
            rgb = _to_float(a[..., :3])
        else:
            rgb = _to_float(np.asarray(im.convert("RGB")))
    if alpha is not None and background is not None:
        rgb = rgb * alpha[..., None] + float(background) * (1.0 - alpha[..., None])
    return torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1))).clamp_(0, 1)


def read_mask(path: str | Path) -> Tensor:
    """Read an object mask.

    Foreground is where the alpha channel (if the file has one) or else the brightest colour
    channel is > 127 of 255 (DTU/IDR masks are RGB 0/255; BlendedMVS masks keep it in alpha,
    docs/method.md 1.1).

    Args:
        path: mask image file.

    Returns:
        (1, H, W) float32 in {0, 1}.
    """
    im = _open(Path(path))
    if im.mode == "1":
        m = np.asarray(im, dtype=bool)
    elif "A" in im.getbands():
        m = np.asarray(im.convert("RGBA"))[..., 3] > 127
    elif im.mode in ("I;16", "I;16B", "I;16L", "I"):
        m = np.asarray(im).astype(np.float64) > 32767
    else:
        a = np.asarray(im.convert("RGB"))
        m = a.max(axis=-1) > 127
    return torch.from_numpy(m[None].astype(np.float32))


def resize_image(image: Tensor, width: int, height: int) -> Tensor:
    """Bicubic resize (antialiased when shrinking), as docs/method.md 1.3 resizes inputs.

    Args:
        image: (C, H, W) or (N, C, H, W) float in [0, 1].
        width, height: target size in pixels.

    Returns:
        The resized tensor, same rank, clamped to [0, 1].
    """
    if image.ndim not in (3, 4):
        raise ValueError(
            f"resize_image expects (C, H, W) or (N, C, H, W), got {tuple(image.shape)}")
    if image.shape[-2:] == (height, width):
        return image
    x = image[None] if image.ndim == 3 else image
    shrink = height < x.shape[-2] or width < x.shape[-1]
    y = F.interpolate(x, size=(height, width), mode="bicubic", align_corners=False,
                      antialias=shrink).clamp_(0, 1)
    return y[0] if image.ndim == 3 else y


def resize_mask(mask: Tensor, width: int, height: int) -> Tensor:
    """Resize a {0, 1} mask: area-weighted (antialiased bilinear) then thresholded at 0.5.

    Args:
        mask: (1, H, W) or (N, 1, H, W) float in {0, 1}.

    Returns:
        Same rank at the new size, float32 in {0, 1}.
    """
    if mask.shape[-2:] == (height, width):
        return mask
    x = mask[None] if mask.ndim == 3 else mask
    shrink = height < x.shape[-2] or width < x.shape[-1]
    y = (F.interpolate(x.float(), size=(height, width), mode="bilinear", align_corners=False,
                       antialias=shrink) > 0.5).float()
    return y[0] if mask.ndim == 3 else y


def _to_uint8_hwc(image: Tensor | np.ndarray) -> np.ndarray:
    a = image.detach().cpu().float().numpy() if isinstance(image, Tensor) else np.asarray(image)
    if a.ndim == 3:
        if a.shape[0] not in (1, 3, 4):
            raise ValueError(f"write_image expects (3, H, W) or (H, W), got {a.shape}")
        a = a.transpose(1, 2, 0)
    if a.ndim == 3 and a.shape[-1] == 1:
        a = a[..., 0]
    if a.ndim not in (2, 3):
        raise ValueError(f"write_image expects (3, H, W) or (H, W), got {a.shape}")
    if a.dtype != np.uint8:
        a = (np.clip(np.nan_to_num(a.astype(np.float64)), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return a


def write_image(path: str | Path, image: Tensor | np.ndarray) -> Path:
    """Write an image atomically (temporary file in the same folder, then ``os.replace``).

    Args:
        path: target file; the format follows the suffix (.png, .jpg, ...). Parent folders
            are created.
        image: (3, H, W) or (1, H, W) or (H, W) float in [0, 1] (uint8 arrays are written as is).

    Returns:
        The path written.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    a = _to_uint8_hwc(image)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix or ".png",
                               dir=path.parent)
    os.close(fd)
    try:
        fmt = Image.registered_extensions().get(path.suffix.lower(), "PNG")
        Image.fromarray(a).save(tmp, format=fmt)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def depth_to_colormap(depth: Tensor, mask: Tensor | None = None, cmap: str = "turbo",
                      lo: float | None = None, hi: float | None = None) -> Tensor:
    """Colour-code a depth map for viewing (near = one end of the colour map, far = the other).

    The range defaults to the 1st..99th percentile of the valid depths (finite, > 0, inside
    ``mask``); invalid pixels are black.

    Args:
        depth: (H, W) z-depth.
        mask: optional (H, W) or (1, H, W) bool/float; pixels outside are shown black.
        cmap: a matplotlib colour map name ("turbo", "viridis", ...).
        lo, hi: explicit depth range.

    Returns:
        (3, H, W) float32 in [0, 1].
    """
    from matplotlib import colormaps

    if depth.ndim == 3 and depth.shape[0] == 1:
        depth = depth[0]
    if depth.ndim != 2:
        raise ValueError(f"depth_to_colormap expects (H, W), got {tuple(depth.shape)}")
    d = depth.detach().cpu().double()
    valid = torch.isfinite(d) & (d > 0)
    if mask is not None:
        m = mask.detach().cpu()
        m = m[0] if m.ndim == 3 else m
        valid &= m.bool()
    if valid.any():
        vals = d[valid]
        q = torch.quantile(vals[:: max(1, vals.numel() // 100000)], torch.tensor([0.01, 0.99],
                                                                                  dtype=d.dtype))
        lo = float(q[0]) if lo is None else lo
        hi = float(q[1]) if hi is None else hi
    lo = 0.0 if lo is None else lo
    hi = lo + 1.0 if hi is None or hi <= lo else hi
    t = ((d - lo) / (hi - lo)).clamp(0, 1).nan_to_num(0.0).numpy()
    rgb = colormaps[cmap](t)[..., :3].astype(np.float32)
    rgb[~valid.numpy()] = 0.0
    return torch.from_numpy(rgb.transpose(2, 0, 1).copy())


def write_depth_preview(path: str | Path, depth: Tensor, mask: Tensor | None = None,
                        cmap: str = "turbo", lo: float | None = None,
                        hi: float | None = None) -> Path:
    """Write :func:`depth_to_colormap` of an (H, W) depth map as an image file (atomic)."""
    return write_image(path, depth_to_colormap(depth, mask=mask, cmap=cmap, lo=lo, hi=hi))


def save_figure(fig, path: str | Path, dpi: int = 100) -> Path:
    """Write a matplotlib figure as a PNG beside ``path`` and move it into place (a reader never
    sees half a picture), then close the figure; returns ``path``."""
    import matplotlib.pyplot as plt

    path = Path(path)
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    tmp.replace(path)
    return path
