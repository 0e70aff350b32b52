"""Source-view pairs: reading and writing MVSNet's ``pair.txt``, and MVSNet's view selection.

View selection (MVSNet, Yao et al. 2018, Sec. 4.1; ``colmap2mvsnet.py``): the score of the view
pair (i, j) is s(i, j) = sum_p G(theta_ij(p)) over the points p seen by both views, where
theta_ij(p) = (180 / pi) * arccos((c_i - p) . (c_j - p) / (|c_i - p| |c_j - p|)) is the
triangulation angle and G is a piecewise Gaussian, G(theta) = exp(-(theta - theta0)^2 / (2
sigma1^2)) for theta <= theta0 and exp(-(theta - theta0)^2 / (2 sigma2^2)) otherwise, with
theta0 = 5, sigma1 = 1, sigma2 = 10 (degrees). Without sparse points, points sampled in the
normalization sphere stand in for them (visible = in front of the camera and inside the image).
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
from torch import Tensor

from svolsdf.scene.cameras import Cameras
from svolsdf.scene.scene import Normalization, SceneError

__all__ = [
    "compute_pairs",
    "read_pair_file",
    "sample_sphere_points",
    "covisibility",
    "select_views",
    "view_selection_scores",
    "visible_in_views",
    "write_pair_file",
]


def read_pair_file(path: str | Path) -> tuple[dict[int, list[int]], dict[int, list[float]]]:
    """Read MVSNet's ``pair.txt`` (docs/method.md 1.1).

    Line 1 is the number of views; then per view a line with the reference id and a line
    ``K src1 score1 src2 score2 ...``.

    Returns:
        pairs: ref id -> source ids, best first.
        scores: ref id -> their scores.

    Raises:
        SceneError: naming the file and the line when it is malformed.
    """
    path = Path(path)
    try:
        lines = [ln.strip() for ln in path.read_text().splitlines() if ln.strip()]
    except (OSError, UnicodeDecodeError) as e:
        raise SceneError(f"{path}: cannot read pair file ({e})") from None
    pairs: dict[int, list[int]] = {}
    scores: dict[int, list[float]] = {}
    try:
        n = int(lines[0])
        for k in range(n):
            ref = int(lines[1 + 2 * k].split()[0])
            tok = lines[2 + 2 * k].split()
            m = int(tok[0])
            if len(tok) < 1 + 2 * m:
                raise ValueError(f"line {3 + 2 * k} lists {m} sources but has {len(tok) - 1} "
                                 "tokens")
            pairs[ref] = [int(tok[1 + 2 * i]) for i in range(m)]
            scores[ref] = [float(tok[2 + 2 * i]) for i in range(m)]
    except (IndexError, ValueError) as e:
        raise SceneError(f"{path}: malformed pair file ({e})") from None
    return pairs, scores


def write_pair_file(path: str | Path, pairs: dict[int, list[int]],
                    scores: dict[int, list[float]] | None = None) -> Path:
    """Write ``pairs`` (ref id -> source ids) in MVSNet's ``pair.txt`` format."""
    path = Path(path)
    out = [str(len(pairs))]
    for ref, srcs in pairs.items():
        sc = (scores or {}).get(ref) or [0.0] * len(srcs)
        out.append(str(ref))
        body = [f"{s} {v:.4f}" for s, v in zip(srcs, sc, strict=False)]
        out.append(" ".join([str(len(srcs))] + body))
    path.write_text("\n".join(out) + "\n")
    return path


def visible_in_views(cameras: Cameras, points: Tensor) -> Tensor:
    """Which views see each point: in front of the camera and inside the image.

    Args:
        points: (N, 3) world points.

    Returns:
        (N, V) bool.
    """
    uv, z = cameras.project(points.to(cameras.w2c.dtype))
    inside = ((uv[..., 0] >= -0.5) & (uv[..., 0] <= cameras.width - 0.5)
              & (uv[..., 1] >= -0.5) & (uv[..., 1] <= cameras.height - 0.5))
    return (inside & (z > 0)).T


