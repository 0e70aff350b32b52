"""Losses of S-VolSDF (docs/method.md 4), as pure functions of tensors.

R rays, S samples per ray. ``p_prime`` is the soft-consistency label P' (docs/method.md 3) at the
same samples whose rendering weights ``w`` are the prediction (docs/method.md 4.1).
"""

from __future__ import annotations

import kornia
import torch
from torch import Tensor

__all__ = [
    "gce_weight_loss",
    "sparse_loss",
    "eikonal_loss",
    "rgb_l1_loss",
    "sparse_weight_at",
    "warmup_rgb_target",
    "warmup_ray_mask",
    "depth_mse_loss",
    "onehot_label",
]

_LOG_EPS = 1e-8


def _check_rs(name: str, **tensors: Tensor) -> None:
    shapes = {k: tuple(v.shape) for k, v in tensors.items()}
    first = next(iter(shapes.values()))
    if len(first) != 2 or any(s != first for s in shapes.values()):
        raise ValueError(f"{name}: expected equal (R, S) shapes, got {shapes}")


def gce_weight_loss(
    w: Tensor,
    p_prime: Tensor,
    q: float = 0.5,
    form: str = "paper",
    thresh: float = 1e-3,
) -> Tensor:
    """Generalized cross-entropy between rendering weights and the label P' (docs/method.md 4.2).

    Per ray r (mask m_r = 1[sum_k P'_rk > thresh]; the mean runs over all R rays, masked rays
    counting as zeros):

    - form "paper" (S-VolSDF Eq. for GCE, the default):
        l_r = m_r * sum_k P'_rk (1 - (w_rk + 1e-8)^q) / q   (the 1e-8 keeps the gradient finite
        at w = 0)
    - form "released" (the reference code's gradient-equivalent surrogate; docs/method.md 9.2.4):
        l_r = m_r * sum_k -P'_rk sg(w_rk)^q log(w_rk + 1e-8)
      whose gradient -P' w^q / (w + 1e-8) equals the paper's -P' w^(q-1) (up to the 1e-8);
      the code writes q = 1 as -P' w (same gradient, that value).
    - q = 0 (both forms): cross-entropy l_r = m_r * sum_k -P'_rk log(w_rk + 1e-8), the limit of
      the paper form as q -> 0, since (1 - w^q)/q -> -log w.

    L = (1/R) sum_r l_r.

    Args:
        w: (R, S) rendering weights in [0, 1].
        p_prime: (R, S) labels (no gradient is taken through them).
        q: GCE exponent in [0, 1] (paper 0.5).
        form: "paper" or "released".
        thresh: weak-supervision threshold on sum_k P' (paper 1e-3).

    Returns:
        () loss.
    """
    _check_rs("gce_weight_loss", w=w, p_prime=p_prime)
    if form not in ("paper", "released"):
        raise ValueError(f"gce_weight_loss: form must be 'paper' or 'released', got {form!r}")
    if not 0.0 <= q <= 1.0:
        raise ValueError(f"gce_weight_loss: q must be in [0, 1], got {q}")
    p = p_prime.detach()
    mask = (p.sum(-1) > thresh).to(w.dtype)
    if q == 0:
        per = -p * torch.log(w + _LOG_EPS)
    elif form == "paper":
        # w + eps: d(w^q)/dw is infinite at w = 0 (every empty sample), which would make the
        # step's gradient NaN; eps = the released form's 1e-8 (docs/method.md 9.2.4). Negatives are
        # rounded to 0 with the gradient passed straight through: at exactly w = 0, clamp_min's
        # own gradient depends on the torch version (1 up to 2.13, 0 from 2.14: pytorch/pytorch
        # #195931; tests/optimize/test_losses.py caught it), and without it the loss cannot
        # pull up the empty samples it labels
        w_pos = w + (w.clamp_min(0.0) - w).detach()
        per = p * (1.0 - (w_pos + _LOG_EPS) ** q) / q
    elif q == 1:
        per = -p * w
    else:
        per = -p * w.detach().clamp_min(0.0) ** q * torch.log(w + _LOG_EPS)
    return (per.sum(-1) * mask).mean()


def sparse_loss(
    depth: Tensor, p_prime: Tensor, thresh: float = 1e-3, normalize: str = "unsupervised"
) -> Tensor:
    """Sparsity loss on rays without MVS support (docs/method.md 4.3).

    Q = {r : sum_k P'_rk < thresh};  L = (1/N) sum_{r in Q} 1 / (d_r + 1e-3), with
    N = |Q| for ``normalize="unsupervised"`` (the paper, default; 0 when Q is empty) or N = R
    for ``normalize="all"`` (the released code).

    Args:
        depth: (R,) rendered z-depth in unit-frame units.
        p_prime: (R, S) labels.
        thresh: support threshold (1e-3).
        normalize: "unsupervised" or "all".

    Returns:
        () loss.
    """
    if depth.ndim != 1 or p_prime.ndim != 2 or p_prime.shape[0] != depth.shape[0]:
        raise ValueError(f"sparse_loss: depth (R,) and p_prime (R, S) expected, got "
                         f"{tuple(depth.shape)} and {tuple(p_prime.shape)}")
    q_mask = (p_prime.detach().sum(-1) < thresh).to(depth.dtype)
    total = (q_mask / (depth + 1e-3)).sum()
    if normalize == "unsupervised":
        return total / q_mask.sum().clamp_min(1.0)
    if normalize == "all":
        return total / depth.shape[0]
    raise ValueError(f"sparse_loss: normalize must be 'unsupervised' or 'all', got {normalize!r}")


