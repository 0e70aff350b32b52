"""Depth hypotheses per cascade stage (docs/method.md 2.5).

Notation: d_min, d_max are the view's depth range (z-depth, world units) and the base interval is
Δ̄ = (d_max - d_min) / 192 (docs/method.md 2.5: the divisor is 192, not 191; for DTU with
d_min = 425, d_max = 931.15, Δ̄ = 2.6362 mm).

Stage 1: D planes, linear d_k = d_min + k (d_max - d_min)/(D - 1), or uniform in inverse depth
d_k = 1 / ((1 - t_k)/d_min + t_k/d_max), t_k = k/(D - 1).

Stages 2 and 3: per pixel, centred on a guide depth d: lower = d - (D/2) r Δ̄,
upper = d + (D/2) r Δ̄, D values spaced (upper - lower)/(D - 1); the total width is D r Δ̄.

Widths (docs/method.md 2.5 and 9.2.1), with counts (192, 32, 8):

- ``width="paper"`` (default): the paper's implementation details, "192, 32, and 8 depth
  hypotheses with intervals 1, 0.5, and 0.5", i.e. r = 0.5 at stages 2 and 3: 32·0.5Δ̄ = 16Δ̄
  and 8·0.5Δ̄ = 4Δ̄. DTU: ≈ 42.2 mm and ≈ 10.5 mm. The released code runs the same.
- ``width="released"``: the released code's ratios, the same numbers as ``paper`` (a name kept
  for configs that say where their value comes from).
- ``width="half-default"``: a reading of the paper's method section, "half of the depth search
  width in the finer stages compared to the default": the default CasMVSNet widths are
  48·4Δ̄ = 192Δ̄, 32·2Δ̄ = 64Δ̄ and 8·1Δ̄ = 8Δ̄; half of them at stages 2 and 3 is 32Δ̄ and 4Δ̄,
  i.e. r = 1.0 at stage 2 and r = 0.5 at stage 3. DTU: ≈ 84.4 mm and ≈ 10.5 mm. It was
  svolsdf's ``paper`` until the explicit numbers were taken as the paper's setting.

Stage 1 covers the whole range in both cases (DTU: 506 mm at 2.65 mm spacing).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "STAGE_DEPTHS",
    "WIDTHS",
    "base_interval",
    "interval_ratio",
    "stage_width",
    "plane_hypotheses",
    "guided_hypotheses",
    "stage_hypotheses",
]

#: hypothesis counts per stage (docs/method.md 0, 2.5)
STAGE_DEPTHS: tuple[int, int, int] = (192, 32, 8)

#: interval ratio r per stage for each width option (docs/method.md 2.5, 9.2 item 1)
WIDTHS: dict[str, tuple[float, float, float]] = {
    "paper": (1.0, 0.5, 0.5),
    "released": (1.0, 0.5, 0.5),
    "half-default": (1.0, 1.0, 0.5),
}


def base_interval(d_min: float | Tensor, d_max: float | Tensor) -> float | Tensor:
    """Δ̄ = (d_max - d_min) / 192 (docs/method.md 2.5)."""
    return (d_max - d_min) / 192.0


def interval_ratio(stage: int, width: str = "paper") -> float:
    """Interval ratio r of ``stage`` (1-based) for the width option (`WIDTHS`: "paper",
    "released" or "half-default")."""
    if width not in WIDTHS:
        raise ValueError(f"width must be one of {sorted(WIDTHS)}, got {width!r}")
    if not 1 <= stage <= 3:
        raise ValueError(f"stage must be 1, 2 or 3, got {stage}")
    return WIDTHS[width][stage - 1]


def stage_width(stage: int, d_min: float, d_max: float, num_depths: int | None = None,
                width: str = "paper") -> float:
    """Total search width D r Δ̄ of a finer stage, or d_max - d_min at stage 1 (world units)."""
    if stage == 1:
        return float(d_max - d_min)
    D = num_depths if num_depths is not None else STAGE_DEPTHS[stage - 1]
    return float(D * interval_ratio(stage, width) * base_interval(d_min, d_max))


def plane_hypotheses(
    d_min: float,
    d_max: float,
    num_depths: int,
    height: int,
    width: int,
    inverse: bool = False,
    device=None,
    dtype=torch.float32,
) -> Tensor:
    """Stage-1 fronto-parallel planes across [d_min, d_max] (docs/method.md 1.4, 2.5).

    Linear: d_k = d_min + k (d_max - d_min)/(D - 1). Inverse: d_k = 1/((1 - t_k)/d_min + t_k/d_max)
    with t_k = k/(D - 1).

    Args:
        d_min, d_max: z-depth range, 0 < d_min < d_max (world units).
        num_depths: D >= 2.
        height, width: the volume's H, W.
        inverse: space uniformly in inverse depth.

    Returns:
        (D, H, W) increasing depths (an expanded view; call ``.contiguous()`` to own memory).
    """
    d_min, d_max = float(d_min), float(d_max)
    if not 0 < d_min < d_max:
        raise ValueError(f"depth range must satisfy 0 < d_min < d_max, got [{d_min}, {d_max}]")
    if num_depths < 2:
        raise ValueError(f"need at least 2 hypotheses, got {num_depths}")
    t = torch.linspace(0.0, 1.0, num_depths, dtype=torch.float64)
    d = 1.0 / ((1 - t) / d_min + t / d_max) if inverse else d_min + t * (d_max - d_min)
    d[0], d[-1] = d_min, d_max
    return d.to(device=device, dtype=dtype).view(-1, 1, 1).expand(-1, height, width)


def guided_hypotheses(guide: Tensor, num_depths: int, interval: float | Tensor) -> Tensor:
    """Per-pixel hypotheses centred on a guide depth (docs/method.md 2.5, stages 2 and 3).

    lower = d - (D/2)·interval, upper = d + (D/2)·interval, D values spaced (upper - lower)/(D - 1).
    There is no clamping (as released); callers that need positive depths clamp the guide.

    Args:
        guide: (..., H, W) guide z-depth (world units).
        num_depths: D >= 2.
        interval: r·Δ̄ in world units, a float or a tensor broadcastable to (..., H, W).

    Returns:
        (..., D, H, W) hypotheses, increasing along D.
    """
    if num_depths < 2:
        raise ValueError(f"need at least 2 hypotheses, got {num_depths}")
    interval = torch.as_tensor(interval, dtype=guide.dtype, device=guide.device)
    half = (0.5 * num_depths * interval).expand_as(guide).unsqueeze(-3)
    lower = guide.unsqueeze(-3) - half
    step = 2 * half / (num_depths - 1)
    k = torch.arange(num_depths, dtype=guide.dtype, device=guide.device).view(-1, 1, 1)
    return lower + k * step


def stage_hypotheses(
    stage: int,
    d_min: float,
    d_max: float,
    height: int,
    width: int,
    guide: Tensor | None = None,
    num_depths: int | None = None,
    width_mode: str = "paper",
    inverse: bool = False,
    device=None,
) -> Tensor:
    """Hypotheses of one cascade stage for one view.

    Args:
        stage: 1, 2 or 3.
        d_min, d_max: the view's depth range (defines Δ̄ for all stages).
        height, width: the stage's H, W; ``guide`` must be (H, W) at stages 2 and 3.
        guide: (H, W) guide z-depth, required at stages 2 and 3.
        num_depths: D, default ``STAGE_DEPTHS[stage - 1]``.
        width_mode: "paper" or "released" (module docstring).
        inverse: inverse-depth spacing at stage 1 (stages 2-3 are always linear,
        docs/method.md 2.5).

    Returns:
        (D, H, W) hypotheses.
    """
    D = num_depths if num_depths is not None else STAGE_DEPTHS[stage - 1]
    if stage == 1:
        return plane_hypotheses(d_min, d_max, D, height, width, inverse, device=device)
    if guide is None:
        raise ValueError(f"stage {stage} needs a guide depth")
    if guide.shape != (height, width):
        raise ValueError(f"guide must be ({height}, {width}), got {tuple(guide.shape)}")
    r = interval_ratio(stage, width_mode)
    return guided_hypotheses(guide, D, r * base_interval(float(d_min), float(d_max)))
