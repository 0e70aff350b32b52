"""Semi-global aggregation of a plane-sweep cost volume (Hirschmüller 2008), the plane sweep's
last step per stage (`svolsdf.mvs.planesweep`; beyond the paper, docs/method.md 9.3)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["sgm_aggregate"]


def sgm_aggregate(cost: Tensor, guide: Tensor, p1: float, p2: float, sigma: float,
                  directions: int = 4) -> Tensor:
    """Semi-global aggregation of a cost volume along 4 or 8 scanlines (Hirschmüller 2008).

    Along each direction r: L_r(x, k) = C(x, k) + min(L_r(x-r, k), L_r(x-r, k±1) + P1,
    min_j L_r(x-r, j) + P2(x)) - min_j L_r(x-r, j), with an edge-aware
    P2(x) = P1 + (P2 - P1) exp(-|I(x) - I(x-r)| / sigma) so that depth may jump at intensity
    edges. The result is the mean over the directions, on the scale of ``cost``. Neighbouring
    hypotheses k are neighbouring depths of the per-pixel hypothesis lists. With 8 directions the
    4 diagonals are added; they remove most of the horizontal and vertical streaks that 4 paths
    leave on weakly textured surfaces.

    Args:
        cost: (D, H, W) matching cost.
        guide: (H, W) grayscale reference image.
        p1, p2: penalties for a change of 1 and of more than 1 hypothesis.
        sigma: intensity scale of the edge-aware P2.
        directions: 4 (horizontal and vertical) or 8 (and the diagonals).

    Returns:
        (D, H, W) aggregated cost.
    """
    if directions not in (4, 8):
        raise ValueError(f"directions must be 4 or 8, got {directions}")
    if p1 < 0 or p2 < 0:
        raise ValueError(f"SGM penalties must be >= 0, got p1 = {p1}, p2 = {p2}")
    # Each pass walks slices c[i] (D, m) and takes its predecessors from slice i - 1, column
    # x - shift. A reverse pass is a forward pass over the flipped slices with the opposite
    # shift, so all passes over the same slices run as one batch: W steps for the horizontal
    # pair, H steps for the vertical pair and the 4 diagonal passes.
    # (shift, reverse) per pass; the diagonals (1, +-1) are the shifts +-1
    rows = [(0, False), (0, True)] + (
        [(1, False), (1, True), (-1, False), (-1, True)] if directions == 8 else [])
    total = _sgm_passes(cost.movedim(2, 0), guide.movedim(1, 0), p1, p2, sigma,
                        [(0, False), (0, True)]).movedim(0, 2)
    total += _sgm_passes(cost.movedim(1, 0), guide, p1, p2, sigma, rows).movedim(0, 1)
    return total / (len(rows) + 2)


def _sgm_passes(c: Tensor, g: Tensor, p1: float, p2: float, sigma: float,
                passes: list[tuple[int, bool]]) -> Tensor:
    """SGM scanline passes over slices c[i] (D, m), batched; returns their sum (n, D, m).

    A forward pass with shift s takes the predecessor of column x in slice i from column x - s
    of slice i - 1 (columns without one keep C); a reverse pass walks from the last slice, with
    the predecessor at column x + s of slice i + 1. Hirschmüller's recursion, see
    `sgm_aggregate`.

    Args:
        c: (n, D, m) cost slices.
        g: (n, m) guide intensities of the slices.
        p1, p2, sigma: as `sgm_aggregate`.
        passes: (shift, reverse) per pass.

    Returns:
        (n, D, m) the passes' aggregated costs, summed.
    """
    n, D, m = c.shape
    B = len(passes)
    # one contiguous copy (``c`` is a moved view of the volume): each step then reads whole
    # slices instead of a column of every row
    c = c.contiguous()
    # a reverse pass = a forward pass over flipped slices with the opposite shift. The batch
    # holds the forward passes first: their slice i is c[i] and the reverse passes' is
    # c[n - 1 - i], read in place (no flipped copy of the volume)
    order = ([b for b, (_, rev) in enumerate(passes) if not rev]
             + [b for b, (_, rev) in enumerate(passes) if rev])
    nf = sum(1 for _, rev in passes if not rev)
    rev_idx = torch.arange(n - 1, -1, -1, device=c.device)
    gr = torch.index_select(g, 0, rev_idx)
    G = torch.stack([gr if passes[b][1] else g for b in order])  # (B, n, m)
    shifts = torch.tensor([-passes[b][0] if passes[b][1] else passes[b][0] for b in order],
                          device=c.device)
    # column of each predecessor in the output padded by one zero column per side; a padded
    # predecessor is constant over D, so the penalty term vanishes there (C is kept)
    cols = torch.arange(m, device=c.device)[None] - shifts[:, None] + 1  # (B, m)
    idx = cols[:, None, :].expand(B, D, m)
    Gp = F.pad(G, (1, 1), mode="replicate")
    g_prev = torch.gather(Gp[:, :-1], 2, cols[:, None, :].expand(B, n - 1, m))  # (B, n-1, m)
    pen2 = p1 + (p2 - p1) * torch.exp(-(G[:, 1:] - g_prev).abs() / sigma)  # (B, n-1, m)
    del G, Gp, g_prev, gr
    # the passes' outputs with a zero column on each side: slice i - 1 is slice i's buffer of
    # predecessors, so no copy per step
    out = c.new_empty(B, n, D, m + 2)
    out[..., 0] = 0
    out[..., -1] = 0
    out[:nf, 0, :, 1:-1] = c[0]
    out[nf:, 0, :, 1:-1] = c[n - 1]
    # min is exact, so the order of the minima does not change the result:
    # best = min(P, min_j P + pen2, P[k-1] + P1, P[k+1] + P1) at hypothesis k
    for i in range(1, n):
        P = torch.gather(out[:, i - 1], 2, idx)  # (B, D, m) predecessors
        mval = P.amin(dim=1, keepdim=True)
        P1 = P + p1
        best = torch.minimum(P, mval + pen2[:, i - 1, None])
        torch.minimum(best[:, 1:], P1[:, :-1], out=best[:, 1:])
        torch.minimum(best[:, :-1], P1[:, 1:], out=best[:, :-1])
        cur = out[:, i, :, 1:-1]
        if nf:
            torch.add(c[i], best[:nf], out=cur[:nf])
        if nf < B:
            torch.add(c[n - 1 - i], best[nf:], out=cur[nf:])
        cur.sub_(mval)
    # summed in the order of ``passes``; a reverse pass's slices are added back flipped
    total = torch.zeros_like(c)
    for b in range(B):
        o = out[order.index(b), :, :, 1:-1]
        if passes[b][1]:
            total.index_add_(0, rev_idx, o)
        else:
            total += o
    return total