def sample_sphere_points(normalization: Normalization, n: int = 4096, seed: int = 0) -> Tensor:
    """(n, 3) float64 world points uniform in the object sphere (unit-frame radius 1, where
    VolSDF's normalization puts the object, docs/method.md 1.2; deterministic)."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    r = torch.rand(n, 1, generator=g, dtype=torch.float64) ** (1.0 / 3.0)
    return normalization.to_world(d * r)


def view_selection_scores(centers: Tensor, points: Tensor, visibility: Tensor,
                          theta0: float = 5.0, sigma1: float = 1.0, sigma2: float = 10.0,
                          chunk: int = 1024) -> Tensor:
    """MVSNet's pairwise view-selection scores (module docstring).

    Args:
        centers: (V, 3) camera centres.
        points: (N, 3) world points.
        visibility: (N, V) bool, which views see each point.
        theta0, sigma1, sigma2: the piecewise Gaussian's parameters in degrees.
        chunk: points per batch (memory ~ chunk * V^2).

    Returns:
        (V, V) float64 scores, symmetric, zero diagonal.
    """
    V = centers.shape[0]
    if points.ndim != 2 or points.shape[-1] != 3 or visibility.shape != (points.shape[0], V):
        raise ValueError(f"view_selection_scores: points (N, 3) and visibility (N, {V}) expected, "
                         f"got {tuple(points.shape)} and {tuple(visibility.shape)}")
    c = centers.double()
    score = torch.zeros(V, V, dtype=torch.float64)
    for s in range(0, points.shape[0], chunk):
        p = points[s:s + chunk].double()
        vis = visibility[s:s + chunk].bool()
        keep = vis.sum(1) >= 2
        if not keep.any():
            continue
        p, vis = p[keep], vis[keep].float()
        d = c[None] - p[:, None]  # (n, V, 3) point -> camera
        d = (d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)).float()
        cos = (d @ d.transpose(1, 2)).clamp_(-1, 1)  # (n, V, V)
        dtheta = torch.rad2deg(torch.arccos(cos)).sub_(theta0)
        inv2s2 = torch.where(dtheta <= 0, 1.0 / (2 * sigma1**2), 1.0 / (2 * sigma2**2))
        g = torch.exp(-(dtheta**2) * inv2s2)
        # sum over points of g * vis_i * vis_j
        score += torch.einsum("nij,ni,nj->ij", g, vis, vis).double()
    score.fill_diagonal_(0.0)
    return score


def compute_pairs(cameras: Cameras, view_ids: list[int], points: Tensor | None = None,
                  visibility: Tensor | None = None, normalization: Normalization | None = None,
                  num: int = 10, n_samples: int = 2048
                  ) -> tuple[dict[int, list[int]], dict[int, list[float]]]:
    """Source views per reference view, best first, by MVSNet's view selection.

    Args:
        cameras: V cameras.
        view_ids: V ids naming them.
        points: (N, 3) sparse points; default: ``n_samples`` points sampled in the
            normalization sphere.
        visibility: (N, V) bool; default: projected inside the image and in front.
        normalization: needed when ``points`` is None.
        num: sources kept per view (MVSNet: 10); views with a zero score are dropped.

    Returns:
        pairs: id -> source ids; scores: id -> their scores.
    """
    if points is None:
        if normalization is None:
            raise ValueError("compute_pairs needs points or a normalization")
        points = sample_sphere_points(normalization, n_samples)
    if visibility is None:
        visibility = visible_in_views(cameras, points)
    score = view_selection_scores(cameras.centers, points, visibility)
    pairs: dict[int, list[int]] = {}
    scores: dict[int, list[float]] = {}
    k = min(num, len(view_ids) - 1)
    for i, vid in enumerate(view_ids):
        if k <= 0:
            pairs[int(vid)], scores[int(vid)] = [], []
            continue
        val, idx = torch.topk(score[i], k)
        sel = [(int(view_ids[j]), float(s)) for j, s in zip(idx.tolist(), val.tolist(),
                                                                    strict=True)
               if s > 0 and math.isfinite(s)]
        pairs[int(vid)] = [j for j, _ in sel]
        scores[int(vid)] = [s for _, s in sel]
    return pairs, scores



def covisibility(visibility: Tensor) -> Tensor:
    """(N, V) bool visibility -> (V, V) float64 counts of points seen by both views."""
    v = visibility.double()
    return v.T @ v


def select_views(covisible: Tensor, centers: Tensor, target: Tensor, n: int = 3,
                 baseline: float = 20.0, min_angle: float = 5.0, max_angle: float = 45.0
                 ) -> list[int]:
    """Pick ``n`` views with good overlap and useful baselines (``--views auto``).

    Like DTU's inputs 25 / 22 / 28 (a reference, and sources on either side of it, 30 degrees
    away): each pair (reference, source) scores its shared points times a baseline weight
    w(theta) = exp(-(theta - baseline)^2 / (2 * 10^2)), theta the angle between the two views
    seen from ``target``. For every candidate reference, sources are added greedily by that
    score among views ``min_angle`` to ``max_angle`` degrees from the reference and at least
    ``min_angle`` from every source picked, and no closer to a picked source than to the
    reference (so sources spread around it rather than line up on one side); the set with the
    largest total score wins.

    Args:
        covisible: (V, V) points seen by both views (`covisibility`).
        centers: (V, 3) camera centres.
        target: (3,) the point the views look at (the object centre).
        n: views to pick (2 <= n <= V).
        baseline, min_angle, max_angle: degrees.

    Returns:
        n view positions (indices into ``centers``), the reference first.

    Raises:
        SceneError: fewer than ``n`` views, or no ``n`` views that meet the conditions.
    """
    V = centers.shape[0]
    if covisible.shape != (V, V) or centers.shape != (V, 3) or target.shape != (3,):
        raise ValueError(f"select_views: covisible (V, V), centers (V, 3), target (3,) expected, "
                         f"got {tuple(covisible.shape)}, {tuple(centers.shape)}, "
                         f"{tuple(target.shape)}")
    if n < 2 or n > V:
        raise SceneError(f"cannot pick {n} views from a scene of {V} view(s): "
                         + ("a reconstruction needs at least 2" if V < 2 or n < 2 else
                            f"ask for at most {V}"))
    d = centers.double() - target.double()
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    angle = torch.rad2deg(torch.arccos((d @ d.T).clamp(-1, 1)))
    C = covisible.double().clone()
    C.fill_diagonal_(0.0)
    score = C / C.max().clamp_min(1e-12) * torch.exp(-((angle - baseline) ** 2) / (2 * 10.0**2))
    best: tuple[float, list[int]] | None = None
    for ref in range(V):
        sel = [ref]
        allowed = (angle[ref] >= min_angle) & (angle[ref] <= max_angle) & (C[ref] > 0)
        while len(sel) < n and allowed.any():
            j = int(torch.argmax(torch.where(allowed, score[ref], -1.0)))
            sel.append(j)
            allowed &= (angle[j] >= min_angle) & (angle[j] >= angle[ref])
            allowed[sel] = False
        if len(sel) < n:
            continue
        total = float(score[ref, sel[1:]].sum())
        if best is None or total > best[0] + 1e-12:
            best = (total, sel)
    if best is None:
        raise SceneError(f"no {n} views overlap with {min_angle:g}-{max_angle:g} degree "
                         f"baselines; pick --views by hand")
    return best[1]
