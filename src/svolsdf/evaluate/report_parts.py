"""The pieces of the HTML report that its sections share: the record of one evaluated view,
pictures as embedded PNGs with captions, colour maps and colour bars, and number formatting."""

from __future__ import annotations

import base64
import html
import io
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from torch import Tensor

from svolsdf.errors import raise_if_interrupted

__all__ = ["DEPTH_CMAP", "ERROR_CMAP", "THUMB", "ViewImages", "colorbar", "colorize", "figure",
           "file_b64", "fmt", "png_b64", "tensor_u8", "units_label"]

log = logging.getLogger(__name__)

THUMB = 360  # width in pixels of embedded pictures
DEPTH_CMAP = "viridis"
ERROR_CMAP = "inferno"


@dataclass
class ViewImages:
    """One evaluated novel view.

    Attributes:
        view_id: the view id.
        pred: (3, H, W) float rendering in [0, 1].
        gt: (3, H, W) float ground truth in [0, 1].
        mask: (1, H, W) object mask or None.
        metrics: metric name -> value for this view.
        kind: which renderer ("volume" or "ibr").
        role: "novel" for a view the run held out, "input" for one of its input (training)
            views rendered back, which no mean of novel views counts.
    """

    view_id: int
    pred: Tensor
    gt: Tensor
    mask: Tensor | None = None
    metrics: dict = field(default_factory=dict)
    kind: str = "volume"
    role: str = "novel"


# --------------------------------------------------------------------------- small helpers
def png_b64(a: np.ndarray, width: int = THUMB) -> str:
    """(H, W, 3|4) uint8 or (H, W) -> base64 PNG of at most ``width`` pixels across."""
    from PIL import Image

    im = Image.fromarray(a)
    if im.width > width:
        im = im.resize((width, max(1, round(im.height * width / im.width))), Image.LANCZOS)
    buf = io.BytesIO()
    im.save(buf, format="PNG")
    return base64.b64encode(buf.getvalue()).decode("ascii")


def file_b64(path: Path) -> str | None:
    from PIL import Image

    try:
        with Image.open(path) as im:
            return png_b64(np.asarray(im.convert("RGB")))
    except Exception as e:  # a broken preview must not break the report
        raise_if_interrupted()
        log.warning("report: cannot read %s (%s)", path, e)
        return None


def tensor_u8(x: Tensor) -> np.ndarray:
    return (x.detach().float().clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255 + 0.5).astype(
        np.uint8)


def figure(b64: str, caption: str, extra: str = "") -> str:
    return (f'<figure><img src="data:image/png;base64,{b64}" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption>{extra}</figure>")


def fmt(v) -> str:
    if v is None:
        return "&ndash;"
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        return f"{v:.4g}" if abs(v) < 1e4 else f"{v:.0f}"
    return html.escape(str(v))


def colorize(values: np.ndarray, valid: np.ndarray, cmap: str, vmin: float, vmax: float
              ) -> np.ndarray:
    """(H, W) values -> (H, W, 3) uint8 through a matplotlib colour map; invalid pixels grey."""
    from matplotlib import colormaps

    t = np.clip((values - vmin) / max(vmax - vmin, 1e-12), 0, 1)
    rgb = (colormaps[cmap](t)[..., :3] * 255 + 0.5).astype(np.uint8)
    rgb[~valid] = 200
    return rgb


def colorbar(cmap: str, vmin: float, vmax: float, label: str) -> str:
    """A horizontal colour bar as a CSS gradient with min / middle / max ticks."""
    from matplotlib import colormaps

    cm = colormaps[cmap]
    stops = ",".join(
        "rgb({},{},{}) {:.0f}%".format(*(int(255 * x + 0.5) for x in cm(t)[:3]), 100 * t)
        for t in np.linspace(0, 1, 11))
    ticks = "".join(f"<span>{v:.4g}</span>" for v in (vmin, (vmin + vmax) / 2, vmax))
    return (f'<div class="cbar"><div class="grad" style="background:linear-gradient(to right,'
            f'{stops})"></div><div class="ticks">{ticks}</div>'
            f'<div class="cbl">{html.escape(label)}</div></div>')


def units_label(units: str | None) -> str:
    return units if units and units != "unknown" else "world units"

