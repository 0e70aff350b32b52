"""Positional encoding gamma(x) (docs/method.md 5.1; NeRF/IDR ``embedder.py``)."""

from __future__ import annotations

import torch
from torch import Tensor, nn

__all__ = ["positional_encoding", "PositionalEncoding"]


def positional_encoding(x: Tensor, multires: int) -> Tensor:
    """gamma(x) = [x, sin(2^0 x), cos(2^0 x), ..., sin(2^(L-1) x), cos(2^(L-1) x)]
    (docs/method.md 5.1).

    Frequencies are log-spaced 2^0 .. 2^(L-1) with L = ``multires``; per frequency the sin block
    (d values) comes before the cos block (d values), so the output has d + 2 d L channels and its
    first d channels are x itself (the SDF network's geometric init relies on that order).

    Args:
        x: (..., d) float.
        multires: L >= 0; 0 returns x unchanged.

    Returns:
        (..., d + 2 d L) float.
    """
    if multires < 0:
        raise ValueError(f"positional_encoding: multires must be >= 0, got {multires}")
    if multires == 0:
        return x
    freqs = 2.0 ** torch.arange(multires, device=x.device, dtype=x.dtype)  # (L,)
    xf = x[..., None, :] * freqs[:, None]  # (..., L, d)
    enc = torch.stack([torch.sin(xf), torch.cos(xf)], dim=-2)  # (..., L, 2, d)
    return torch.cat([x, enc.flatten(-3)], dim=-1)


class PositionalEncoding(nn.Module):
    """Module form of :func:`positional_encoding`; ``out_dim`` = d + 2 d L."""

    def __init__(self, d_in: int, multires: int):
        super().__init__()
        self.d_in = int(d_in)
        self.multires = int(multires)
        self.out_dim = self.d_in * (1 + 2 * self.multires)

    def forward(self, x: Tensor) -> Tensor:
        """x: (..., d_in) -> (..., out_dim)."""
        if x.shape[-1] != self.d_in:
            raise ValueError(
                f"PositionalEncoding: expected (..., {self.d_in}), got {tuple(x.shape)}"
            )
        return positional_encoding(x, self.multires)
