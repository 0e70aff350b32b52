"""Ray samplers: uniform, inverse-CDF, and VolSDF's error-bounded sampler (docs/method.md 5.4).

All functions are vectorised over rays; only the sampler's outer iterations and the 10-step
bisection are Python loops. Distances are along unit ray directions (ray distance, not z-depth).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from svolsdf.field.base import SurfaceModel
from svolsdf.render.rays import RayBundle

__all__ = [
    "uniform_sampler",
    "sample_pdf",
    "interval_min_distance",
    "opacity_error_bound",
    "ErrorBoundSamplerConfig",
    "SamplerOutput",
    "ErrorBoundSampler",
    "error_bound_sample",
    "UniformRaySampler",
]


def uniform_sampler(near: Tensor, far: Tensor, n: int, stratified: bool = False) -> Tensor:
    """n samples on [near, far] per ray (docs/method.md 5.4 step 1).

    Deterministic: linspace(near, far, n). Stratified (training): each sample is drawn uniformly
    in [mid_{i-1}, mid_i] between the linspace midpoints, with half-cells at the two ends.

    Args:
        near, far: (R,) distances.
        n: number of samples.
        stratified: jitter as above.

    Returns:
        (R, n) increasing distances.
    """
    if near.ndim != 1 or far.shape != near.shape:
        raise ValueError(f"uniform_sampler: near/far must be (R,), got {tuple(near.shape)}, "
                         f"{tuple(far.shape)}")
    t = torch.linspace(0.0, 1.0, n, device=near.device, dtype=near.dtype)
    z = near[:, None] + (far - near)[:, None] * t
    if stratified and n > 1:
        mids = 0.5 * (z[:, 1:] + z[:, :-1])
        upper = torch.cat([mids, z[:, -1:]], dim=-1)
        lower = torch.cat([z[:, :1], mids], dim=-1)
        z = lower + (upper - lower) * torch.rand_like(z)
    return z


def sample_pdf(bins: Tensor, weights: Tensor, n: int, det: bool) -> Tensor:
    """Inverse-CDF sampling of a piecewise-constant pdf over intervals (docs/method.md 5.4,
    3.7-3.8).

    pdf_i = weights_i / sum(weights) on [bins_i, bins_{i+1}]; u = linspace(0, 1, n) when ``det``,
    else u ~ U[0, 1). Each u is mapped linearly inside the interval whose CDF bracket contains it
    (a near-empty bracket, cdf difference < 1e-5, maps to its left end). A ray whose weights sum
    to 0 is sampled from the uniform pdf instead of producing NaNs.

    Args:
        bins: (R, B) increasing interval edges.
        weights: (R, B - 1) non-negative.
        n: samples per ray.
        det: deterministic u.

    Returns:
        (R, n) samples, non-decreasing in u.
    """
    R, B = bins.shape
    if weights.shape != (R, B - 1):
        raise ValueError(f"sample_pdf: weights must be (R, B-1) = ({R}, {B - 1}), "
                         f"got {tuple(weights.shape)}")
    total = weights.sum(-1, keepdim=True)
    pdf = torch.where(total > 0, weights / total.clamp_min(1e-30),
                      torch.full_like(weights, 1.0 / (B - 1)))
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, -1)], dim=-1)  # (R, B)
    if det:
        u = torch.linspace(0.0, 1.0, n, device=bins.device, dtype=bins.dtype).expand(R, n)
    else:
        u = torch.rand(R, n, device=bins.device, dtype=bins.dtype)
    u = u.contiguous()
    inds = torch.searchsorted(cdf.contiguous(), u, right=True)
    below = (inds - 1).clamp_min(0)
    above = inds.clamp_max(B - 1)
    cdf_lo, cdf_hi = cdf.gather(1, below), cdf.gather(1, above)
    bin_lo, bin_hi = bins.gather(1, below), bins.gather(1, above)
    denom = cdf_hi - cdf_lo
    denom = torch.where(denom < 1e-5, torch.ones_like(denom), denom)
    t = (u - cdf_lo) / denom
    return bin_lo + t * (bin_hi - bin_lo)


def interval_min_distance(z: Tensor, sdf: Tensor) -> Tensor:
    """d*_i: a lower bound of |SDF| on [z_i, z_{i+1}] for a 1-Lipschitz SDF (docs/method.md 5.4,
    3.2).

    With a = delta_i, b = |s_i|, c = |s_{i+1}|: d* = b if a^2 + b^2 <= c^2; c if a^2 + c^2 <= b^2;
    else 2 Area(a, b, c) / a (Heron) if b + c > a; else 0. d* = 0 unless sign(s_i) = sign(s_{i+1}).

    Args:
        z: (R, N) increasing distances.
        sdf: (R, N) SDF at z.

    Returns:
        (R, N - 1) non-negative.
    """
    a = z[:, 1:] - z[:, :-1]
    b = sdf[:, :-1].abs()
    c = sdf[:, 1:].abs()
    first = a**2 + b**2 <= c**2
    second = a**2 + c**2 <= b**2
    s = 0.5 * (a + b + c)
    area2 = (s * (s - a) * (s - b) * (s - c)).clamp_min(0.0)
    heron = 2.0 * area2.sqrt() / a.clamp_min(1e-12)
    d = torch.where(first, b, torch.where(second, c,
                    torch.where(b + c - a > 0, heron, torch.zeros_like(a))))
    same_sign = (sdf[:, 1:].sign() * sdf[:, :-1].sign()) == 1
    return d * same_sign


def _free_energy_prefix(model: SurfaceModel, sdf: Tensor, dists: Tensor, beta) -> Tensor:
    """(R, N-1): sum_{k<i} delta_k sigma_beta(s_k) for i = 0..N-2 (left Riemann sum)."""
    sigma = model.density(sdf[:, :-1], beta=beta)
    shifted = torch.cat([torch.zeros_like(dists[:, :1]), dists[:, :-1] * sigma[:, :-1]], dim=-1)
    return torch.cumsum(shifted, dim=-1)


def opacity_error_bound(
    model: SurfaceModel, sdf: Tensor, z: Tensor, d_star: Tensor, beta: Tensor
) -> tuple[Tensor, Tensor]:
    """VolSDF's opacity error bound (docs/method.md 5.4 step 3.3, paper VolSDF Thm. 1 / Lemma 2).

    bound_i = (min(exp(sum_{k<=i} delta_k^2 exp(-d*_k/beta) / (4 beta^2)), 1e6) - 1)
              * exp(-sum_{k<i} delta_k sigma_beta(s_k)),    E(beta) = max_i bound_i.

    Args:
        model: gives the Laplace density sigma_beta (``model.density(sdf, beta=...)``).
        sdf: (R, N) SDF at the samples; z: (R, N) distances; d_star: (R, N - 1).
        beta: (R, 1) per-ray beta (or a scalar tensor).

    Returns:
        E: (R,) the bound; bound: (R, N - 1) per-interval bound on the opacity error.
    """
    dists = z[:, 1:] - z[:, :-1]
    prefix = _free_energy_prefix(model, sdf, dists, beta)
    err = torch.exp(-d_star / beta) * dists**2 / (4.0 * beta**2)
    bound = (torch.exp(torch.cumsum(err, dim=-1)).clamp(max=1e6) - 1.0) * torch.exp(-prefix)
    return bound.max(dim=-1).values, bound


def _weights(model: SurfaceModel, sdf: Tensor, z: Tensor, beta: Tensor) -> Tensor:
    """(R, N) rendering weights with sigma_beta and a last delta of 1e10 (docs/method.md 5.4)."""
    dists = torch.cat([z[:, 1:] - z[:, :-1], torch.full_like(z[:, :1], 1e10)], dim=-1)
    fe = dists * model.density(sdf, beta=beta)
    shifted = torch.cat([torch.zeros_like(fe[:, :1]), fe[:, :-1]], dim=-1)
    return (1.0 - torch.exp(-fe)) * torch.exp(-torch.cumsum(shifted, dim=-1))


@dataclass
class ErrorBoundSamplerConfig:
    """VolSDF ``ErrorBoundSampler`` constants (docs/method.md 5.4)."""

    n_samples: int = 64
    """Final samples drawn from the beta-weights."""
    n_samples_eval: int = 128
    """Uniform samples, and samples added per refinement iteration."""
    n_samples_extra: int = 32
    """Samples of the refined set kept beside the final ones (plus near and far): 64+2+32 = 98."""
    eps: float = 0.1
    """Target bound on the opacity error."""
    beta_iters: int = 10
    """Bisection steps of the beta line search."""
    max_total_iters: int = 5
    """Refinement iterations when rendering (eval)."""
    max_total_iters_train: int = 1
    """Refinement iterations in training (the released code's ``fast=1``, docs/method.md 4.6)."""
    add_tiny: float = 0.0
    """Added to the bound pdf before resampling (DTU 0, BlendedMVS 1e-6)."""


@dataclass
class SamplerOutput:
    """Result of :func:`error_bound_sample`.

    Attributes:
        z: (R, S) sorted final distances (S = n_samples + 2 + n_samples_extra = 98).
        eik_index: (R,) long, a random index into z per ray (the eikonal sample,
        docs/method.md 5.5). z_eval: (R, N) the refined sample set the bound was computed on
        (error-bound only). sdf_eval: (R, N) SDF at z_eval (no grad; error-bound only).
        beta: (R,) per-ray beta from the line search (<= model beta means converged).
        beta0: () the model's beta (detached).
        iters: iterations run.
    """

    z: Tensor
    eik_index: Tensor
    z_eval: Tensor | None = None
    sdf_eval: Tensor | None = None
    beta: Tensor | None = None
    beta0: Tensor | None = None
    iters: int = 0


@torch.no_grad()
def _sdf_at(model: SurfaceModel, rays: RayBundle, z: Tensor) -> Tensor:
    pts = rays.origins[:, None] + z[..., None] * rays.dirs[:, None]
    return model.sdf(pts.reshape(-1, 3)).reshape(z.shape)


@torch.no_grad()
def error_bound_sample(
    model: SurfaceModel,
    rays: RayBundle,
    config: ErrorBoundSamplerConfig | None = None,
    training: bool | None = None,
) -> SamplerOutput:
    """VolSDF's error-bounded sampler (docs/method.md 5.4, steps 1-5).

    1. n_samples_eval uniform samples on [near, far] (stratified in training).
    2. beta+ = sqrt(sum_i delta_i^2 / (4 log(1 + eps))).
    3. Loop while not converged and iter < max_iters (1 in training, 5 otherwise): SDF at new
       samples (no grad, sphere-clamped ``model.sdf``), d* per interval, error bound E(beta);
       rays with E(beta0) <= eps take beta0, the others bisect ``beta_iters`` times on
       [beta0, beta+] keeping E(hi) <= eps; converged when max_r beta_r <= beta0; if not and
       iterations remain, add n_samples_eval samples by inverse CDF of the bound opacity
       (+ add_tiny) with deterministic u, else draw n_samples from the beta-weights + 1e-5
       (u random in training, linspace otherwise).
    4. Final z = sort(final samples, near, far, n_samples_extra of the refined set (a random
       subset in training, evenly spaced indices otherwise)).
    5. One random eikonal index per ray.

    In training the convergence test is not evaluated (all ``max_total_iters_train``
    iterations run; 1 in the paper, docs/method.md 4.6), so the step has no device-host
    synchronisation.

    Args:
        model: any :class:`SurfaceModel` (``sdf``, ``density(sdf, beta)``, ``beta``).
        rays: R rays.
        config: sampler constants.
        training: default ``model.training``.

    Returns:
        SamplerOutput.
    """
    cfg = config or ErrorBoundSamplerConfig()
    training = model.training if training is None else training
    max_iters = cfg.max_total_iters_train if training else cfg.max_total_iters
    R = len(rays)
    beta0 = model.beta.detach()
    z = uniform_sampler(rays.near, rays.far, cfg.n_samples_eval, stratified=training)
    dists = z[:, 1:] - z[:, :-1]
    beta = torch.sqrt((dists**2).sum(-1) / (4.0 * math.log(1.0 + cfg.eps)))  # (R,) beta+
    samples, samples_idx, sdf = z, None, None
    it = 0
    while True:
        new_sdf = _sdf_at(model, rays, samples)
        if samples_idx is None:
            sdf = new_sdf
        else:
            sdf = torch.cat([sdf, new_sdf], dim=-1).gather(1, samples_idx)
        d_star = interval_min_distance(z, sdf)
        err0, _ = opacity_error_bound(model, sdf, z, d_star, beta0)
        beta = torch.where(err0 <= cfg.eps, beta0.expand(R), beta)
        lo, hi = beta0.expand(R).clone(), beta
        for _ in range(cfg.beta_iters):
            mid = 0.5 * (lo + hi)
            err, _ = opacity_error_bound(model, sdf, z, d_star, mid[:, None])
            ok = err <= cfg.eps
            hi = torch.where(ok, mid, hi)
            lo = torch.where(ok, lo, mid)
        beta = hi
        weights = _weights(model, sdf, z, beta[:, None])
        it += 1
        # The convergence test (max_r beta_r <= beta0) only matters when iterations remain. In
        # training it is skipped (every iteration runs): reading it would stall the device
        # each step, and refining a converged set changes no ray's beta (it stays beta0, the
        # lower end of the line search), it only adds candidate samples.
        refine = it < max_iters and (training or bool((beta.max() > beta0).item()))
        if refine:
            # More samples where the bound says the opacity is uncertain (step 3.7).
            _, bound = opacity_error_bound(model, sdf, z, d_star, beta[:, None])
            samples = sample_pdf(z, bound + cfg.add_tiny, cfg.n_samples_eval, det=True)
            z, samples_idx = torch.sort(torch.cat([z, samples], dim=-1), dim=-1)
            continue
        z_final = sample_pdf(z, weights[:, :-1] + 1e-5, cfg.n_samples, det=not training)
        break
    N = z.shape[1]
    if cfg.n_samples_extra > 0:
        k = min(cfg.n_samples_extra, N)
        if training:
            idx = torch.randperm(N, device=z.device)[:k]
        else:
            idx = torch.linspace(0, N - 1, k, device=z.device).long()
        extra = z[:, idx]
    else:
        extra = z[:, :0]
    z_all, _ = torch.sort(
        torch.cat([z_final, rays.near[:, None], rays.far[:, None], extra], dim=-1), dim=-1
    )
    eik = torch.randint(z_all.shape[1], (R,), device=z.device)
    return SamplerOutput(z_all, eik, z, sdf, beta, beta0, it)


class ErrorBoundSampler:
    """Callable form of :func:`error_bound_sample`: ``sampler(model, rays) -> SamplerOutput``."""

    def __init__(self, config: ErrorBoundSamplerConfig | None = None):
        self.config = config or ErrorBoundSamplerConfig()

    def __call__(self, model: SurfaceModel, rays: RayBundle,
                 training: bool | None = None) -> SamplerOutput:
        return error_bound_sample(model, rays, self.config, training)


class UniformRaySampler:
    """``sampler(model, rays) -> SamplerOutput`` with n uniform samples on [near, far]
    (stratified in training); ignores the model. A baseline and a deterministic test sampler."""

    def __init__(self, n_samples: int = 128):
        self.n_samples = int(n_samples)

    def __call__(self, model: SurfaceModel, rays: RayBundle,
                 training: bool | None = None) -> SamplerOutput:
        training = model.training if training is None else training
        z = uniform_sampler(rays.near, rays.far, self.n_samples, stratified=training)
        eik = torch.randint(self.n_samples, (len(rays),), device=z.device)
        return SamplerOutput(z, eik)