def eikonal_loss(grad: Tensor) -> Tensor:
    """L_eik = mean_i (||grad_i|| - 1)^2 (docs/method.md 4.5).  grad: (N, 3) -> ()."""
    if grad.ndim != 2 or grad.shape[-1] != 3:
        raise ValueError(f"eikonal_loss: grad must be (N, 3), got {tuple(grad.shape)}")
    return ((grad.norm(dim=-1) - 1.0) ** 2).mean()


def rgb_l1_loss(pred: Tensor, target: Tensor, mask: Tensor | None = None) -> Tensor:
    """L1 colour loss (docs/method.md 4.4).

    Without a mask: mean over rays and channels of |c_hat - c|. With a mask m (R,):
    (1/R) sum_r m_r * mean_c |c_hat_rc - c_rc| (masked rays count as zeros in the mean, as in the
    released warm-up).

    Args:
        pred, target: (R, 3).
        mask: optional (R,) bool or float.

    Returns:
        () loss.
    """
    if pred.shape != target.shape or pred.ndim != 2:
        raise ValueError(f"rgb_l1_loss: pred and target must be equal (R, 3), got "
                         f"{tuple(pred.shape)} and {tuple(target.shape)}")
    per = (pred - target).abs().mean(-1)
    if mask is not None:
        per = per * mask.to(per.dtype)
    return per.mean()


def sparse_weight_at(step: int, w0: float, anneal: int = 200, decay: str = "linear") -> float:
    """Weight of the sparsity loss at ``step`` (docs/method.md 4.3, 4.6).

    "linear" (released code): w0 (1 - step / anneal) for step < anneal, else 0.
    "constant" (the paper's wording): w0 for step < anneal, else 0.
    """
    if step >= anneal or w0 == 0:
        return 0.0
    if decay == "linear":
        return float(w0) * (1.0 - step / anneal)
    if decay == "constant":
        return float(w0)
    raise ValueError(f"sparse_weight_at: decay must be 'linear' or 'constant', got {decay!r}")


def warmup_rgb_target(images: Tensor, kernel: int = 31, sigma: float = 90.0) -> Tensor:
    """Heavily smoothed images for the RGB warm-up (docs/method.md 4.4).

    A kernel x kernel Gaussian of std ``sigma`` (31, 90: practically a box blur) with reflect-101
    borders (OpenCV's default in the released ``cv2.GaussianBlur``).

    Args:
        images: (V, 3, H, W) float.

    Returns:
        (V, 3, H, W) blurred images.
    """
    if images.ndim != 4:
        raise ValueError(
            f"warmup_rgb_target: images must be (V, C, H, W), got {tuple(images.shape)}"
        )
    return kornia.filters.gaussian_blur2d(images, (kernel, kernel), (sigma, sigma),
                                          border_type="reflect")


def warmup_ray_mask(p_prime: Tensor, rule: str = "released", thresh: float = 1e-8) -> Tensor:
    """Which rays get the (smoothed) RGB loss during warm-up (docs/method.md 4.4, 9.2.6).

    "released": only rays with sum_k P'_rk < thresh (1e-8); MVS-supervised rays get no RGB loss.
    "all": every ray (the paper's description).

    Args:
        p_prime: (R, S).

    Returns:
        (R,) bool.
    """
    if rule == "released":
        return p_prime.detach().sum(-1) < thresh
    if rule == "all":
        return torch.ones(p_prime.shape[0], dtype=torch.bool, device=p_prime.device)
    raise ValueError(f"warmup_ray_mask: rule must be 'released' or 'all', got {rule!r}")


def depth_mse_loss(depth: Tensor, mvs_depth: Tensor, valid: Tensor) -> Tensor:
    """Ablation "mse": L = mean_{r valid} (d_r - d^mvs_r)^2 (0 without valid rays).

    Args:
        depth: (R,) rendered z-depth; mvs_depth: (R,) filtered MVS z-depth (same units);
        valid: (R,) bool, where the filtered MVS depth exists.

    Returns:
        () loss.
    """
    if not (depth.shape == mvs_depth.shape == valid.shape) or depth.ndim != 1:
        raise ValueError(f"depth_mse_loss: expected equal (R,) shapes, got {tuple(depth.shape)}, "
                         f"{tuple(mvs_depth.shape)}, {tuple(valid.shape)}")
    v = valid.to(depth.dtype)
    return ((depth - mvs_depth.detach()) ** 2 * v).sum() / v.sum().clamp_min(1.0)


def onehot_label(z: Tensor, mvs_depth: Tensor, cos: Tensor | None = None) -> Tensor:
    """Ablation "no probability volume": a one-hot label at the sample nearest the MVS depth.

    label_rk = 1 if k = argmin_k |cos_r z_rk - d^mvs_r| and d^mvs_r > 0, else 0; feed it to
    :func:`gce_weight_loss` in place of P'. Rays without an MVS depth (<= 0 or non-finite) get
    an all-zero row, so the loss's support mask drops them.

    Args:
        z: (R, S) sample ray distances.
        mvs_depth: (R,) MVS z-depth (same frame).
        cos: optional (R,) ray cosines converting distance to z-depth (default 1).

    Returns:
        (R, S) float one-hot rows.
    """
    if z.ndim != 2 or mvs_depth.shape != (z.shape[0],):
        raise ValueError(f"onehot_label: z (R, S) and mvs_depth (R,) expected, got "
                         f"{tuple(z.shape)} and {tuple(mvs_depth.shape)}")
    zd = z if cos is None else z * cos[:, None]
    k = (zd - mvs_depth[:, None]).abs().argmin(dim=-1)
    ok = torch.isfinite(mvs_depth) & (mvs_depth > 0)
    lab = torch.zeros_like(z)
    lab.scatter_(1, k[:, None], 1.0)
    return lab * ok[:, None].to(z.dtype)
