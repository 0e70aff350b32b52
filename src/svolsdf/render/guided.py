"""A sampler that uses what MVS already knows (the `fast` preset; not in the paper).

The error-bounded sampler (docs/method.md 5.4) spends 128+ SDF evaluations per ray and up to five
iterations finding the surface. The fast preset instead places samples where the soft-consistency
label P' (docs/method.md 3) and the current surface say the surface is:

1. ``samples_coarse`` stratified probe distances on [near, far] (no gradients).
2. At the probes: P' from the MVS prior (rays of input views only) and the current rendering
   weights w from the field's Laplace density (docs/method.md 5.4 compositing), with beta widened to
   at least the probe spacing so that a sharp surface between two probes is still found.
3. pdf = mix * P'/sum(P') + (1 - mix) * w/sum(w) + floor / n, per ray; a ray without MVS support
   (sum P' < ``thresh``) uses only the field's weights.
4. ``samples_fine`` samples by inverse CDF from that pdf, merged with ``samples_uniform``
   stratified samples so that every ray still sees the whole [near, far] (the sparsity loss and
   free space need it).

All of it is vectorized over rays and samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from svolsdf.field.base import SurfaceModel
from svolsdf.render.rays import RayBundle
from svolsdf.render.samplers import SamplerOutput, sample_pdf, uniform_sampler
from svolsdf.render.volume import composite

__all__ = ["GuidedSamplerConfig", "MVSGuidedSampler"]


@dataclass
class GuidedSamplerConfig:
    """Configuration of `MVSGuidedSampler`."""

    samples_coarse: int = 64
    """Probe distances per ray where P' and the field's weights are evaluated (no gradients)."""
    samples_uniform: int = 32
    """Stratified samples spread over [near, far] in the final set (``train.samples_uniform``)."""
    samples_fine: int = 48
    """Importance samples drawn from the mixed pdf (``train.samples_fine``)."""
    mix: float = 0.5
    """Share of the pdf taken from P' on MVS-supported rays (the rest from the field's weights)."""
    floor: float = 0.02
    """Uniform share added to the pdf so no interval is starved."""
    thresh: float = 1e-3
    """A ray is MVS-supported when sum_k P'_k > thresh (docs/method.md 4.2)."""
    probe_beta: float = 1.0
    """The probe weights use beta >= probe_beta x the probe spacing (module docstring)."""

    @classmethod
    def from_config(cls, train) -> GuidedSamplerConfig:
        """The sampler of a run's training section ``train`` (a `svolsdf.config.TrainConfig`):
        its ``samples_uniform`` and ``samples_fine``, the other fields at their defaults."""
        return cls(samples_uniform=train.samples_uniform, samples_fine=train.samples_fine)


class MVSGuidedSampler:
    """Samples concentrated where P' and the current surface are.

    Args:
        prior: an `svolsdf.prior.consistency.MVSPrior` (or None: field weights only, e.g. for
            novel views).
        config: `GuidedSamplerConfig`.
        use_prior_at_eval: also use P' when not training (input views only).
    """

    def __init__(self, prior=None, config: GuidedSamplerConfig | None = None,
                 use_prior_at_eval: bool = False):
        self.prior = prior
        self.config = config or GuidedSamplerConfig()
        self.use_prior_at_eval = use_prior_at_eval

    @torch.no_grad()
    def __call__(self, model: SurfaceModel, rays: RayBundle,
                 training: bool | None = None) -> SamplerOutput:
        """rays: R rays -> SamplerOutput with z (R, samples_uniform + samples_fine) sorted (one
        more, the far bound, when the model has a ``background``), eik_index (R,)."""
        cfg = self.config
        training = model.training if training is None else training
        R = len(rays)
        zc = uniform_sampler(rays.near, rays.far, cfg.samples_coarse, stratified=training)
        pts = rays.origins[:, None] + zc[..., None] * rays.dirs[:, None]  # (R, C, 3)
        sdf = model.sdf(pts.reshape(-1, 3)).reshape(R, cfg.samples_coarse)
        deltas = torch.cat([zc[:, 1:] - zc[:, :-1], torch.full_like(zc[:, :1], 1e10)], -1)
        # probe weights with beta widened to the probe spacing: a sharp surface (beta << spacing)
        # between two probes would otherwise get no mass and no fine samples (the reason
        # VolSDF's sampler raises beta until its error bound holds, docs/method.md 5.4)
        spacing = ((rays.far - rays.near) / cfg.samples_coarse)[:, None]
        beta_probe = torch.maximum(torch.as_tensor(model.beta).detach(), cfg.probe_beta * spacing)
        w, _ = composite(model.density(sdf, beta=beta_probe), deltas)
        w = w[:, :-1]
        w_n = w / w.sum(-1, keepdim=True).clamp_min(1e-12)
        pdf = w_n
        if self.prior is not None and (training or self.use_prior_at_eval):
            pp = self.prior.label(pts, rays.view)[:, :-1]  # P' (docs/method.md 3)
            s = pp.sum(-1, keepdim=True)
            supported = s > cfg.thresh
            pp_n = pp / s.clamp_min(1e-12)
            pdf = torch.where(supported, cfg.mix * pp_n + (1 - cfg.mix) * w_n, w_n)
        pdf = pdf + cfg.floor / pdf.shape[-1]
        zf = sample_pdf(zc, pdf, cfg.samples_fine, det=not training)
        zu = uniform_sampler(rays.near, rays.far, cfg.samples_uniform, stratified=training)
        z, _ = torch.sort(torch.cat([zu, zf], dim=-1), dim=-1)
        if model.get_background() is not None:
            # render_rays takes the last entry as the far bound where the background starts
            # (docs/method.md 5.5), as with the error-bounded sampler's final set
            z = torch.cat([z, rays.far[:, None]], dim=-1)
        eik = torch.randint(z.shape[1], (R,), device=z.device)
        return SamplerOutput(z, eik)
