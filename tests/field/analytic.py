"""Analytic surface models for tests and debugging: an exact sphere SDF."""

from __future__ import annotations

import torch
from torch import Tensor

from svolsdf.field.base import SurfaceModel
from svolsdf.field.density import laplace_density

__all__ = ["SphereSDF"]


class SphereSDF(SurfaceModel):
    """s(x) = |x - center| - r with a fixed Laplace beta and a constant colour.

    No learnable parameters; useful to test samplers and renderers against closed forms.

    Args:
        radius: sphere radius r.
        center: (3,) sphere centre (default origin).
        beta: Laplace scale (docs/method.md 5.4).
        colour: (3,) rgb returned everywhere.
    """

    def __init__(self, radius: float = 1.0, center=(0.0, 0.0, 0.0), beta: float = 0.01,
                 colour=(0.8, 0.4, 0.2)):
        super().__init__()
        self.r = float(radius)
        self.register_buffer("center", torch.as_tensor(center, dtype=torch.float32))
        self.register_buffer("beta_value", torch.tensor(float(beta)))
        self.register_buffer("rgb", torch.as_tensor(colour, dtype=torch.float32))
        self.feature_dim = 1

    def sdf(self, x: Tensor, clamp: bool = True) -> Tensor:
        """x: (N, 3) -> (N,) exact signed distance."""
        return (x - self.center).norm(dim=-1) - self.r

    def sdf_and_grad(self, x: Tensor, create_graph: bool = True, clamp: bool = True):
        """x: (N, 3) -> sdf (N,), unit gradient (N, 3), zero feature (N, 1)."""
        d = x - self.center
        n = d.norm(dim=-1)
        return n - self.r, d / n.clamp_min(1e-12)[:, None], torch.zeros_like(n)[:, None]

    def colour(self, x: Tensor, view_dir: Tensor, normal: Tensor, feature: Tensor) -> Tensor:
        """(N, 3) constant colour."""
        return self.rgb.expand(x.shape[0], 3)

    def density(self, sdf: Tensor, beta: Tensor | None = None) -> Tensor:
        """Laplace density (docs/method.md 5.4) with the fixed beta unless overridden."""
        return laplace_density(sdf, self.beta_value if beta is None else beta)

    @property
    def beta(self) -> Tensor:
        return self.beta_value
