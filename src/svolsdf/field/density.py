"""Laplace density of VolSDF (docs/method.md 5.4, paper Eq. 2).

Sign conventions (docs/method.md 5.4 and 9.2.7):

- Ours (and the released VolSDF / S-VolSDF code): the SDF s is > 0 outside and < 0 inside, and
  sigma(s) = alpha * Psi_beta(-s), with Psi_beta the CDF of a zero-mean Laplace distribution of
  scale beta:

      sigma(s) = (1/beta) * (1/2 + 1/2 * sign(s) * (exp(-|s|/beta) - 1))
               = (1/(2 beta)) exp(-s/beta)            for s > 0  (outside: decays to 0)
               = (1/beta) (1 - 1/2 exp(s/beta))      for s <= 0 (inside: tends to 1/beta)

  The density is high inside, where s < 0.
- Paper Eq. 2 writes the two branches the other way round (as if s were < 0 outside), and lists
  alpha as a learnable parameter; the code ties alpha = 1/beta and learns only beta. We follow the
  code: alpha = 1/beta, beta = |beta_param| + beta_min.

Both branches equal 1/(2 beta) at s = 0, so sigma is continuous.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

__all__ = ["laplace_density", "LaplaceDensity"]


def laplace_density(sdf: Tensor, beta: Tensor | float) -> Tensor:
    """sigma(s) = (1/beta) (1/2 + 1/2 sign(s) (exp(-|s|/beta) - 1))   (docs/method.md 5.4).

    Args:
        sdf: (...) signed distances, > 0 outside.
        beta: scalar or a tensor broadcastable to ``sdf`` (e.g. (R, 1) per-ray betas), > 0.

    Returns:
        (...) density >= 0, in (0, 1/beta]; high inside.
    """
    beta = torch.as_tensor(beta, dtype=sdf.dtype, device=sdf.device)
    alpha = 1.0 / beta
    return alpha * (0.5 + 0.5 * sdf.sign() * torch.expm1(-sdf.abs() / beta))


class LaplaceDensity(nn.Module):
    """Laplace density with a learnable scale: beta = |beta_param| + beta_min, alpha = 1/beta.

    docs/method.md 5.4: beta_param initialised to 0.1, beta_min = 1e-4; only beta is learnable.
    """

    def __init__(self, beta_init: float = 0.1, beta_min: float = 1e-4):
        super().__init__()
        self.beta_param = nn.Parameter(torch.tensor(float(beta_init)))
        self.beta_min = float(beta_min)

    def get_beta(self) -> Tensor:
        """() current beta = |beta_param| + beta_min."""
        return self.beta_param.abs() + self.beta_min

    def forward(self, sdf: Tensor, beta: Tensor | None = None) -> Tensor:
        """sdf: (...) -> sigma (...); ``beta`` overrides the learned one (broadcastable)."""
        return laplace_density(sdf, self.get_beta() if beta is None else beta)
